"""Masks in, masks out: every supported mask format becomes (H,W) uint8 class ids, 255 = ignore.

Formats read (the README, "The capture folder"):

- single-channel PNG of class ids (8 or 16 bit);
- palette PNG: indices are kept when each used index carries its own class's colour (our
  palette outputs of ``write_mask``); else, when the colours of every used index are class colours
  (Pascal VOC, CVAT exports with their own index order) pixels are mapped *by colour*;
  otherwise the indices are taken as class ids. Index 255 is always ignore (VOC's void);
- RGB(A) colour PNG, mapped through the colour table (``classes.json`` colours, overridden
  by a CVAT ``labelmap.txt``); VOC's boundary colour (224,224,192) and the grey that
  ``ClassMap.colorize`` gives ignore (128,128,128) mean ignore, and fully
  transparent pixels are ignore. A grey RGB image whose values are all class ids is read
  as ids (some tools save id masks as RGB).

That is the ``classes`` kind, the default. A capture may say its masks in one folder are of
another kind (``Capture.mask_kinds``), read through the same ``read_mask``:

- ``binary``: object masks as NeuS / IDR ship them for DTU and BlendedMVS (3-channel or
  single-channel, 0/255): a pixel with any colour channel above half range is the object
  (id 1), every other pixel background (id 0).

Masks are opened with PIL, not OpenCV: OpenCV silently turns palette PNGs into BGR and the
indices are lost.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..classes import BACKGROUND_ID, IGNORE_ID, ClassMap
from ..errors import CaptureError, ClassMapError

ColorTable = dict[tuple[int, int, int], int]

VOC_BOUNDARY_COLOR: tuple[int, int, int] = (224, 224, 192)
IGNORE_COLOR: tuple[int, int, int] = (128, 128, 128)  # ClassMap.palette()/colorize() grey for 255
MASK_EXTENSIONS: tuple[str, ...] = (".png", ".PNG")
MASK_KINDS: tuple[str, ...] = ("classes", "binary")
BINARY_OBJECT_ID = 1  # what a binary object mask's foreground becomes


# --- colour tables ------------------------------------------------------------------------
def color_table_for(classes: ClassMap, labelmap: str | Path | None = None) -> ColorTable:
    """Colour -> class id: class colours, then CVAT ``labelmap.txt`` colours (which win),
    then VOC's boundary colour and our own ignore grey -> ignore (unless a class uses them)."""
    table: ColorTable = {}
    for c in classes.classes:
        table.setdefault(tuple(int(v) for v in c.color), c.id)
    if labelmap is not None:
        table.update(read_labelmap(labelmap, classes))
    table.setdefault(VOC_BOUNDARY_COLOR, IGNORE_ID)
    table.setdefault(IGNORE_COLOR, IGNORE_ID)
    return table


IGNORE_LABEL_NAMES: tuple[str, ...] = ("ignored", "ignore", "void")  # labelmap names meaning 255 (VOC's void)


def read_labelmap(path: str | Path, classes: ClassMap, *, strict: bool = False) -> ColorTable:
    """Parse CVAT's ``labelmap.txt`` (``name:r,g,b:parts:actions`` per line) into colour -> id.

    Names are matched to class names case-insensitively (``background`` is id 0; ``ignored``,
    ``ignore`` and ``void``, VOC's names for its void colour, are 255 unless a class has the
    name). Labels the class map does not know are skipped with a warning (a mask that uses
    their colour then fails with an "unknown colour" error, while unused labels do no harm),
    or, with ``strict`` (a CVAT export read as annotations), a one-line error listing them.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ClassMapError(f"{path}: cannot read labelmap ({exc})") from exc
    return labelmap_table(parse_labelmap(text, path), classes, path, strict=strict)


def parse_labelmap(text: str, where: str | Path) -> list[tuple[str, tuple[int, int, int]]]:
    """The (name, colour) entries of a CVAT / Pascal VOC ``labelmap.txt``; ``where`` names it in errors."""
    entries: list[tuple[str, tuple[int, int, int]]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split(":")
        try:
            name = fields[0].strip()
            rgb = tuple(int(v) for v in fields[1].split(","))
            if len(rgb) != 3 or not all(0 <= v <= 255 for v in rgb):
                raise ValueError("colour must be r,g,b in 0..255")
        except (IndexError, ValueError) as exc:
            raise ClassMapError(f"{where}: line {lineno} is not 'name:r,g,b:parts:actions' ({exc})") from exc
        entries.append((name, rgb))  # type: ignore[arg-type]
    return entries


def labelmap_table(
    entries: list[tuple[str, tuple[int, int, int]]], classes: ClassMap, where: str | Path, *, strict: bool = False
) -> ColorTable:
    """Colour -> class id for labelmap entries, matched to ``classes`` by name (``read_labelmap``)."""
    by_name = label_ids_by_name(classes)
    table: ColorTable = {}
    unknown: list[str] = []
    for name, rgb in entries:
        class_id = by_name.get(name.lower())
        if class_id is None:
            unknown.append(name)
            continue
        table[rgb] = class_id
    if unknown and strict:
        raise ClassMapError(f"{where}: label(s) not in the class table: {', '.join(unknown)} "
                            f"(classes: {', '.join(classes.names)})")
    if unknown:
        warnings.warn(
            f"{where}: {len(unknown)} label(s) not in the class map, ignored: {', '.join(unknown)}",
            stacklevel=3,
        )
    return table


def label_ids_by_name(classes: ClassMap) -> dict[str, int]:
    """Lower-cased label name -> class id, as annotation tools' files are matched to the class
    table: the class names, ``background`` for id 0, VOC's names for void -> 255."""
    by_name = {c.name.lower(): c.id for c in classes.classes}
    by_name.setdefault("background", BACKGROUND_ID)
    for name in IGNORE_LABEL_NAMES:
        by_name.setdefault(name, IGNORE_ID)
    return by_name


def labelmap_text(entries: list[tuple[str, tuple[int, int, int]]]) -> str:
    """A ``labelmap.txt`` as CVAT writes it: a header, then ``name:r,g,b::`` per label."""
    lines = ["# label:color_rgb:parts:actions"]
    lines += [f"{name}:{','.join(str(int(v)) for v in rgb)}::" for name, rgb in entries]
    return "\n".join(lines) + "\n"


# --- reading ------------------------------------------------------------------------------
def mask_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the PNG header, without decoding pixels (for a mask inside an
    annotation tool's export, from that file's index: ``capture.archives``)."""
    from . import archives
    from .images import header_size

    if archives.container_of(path) is not None:
        return archives.member_size(path)
    return header_size(path, "mask")


def mask_exists(path: str | Path) -> bool:
    """Whether a mask file, or a mask inside an annotation tool's export, is there."""
    from . import archives

    return Path(path).is_file() or archives.member_exists(path)


def read_mask(
    path: str | Path,
    size: tuple[int, int] | None,
    classes: ClassMap,
    color_table: ColorTable | None = None,
    kind: str = "classes",
) -> np.ndarray:
    """Read a mask file as (H,W) uint8 class ids (255 = ignore).

    ``size`` = (width, height) of the frame; a mask of another size, unknown ids or
    unknown colours raise a one-line ``CaptureError`` naming the file. ``kind`` says how the
    pixels are coded (see the module docstring): ``classes`` or ``binary``.
    """
    from PIL import Image

    from . import archives

    path = Path(path)
    if kind not in MASK_KINDS:
        raise ValueError(f"mask kind must be one of {', '.join(MASK_KINDS)}, not {kind!r}")
    if kind == "binary" and BINARY_OBJECT_ID not in classes.ids:
        raise CaptureError(f"{path}: a binary object mask needs class id {BINARY_OBJECT_ID} (object) in the class table")
    if color_table is None and kind == "classes":
        color_table = color_table_for(classes)
    if archives.container_of(path) is not None:
        return archives.read_member_mask(path, size, classes, color_table, kind)
    try:
        with Image.open(path) as im:
            return decode_mask_image(im, path, size, classes, color_table, kind)
    except CaptureError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise CaptureError(f"{path}: cannot read mask ({exc})") from exc


def decode_mask_image(
    im, path: Path, size: tuple[int, int] | None, classes: ClassMap, color_table: ColorTable | None, kind: str
) -> np.ndarray:
    """An opened PIL image -> (H,W) uint8 class ids (``read_mask``'s rules); ``path`` names it in errors."""
    im.load()
    mode = im.mode
    if size is not None and tuple(im.size) != (int(size[0]), int(size[1])):
        raise CaptureError(f"{path}: mask is {im.size[0]}x{im.size[1]} but its image is {int(size[0])}x{int(size[1])}")
    if color_table is None:
        color_table = color_table_for(classes)
    if kind == "binary":
        return _from_binary(im, path)
    if mode == "P":
        indices = np.asarray(im, dtype=np.uint8)
        palette = np.asarray(im.getpalette() or [], dtype=np.uint8).reshape(-1, 3)
        return _from_palette(indices, palette, classes, color_table, path)
    if mode in ("RGB", "RGBA"):
        return _from_color(np.asarray(im), classes, color_table, path)
    if mode == "LA":
        return _from_ids(np.asarray(im)[:, :, 0], classes, path)
    if mode in ("L", "1", "I", "I;16", "I;16B", "I;16L"):
        return _from_ids(np.asarray(im), classes, path)
    raise CaptureError(f"{path}: unsupported mask mode {mode!r}; use a single-channel PNG of class ids")


def _from_binary(im, path: Path) -> np.ndarray:
    """Object (any colour channel above half range) -> 1, else 0; alpha is not a colour."""
    mode = im.mode
    if mode == "P":
        im, mode = im.convert("RGB"), "RGB"
    a = np.asarray(im)
    if mode in ("RGB", "RGBA", "LA"):
        a = a[:, :, :3] if mode != "LA" else a[:, :, :1]
    elif mode not in ("L", "1", "I", "I;16", "I;16B", "I;16L"):
        raise CaptureError(f"{path}: unsupported mask mode {mode!r} for a binary object mask")
    if a.ndim == 2:
        a = a[:, :, None]
    half = 0 if mode == "1" else 127 if a.dtype == np.uint8 else 32767
    return (a > half).any(axis=2).astype(np.uint8) * np.uint8(BINARY_OBJECT_ID)


def _check_ids(ids: np.ndarray, classes: ClassMap, path: Path) -> np.ndarray:
    valid = np.zeros(65536 if ids.dtype != np.uint8 else 256, dtype=bool)
    valid[classes.ids] = True
    valid[IGNORE_ID] = True
    if ids.dtype not in (np.uint8, np.uint16):
        if ids.size and (ids.min() < 0 or ids.max() > 65535):
            raise CaptureError(f"{path}: mask values out of range ({int(ids.min())}..{int(ids.max())})")
        ids = ids.astype(np.uint16)
    bad = ~valid[ids]
    if bad.any():
        unknown = np.unique(ids[bad])
        shown = ", ".join(str(int(v)) for v in unknown[:8]) + (" ..." if len(unknown) > 8 else "")
        raise CaptureError(
            f"{path}: {int(bad.sum())} pixels have class ids not in the class map ({shown}); "
            f"known ids: {', '.join(str(int(i)) for i in classes.ids)} and 255 = ignore"
        )
    return ids.astype(np.uint8)


def _from_ids(ids: np.ndarray, classes: ClassMap, path: Path) -> np.ndarray:
    if ids.dtype == bool:
        ids = ids.astype(np.uint8)
    return _check_ids(ids, classes, path)


def _from_palette(
    indices: np.ndarray, palette: np.ndarray, classes: ClassMap, table: ColorTable, path: Path
) -> np.ndarray:
    used = [int(u) for u in np.unique(indices) if u != IGNORE_ID]
    colors = [tuple(int(v) for v in palette[u]) if u < len(palette) else None for u in used]
    own = {c.id: tuple(int(v) for v in c.color) for c in classes.classes}
    if all(own.get(u) == c for u, c in zip(used, colors)):  # our own outputs: ids with class colours
        return indices.copy()
    if used and all(c is not None and c in table for c in colors):
        lut = np.arange(256, dtype=np.uint8)
        for u, c in zip(used, colors):
            lut[u] = table[c]  # type: ignore[index]
        lut[IGNORE_ID] = IGNORE_ID
        return lut[indices]
    return _check_ids(indices, classes, path)


def _from_color(rgb: np.ndarray, classes: ClassMap, table: ColorTable, path: Path) -> np.ndarray:
    transparent = None
    if rgb.shape[2] == 4:
        transparent = rgb[:, :, 3] == 0
        rgb = rgb[:, :, :3]
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    packed = (rgb[:, :, 0].astype(np.uint32) << 16) | (rgb[:, :, 1].astype(np.uint32) << 8) | rgb[:, :, 2]
    uniq, inverse = np.unique(packed.ravel(), return_inverse=True)
    ids = np.full(len(uniq), -1, dtype=np.int64)
    for i, p in enumerate(uniq):
        ids[i] = table.get((int(p >> 16), int((p >> 8) & 255), int(p & 255)), -1)
    out = ids[inverse].reshape(packed.shape)
    unknown = out < 0
    if transparent is not None:
        unknown &= ~transparent
    if unknown.any():
        grey = (rgb[:, :, 0] == rgb[:, :, 1]) & (rgb[:, :, 1] == rgb[:, :, 2])
        if grey.all():  # an id mask saved as RGB: accept it only if every value is a class id
            try:
                return _check_ids(rgb[:, :, 0].copy(), classes, path)
            except CaptureError:
                pass
        ys, xs = np.nonzero(unknown)
        r, g, b = (int(v) for v in rgb[ys[0], xs[0]])
        raise CaptureError(
            f"{path}: {int(unknown.sum())} pixels have colours not in the class colours, "
            f"e.g. RGB ({r},{g},{b}) at x={int(xs[0])} y={int(ys[0])}; add it to classes.json or labelmap.txt"
        )
    if transparent is not None:
        out[transparent] = IGNORE_ID
    return out.astype(np.uint8)


# --- writing ------------------------------------------------------------------------------
def as_id_mask(mask: np.ndarray) -> np.ndarray:
    """A (H, W) uint8 class-id array from any integer array of ids in 0..255 (ValueError otherwise)."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"a mask must be 2-D (H, W) class ids, got shape {mask.shape}")
    if mask.dtype != np.uint8:
        if mask.size and (mask.min() < 0 or mask.max() > 255):
            raise ValueError("mask ids must be in 0..255")
        mask = mask.astype(np.uint8)
    return mask


def write_mask(
    path: str | Path, mask: np.ndarray, classes: ClassMap | None = None, *, palette: bool | None = None
) -> Path:
    """The one writer of class-id masks: (H,W) ids -> an 8-bit PNG whose pixel values are the ids.

    ``palette`` (default: when ``classes`` is given) writes a palette PNG whose palette shows
    the class colours in any image viewer; ids come back through PIL and ``read_mask``, but
    OpenCV expands palettes to colours. ``palette=False`` writes plain greyscale, which gives
    the ids back with PIL and ``cv2.imread(..., IMREAD_UNCHANGED)`` alike: the outputs
    (``OUT/masks``, ``segment``, ``synth``) use it. Ids are not checked against ``classes``
    (callers that must, check first); the parent folder is created. Returns ``path``.
    """
    mask = as_id_mask(mask)
    if palette is None:
        palette = classes is not None
    if palette and classes is None:
        raise ValueError("a palette mask needs the class table for its colours")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = encode_mask_png(mask, classes.palette() if palette else None)  # type: ignore[union-attr]
    try:
        path.write_bytes(data)  # works for non-ASCII paths where cv2.imwrite may not
    except OSError as exc:
        raise CaptureError(f"{path}: cannot write mask ({exc.strerror or exc})") from exc
    return path


def encode_mask_png(mask: np.ndarray, palette: list[int] | None = None) -> bytes:
    """(H,W) ids -> PNG bytes: greyscale, or a palette PNG (indices = the ids) with ``palette``
    (768 values, r,g,b per index) for the colours any viewer shows. ``write_mask`` and the
    exports (``labelsynth.export.formats``) write masks through it."""
    mask = np.ascontiguousarray(as_id_mask(mask))
    if palette is not None:
        import io

        from PIL import Image

        im = Image.frombytes("P", (mask.shape[1], mask.shape[0]), mask.tobytes())
        im.putpalette(list(palette))
        buf = io.BytesIO()
        im.save(buf, format="PNG")
        return buf.getvalue()
    import cv2

    ok, enc = cv2.imencode(".png", mask)
    if not ok:  # pragma: no cover - cv2 always encodes uint8 2-D arrays
        raise CaptureError("cannot encode a mask as PNG")
    return enc.tobytes()
