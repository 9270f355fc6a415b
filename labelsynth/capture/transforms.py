"""``transforms.json`` in its common dialects -> frames with cameras.

Dialects accepted:

- nerfstudio: intrinsics ``fl_x fl_y cx cy w h`` shared at the top level or per frame
  (per-frame values win), ``camera_model`` OPENCV (``k1 k2 p1 p2``; ``k3``/``k4`` only if
  zero), PINHOLE or SIMPLE_PINHOLE. Fisheye and other models are rejected: the ray model
  (``cameras.Camera``) is radial-tangential only. An optional ``ply_file_path`` (nerfstudio's
  ``sparse_pc.ply``) supplies SfM points for the region of interest.
- instant-ngp / Blender / NeRF-synthetic: ``camera_angle_x`` (and ``camera_angle_y``)
  instead of focal lengths; ``w``/``h`` may be missing (then read from the first image);
  ``file_path`` may lack an extension (``./train/r_0``); ``aabb_scale`` and other extra keys
  are ignored.

Background choice for RGBA frames: white when the file says ``"white_background": true``,
black when it says false, and otherwise white for Blender-style files (``camera_angle_x``
without any ``fl_x``), since NeRF-synthetic scenes are conventionally shown on white, and
black for everything else.

Frames are sorted by name (the image stem), as nerfstudio does, so the order does not
depend on how a tool happened to write the list.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..cameras import Camera
from ..classes import ClassMap
from ..errors import CaptureError
from .images import IMAGE_EXTENSIONS, find_image, image_size
from .model import Frame, SceneNormalization

SUPPORTED_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE"}
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                  "camera_model", "camera_angle_x", "camera_angle_y")


@dataclass
class PosedFrames:
    """What a pose source yields: frames with cameras, plus what the loader needs to know."""

    frames: list[Frame]
    skipped: list[str] = field(default_factory=list)  # names of frames whose image is missing
    points: np.ndarray | None = None
    white_background: bool = False
    source: str = "transforms.json"
    # What a layout fixes itself (NeuS): its unit sphere instead of a region of interest found
    # from the cameras, its class table when there is no classes.json, its mask folders' kinds.
    normalization: SceneNormalization | None = None
    classes: ClassMap | None = None
    mask_kinds: dict[Path, str] = field(default_factory=dict)


def read_transforms(path: str | Path) -> PosedFrames:
    """Parse a transforms.json; image paths are relative to the file's folder."""
    path = Path(path)
    root = path.parent
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CaptureError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(f"{path}: cannot read ({exc})") from exc
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: expected a JSON object with 'frames'")
    frames_in = data.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise CaptureError(f"{path}: missing or empty 'frames' list")

    white_background = white_background_of(data)

    shared = {k: data[k] for k in INTRINSIC_KEYS if k in data}
    frames: list[Frame] = []
    skipped: list[str] = []
    first_size: tuple[int, int] | None = None
    for i, entry in enumerate(frames_in):
        where = f"{path}: frame {i}"
        if not isinstance(entry, dict):
            raise CaptureError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
        file_path = entry.get("file_path")
        if not isinstance(file_path, str) or not file_path.strip():
            raise CaptureError(f"{where}: missing 'file_path'")
        c2w = _matrix(entry.get("transform_matrix"), where)
        base = root / _clean_relpath(file_path)
        image_path = find_image(base)
        if image_path is None:
            skipped.append(_stem(base))
            continue
        intr = {**shared, **{k: entry[k] for k in INTRINSIC_KEYS if k in entry}}
        if "w" not in intr or "h" not in intr:
            if first_size is None:
                first_size = image_size(image_path)
            intr.setdefault("w", first_size[0])
            intr.setdefault("h", first_size[1])
        camera = _camera(intr, c2w, where)
        frames.append(Frame(name=image_path.stem, image_path=image_path, camera=camera))

    points = _read_points(root, data.get("ply_file_path"), path)
    return PosedFrames(frames=frames, skipped=skipped, points=points,
                       white_background=white_background, source=path.name)


def white_background_of(data: dict) -> bool:
    """The background RGBA frames are composited on (module docstring): the file's
    ``white_background`` if it says, else white for Blender-style files, else black."""
    frames = data.get("frames") if isinstance(data.get("frames"), list) else []
    blender_style = "camera_angle_x" in data and not any(
        "fl_x" in f for f in [data, *frames] if isinstance(f, dict)
    )
    return bool(data.get("white_background", blender_style))


def _stem(base: Path) -> str:
    """The frame name a missing image would have had (Blender paths have no extension)."""
    return base.stem if base.suffix in IMAGE_EXTENSIONS else base.name


def _clean_relpath(file_path: str) -> str:
    file_path = file_path.strip().replace("\\", "/")
    while file_path.startswith("./"):
        file_path = file_path[2:]
    return file_path


def _matrix(value: Any, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise CaptureError(f"{where}: 'transform_matrix' must be a finite 4x4 camera-to-world matrix")
    if abs(np.linalg.det(m[:3, :3])) < 1e-9:
        raise CaptureError(f"{where}: 'transform_matrix' has a singular rotation part")
    return m


def _number(intr: dict, key: str, where: str) -> float:
    value = intr[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):  # "44" is text, not a focal length
        raise CaptureError(f"{where}: '{key}' is not a number ({value!r:.40})")
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise CaptureError(f"{where}: '{key}' is not a number") from exc
    if not math.isfinite(v):
        raise CaptureError(f"{where}: '{key}' is not finite")
    return v


def _camera(intr: dict, c2w: np.ndarray, where: str) -> Camera:
    model = str(intr.get("camera_model", "OPENCV")).upper()
    if model not in SUPPORTED_MODELS:
        raise CaptureError(
            f"{where}: camera_model {model} is not supported (use OPENCV or PINHOLE; "
            "undistort fisheye images first, e.g. with ns-process-data or colmap image_undistorter)"
        )
    w, h = int(round(_number(intr, "w", where))), int(round(_number(intr, "h", where)))
    if "fl_x" in intr:
        fx = _number(intr, "fl_x", where)
    elif "camera_angle_x" in intr:
        fx = 0.5 * w / math.tan(0.5 * _number(intr, "camera_angle_x", where))
    else:
        raise CaptureError(f"{where}: no focal length (need 'fl_x' or 'camera_angle_x')")
    if "fl_y" in intr:
        fy = _number(intr, "fl_y", where)
    elif "camera_angle_y" in intr and "fl_x" not in intr:
        fy = 0.5 * h / math.tan(0.5 * _number(intr, "camera_angle_y", where))
    else:
        fy = fx
    cx = _number(intr, "cx", where) if "cx" in intr else w / 2.0
    cy = _number(intr, "cy", where) if "cy" in intr else h / 2.0
    dist = {k: _number(intr, k, where) if k in intr else 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if model != "OPENCV" and any(dist[k] != 0.0 for k in dist):
        raise CaptureError(f"{where}: camera_model {model} cannot have distortion coefficients")
    if dist["k3"] != 0.0 or dist["k4"] != 0.0:
        raise CaptureError(f"{where}: only k1 k2 p1 p2 distortion is supported (k3/k4 must be 0)")
    try:
        return Camera(width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy, c2w=c2w,
                      k1=dist["k1"], k2=dist["k2"], p1=dist["p1"], p2=dist["p2"])
    except ValueError as exc:
        raise CaptureError(f"{where}: {exc}") from exc


def _read_points(root: Path, ply: Any, path: Path) -> np.ndarray | None:
    """SfM points from nerfstudio's ``ply_file_path`` (already in the transforms' world frame)."""
    if not isinstance(ply, str):
        return None
    ply_path = root / _clean_relpath(ply)
    if not ply_path.is_file():
        return None
    try:
        import trimesh

        cloud = trimesh.load(ply_path, process=False)
        pts = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    except Exception as exc:  # a broken optional point cloud is not worth failing the capture
        import warnings

        warnings.warn(f"{ply_path}: cannot read point cloud ({exc}); ignoring it", stacklevel=2)
        return None
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    return pts if len(pts) else None
