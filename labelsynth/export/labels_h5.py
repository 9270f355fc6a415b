"""labels.h5, the file users train from: its schema, the one writer and the one reader.

Everything that writes or reads a labels.h5 (``expand``'s ``OUT/labels.h5``, ``augment``'s
``augment.h5``, ``batch``'s merged ``OUT/dataset.h5``) goes through this module, so the format
is defined once (the README, "The output folder", describes it for users).

=============  ============  ==========  =====================================================
dataset        shape         dtype       notes
=============  ============  ==========  =====================================================
images         (N,H,W,3)     uint8       RGB
masks          (N,H,W)       uint8       class ids, 255 = ignore (also the fill value)
confidence     (N,H,W)       float16     probability of the label written, in [0, 1] (capped: render.support)
annotated      (N,)          bool        frame had an expert annotation
frame_names    (N,)          utf-8 str   image file names as in the capture
=============  ============  ==========  =====================================================

The per-frame datasets are chunked one frame per chunk and compressed (gzip by default,
lzf optional), so a reader reads one frame without touching the others. File attributes:
``class_names``, ``class_ids``, ``class_colors`` (K,3 RGB), ``wound_bed_ids``,
``classes_json`` (the exact class table), ``ignore_id``, ``source`` (capture path),
``recipe`` (YAML/JSON text), ``labelsynth_version``, ``format``/``format_version``,
``created`` and any extra attributes the caller passes.

All frames of one labels.h5 have the same size (the contract: masks are the size of their image,
and a capture has one image size); a frame of another size is an ``ExportError``.

A merged dataset.h5 (``write_merged``) has the same datasets and attributes, so every reader of
labels.h5 reads it, plus ``capture`` (N,) utf-8 (each frame's capture name), ``frame_sizes``
(N,2) int32 (each frame's height, width) and the attribute ``merged`` (JSON: each capture's name,
file, first frame, frame count and size). Its ``images``, ``masks`` and ``confidence`` are HDF5
virtual datasets over the captures' own labels.h5 (paths relative to dataset.h5) at the largest
size; a smaller frame sits in the top-left corner and the rest reads as the fill values.
``LabelsReader`` crops every frame to its ``frame_sizes`` and refuses a file whose virtual
sources are missing (HDF5 would read them as fill values without a word).

The writer streams frame by frame into ``labels.h5.partial`` and renames it to ``labels.h5``
only when all N frames are in, so a crash or Ctrl-C never leaves a complete-looking file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .. import __version__
from ..classes import IGNORE_ID, ClassInfo, ClassMap
from ..errors import LabelsynthError
from ..outdir import atomic_file, ensure_space, partial_path

# --- the schema ----------------------------------------------------------------------------
FORMAT = "labelsynth-labels"
FORMAT_VERSION = 1
PIXEL_DATASETS = ("images", "masks", "confidence")  # (N,H,W[,3]), one chunk per frame
DATASETS = (*PIXEL_DATASETS, "annotated", "frame_names")
DTYPES = {"images": np.dtype(np.uint8), "masks": np.dtype(np.uint8), "confidence": np.dtype(np.float16)}
FILL_VALUES = {"images": 0, "masks": IGNORE_ID, "confidence": 0}  # what a pixel no frame covers reads as
RESERVED_ATTRS = frozenset({
    "class_names", "class_ids", "class_colors", "wound_bed_ids", "classes_json", "ignore_id",
    "source", "recipe", "labelsynth_version", "format", "format_version", "created",
})  # fmt: skip  # set by the writer; a caller's ``attrs`` may not name them
# A merged dataset.h5: per-frame capture name and true size, and the merge table as JSON.
CAPTURE = "capture"
FRAME_SIZES = "frame_sizes"
MERGED_ATTR = "merged"
MERGED_COPIED_ATTRS = ("format", "format_version", "class_names", "class_ids", "class_colors", "wound_bed_ids",
                       "classes_json", "ignore_id", "recipe", "labels", "recipe_name")  # from the first capture


class ExportError(LabelsynthError, ValueError):
    """Output that cannot be written as asked (bad frame, wrong size, unknown class id)."""


class LabelsReadError(ExportError):
    """A labels.h5 that cannot be read as one (one line naming the file and the problem)."""


# --- writing -------------------------------------------------------------------------------
def _recipe_text(recipe: Any) -> str:
    """A recipe as text: strings (YAML or JSON) as they are, mappings/dataclasses as JSON."""
    if recipe is None:
        return ""
    if isinstance(recipe, str):
        return recipe
    if dataclasses.is_dataclass(recipe) and not isinstance(recipe, type):
        recipe = dataclasses.asdict(recipe)
    if isinstance(recipe, Mapping):
        return json.dumps(recipe, sort_keys=True, default=str)
    return str(recipe)


def _attr_value(value: Any) -> Any:
    """h5py stores numbers, strings and arrays; anything else goes in as JSON text."""
    if isinstance(value, (str, bytes, int, float, bool, np.generic, np.ndarray)):
        return value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) for v in value):
        return np.asarray(value)
    return json.dumps(value, sort_keys=True, default=str)


def valid_id_table(classes: ClassMap) -> np.ndarray:
    """(256,) bool: the ids a mask of ``classes`` may hold (its classes and 255 = ignore)."""
    ok = np.zeros(256, dtype=bool)
    ok[classes.ids] = True
    ok[IGNORE_ID] = True
    return ok


def check_mask_ids(mask: np.ndarray, valid: np.ndarray, what: str) -> None:
    """ExportError naming ``what`` when ``mask`` holds an id that ``valid`` (``valid_id_table``) lacks."""
    present = np.bincount(mask.reshape(-1), minlength=256) > 0
    bad = np.nonzero(present & ~valid)[0]
    if bad.size:
        raise ExportError(f"{what}: class ids {bad.tolist()} are not in the class map")


def as_mask(mask: Any, what: str) -> np.ndarray:
    """A mask as (H, W) uint8 class ids; anything else is an ExportError naming ``what``."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ExportError(f"{what}: a mask must be (H, W) class ids, got shape {mask.shape}")
    if mask.dtype != np.uint8:
        if not np.issubdtype(mask.dtype, np.integer):
            raise ExportError(f"{what}: a mask must hold integer class ids, got {mask.dtype}")
        if mask.size and (mask.min() < 0 or mask.max() > 255):
            raise ExportError(f"{what}: mask ids must be in 0..255")
        mask = mask.astype(np.uint8)
    return mask


class LabelsWriter:
    """Streams frames into labels.h5 without holding them all in memory.

    Use as a context manager::

        with LabelsWriter(out / "labels.h5", n_frames=len(names), classes=cm,
                          source=capture_dir, recipe=recipe_yaml) as w:
            for name in names:
                w.add(name, image, mask, confidence, annotated)

    Datasets are created at the first ``add`` from that frame's size, unless ``height`` and
    ``width`` are given. Leaving the block normally with all ``n_frames`` added renames the
    ``.partial`` file to ``path``; an exception (or too few frames) removes the partial file
    (``keep_partial=True`` keeps it for debugging) and leaves any existing ``path`` untouched.
    """

    def __init__(
        self,
        path: str | Path,
        n_frames: int,
        classes: ClassMap,
        *,
        height: int | None = None,
        width: int | None = None,
        source: str | Path | None = None,
        recipe: Any = None,
        attrs: Mapping[str, Any] | None = None,
        compression: str = "gzip",
        compression_level: int = 4,
        keep_partial: bool = False,
    ) -> None:
        if n_frames < 1:
            raise ExportError("labels.h5 needs at least one frame")
        if compression not in ("gzip", "lzf"):
            raise ExportError(f"compression must be 'gzip' or 'lzf', not {compression!r}")
        clash = RESERVED_ATTRS & set(attrs or {})
        if clash:
            raise ExportError(f"attributes {sorted(clash)} are set by labelsynth itself")
        self.path = Path(path)
        self.partial_path = partial_path(self.path)
        self.n_frames = int(n_frames)
        self.classes = classes
        self.height = height
        self.width = width
        self.count = 0
        self._compression = compression
        self._level = compression_level
        self._keep_partial = keep_partial
        self._valid_ids = valid_id_table(classes)
        self._names: set[str] = set()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: h5py.File | None = h5py.File(self.partial_path, "w")
        self._write_attrs(source, recipe, attrs or {})
        if height is not None and width is not None:
            self._create(int(height), int(width))

    # --- setup ----------------------------------------------------------------------------
    def _write_attrs(self, source: Any, recipe: Any, extra: Mapping[str, Any]) -> None:
        a = self._f.attrs
        cm = self.classes
        a["format"] = FORMAT
        a["format_version"] = FORMAT_VERSION
        a["labelsynth_version"] = __version__
        a["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        a.create("class_names", np.array(cm.names, dtype=object), dtype=h5py.string_dtype("utf-8"))
        a["class_ids"] = cm.ids
        a["class_colors"] = cm.colors
        a["wound_bed_ids"] = np.asarray(cm.wound_bed_ids, dtype=np.int64)
        a["classes_json"] = json.dumps(cm.to_json())
        a["ignore_id"] = IGNORE_ID
        a["source"] = "" if source is None else str(source)
        a["recipe"] = _recipe_text(recipe)
        for k, v in extra.items():
            a[str(k)] = _attr_value(v)

    def _create(self, h: int, w: int) -> None:
        n, f = self.n_frames, self._f
        self.height, self.width = h, w
        comp = {"compression": self._compression}
        if self._compression == "gzip":
            comp["compression_opts"] = self._level
        f.create_dataset("images", (n, h, w, 3), DTYPES["images"], chunks=(1, h, w, 3), **comp)
        f.create_dataset("masks", (n, h, w), DTYPES["masks"], chunks=(1, h, w), fillvalue=FILL_VALUES["masks"], **comp)
        f.create_dataset("confidence", (n, h, w), DTYPES["confidence"], chunks=(1, h, w), shuffle=True, **comp)
        f.create_dataset("annotated", (n,), bool)
        f.create_dataset("frame_names", (n,), h5py.string_dtype("utf-8"))

    # --- writing --------------------------------------------------------------------------
    def add(
        self,
        name: str,
        image: np.ndarray,
        mask: np.ndarray,
        confidence: np.ndarray | None = None,
        annotated: bool = False,
    ) -> int:
        """Write the next frame; returns its index. ``confidence=None`` stores 1.0 everywhere."""
        if self._f is None:
            raise ExportError(f"{self.path}: the writer is closed")
        if self.count >= self.n_frames:
            raise ExportError(f"{self.path}: already holds the {self.n_frames} frames it was created for")
        what = f"frame {name!r}"
        if not isinstance(name, str) or not name:
            raise ExportError(f"frame names must be non-empty strings, got {name!r}")
        if name in self._names:
            raise ExportError(f"{what}: duplicate frame name")
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ExportError(f"{what}: image must be (H, W, 3) RGB, got shape {image.shape}")
        if image.dtype != np.uint8:
            raise ExportError(f"{what}: image must be uint8, got {image.dtype}")
        mask = as_mask(mask, what)
        if mask.shape != image.shape[:2]:
            raise ExportError(f"{what}: mask is {mask.shape[1]}x{mask.shape[0]} but image is "
                              f"{image.shape[1]}x{image.shape[0]}")
        check_mask_ids(mask, self._valid_ids, what)
        h, w = mask.shape
        if "images" not in self._f:
            self._create(h, w)
        if (h, w) != (self.height, self.width):
            raise ExportError(
                f"{what}: size {w}x{h} differs from the first frame's {self.width}x{self.height}; "
                "all frames of a capture must have the same size"
            )
        if confidence is None:
            conf = np.ones((h, w), dtype=np.float16)
        else:
            conf = np.asarray(confidence, dtype=np.float32)
            if conf.shape != (h, w):
                raise ExportError(f"{what}: confidence shape {conf.shape} != mask shape {(h, w)}")
            if not np.isfinite(conf).all():
                raise ExportError(f"{what}: confidence has NaN or infinite values")
            conf = np.clip(conf, 0.0, 1.0).astype(np.float16)
        # HDF5 crashes the process when a write meets a full disk: ask for the room first
        ensure_space(self.partial_path, image.nbytes + mask.nbytes + conf.nbytes, f"{what} of {self.path.name}")
        i = self.count
        f = self._f
        f["images"][i] = image
        f["masks"][i] = mask
        f["confidence"][i] = conf
        f["annotated"][i] = bool(annotated)
        f["frame_names"][i] = name
        self._names.add(name)
        self.count += 1
        return i

    # --- finishing ------------------------------------------------------------------------
    def close(self) -> Path:
        """Finish: all frames written -> rename to ``path``; otherwise ExportError."""
        if self._f is None:
            return self.path
        if self.count != self.n_frames:
            self.abort()
            raise ExportError(f"{self.path}: {self.count} of {self.n_frames} frames written; not saved")
        self._f.close()
        self._f = None
        os.replace(self.partial_path, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the partial file (kept with ``keep_partial=True``); ``path`` is not touched."""
        if self._f is not None:
            try:
                self._f.close()
            finally:
                self._f = None
        if not self._keep_partial:
            self.partial_path.unlink(missing_ok=True)

    def __enter__(self) -> "LabelsWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        else:
            self.close()


def _getter(source: Any, what: str, n: int) -> Callable[[int], Any]:
    """Index -> item for a callable, a sequence/array, or a one-pass iterable (in order)."""
    if source is None:
        return lambda i: None
    if callable(source) and not hasattr(source, "__getitem__"):
        return source
    if hasattr(source, "__getitem__") and hasattr(source, "__len__") and not isinstance(source, Mapping):
        if len(source) != n:
            raise ExportError(f"{what}: {len(source)} items for {n} frame names")
        return lambda i: source[i]
    if isinstance(source, Iterable):
        it = iter(source)
        state = {"next": 0}

        def get(i: int) -> Any:
            if i != state["next"]:
                raise ExportError(f"{what}: an iterable can only be read in order")
            state["next"] += 1
            try:
                return next(it)
            except StopIteration:
                raise ExportError(f"{what}: fewer items than frame names") from None

        return get
    raise ExportError(f"{what}: expected a sequence, an iterable or a callable(index)")


def write_labels_h5(
    path: str | Path,
    *,
    images: Iterable[np.ndarray] | Callable[[int], np.ndarray],
    masks: Iterable[np.ndarray] | Callable[[int], np.ndarray],
    frame_names: Sequence[str],
    classes: ClassMap,
    confidence: Iterable[np.ndarray] | Callable[[int], np.ndarray] | None = None,
    annotated: np.ndarray | Sequence[bool] | None = None,
    source: str | Path | None = None,
    recipe: Any = None,
    attrs: Mapping[str, Any] | None = None,
    compression: str = "gzip",
) -> Path:
    """Write a whole labels.h5, pulling one frame at a time.

    ``images``, ``masks`` and ``confidence`` may be sequences/arrays, iterables (consumed in
    order) or callables taking the frame index, so a caller can load or render each frame
    on demand. ``confidence=None`` stores 1.0; ``annotated=None`` stores False.
    """
    names = list(frame_names)
    n = len(names)
    if annotated is None:
        flags = np.zeros(n, dtype=bool)
    else:
        flags = np.asarray(annotated, dtype=bool).reshape(-1)
        if flags.shape[0] != n:
            raise ExportError(f"annotated has {flags.shape[0]} entries for {n} frames")
    get_image = _getter(images, "images", n)
    get_mask = _getter(masks, "masks", n)
    get_conf = _getter(confidence, "confidence", n)
    with LabelsWriter(path, n, classes, source=source, recipe=recipe, attrs=attrs,
                      compression=compression) as w:
        for i, name in enumerate(names):
            w.add(name, get_image(i), get_mask(i), get_conf(i), bool(flags[i]))
    return Path(path)


# --- reading -------------------------------------------------------------------------------
def _str(v: Any) -> str:
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def classes_from_attrs(attrs: Mapping[str, Any]) -> ClassMap:
    """Rebuild the ClassMap stored in a labels.h5 (exact table first, arrays as fallback)."""
    if "classes_json" in attrs:
        return ClassMap.from_dict(json.loads(_str(attrs["classes_json"])), "labels.h5 classes_json")
    names = [_str(v) for v in attrs["class_names"]]
    ids = [int(v) for v in attrs["class_ids"]]
    colors = np.asarray(attrs["class_colors"]).reshape(-1, 3)
    wb = {int(v) for v in attrs.get("wound_bed_ids", [])}
    return ClassMap(tuple(
        ClassInfo(i, n, tuple(int(c) for c in col), i in wb) for i, n, col in zip(ids, names, colors)
    ))  # fmt: skip


def attrs_dict(attrs: h5py.AttributeManager) -> dict[str, Any]:
    """A file's attributes as Python values (bytes and string arrays decoded)."""
    out = {}
    for k, v in attrs.items():
        if isinstance(v, bytes):
            v = v.decode("utf-8")
        elif isinstance(v, np.ndarray) and v.dtype == object:
            v = [_str(x) for x in v]
        out[k] = v
    return out


def missing_virtual_sources(path: Path, f: h5py.File) -> list[Path]:
    """Source files of the per-frame virtual datasets that do not exist (HDF5 would read their
    frames as fill values without a word). Relative sources are relative to ``path``'s folder."""
    missing: list[Path] = []
    for key in PIXEL_DATASETS:
        if key in f and f[key].is_virtual:
            for m in f[key].virtual_sources():
                src = Path(m.file_name)
                src = src if src.is_absolute() or m.file_name == "." else Path(path).parent / src
                if m.file_name != "." and not src.is_file() and src not in missing:
                    missing.append(src)
    return missing


class LabelsReader:
    """One labels.h5 (or augment.h5, or a merged dataset.h5), checked when opened and streamed.

    Opening reads only the small things (names, flags, sizes, attributes) and checks, with a
    one-line ``LabelsReadError`` naming the file: the format and its version, the datasets, their
    shapes and dtypes, the class table, a merged file's ``capture``/``frame_sizes`` and that every
    virtual source file exists. ``read(i)`` then reads frame ``i`` (one chunk) cropped to its
    true size. The HDF5 handle is opened lazily in whichever process reads, reopened after a
    fork (h5py handles must not cross processes) and never pickled, so a reader is safe inside
    a ``DataLoader`` with workers.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._handle: h5py.File | None = None
        self._pid: int | None = None
        if not self.path.is_file():
            raise LabelsReadError(f"{self.path}: no such file")
        try:
            f = h5py.File(self.path, "r")
        except OSError as exc:
            raise LabelsReadError(f"{self.path}: not a readable HDF5 file ({_first_line(exc)})") from None
        with f:
            self._check(f)

    def _check(self, f: h5py.File) -> None:
        path = self.path
        fmt = _str(f.attrs.get("format", ""))
        if fmt != FORMAT:
            raise LabelsReadError(f"{path}: not a labelsynth labels.h5 (format {fmt!r}, expected {FORMAT!r})")
        version = int(f.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            raise LabelsReadError(f"{path}: labels.h5 format version {version}; "
                                  f"this labelsynth reads version {FORMAT_VERSION}")
        missing = [d for d in DATASETS if d not in f]
        if missing:
            raise LabelsReadError(f"{path}: labels.h5 lacks the datasets {missing}")
        n = len(f["annotated"])
        shapes = {d: f[d].shape for d in PIXEL_DATASETS}
        image = shapes["images"]
        if (len(image) != 4 or image[3] != 3 or image[0] != n or shapes["masks"] != image[:3]
                or shapes["confidence"] != image[:3] or len(f["frame_names"]) != n):
            raise LabelsReadError(f"{path}: labels.h5 datasets do not fit together "
                                  f"({', '.join(f'{k} {v}' for k, v in shapes.items())}, {n} frames)")
        for key in ("images", "masks"):
            if f[key].dtype != DTYPES[key]:
                raise LabelsReadError(f"{path}: {key} are {f[key].dtype}, expected {DTYPES[key]}")
        if f["confidence"].dtype.kind != "f":
            raise LabelsReadError(f"{path}: confidence is {f['confidence'].dtype}, expected floats")
        self.attrs = attrs_dict(f.attrs)
        try:
            self.classes = classes_from_attrs(self.attrs)
        except (LabelsynthError, KeyError, ValueError, TypeError) as exc:
            raise LabelsReadError(f"{path}: unusable class table ({_first_line(exc)})") from None
        self.height, self.width = int(image[1]), int(image[2])
        self.frame_names = [str(s) for s in f["frame_names"].asstr()[()]]
        self.annotated = f["annotated"][()].astype(bool)
        self.capture_names = [str(s) for s in f[CAPTURE].asstr()[()]] if CAPTURE in f else None
        if self.capture_names is not None and len(self.capture_names) != n:
            raise LabelsReadError(f"{path}: {CAPTURE} names {len(self.capture_names)} frames, the file holds {n}")
        seen: dict[tuple[str, str], int] = {}
        for i, name in enumerate(self.frame_names):
            key = (self.capture_names[i] if self.capture_names is not None else "", name)
            if not name:
                raise LabelsReadError(f"{path}: frame {i} has no name")
            if key in seen:
                raise LabelsReadError(f"{path}: frame name {name!r} is given twice (frames {seen[key]} and {i})")
            seen[key] = i
        self.frame_sizes = f[FRAME_SIZES][()].astype(np.int64) if FRAME_SIZES in f else None
        if self.frame_sizes is not None:
            sizes = self.frame_sizes
            if (sizes.shape != (n, 2) or (sizes < 1).any() or (sizes[:, 0] > self.height).any()
                    or (sizes[:, 1] > self.width).any()):
                raise LabelsReadError(f"{path}: {FRAME_SIZES} {sizes.shape} do not fit {n} frames of at most "
                                      f"{self.width}x{self.height}")
        missing_sources = missing_virtual_sources(path, f)
        if missing_sources:
            raise LabelsReadError(f"{path}: reads its frames from {missing_sources[0]}, which is missing "
                                  f"({len(missing_sources)} source file(s) missing; the rest would read as fill values)")

    def __len__(self) -> int:
        return len(self.frame_names)

    def size(self, i: int) -> tuple[int, int]:
        """Frame ``i``'s true (height, width): its ``frame_sizes`` row, else the datasets' size."""
        if self.frame_sizes is None:
            return self.height, self.width
        h, w = self.frame_sizes[i]
        return int(h), int(w)

    def file(self) -> h5py.File:
        """This process's read handle (a handle inherited through fork is dropped, not closed)."""
        if self._handle is None or self._pid != os.getpid():
            try:
                self._handle = h5py.File(self.path, "r")
            except OSError as exc:
                raise LabelsReadError(f"{self.path}: no longer readable ({_first_line(exc)})") from None
            self._pid = os.getpid()
        return self._handle

    def read(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame ``i`` (0 <= i < N): image (h,w,3) uint8 RGB, mask (h,w) uint8 class ids and
        confidence (h,w) float16, cropped to the frame's true size."""
        f = self.file()
        h, w = self.size(i)
        try:
            return f["images"][i, :h, :w], f["masks"][i, :h, :w], f["confidence"][i, :h, :w]
        except (OSError, KeyError, ValueError) as exc:
            raise LabelsReadError(f"{self.path}: frame {i} cannot be read ({_first_line(exc)})") from None

    def read_checked(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``read``, and a check of what ``read`` does not: the mask holds only the class table's
        ids (or 255), the confidences are finite and in 0..1 (one line naming the file and frame).
        What a reader of a hand-edited or foreign file uses (``export``), frame by frame."""
        image, mask, confidence = self.read(i)
        what = f"{self.path}: frame {i} ({self.frame_names[i]!r})"
        try:
            check_mask_ids(np.asarray(mask), valid_id_table(self.classes), what)
        except ExportError as exc:
            raise LabelsReadError(str(exc)) from None
        conf = np.asarray(confidence, dtype=np.float32)
        if not np.isfinite(conf).all() or conf.min(initial=0.0) < 0 or conf.max(initial=0.0) > 1:
            raise LabelsReadError(f"{what}: confidence must be finite and in 0..1")
        return image, mask, confidence

    def verify(self) -> None:
        """``read_checked`` every frame once: before training on a file (one line naming the frame)."""
        for i in range(len(self)):
            self.read_checked(i)

    def __getstate__(self) -> dict[str, Any]:  # DataLoader workers open their own handle
        return {**self.__dict__, "_handle": None, "_pid": None}

    def close(self) -> None:
        if self._handle is not None and self._pid == os.getpid():
            self._handle.close()
        self._handle = None
        self._pid = None

    def __enter__(self) -> "LabelsReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: h5py may already be gone
            pass


def read_labels_h5(path: str | Path) -> dict[str, Any]:
    """Everything in a (small) labels.h5 as numpy arrays, plus ``attrs`` and ``classes``.

    The file is checked as ``LabelsReader`` checks it; the arrays are the datasets as stored
    (a merged dataset.h5 of several sizes keeps its padding: crop with ``frame_sizes``).
    """
    with LabelsReader(path) as reader:
        f = reader.file()
        out = {key: f[key][()] for key in PIXEL_DATASETS}
        out.update(annotated=reader.annotated, frame_names=list(reader.frame_names), attrs=reader.attrs,
                   classes=reader.classes)
        if reader.frame_sizes is not None:
            out[FRAME_SIZES] = reader.frame_sizes
        return out


# --- a merged dataset.h5 ---------------------------------------------------------------------
def write_merged(target: str | Path, parts: Sequence[tuple[str, LabelsReader]]) -> Path:
    """``target`` (a dataset.h5) over the (capture name, reader of its labels.h5) ``parts``, in order.

    No pixel is copied: ``images``/``masks``/``confidence`` are virtual datasets whose sources
    are the parts' files by path relative to ``target``'s folder (the parts must lie below it),
    so the folder can be moved as a whole. The parts' class tables must agree (the caller says
    why not in its own terms). Written as ``target.partial`` and renamed.
    """
    target = Path(target)
    root = target.parent.resolve()
    first = parts[0][1].file()  # attributes are copied raw, as stored

    def shape(key: str, n: int, h: int, w: int) -> tuple[int, ...]:
        return (n, h, w, 3) if key == "images" else (n, h, w)

    total = sum(len(r) for _, r in parts)
    hmax, wmax = max(r.height for _, r in parts), max(r.width for _, r in parts)
    layouts = {key: h5py.VirtualLayout(shape=shape(key, total, hmax, wmax), dtype=first[key].dtype)
               for key in PIXEL_DATASETS}
    merged, start = [], 0
    for name, reader in parts:
        rel = reader.path.resolve().relative_to(root).as_posix()
        n, h, w = len(reader), reader.height, reader.width
        for key, layout in layouts.items():
            layout[start:start + n, :h, :w] = h5py.VirtualSource(rel, key, shape=shape(key, n, h, w),
                                                                 dtype=reader.file()[key].dtype)
        merged.append({"name": name, "file": rel, "first": start, "frames": n, "height": h, "width": w})
        start += n
    strings = h5py.string_dtype("utf-8")
    ensure_space(target, 65536 + 512 * total, target.name)  # no pixels: names, sizes and the virtual layout
    with atomic_file(target) as tmp, h5py.File(tmp, "w") as f:
        for key in MERGED_COPIED_ATTRS:
            if key in first.attrs:
                f.attrs[key] = first.attrs[key]
        f.attrs["labelsynth_version"] = __version__
        f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        f.attrs["source"] = str(root)
        f.attrs[MERGED_ATTR] = json.dumps(merged)
        for key, layout in layouts.items():
            f.create_virtual_dataset(key, layout, fillvalue=FILL_VALUES[key])
        f.create_dataset("annotated", data=np.concatenate([r.annotated for _, r in parts]))
        f.create_dataset("frame_names", data=np.array([s for _, r in parts for s in r.frame_names], dtype=object),
                         dtype=strings)
        f.create_dataset(CAPTURE, data=np.array([name for name, r in parts for _ in range(len(r))], dtype=object),
                         dtype=strings)
        f.create_dataset(FRAME_SIZES, data=np.array([(r.height, r.width) for _, r in parts for _ in range(len(r))],
                                                    dtype=np.int32))
    return target
