"""What every export format shares: the frame record, where files go (a folder or a zip), the
confidence threshold, image encoding and the export's README."""

from __future__ import annotations

import textwrap
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ... import __version__
from ...classes import IGNORE_ID, ClassMap
from ..dataset import ExportError


@dataclass
class ExportFrame:
    """One frame to export. ``name`` is the image stem (files are named after it)."""

    name: str
    mask: np.ndarray
    """(H, W) class ids, 255 = ignore."""
    image: np.ndarray | None = None
    """(H, W, 3) uint8 RGB; None writes no image (the annotations alone)."""
    confidence: np.ndarray | None = None
    """(H, W) in [0, 1]: pixels below the export's ``min_confidence`` become ignore, and COCO's
    ``score`` of a region is its mean. None: every pixel counts as certain."""
    annotated: bool = False
    """Whether an expert annotated this frame (``--frames unannotated`` leaves it out)."""


def checked_mask(frame: ExportFrame, classes: ClassMap, min_confidence: float | None) -> np.ndarray:
    """The frame's mask as uint8 ids with ignore where its confidence is below ``min_confidence``;
    an ExportError names the frame when its arrays do not fit or hold ids not in the table."""
    what = f"frame {frame.name!r}"
    mask = np.asarray(frame.mask)
    if mask.ndim != 2 or not np.issubdtype(mask.dtype, np.integer):
        raise ExportError(f"{what}: a mask must be (H, W) integer class ids, got {mask.dtype} {mask.shape}")
    valid = np.zeros(256, dtype=bool)
    valid[classes.ids] = True
    valid[IGNORE_ID] = True
    if mask.size and (mask.min() < 0 or mask.max() > 255 or not valid[mask.astype(np.uint8)].all()):
        bad = sorted(set(np.unique(mask).tolist()) - set(np.nonzero(valid)[0].tolist()))
        raise ExportError(f"{what}: class ids {bad} are not in the class table")
    mask = mask.astype(np.uint8, copy=True)
    if frame.image is not None:
        image = np.asarray(frame.image)
        if image.shape != (*mask.shape, 3) or image.dtype != np.uint8:
            raise ExportError(f"{what}: image must be uint8 {mask.shape[1]}x{mask.shape[0]} RGB like its mask, "
                              f"got {image.dtype} {image.shape}")
    if frame.confidence is not None:
        conf = np.asarray(frame.confidence, dtype=np.float32)
        if conf.shape != mask.shape:
            raise ExportError(f"{what}: confidence is {conf.shape} but the mask is {mask.shape}")
        if min_confidence is not None:
            mask[conf < min_confidence] = IGNORE_ID
    return mask


def png_image(image: np.ndarray) -> bytes:
    """RGB uint8 -> PNG bytes (lossless: the exported frames are the pixels the masks belong to)."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 HxWx3 array
        raise ExportError("cannot encode an image as PNG")
    return buf.tobytes()


def distinct_colors(classes: ClassMap, reserved: Sequence[tuple[tuple[int, int, int], str]] = ()) -> None:
    """Colour masks tell classes apart by colour alone: two classes (or a class and a colour the
    format reserves, e.g. VOC's void) with one colour are an ExportError naming them."""
    seen: dict[tuple[int, int, int], str] = {tuple(int(v) for v in rgb): what for rgb, what in reserved}
    for c in classes.classes:
        rgb = tuple(int(v) for v in c.color)
        if rgb in seen:
            raise ExportError(f"class table: '{c.name}' and {seen[rgb]} share the colour {','.join(map(str, rgb))}; "
                              "a colour mask cannot tell them apart (give them distinct colours in classes.json)")
        seen[rgb] = f"'{c.name}'"  # type: ignore[index]


class Sink:
    """Where an export's files go: a folder, or a zip (PNGs stored as they are, text deflated)."""

    def __init__(self, root: Path | None = None, archive: zipfile.ZipFile | None = None) -> None:
        self.root, self.archive = root, archive

    def write(self, relpath: str, data: bytes | str) -> None:
        if isinstance(data, str):
            data = data.encode("utf-8")
        if self.archive is not None:
            compress = zipfile.ZIP_STORED if relpath.lower().endswith(".png") else zipfile.ZIP_DEFLATED
            self.archive.writestr(relpath, data, compress_type=compress)
            return
        assert self.root is not None
        path = self.root / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def layout_of(doc: str | None) -> str:
    """The file tree a format module's docstring shows (its ``::`` block), for the README."""
    block = (doc or "").split("::", 1)[-1].lstrip("\n").split("\n\n")[0]
    return textwrap.dedent(block)


def readme_text(fmt: str, layout: str, classes: ClassMap, names: Sequence[str], flagged: Sequence[str],
                min_confidence: float | None, ignore: str, source: str | None) -> str:
    """README.txt of an export: what it holds, how ignore is written, which frames to review first."""
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    lines = [
        f"labelsynth export ({fmt}): {len(names)} frames" + (f" from {source}" if source else ""),
        f"made by labelsynth {__version__} on {stamp}",
        "",
        "layout:",
        textwrap.indent(layout.rstrip(), "  "),
        "",
        "classes (id, name, colour r,g,b):",
        *[f"  {c.id:3d}  {c.name}  {','.join(str(v) for v in c.color)}" for c in classes.classes],
        "",
        (f"ignore: pixels whose confidence is below {min_confidence:g} and pixels the masks left unlabelled: {ignore}"
         if min_confidence is not None else f"ignore: pixels the masks left unlabelled (if any): {ignore}"),
        "",
    ]
    in_export = set(names)
    if flagged:
        lines.append("flagged frames (their input mask disagrees with the field's; review them first):")
        lines += [f"  {n}" + ("" if n in in_export else "  (not in this export)") for n in flagged]
    else:
        lines.append("flagged frames: none (or no consistency report was made)")
    lines += ["", "frames:", *[f"  {n}" for n in names], ""]
    return "\n".join(lines)
