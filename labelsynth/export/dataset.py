"""Writers for the output folder (labels.h5, masks/*.png) and a torch Dataset over labels.h5.

labels.h5 (the contract in the README, "The output folder"):

=============  ============  ==========  =====================================================
dataset        shape         dtype       notes
=============  ============  ==========  =====================================================
images         (N,H,W,3)     uint8       RGB
masks          (N,H,W)       uint8       class ids, 255 = ignore (also the fill value)
confidence     (N,H,W)       float16     max class probability in [0, 1]
annotated      (N,)          bool        frame had an expert annotation
frame_names    (N,)          utf-8 str   image file names as in the capture
=============  ============  ==========  =====================================================

The per-frame datasets are chunked one frame per chunk and compressed (gzip by default,
lzf optional), so a Dataset reads one frame without touching the others. File attributes:
``class_names``, ``class_ids``, ``class_colors`` (K,3 RGB), ``wound_bed_ids``,
``classes_json`` (the exact class table), ``ignore_id``, ``source`` (capture path),
``recipe`` (YAML/JSON text), ``labelsynth_version``, ``format``/``format_version``,
``created`` and any extra attributes the caller passes.

All frames of one file have the same size (the contract: masks are the size of their image, and a
capture has one image size); a frame of another size is an ``ExportError``.

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
import torch

from .. import __version__
from ..classes import IGNORE_ID, ClassInfo, ClassMap
from ..capture.masks import write_mask
from ..errors import LabelsynthError
from ..outdir import partial_path

FORMAT = "labelsynth-labels"
FORMAT_VERSION = 1
_RESERVED_ATTRS = {
    "class_names", "class_ids", "class_colors", "wound_bed_ids", "classes_json", "ignore_id",
    "source", "recipe", "labelsynth_version", "format", "format_version", "created",
}  # fmt: skip


class ExportError(LabelsynthError, ValueError):
    """Output that cannot be written as asked (bad frame, wrong size, unknown class id)."""


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


def _valid_id_table(classes: ClassMap) -> np.ndarray:
    ok = np.zeros(256, dtype=bool)
    ok[classes.ids] = True
    ok[IGNORE_ID] = True
    return ok


def _check_mask_ids(mask: np.ndarray, valid: np.ndarray, what: str) -> None:
    present = np.bincount(mask.reshape(-1), minlength=256) > 0
    bad = np.nonzero(present & ~valid)[0]
    if bad.size:
        raise ExportError(f"{what}: class ids {bad.tolist()} are not in the class map")


def _as_mask(mask: Any, what: str) -> np.ndarray:
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
        clash = _RESERVED_ATTRS & set(attrs or {})
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
        self._valid_ids = _valid_id_table(classes)
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
        f.create_dataset("images", (n, h, w, 3), np.uint8, chunks=(1, h, w, 3), **comp)
        f.create_dataset("masks", (n, h, w), np.uint8, chunks=(1, h, w), fillvalue=IGNORE_ID, **comp)
        f.create_dataset("confidence", (n, h, w), np.float16, chunks=(1, h, w), shuffle=True, **comp)
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
        mask = _as_mask(mask, what)
        if mask.shape != image.shape[:2]:
            raise ExportError(f"{what}: mask is {mask.shape[1]}x{mask.shape[0]} but image is "
                              f"{image.shape[1]}x{image.shape[0]}")
        _check_mask_ids(mask, self._valid_ids, what)
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


# --- reading -----------------------------------------------------------------------------
def _str(v: Any) -> str:
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


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


def _attrs_dict(attrs: h5py.AttributeManager) -> dict[str, Any]:
    out = {}
    for k, v in attrs.items():
        if isinstance(v, bytes):
            v = v.decode("utf-8")
        elif isinstance(v, np.ndarray) and v.dtype == object:
            v = [_str(x) for x in v]
        out[k] = v
    return out


def read_labels_h5(path: str | Path) -> dict[str, Any]:
    """Everything in a (small) labels.h5 as numpy arrays, plus ``attrs`` and ``classes``."""
    with h5py.File(path, "r") as f:
        attrs = _attrs_dict(f.attrs)
        return {
            "images": f["images"][()],
            "masks": f["masks"][()],
            "confidence": f["confidence"][()],
            "annotated": f["annotated"][()].astype(bool),
            "frame_names": [str(s) for s in f["frame_names"].asstr()[()]],
            "attrs": attrs,
            "classes": classes_from_attrs(attrs),
        }


def missing_virtual_sources(path: Path, f: h5py.File) -> list[Path]:
    """Source files of the per-frame virtual datasets that do not exist (HDF5 would read their
    frames as fill values without a word). Relative sources are relative to ``path``'s folder."""
    missing: list[Path] = []
    for key in ("images", "masks", "confidence"):
        if key in f and f[key].is_virtual:
            for m in f[key].virtual_sources():
                src = Path(m.file_name)
                src = src if src.is_absolute() or m.file_name == "." else Path(path).parent / src
                if m.file_name != "." and not src.is_file() and src not in missing:
                    missing.append(src)
    return missing


class LabelsDataset(torch.utils.data.Dataset):
    """One frame of labels.h5 per item, for training a 2D segmenter.

    Safe with ``DataLoader(num_workers>=2)``: the HDF5 handle is opened lazily in whichever
    process reads, reopened after a fork (h5py handles must not cross processes), and never
    pickled. Items: ``image`` float32 (3,H,W) in [0,1] (uint8 with ``uint8=True``), ``mask``
    int64 (H,W) class ids (255 = ignore), ``confidence`` float32 (H,W), ``annotated`` bool
    tensor, ``name`` str, ``index`` int (and ``capture`` str from a batch's merged dataset.h5).

    ``transform`` is called as ``transform(image=HxWx3 uint8, mask=HxW uint8)`` and must
    return a dict with ``image`` and ``mask`` (albumentations style, numpy or tensors).
    Confidence is passed too, as ``confidence=``, when the transform declares it, e.g.
    ``A.Compose([...], additional_targets={"confidence": "mask"})``; a transform that
    changes the frame size without it is an error rather than a silently misaligned map.
    """

    def __init__(
        self,
        path: str | Path,
        transform: Callable[..., Mapping[str, Any]] | None = None,
        uint8: bool = False,
    ) -> None:
        self.path = Path(path)
        self.transform = transform
        self.uint8 = uint8
        self._f: h5py.File | None = None
        self._pid: int | None = None
        with h5py.File(self.path, "r") as f:
            missing = {"images", "masks", "confidence", "annotated", "frame_names"} - set(f)
            if missing:
                raise ExportError(f"{self.path}: not a labels.h5 (missing {sorted(missing)})")
            self._len = int(f["masks"].shape[0])
            self.height, self.width = (int(v) for v in f["masks"].shape[1:])
            self.attrs = _attrs_dict(f.attrs)
            self.frame_names = [str(s) for s in f["frame_names"].asstr()[()]]
            # A merged dataset.h5 (``labelsynth batch``): frames name their capture, are read
            # through virtual datasets from each capture's labels.h5, and are cropped to their size.
            self.capture_names = [str(s) for s in f["capture"].asstr()[()]] if "capture" in f else None
            self._sizes = f["frame_sizes"][()] if "frame_sizes" in f else None
            missing = missing_virtual_sources(self.path, f)
            if missing:
                raise ExportError(f"{self.path}: reads its frames from {missing[0]}, which is missing "
                                  f"({len(missing)} source file(s) missing; the rest would read as fill values)")
        self._classes = classes_from_attrs(self.attrs)

    @property
    def classes(self) -> ClassMap:
        return self._classes

    def __len__(self) -> int:
        return self._len

    def _file(self) -> h5py.File:
        if self._f is None or self._pid != os.getpid():
            # A handle inherited through fork belongs to the parent: drop it, don't close it.
            self._f = h5py.File(self.path, "r")
            self._pid = os.getpid()
        return self._f

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_f"] = None
        state["_pid"] = None
        return state

    def close(self) -> None:
        if self._f is not None and self._pid == os.getpid():
            self._f.close()
        self._f = None
        self._pid = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: h5py may already be gone
            pass

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = self._len
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        i = int(index) % n
        f = self._file()
        image = f["images"][i]
        mask = f["masks"][i]
        conf = f["confidence"][i].astype(np.float32)
        if self._sizes is not None:
            h, w = (int(v) for v in self._sizes[i])
            image, mask, conf = image[:h, :w], mask[:h, :w], conf[:h, :w]
        if self.transform is not None:
            kwargs: dict[str, Any] = {"image": image, "mask": mask}
            wants_conf = "confidence" in (getattr(self.transform, "additional_targets", None) or {})
            if wants_conf:
                kwargs["confidence"] = conf
            out = self.transform(**kwargs)
            image, mask = out["image"], out["mask"]
            if wants_conf:
                conf = out["confidence"]
            if tuple(np.shape(conf))[-2:] != tuple(np.shape(mask))[-2:]:
                raise ExportError(
                    "the transform changed the frame size but not the confidence map; build it with "
                    "additional_targets={'confidence': 'mask'}"
                )
        return {
            "image": self._image_tensor(image),
            "mask": torch.as_tensor(np.asarray(mask)).long(),
            "confidence": torch.as_tensor(np.asarray(conf, dtype=np.float32)),
            "annotated": torch.tensor(bool(f["annotated"][i])),
            "name": self.frame_names[i],
            "index": i,
            **({"capture": self.capture_names[i]} if self.capture_names is not None else {}),
        }

    def _image_tensor(self, image: Any) -> torch.Tensor:
        if isinstance(image, torch.Tensor):
            t = image
            if t.ndim == 3 and t.shape[0] not in (1, 3) and t.shape[-1] in (1, 3):
                t = t.permute(2, 0, 1)
        else:
            t = torch.from_numpy(np.ascontiguousarray(np.asarray(image).transpose(2, 0, 1)))
        if t.dtype == torch.uint8 and not self.uint8:
            return t.float().div_(255.0)
        return t.contiguous()


# --- PNG masks ---------------------------------------------------------------------------
def write_masks_png(out_dir: str | Path, name: str, mask: np.ndarray, classes: ClassMap | None = None) -> Path:
    """Write ``out_dir/<stem of name>.png``: an 8-bit single-channel (greyscale) PNG of class ids.

    Why not a palette PNG: OpenCV expands palettes to BGR colours even with
    ``IMREAD_UNCHANGED``, so ids would come back only through PIL; PNG does not allow a
    palette on a greyscale image. A plain greyscale PNG returns the ids with both
    ``np.array(PIL.Image.open(p))`` and ``cv2.imread(p, cv2.IMREAD_UNCHANGED)``. Use
    ``ClassMap.colorize`` for a colour view. ``classes`` (if given) validates the ids.
    The file is written by ``capture.masks.write_mask``, the one mask writer.
    """
    what = f"mask {name!r}"
    mask = _as_mask(mask, what)
    if classes is not None:
        _check_mask_ids(mask, _valid_id_table(classes), what)
    return write_mask(Path(out_dir) / f"{Path(name).stem}.png", mask, palette=False)
