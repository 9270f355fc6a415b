"""The NeuS / IDR capture layout (DTU, BlendedMVS as SDF methods ship them) -> frames with cameras.

```
CAPTURE/
  image/ (or images/)   the frames, PNG or JPEG; image i is the i-th file in sorted order
  mask/                 optional object masks (PNG, 0/255, 3- or 1-channel), paired with the
                        images by sorted order: DTU has image/000000.png with mask/000.png
  cameras_sphere.npz    world_mat_i: 4x4 whose top 3x4 is the projection P = K [R|t];
                        scale_mat_i: 4x4 mapping the unit sphere into the world
```
Other keys (``camera_mat_i``, ``*_inv_i``) are ignored, as NeuS ignores them.

- Cameras stay in the npz's world (the frame of P). P is split by OpenCV
  (``decomposeProjectionMatrix``) into K (scaled so K[2,2] = 1), R and the camera centre,
  and R, t = -R C become an OpenGL camera-to-world with the same conversion the COLMAP
  loader uses. Skew is dropped when it moves no pixel by more than half a pixel, else
  refused. P's pixel coordinates are taken as this project's (pixel centres at +0.5, as
  nerfstudio and sdfstudio read DTU), where NeuS samples rays at integer coordinates: the
  two differ by half a pixel.
- The region of interest is NeuS's unit sphere: ``scale_mat`` must be a uniform scale plus
  a translation, the same for every frame, and it becomes the capture's
  ``SceneNormalization`` as it is (centre = its translation, scale = its scale), so the
  sphere is the ball inscribed in the field's cube; ``region_of_interest`` is not used.
  Most cameras inside the sphere is refused (its scale_mat and the world_mat are then from
  two different worlds).
- ``mask/`` masks are exact object masks, so they are the frames' expert annotations
  (kind ``binary``: object = id 1); without a ``classes.json`` the class table is
  background (0) and object (1). ``load_capture`` lets an ``annotations/`` folder win over
  them, and ``annotated_frames`` choose which of them teach.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from ..cameras import Camera, w2c_cv_to_c2w_gl
from ..classes import ClassInfo, ClassMap
from ..errors import CaptureError
from .images import image_size, list_images
from .masks import MASK_EXTENSIONS
from .model import Frame, SceneNormalization
from .transforms import PosedFrames

NPZ_NAME = "cameras_sphere.npz"
IMAGE_FOLDERS = ("image", "images")
MASK_FOLDER = "mask"
SKEW_TOLERANCE_PX = 0.5  # the most that dropping K's skew may move a pixel
SCALE_RTOL = 1e-6
NEUS_CLASSES = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "object", (255, 255, 255))))
_KEY = re.compile(r"^(world_mat|scale_mat)_(\d+)$")


def find_neus(root: str | Path) -> Path | None:
    """``root/cameras_sphere.npz`` if the capture is in the NeuS layout, else None."""
    path = Path(root) / NPZ_NAME
    return path if path.is_file() else None


def read_neus(npz_path: str | Path) -> PosedFrames:
    """Load a NeuS capture: cameras, the unit-sphere normalisation, object masks as annotations."""
    npz_path = Path(npz_path)
    root = npz_path.parent
    image_dir = next((root / d for d in IMAGE_FOLDERS if (root / d).is_dir()), None)
    if image_dir is None:
        raise CaptureError(f"{root}: {NPZ_NAME} but no image/ (or images/) folder with the frames")
    images = list_images(image_dir)
    n = len(images)
    where_images = f"{n} images in {image_dir.name}/"

    mats = _load_npz(npz_path)
    for kind in ("world_mat", "scale_mat"):
        found = mats[kind]
        missing = [i for i in range(n) if i not in found]
        first = f"{kind}_{missing[0]}" + (f" and {len(missing) - 1} more" if len(missing) > 1 else "") if missing else ""
        if len(found) != n:
            raise CaptureError(
                f"{npz_path}: {len(found)} {kind}_i for {where_images}" + (f" (missing {first})" if first else "")
                + "; image i is the i-th image in sorted order, so the counts must match"
            )
        if missing:
            raise CaptureError(f"{npz_path}: missing {first} ({where_images})")

    normalization = _normalization(mats["scale_mat"], n, npz_path)
    masks = _masks(root / MASK_FOLDER, n, where_images)
    frames: list[Frame] = []
    for i, image_path in enumerate(images):
        w, h = image_size(image_path)
        camera = camera_from_projection(mats["world_mat"][i], w, h, f"{npz_path}: world_mat_{i}",
                                        target=normalization.center)
        frames.append(Frame(name=image_path.stem, image_path=image_path, camera=camera,
                            annotation_path=masks[i] if masks else None))
    _check_cameras_outside(frames, normalization, npz_path)
    return PosedFrames(
        frames=frames, source=NPZ_NAME, normalization=normalization, classes=NEUS_CLASSES,
        mask_kinds={root / MASK_FOLDER: "binary"} if masks else {},
    )


def _check_cameras_outside(frames: list[Frame], sphere: SceneNormalization, path: Path) -> None:
    """NeuS frames an object inside the unit sphere from cameras outside it. Most cameras
    inside it means scale_mat_i and world_mat_i are not in one world (a file whose world_mat_i
    were normalised already, say): the field would model a region around the cameras."""
    inside = sum(np.linalg.norm(f.camera.center - sphere.center) < sphere.scale for f in frames)
    if inside > len(frames) // 2:
        centre = ", ".join(f"{v:.3g}" for v in sphere.center)
        raise CaptureError(
            f"{path}: {inside} of {len(frames)} cameras lie inside the unit sphere of scale_mat_0 (centre {centre}, "
            f"radius {sphere.scale:.3g}); the object must be inside it and the cameras outside "
            "(are world_mat_i and scale_mat_i in the same world?)"
        )


def camera_from_projection(
    P: np.ndarray, width: int, height: int, where: str, target: np.ndarray | None = None
) -> Camera:
    """A 3x4 (or 4x4 with it on top) projection K [R|t] -> Camera (OpenGL camera-to-world).

    Refused, one line starting with ``where``: a wrong shape, non-finite values, a singular
    left 3x3, a mirrored frame, significant skew, or ``target`` (a point the camera must
    see, e.g. the unit sphere's centre) behind the camera.
    """
    m = np.asarray(P, dtype=np.float64)
    if m.shape == (4, 4):
        m = m[:3]
    if m.shape != (3, 4):
        raise CaptureError(f"{where}: expected a 4x4 (or 3x4) projection matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise CaptureError(f"{where}: the projection matrix has non-finite values")
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(m[:, :3])
    if not np.isfinite(cond) or cond > 1e12:
        raise CaptureError(f"{where}: not a projection matrix (its left 3x3 part is singular)")
    if np.linalg.det(m[:, :3]) < 0:
        m = -m  # P and -P project alike; det > 0 makes the camera look at what it projects
    K, R, centre = cv2.decomposeProjectionMatrix(m)[:3]
    D = np.diag(np.sign(np.diag(K)))  # RQ leaves the signs free: make K's diagonal positive
    K, R = K @ D, D @ R
    K = K / K[2, 2]
    if np.linalg.det(R) < 0.5:
        raise CaptureError(f"{where}: not a camera (the rotation is a reflection)")
    c = centre[:3, 0] / centre[3, 0]
    t = -R @ c
    if target is not None and float((R @ np.asarray(target, dtype=np.float64) + t)[2]) <= 0:
        raise CaptureError(f"{where}: the unit sphere's centre is behind this camera (is P = K [R|t] with OpenCV axes?)")
    fx, fy, cx, cy, skew = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(K[0, 1])
    shift = abs(skew) * max(abs(cy), abs(height - cy)) / fy
    if shift > SKEW_TOLERANCE_PX:
        raise CaptureError(
            f"{where}: K has skew {skew:.3g}, which moves pixels by up to {shift:.2g} px; only zero-skew cameras are supported"
        )
    try:
        return Camera(width=int(width), height=int(height), fx=fx, fy=fy, cx=cx, cy=cy, c2w=w2c_cv_to_c2w_gl(R, t))
    except ValueError as exc:
        raise CaptureError(f"{where}: {exc}") from exc


def _load_npz(path: Path) -> dict[str, dict[int, np.ndarray]]:
    """world_mat_i / scale_mat_i by kind and index; a file np.load cannot read is one line."""
    out: dict[str, dict[int, np.ndarray]] = {"world_mat": {}, "scale_mat": {}}
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):  # a plain .npy under the npz's name
            raise CaptureError(f"{path}: not an npz archive (expected world_mat_i and scale_mat_i arrays)")
        with data:
            for key in data.files:
                match = _KEY.match(key)
                if match:
                    out[match[1]][int(match[2])] = np.asarray(data[key])
    except CaptureError:
        raise
    except Exception as exc:  # noqa: BLE001 - zip, pickle and format errors all mean "cannot read"
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise CaptureError(f"{path}: cannot read ({type(exc).__name__}: {msg})") from exc
    return out


def _normalization(scale_mats: dict[int, np.ndarray], n: int, path: Path) -> SceneNormalization:
    """The one uniform scale + translation every scale_mat_i must be."""
    first = np.asarray(scale_mats[0], dtype=np.float64)
    for i in range(n):
        s = np.asarray(scale_mats[i], dtype=np.float64)
        key = f"{path}: scale_mat_{i}"
        if s.shape != (4, 4) or not np.all(np.isfinite(s)):
            raise CaptureError(f"{key}: expected a finite 4x4 matrix, got shape {s.shape}")
        scale = s[0, 0]
        tol = SCALE_RTOL * max(abs(scale), 1e-12)
        if scale <= 0 or np.abs(s[:3, :3] - scale * np.eye(3)).max() > tol or np.abs(s[3] - [0, 0, 0, 1]).max() > tol:
            raise CaptureError(f"{key}: not a uniform scale plus translation (diagonal {np.diag(s)[:3].tolist()})")
        if np.abs(s - first).max() > tol + SCALE_RTOL * np.abs(first[:3, 3]).max():
            raise CaptureError(f"{key}: differs from scale_mat_0 (one unit sphere for all frames is expected)")
    return SceneNormalization(center=first[:3, 3].copy(), scale=float(first[0, 0]))


def _masks(folder: Path, n: int, where_images: str) -> list[Path]:
    """The object masks paired with the images by sorted order ([] without a mask/ folder)."""
    if not folder.is_dir():
        return []
    for p in sorted(folder.iterdir()):
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in (".jpg", ".jpeg"):
            raise CaptureError(f"{p}: masks must be PNG (JPEG compression changes class ids at edges)")
    masks = _listed(folder, MASK_EXTENSIONS)
    if len(masks) != n:
        raise CaptureError(
            f"{folder}: {len(masks)} masks for {where_images}; masks pair with images by sorted order, "
            "so the counts must match"
        )
    return masks


def _listed(folder: Path, extensions: tuple[str, ...]) -> list[Path]:
    """Files of ``folder`` with one of ``extensions``, sorted by name (NeuS sorts the same way);
    hidden and other files (DTU ships a one-byte ``a`` in image/ and mask/) are skipped."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and not p.name.startswith(".") and p.suffix in extensions)
