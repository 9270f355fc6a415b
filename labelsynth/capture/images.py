"""The one pixel reader and lister of frames: (H,W,3) uint8 RGB, whatever the file's bit depth
or channel count, and the frames of an images folder.

Images are read with OpenCV's ``IMREAD_UNCHANGED`` so that alpha survives (Blender scenes
are RGBA) and EXIF orientation is *not* applied: poses from COLMAP and nerfstudio refer to
the stored pixel grid, so rotating the pixels would break the cameras.

Alpha policy: an RGBA frame is composited over its capture's background, white or black
(``capture.load.capture_white_background``: what ``transforms.json`` says, white for
Blender-style files, black otherwise). The capture loader's compositing is the reference:
the field, the input check and the 2D segmenter (``segment``) all read frames through
``read_image`` with that choice, so every consumer sees the same pixels.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import CaptureError

IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")  # compared with the suffix lower-cased


def header_size(path: str | Path, what: str = "image") -> tuple[int, int]:
    """(width, height) of an image or mask file from its header only (no pixel decoding)."""
    from PIL import Image

    path = Path(path)
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (OSError, ValueError) as exc:
        raise CaptureError(f"{path}: cannot read {what} ({exc})") from exc


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image from its header only (cheap: no pixel decoding)."""
    return header_size(path, "image")


def list_images(folder: str | Path) -> list[Path]:
    """The frames of an images folder, sorted by name: PNG or JPEG (any case of the suffix);
    hidden files (``._frame.png`` from macOS, ``.DS_Store``), folders and other files are skipped;
    a broken symbolic link with an image's name is an error.

    One rule for every consumer (``segment``, ``poses``, the NeuS loader), so they agree on
    what the frames are. A missing folder, a folder without images, or two images with the
    same stem (masks are named by stem) is a one-line ``CaptureError`` naming the path.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: images folder not found")
    named = [p for p in folder.iterdir() if not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES]
    for p in named:  # a broken link is an image the user thinks is there: an error, not a skip
        if p.is_symlink() and not p.exists():
            raise CaptureError(f"{p}: {not_a_file(p)} (expected an image)")
    paths = sorted(p for p in named if p.is_file())
    if not paths:
        raise CaptureError(f"{folder}: no PNG or JPEG images")
    seen: dict[str, Path] = {}
    for p in paths:
        if p.stem in seen:
            raise CaptureError(f"{p}: same stem as {seen[p.stem].name}; frames and masks are matched by stem")
        seen[p.stem] = p
    return paths


def _to_uint8(img: np.ndarray, path: Path) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    if img.dtype in (np.float32, np.float64):  # e.g. EXR/TIFF in [0, 1]
        return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    raise CaptureError(f"{path}: unsupported image pixel type {img.dtype}")


def read_image(
    path: str | Path,
    size: tuple[int, int] | None = None,
    white_background: bool = False,
) -> np.ndarray:
    """Read an image as (H,W,3) uint8 RGB.

    RGBA is composited on white (``white_background``, the Blender convention) or black;
    grayscale is replicated to RGB; 16-bit is scaled to 8-bit. ``size`` = (width, height)
    the camera expects: a different size is an error, since intrinsics would not fit.
    """
    path = Path(path)
    check_complete(path)
    try:  # np.fromfile + imdecode copes with non-ASCII paths where cv2.imread may not
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError:
        data = np.zeros(0, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise CaptureError(f"{path}: cannot read image ({_unreadable_reason(path)})")
    img = _to_uint8(img, path)
    if img.ndim == 2:
        rgb = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 1:
        rgb = np.repeat(img, 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 3:
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        rgb = composite_alpha(cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA), white_background)
    else:
        raise CaptureError(f"{path}: unsupported image layout {img.shape}")
    if size is not None:
        w, h = int(size[0]), int(size[1])
        if rgb.shape[1] != w or rgb.shape[0] != h:
            raise CaptureError(
                f"{path}: image is {rgb.shape[1]}x{rgb.shape[0]} but its camera expects {w}x{h}"
            )
    return np.ascontiguousarray(rgb)


_END_MARKERS = {".png": b"IEND\xaeB`\x82", ".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9"}


def check_complete(path: str | Path) -> None:
    """Raise a ``CaptureError`` if a PNG or JPEG stops before its end marker.

    Run before OpenCV decodes: it reads a truncated JPEG without an error (the missing rows
    come out grey, and the geometry would learn them), and for both formats it prints
    libpng/libjpeg complaints on stderr among our own messages. Only the file's last bytes are
    read; a file that does not end with its marker (truncated, or with data appended, as phone
    "motion photos" do) is decoded once by PIL, which tells the two apart.
    """
    from PIL import Image

    path = Path(path)
    marker = _END_MARKERS.get(path.suffix.lower())
    if marker is None or not path.is_file():
        return  # other formats: OpenCV's word; a missing file: read_image says so
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        fh.seek(max(0, fh.tell() - 64))
        tail = fh.read()
    if tail.rstrip(b"\x00\r\n\t ").endswith(marker):
        return
    try:
        with Image.open(path) as im:
            im.load()
    except OSError as exc:
        if "truncated" in str(exc):
            raise CaptureError(f"{path}: cannot read image (file is truncated)") from exc
    except (ValueError, SyntaxError):
        pass  # not PIL's to judge: OpenCV decides below


def _unreadable_reason(path: Path) -> str:
    """Why OpenCV returned nothing, in words a user can act on."""
    from PIL import Image

    if not path.is_file():
        return "file not found"
    if path.stat().st_size == 0:
        return "empty file"
    try:
        with Image.open(path) as im:
            im.load()
    except OSError as exc:
        if "truncated" in str(exc):
            return "file is truncated"
        return "not an image OpenCV can read"
    except (ValueError, SyntaxError):
        return "not an image OpenCV can read"
    return "OpenCV cannot decode it"


def write_image(path: str | Path, rgb: np.ndarray, *, jpeg_quality: int | None = None) -> Path:
    """Write (H,W,3) uint8 RGB (or (H,W) grey) as PNG/JPEG by the suffix (JPEG at ``jpeg_quality``,
    1..100, else OpenCV's 95); one-line error naming the file."""
    path = Path(path)
    img = np.ascontiguousarray(rgb)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if jpeg_quality and path.suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(path.suffix or ".png", img, params)
    if not ok:
        raise CaptureError(f"{path}: could not encode image")
    try:
        path.write_bytes(buf.tobytes())
    except OSError as exc:
        raise CaptureError(f"{path}: could not write image ({exc.strerror or exc})") from exc
    return path


def composite_alpha(rgba: np.ndarray, white_background: bool) -> np.ndarray:
    """(H,W,4) uint8 RGBA -> (H,W,3) uint8 RGB over a white or black background."""
    rgb = rgba[:, :, :3].astype(np.float32)
    alpha = rgba[:, :, 3:4].astype(np.float32) / 255.0
    bg = 255.0 if white_background else 0.0
    out = rgb * alpha + bg * (1.0 - alpha)
    return (out + 0.5).astype(np.uint8)


def not_a_file(path: Path) -> str | None:
    """Why an entry that is there cannot be read as a file (a folder, a dangling or looping
    symbolic link), or None: such an entry is an error, never a file that is merely missing."""
    if path.is_symlink() and not path.exists():
        return "a symbolic link that leads nowhere (or to itself)"
    if path.exists() and not path.is_file():
        return "a folder, not a file"
    return None


def find_image(base: Path) -> Path | None:
    """``base`` itself if it exists, else ``base`` + a known image extension (Blender's
    ``file_path`` has none), else None. An entry that is there but is no file (a folder, a
    broken link, an ``images`` that is a file) is a one-line ``CaptureError``."""
    if base.parent.exists() and not base.parent.is_dir():
        raise CaptureError(f"{base.parent}: not a folder (the capture's images are read from it)")
    problem = not_a_file(base)
    if problem:
        raise CaptureError(f"{base}: {problem} (expected an image)")
    if base.is_file():
        return base
    for ext in IMAGE_EXTENSIONS:
        candidate = base.with_name(base.name + ext)
        if candidate.is_file():
            return candidate
    return None
