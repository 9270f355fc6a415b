"""A layout's scene, camera path and lights, drawn from one generator in that order, and
``SynthScene``, which rebuilds them from a capture's config to render truth at any camera.

Random streams: everything here draws from ``default_rng([seed, SCENE_STREAM])``; each
frame's stages draw from their own ``default_rng([seed, stream, frame])`` (``writer``). A new
random stage takes a new stream number, so the draws of the others, and the files they make
for a given seed, stay as they are. The phone-like options (``camera``, ``paths.PathChanges``)
draw from streams of their own, and only when they are on.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ...cameras import Camera
from ...errors import LabelsynthError
from .around import AroundScene
from .camera import drift_curves, image_effects_on
from .config import SynthConfig
from .paths import hand_held_path, orbit_path, path_changes
from .scene import OneSidedScene

SCENE_STREAM = 0  # the scene, its camera path and lights
PREDICTION_STREAM = 1  # a frame's imitation-segmenter errors
DRIFT_STREAM = 2  # exposure and white-balance drift along the path (``camera.drift_curves``)
IMAGE_STREAM = 3  # a frame's blur and sensor noise (``camera.frame_look``, ``camera.apply_camera``)
PATH_CHANGE_STREAM = 4  # distance and zoom changes along the path (``paths.path_changes``)


class Layout(NamedTuple):
    """What a layout draws before any frame is rendered."""

    scene: OneSidedScene
    cameras: list[Camera]
    path_info: dict  # scene.json's ``camera_path``
    lights: dict  # ``shading.shade``'s lights
    drift: tuple[np.ndarray, np.ndarray] | None = None  # (EV (N,), white balance (N, 3)); None: no image effects


def build_layout(cfg: SynthConfig) -> Layout:
    """The config's scene, camera path and lights; the same config gives the same layout."""
    rng = np.random.default_rng([cfg.seed, SCENE_STREAM])
    changes = path_changes(np.random.default_rng([cfg.seed, PATH_CHANGE_STREAM]), cfg)
    detail = int(np.clip(3.2 * max(cfg.width, cfg.height), 384, 2048))
    key = np.array([0.35, -0.45, 1.0])
    fill = np.array([-0.6, 0.5, 0.5])
    if cfg.layout == "one-sided":
        scene = OneSidedScene(rng, detail)
        cams, path_info = hand_held_path(rng, scene, cfg, changes)
        lights = {"ambient": 0.30, "headlight": 0.12,
                  "directional": [(key / np.linalg.norm(key), 0.62), (fill / np.linalg.norm(fill), 0.18)]}
    else:  # all-around: the underside is seen too, so light comes from below as well
        scene = AroundScene(rng, detail)
        cams, path_info = orbit_path(rng, scene, cfg, changes)
        bounce = np.array([0.25, 0.4, -1.0])
        lights = {"ambient": 0.30, "headlight": 0.2,
                  "directional": [(key / np.linalg.norm(key), 0.55), (fill / np.linalg.norm(fill), 0.18),
                                  (bounce / np.linalg.norm(bounce), 0.3)]}
    drift = drift_curves(cfg, DRIFT_STREAM) if image_effects_on(cfg) else None
    return Layout(scene, cams, path_info, lights, drift)


class SynthScene:
    """The scene of a ``synth`` capture rebuilt from its config, to render exact truth (and the
    image) at any camera: novel views are scored against it (``benchmarks/bench_augment.py``).

    The scene and lights are drawn from the same generator as ``synthesize`` draws them, so at a
    frame's own camera ``render`` gives back that frame's truth exactly, and its image too when
    no phone image effect (``camera``) was on: ``render`` gives the image before them.
    """

    def __init__(self, cfg: SynthConfig) -> None:
        self.config = cfg
        self._layout = build_layout(cfg)
        self.cameras = self._layout.cameras

    @classmethod
    def from_truth(cls, truth_dir: str | Path) -> "SynthScene":
        """From OUT/truth/scene.json as ``synthesize`` wrote it."""
        path = Path(truth_dir) / "scene.json"
        try:
            config = json.loads(path.read_text())["config"]
            return cls(SynthConfig(**config))
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise LabelsynthError(f"{path}: not a synth scene.json ({exc})") from None

    def render(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(RGB uint8 (H,W,3), class ids uint8 (H,W), ray distance float32 (H,W), inf on a miss)
        of a camera in the capture's world coordinates."""
        return self._layout.scene.render(camera, self._layout.lights)
