"""A COLMAP sparse model (``sparse/0``, binary or text) -> frames with cameras and SfM points.

Read with pycolmap, so both formats and every COLMAP version pycolmap knows are handled by
COLMAP's own reader. COLMAP's world-to-camera poses (OpenCV axes) become OpenGL
camera-to-world matrices; the world frame itself is kept as is, so the points stay valid.
Images are looked up as ``CAPTURE/images/<name in the model>``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera, w2c_cv_to_c2w_gl
from ..errors import CaptureError
from .images import find_image
from .model import Frame
from .transforms import PosedFrames

MODEL_FILES = ("cameras.bin", "cameras.txt")


def find_sparse_model(root: str | Path) -> Path | None:
    """``root/sparse/0`` (COLMAP's layout), or ``root/sparse`` when it holds the model directly."""
    root = Path(root)
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if any((candidate / f).is_file() for f in MODEL_FILES):
            return candidate
    return None


def camera_from_colmap(cam, c2w: np.ndarray, where: str) -> Camera:
    """pycolmap.Camera (+ pose) -> Camera; models with more than k1 k2 p1 p2 are refused."""
    name = str(cam.model_name)
    p = [float(v) for v in np.asarray(cam.params, dtype=np.float64)]
    if name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        kw = dict(fx=f, fy=f, cx=cx, cy=cy)
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
        kw = dict(fx=fx, fy=fy, cx=cx, cy=cy)
    elif name == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        kw = dict(fx=f, fy=f, cx=cx, cy=cy, k1=k)
    elif name == "RADIAL":
        f, cx, cy, k1, k2 = p
        kw = dict(fx=f, fy=f, cx=cx, cy=cy, k1=k1, k2=k2)
    elif name == "OPENCV" or (name == "FULL_OPENCV" and not any(p[8:])):
        fx, fy, cx, cy, k1, k2, p1, p2 = p[:8]
        kw = dict(fx=fx, fy=fy, cx=cx, cy=cy, k1=k1, k2=k2, p1=p1, p2=p2)
    else:
        raise CaptureError(
            f"{where}: COLMAP camera model {name} is not supported (use SIMPLE_PINHOLE, PINHOLE, "
            "SIMPLE_RADIAL, RADIAL or OPENCV, or undistort with colmap image_undistorter)"
        )
    try:
        return Camera(width=int(cam.width), height=int(cam.height), c2w=c2w, **kw)
    except ValueError as exc:
        raise CaptureError(f"{where}: {exc}") from exc


def read_colmap(model_dir: str | Path, images_dir: str | Path) -> PosedFrames:
    """Load a sparse model; frames whose image file is missing are reported in ``skipped``."""
    import pycolmap

    model_dir, images_dir = Path(model_dir), Path(images_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with COLMAP's check text
        msg = " ".join(str(exc).split())
        raise CaptureError(f"{model_dir}: cannot read COLMAP model ({msg})") from exc

    frames: list[Frame] = []
    skipped: list[str] = []
    for image_id in sorted(rec.images, key=lambda i: rec.images[i].name):
        image = rec.images[image_id]
        if not image.has_pose:
            continue
        cfw = image.cam_from_world
        cfw = cfw() if callable(cfw) else cfw  # a method in pycolmap >= 3.12, a property before
        m = np.asarray(cfw.matrix(), dtype=np.float64)  # (3,4) world-to-camera, OpenCV axes
        c2w = w2c_cv_to_c2w_gl(m[:, :3], m[:, 3])
        where = f"{model_dir}: image {image.name}"
        camera = camera_from_colmap(rec.cameras[image.camera_id], c2w, where)
        path = find_image(images_dir / image.name)
        if path is None:
            skipped.append(Path(image.name).stem)
            continue
        frames.append(Frame(name=path.stem, image_path=path, camera=camera))

    points = None
    if rec.num_points3D() > 0:
        pts = rec.points3D
        points = np.array([pts[i].xyz for i in sorted(pts)], dtype=np.float64).reshape(-1, 3)
    return PosedFrames(frames=frames, skipped=skipped, points=points, source=f"colmap:{model_dir}")
