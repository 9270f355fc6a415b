"""``synthesize``: render every frame of a layout and write the capture and its exact truth.

A frame goes through stages in order (``render_frame``): the scene renders the camera's image
with its exact truth and ray distance; the phone's camera changes the image alone (``camera``:
exposure and white-balance drift, defocus and motion blur, sensor noise; off by default), with
its own random stream (``layouts``); then the imitation segmenter makes its prediction from the
truth. JPEG compression (``jpeg_quality``) happens when the image is written.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ...capture.images import write_image
from ...capture.masks import write_mask
from ...capture.select import spread_indices
from ...classes import DEFAULT_CLASSES
from ...outdir import building
from ...progress import track
from .camera import apply_camera, frame_look
from .config import PHONE, SynthConfig, SynthResult
from .layouts import IMAGE_STREAM, PREDICTION_STREAM, Layout, build_layout
from .predictions import predict_errors


class SynthFrame(NamedTuple):
    """One frame as the capture and its truth hold it."""

    image: np.ndarray  # RGB uint8 (H,W,3): images/ (before JPEG compression, when jpeg_quality is set)
    truth: np.ndarray  # class ids uint8 (H,W): truth/ (and annotations/ where annotated)
    depth: np.ndarray  # ray distance float32 (H,W), inf on a miss: truth/depth/
    prediction: np.ndarray  # class ids uint8 (H,W): predictions/


def annotated_indices(frames: int, annotated: int) -> list[int]:
    """Evenly spread frame indices (centres of equal segments of the path), the same rule as
    ``--annotated-frames spread:N``."""
    return spread_indices(frames, annotated)


def render_frame(layout: Layout, cfg: SynthConfig, index: int) -> SynthFrame:
    """Frame ``index``: its own random streams for the camera's image effects and the prediction
    errors, so that it does not depend on the frames before it."""
    image, truth, depth = layout.scene.render(layout.cameras[index], layout.lights)
    if layout.drift is not None:
        rng = np.random.default_rng([cfg.seed, IMAGE_STREAM, index])
        image = apply_camera(image, frame_look(cfg, index, *layout.drift, rng), rng)
    rng = np.random.default_rng([cfg.seed, PREDICTION_STREAM, index])
    prediction = predict_errors(truth, np.isfinite(depth), rng, cfg.noise)
    return SynthFrame(image, truth, depth, prediction)


def synthesize(out: Path, cfg: SynthConfig | None = None, *, force: bool = False, progress: bool = True) -> SynthResult:
    """Write a synthetic capture (OUT/capture) and its exact truth (OUT/truth).

    The folder is built in OUT.partial and renamed at the end (``outdir.building``), so an
    interrupted run never leaves an OUT that looks complete. Masks are greyscale class-id PNGs.
    """
    cfg = cfg or SynthConfig()
    out = Path(out)
    start = time.perf_counter()
    with building(out, force=force) as tmp:
        layout = build_layout(cfg)
        cap, truth_dir = tmp / "capture", tmp / "truth"
        for d in (cap / "images", cap / "annotations", cap / "predictions", truth_dir / "depth"):
            d.mkdir(parents=True)
        names = [f"frame_{i:03d}" if cfg.frames <= 1000 else f"frame_{i:05d}" for i in range(cfg.frames)]
        suffix = ".jpg" if cfg.jpeg_quality else ".png"
        ann = set(annotated_indices(cfg.frames, cfg.annotated))
        for i in track(range(cfg.frames), "synth", enabled=progress):
            _write_frame(cap, truth_dir, names[i], render_frame(layout, cfg, i), annotated=i in ann,
                         suffix=suffix, jpeg_quality=cfg.jpeg_quality)
        c0 = layout.cameras[0]
        frames_json = [{"file_path": f"images/{name}{suffix}", "transform_matrix": [[float(v) for v in row] for row in cam.c2w]}
                       for name, cam in zip(names, layout.cameras)]
        if cfg.zoom:  # per-frame intrinsics (they win over the shared ones)
            for entry, cam in zip(frames_json, layout.cameras):
                entry.update(fl_x=float(cam.fx), fl_y=float(cam.fy))
        transforms = {"camera_model": "OPENCV", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy,
                      "w": cfg.width, "h": cfg.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                      "frames": frames_json}
        (cap / "transforms.json").write_text(json.dumps(transforms, indent=2))
        annotated = [names[i] for i in sorted(ann)]
        # the phone options only when on: a capture made without them has the scene.json it always had
        config = {k: v for k, v in asdict(cfg).items() if k not in PHONE or v}
        meta = {"seed": cfg.seed, "layout": cfg.layout, "config": config, "surface": layout.scene.describe(),
                "camera_path": layout.path_info, "class_areas": layout.scene.class_areas(),
                "area_units": "world units squared", "annotated": annotated, "frames": names,
                "classes": [{"id": c.id, "name": c.name} for c in DEFAULT_CLASSES]}
        (truth_dir / "scene.json").write_text(json.dumps(meta, indent=2))
    return SynthResult(capture_dir=out / "capture", truth_dir=out / "truth", num_frames=cfg.frames,
                       annotated=annotated, seconds=time.perf_counter() - start)


def _write_frame(cap: Path, truth_dir: Path, name: str, frame: SynthFrame, *, annotated: bool, suffix: str = ".png",
                 jpeg_quality: int = 0) -> None:
    """A frame's image, prediction, truth, depth and (if annotated) annotation."""
    write_image(cap / "images" / f"{name}{suffix}", frame.image, jpeg_quality=jpeg_quality or None)
    write_mask(cap / "predictions" / f"{name}.png", frame.prediction)
    write_mask(truth_dir / f"{name}.png", frame.truth)
    buffer = io.BytesIO()  # written by Python, so that a full disk is an OSError naming the file
    np.save(buffer, frame.depth)
    (truth_dir / "depth" / f"{name}.npy").write_bytes(buffer.getbuffer())
    if annotated:
        write_mask(cap / "annotations" / f"{name}.png", frame.truth)
