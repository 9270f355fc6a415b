"""The review screen's pictures: every frame as a thumbnail with the field's mask over it, and a
large view of it (the frame, its input mask, the field's mask, their difference).

Sizes are what keep report.html one file that still opens quickly: a thumbnail is a small JPEG
with the mask painted in; a large view is the frame once as a JPEG of moderate size plus each
mask as a palette PNG with transparency (a few kB: masks are flat colours), laid over the frame
by the page, so the frame's pixels are not repeated in every panel.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from PIL import Image

from ..classes import IGNORE_ID, WOUND_BED, ClassMap

THUMB_SIDE = 176
"""Long side of a thumbnail in pixels."""
VIEW_SIDE = 640
"""Long side of the large view's pictures (frames are never enlarged)."""
THUMB_QUALITY = 80
VIEW_QUALITY = 82
MASK_ALPHA = 0.5
"""Opacity of a class colour over the frame."""

# difference colours: what only the input calls wound bed, what only the field does, where both
# do but name different tissues
ONLY_INPUT = (230, 30, 30)
ONLY_FIELD = (30, 90, 240)
OTHER_TISSUE = (250, 200, 0)


@dataclass
class Panel:
    """One picture of the large view: a transparent PNG laid over the frame."""

    title: str
    png: bytes
    note: str = ""


@dataclass
class FrameView:
    """What the page shows of one frame."""

    name: str
    thumb: bytes
    """JPEG, the field's mask painted over the frame."""
    frame: bytes
    """JPEG of the frame at the large view's size."""
    width: int
    height: int
    """Size of ``frame`` (and of every panel)."""
    panels: list[Panel] = field(default_factory=list)
    pixels: int = 0
    """Pixels of the frame at its own size."""


def _fit(shape: tuple[int, int], side: int) -> tuple[int, int]:
    """(width, height) with the long side at most ``side`` (never enlarged)."""
    h, w = shape
    scale = min(1.0, side / max(h, w))
    return max(1, round(w * scale)), max(1, round(h * scale))


def _resize(image: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    if (image.shape[1], image.shape[0]) == size:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - any uint8 HxWx3 encodes
        raise ValueError("cannot encode a JPEG")
    return buf.tobytes()


def _palette_png(index: np.ndarray, colours: Sequence[tuple[int, int, int]], alphas: Sequence[int]) -> bytes:
    """A palette PNG: ``index`` (H, W) into ``colours`` with one alpha per colour (tRNS)."""
    img = Image.fromarray(index.astype(np.uint8), mode="P")
    img.putpalette([v for c in colours for v in c])
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True, transparency=bytes(alphas))
    return buf.getvalue()


def mask_overlay(mask: np.ndarray, classes: ClassMap, size: tuple[int, int]) -> bytes:
    """A class-id mask as a transparent PNG of ``size``: class colours at ``MASK_ALPHA``,
    background clear, ignore a light veil."""
    mask = _resize(mask, size, nearest=True)
    ids = [c.id for c in classes.classes]
    lut = np.full(256, len(ids), dtype=np.uint8)  # ignore (and anything unknown)
    lut[ids] = np.arange(len(ids))
    colours = [tuple(int(v) for v in c.color) for c in classes.classes] + [(255, 255, 255)]
    bg = classes.classes[classes.background_index].id
    alphas = [0 if i == bg else round(255 * MASK_ALPHA) for i in ids] + [110]
    return _palette_png(lut[mask], colours, alphas)


def difference_overlay(reference: np.ndarray, other: np.ndarray, classes: ClassMap, size: tuple[int, int]) -> bytes:
    """Where two masks disagree, as a transparent PNG: red = wound bed only in ``reference``
    (the input), blue = only in ``other`` (the field), yellow = both wound bed but another
    tissue; ignore pixels of the input veiled, agreement clear."""
    reference, other = _resize(reference, size, nearest=True), _resize(other, size, nearest=True)
    wb = np.asarray(classes.wound_bed_ids)
    a, b = np.isin(reference, wb), np.isin(other, wb)
    index = np.zeros(reference.shape, dtype=np.uint8)
    index[a & ~b] = 1
    index[~a & b] = 2
    index[a & b & (reference != other)] = 3
    index[reference == IGNORE_ID] = 4
    return _palette_png(index, [(0, 0, 0), ONLY_INPUT, ONLY_FIELD, OTHER_TISSUE, (255, 255, 255)],
                        [0, 215, 215, 215, 110])


def thumbnail(image: np.ndarray, mask: np.ndarray, classes: ClassMap) -> bytes:
    """A small JPEG of the frame with the field's mask painted over it."""
    size = _fit(mask.shape, THUMB_SIDE)
    return jpeg(blend(_resize(image, size), _resize(mask, size, nearest=True), classes), THUMB_QUALITY)


def blend(image: np.ndarray, mask: np.ndarray, classes: ClassMap, alpha: float = MASK_ALPHA) -> np.ndarray:
    """The frame with the class colours of ``mask`` over it (background and ignore left as they are)."""
    colour = classes.colorize(mask).astype(np.float32)
    out = image.astype(np.float32)
    sel = (mask != classes.classes[classes.background_index].id) & (mask != IGNORE_ID)
    out[sel] = (1 - alpha) * out[sel] + alpha * colour[sel]
    return out.astype(np.uint8)


def frame_view(name: str, image: np.ndarray, field_mask: np.ndarray, classes: ClassMap, *,
               input_mask: np.ndarray | None = None, input_kind: str = "input",
               judge_mask: np.ndarray | None = None) -> FrameView:
    """The thumbnail and large view of one frame. Panels: the input mask (when the frame has
    one), the field's mask, the field without this frame (``judge_mask``: an annotated frame's
    leave-one-out mask, which judged it), and the difference between the input and the mask
    that judged it (``judge_mask``, else the field's)."""
    size = _fit(field_mask.shape, VIEW_SIDE)
    panels = []
    if input_mask is not None:
        panels.append(Panel(f"input mask ({input_kind})", mask_overlay(input_mask, classes, size)))
    panels.append(Panel("field's mask", mask_overlay(field_mask, classes, size), "what masks/ holds"))
    if judge_mask is not None:
        panels.append(Panel("field without this frame", mask_overlay(judge_mask, classes, size),
                            "the semantic stage refitted without this frame"))
    if input_mask is not None:
        against = judge_mask if judge_mask is not None else field_mask
        panels.append(Panel("difference", difference_overlay(input_mask, against, classes, size),
                            "red: wound bed only in the input; blue: only in the field"
                            + (" without this frame" if judge_mask is not None else "")
                            + "; yellow: another tissue"))
    return FrameView(name, thumbnail(image, field_mask, classes), jpeg(_resize(image, size), VIEW_QUALITY),
                     size[0], size[1], panels, int(field_mask.size))


def review_order(frames: Sequence[Mapping]) -> list[str]:
    """Frame names in the order an annotator should look at them: flagged frames first, then
    by how well their input agrees with the field (worst first: leave-one-out Dice for an
    annotated frame, else agreement, wound bed), frames with no input last, in capture order."""
    def score(f: Mapping) -> float | None:
        for key in ("loo_dice", "agreement"):
            value = (f.get(key) or {}).get(WOUND_BED)
            if value is not None:
                return float(value)
        return None

    def key(item: tuple[int, Mapping]) -> tuple:
        i, f = item
        s = score(f)
        return (not f.get("flagged"), s is None, s if s is not None else 0.0, i)

    return [f["name"] for _, f in sorted(enumerate(frames), key=key)]
