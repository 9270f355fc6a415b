"""Sources -> frames: labels.h5 files written by ``expand`` and capture folders (their
``annotations/`` only), one class table for all, and the validation split by capture.

A labels.h5 (also augment.h5 and a batch's merged dataset.h5) is streamed through
``export.labels_h5.LabelsReader``: its format, datasets, class table and (merged) capture files
are checked up front, then each frame is read from the file when a batch needs it, cropped to
its own size (h5py reads one chunk, i.e. one frame; every process opens its own handle, so
DataLoader workers are safe), so memory does not grow with the number of frames. A capture's
annotations are few by nature and are read once, into memory. Frames are resized and normalised
as ``contract`` says, the same way ``segment`` prepares them. ``train`` never writes into a source.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..classes import IGNORE_ID, ClassMap, parse_id_pairs
from ..errors import LabelsynthError
from .contract import normalize, resize_image

HOLDOUT_FRACTION = 0.2  # of each source's frames, a contiguous block, when no source is held out


class TrainError(LabelsynthError, ValueError):
    """A source, option or checkpoint that ``train`` cannot use (one line, names the file)."""


class _InMemory:
    """Frame ``i`` from arrays already read (a capture's annotated frames)."""

    def __init__(self, images: list[np.ndarray], masks: list[np.ndarray]) -> None:
        self.images, self.masks = images, masks

    def __call__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.images[i], self.masks[i], np.ones(self.masks[i].shape, dtype=np.float16)


@dataclass
class Source:
    """The frames of one labels.h5 or one capture folder; ``read(i)`` gives frame i's pixels."""

    path: Path
    kind: str  # "labels" | "capture"
    classes: ClassMap
    names: list[str]
    annotated: np.ndarray  # (N,) bool
    sizes: list[tuple[int, int]]  # (W, H) of each frame
    rows: list[int]  # frame i is row rows[i] of the reader
    reader: Any = field(repr=False)  # row -> (image (H,W,3) uint8 RGB, mask (H,W) uint8 ids, confidence (H,W))

    @property
    def name(self) -> str:
        """The capture's name: the folder, or the folder holding labels.h5."""
        if self.kind == "labels" and self.path.name == "labels.h5":
            return self.path.parent.name
        return self.path.stem if self.kind == "labels" else self.path.name

    def read(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.reader(self.rows[i])

    def __len__(self) -> int:
        return len(self.names)


def resize_frame(image: np.ndarray, mask: np.ndarray, confidence: np.ndarray,
                 size: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """To ``size`` (W, H): the image by ``contract.resize_image`` (what ``segment`` does), the mask
    and its confidence by nearest neighbour (class ids are never blended)."""
    if size is None or (image.shape[1], image.shape[0]) == tuple(size):
        return image, mask, confidence
    w, h = size
    image = resize_image(image, size)
    mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST)
    confidence = cv2.resize(confidence.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    return image, mask, confidence


@dataclass
class Frame:
    """One training or validation frame: where it comes from; its pixels are read by ``load``."""

    src: Source = field(repr=False)
    index: int
    annotated: bool
    source: str
    name: str

    @property
    def size(self) -> tuple[int, int]:
        return self.src.sizes[self.index]

    def load(self, size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image, mask, confidence), resized to ``size`` (W, H) when given."""
        return resize_frame(*self.src.read(self.index), size)


@dataclass
class Split:
    train: list[Frame]
    val: list[Frame]
    description: str  # one line for the log and train.json
    val_sources: list[str] = field(default_factory=list)


# --- reading sources -----------------------------------------------------------------------
def load_labels_h5(path: Path, only_annotated: bool = False) -> Source:
    """A labels.h5 written by ``expand`` (or ``augment``, or ``batch``'s merged dataset.h5),
    checked now by ``export.labels_h5.LabelsReader``; its frames are read when they are used,
    each cropped to its own size."""
    from ..export.labels_h5 import LabelsReader

    try:
        reader = LabelsReader(path)
        reader.verify()  # every frame's ids and confidences, before the first step
    except LabelsynthError as exc:
        raise TrainError(str(exc)) from None
    keep = np.flatnonzero(reader.annotated) if only_annotated else np.arange(len(reader))
    if keep.size == 0:
        raise TrainError(f"{path}: no annotated frames" + (" (--only-annotated)" if only_annotated else ""))
    sizes = [reader.size(int(i))[::-1] for i in keep]
    return Source(path, "labels", reader.classes, [reader.frame_names[i] for i in keep], reader.annotated[keep],
                  sizes, [int(i) for i in keep], reader.read)


def load_capture_source(path: Path) -> Source:
    """A capture folder's expert annotations (``annotations/``): the sparse baseline."""
    from ..capture import load_capture

    capture = load_capture(path)
    indices = [i for i, f in enumerate(capture.frames) if f.annotation_path is not None]
    if not indices:
        raise TrainError(f"{path / 'annotations'}: the capture has no annotations to train from")
    images = [capture.load_image(i) for i in indices]
    masks = [capture.load_annotation(i) for i in indices]
    names = [capture.frames[i].name for i in indices]
    sizes = [(m.shape[1], m.shape[0]) for m in masks]
    return Source(path, "capture", capture.classes, names, np.ones(len(indices), dtype=bool), sizes,
                  list(range(len(indices))), _InMemory(images, masks))


def load_source(path: str | Path, only_annotated: bool = False) -> Source:
    path = Path(path)
    if path.is_dir():
        return load_capture_source(path)
    if path.is_file():
        return load_labels_h5(path, only_annotated)
    raise TrainError(f"{path}: no such labels.h5 or capture folder")


def require_source(path: str | Path) -> Path:
    """``path`` exists (one line if it is missing, a dangling link or a symbolic link loop)."""
    path = Path(path)
    if not path.exists():
        kind = "a symbolic link that leads nowhere (or to itself)" if path.is_symlink() else "not found"
        raise TrainError(f"{path}: {kind} (expected a labels.h5 or a capture folder)")
    return path


def load_sources(paths: list[str | Path], only_annotated: bool = False) -> tuple[list[Source], ClassMap]:
    """Every source, and the one class table they share (a clear error naming the odd file)."""
    if not paths:
        raise TrainError("give at least one SOURCE (a labels.h5 or a capture folder)")
    seen: dict[Path, str | Path] = {}
    for p in paths:
        key = require_source(p).resolve()
        if key in seen:
            raise TrainError(f"{p}: given twice as a SOURCE (also as {seen[key]})")
        seen[key] = p
    sources = [load_source(p, only_annotated) for p in paths]
    first = sources[0]
    for s in sources[1:]:
        if s.classes.to_json() != first.classes.to_json():
            raise TrainError(
                f"{s.path}: its class table ({', '.join(f'{c.id}={c.name}' for c in s.classes.classes)}) differs from "
                f"{first.path}'s ({', '.join(f'{c.id}={c.name}' for c in first.classes.classes)})"
            )
    return sources, first.classes


def class_table_json(classes: ClassMap) -> str:
    return json.dumps(classes.to_json(), sort_keys=True)


# --- the split -----------------------------------------------------------------------------
def _frames(source: Source, indices: range | list[int]) -> list[Frame]:
    return [Frame(source, i, bool(source.annotated[i]), source.name, source.names[i]) for i in indices]


def _matches(source: Source, key: str) -> bool:
    key_path = Path(key)
    return key in (source.name, str(source.path)) or (key_path.exists() and key_path.resolve() == source.path.resolve())


VAL_SPLITS = ("none", "capture", "frames", "auto")


def split_by_capture(sources: list[Source], val_captures: list[str] | None = None, mode: str = "auto") -> Split:
    """Which frames train and which validate: by capture, never by frame at random (frames of
    one video are near-duplicates).

    ``val_captures`` names held-out sources (name or path): they validate, the others train,
    whatever ``mode`` is. Otherwise ``mode`` says: ``none`` trains on every frame given (no
    validation curve); ``capture`` holds out the last source; ``frames`` holds out the last
    contiguous block of each source's frames (``HOLDOUT_FRACTION``, at least one frame of a
    source with two or more); ``auto`` is ``capture`` with 3+ sources, else ``frames``.
    Validation never changes the model (it only draws the curves), so a frame held out is a
    frame not learned from: the description says how many.
    """
    if mode not in VAL_SPLITS:
        raise TrainError(f"--val-split {mode!r}: expected one of {', '.join(VAL_SPLITS)}")
    total = sum(len(s) for s in sources)
    if val_captures:
        held = []
        for key in val_captures:
            hits = [s for s in sources if _matches(s, key)]
            if not hits:
                raise TrainError(f"--val-captures {key!r}: not one of the sources ({', '.join(str(s.path) for s in sources)})")
            held.extend(h for h in hits if h not in held)
    elif mode == "capture" or (mode == "auto" and len(sources) >= 3):
        if len(sources) < 2:
            raise TrainError("--val-split capture: needs two or more sources (one to hold out)")
        held = [sources[-1]]
    else:
        held = []
    if held:
        train_sources = [s for s in sources if s not in held]
        if not train_sources:
            raise TrainError("--val-captures holds out every source; nothing is left to train on")
        train = [fr for s in train_sources for fr in _frames(s, range(len(s)))]
        val = [fr for s in held for fr in _frames(s, range(len(s)))]
        desc = f"validation on held-out captures: {', '.join(str(s.path) for s in held)} ({len(val)} frames)"
        if not val_captures:
            desc += (f"; training on the other {len(train)} of the {total} frames given "
                     "(--val-split none trains on all of them)")
        return Split(train, val, desc, [str(s.path) for s in held])
    if mode == "none":
        return Split([fr for s in sources for fr in _frames(s, range(len(s)))], [],
                     f"no validation (--val-split none): training on all {total} frames given", [])
    train, val, parts = [], [], []
    for s in sources:
        n = len(s)
        k = int(round(n * HOLDOUT_FRACTION)) if n >= 2 else 0
        k = max(k, 1) if n >= 2 else 0
        train.extend(_frames(s, range(n - k)))
        val.extend(_frames(s, range(n - k, n)))
        if k:
            block = s.names[-1] if k == 1 else f"{s.names[n - k]}..{s.names[-1]}"
            parts.append(f"{s.path}: {block}")
    if val:
        desc = (f"validation on the last contiguous block of frames of each source ({'; '.join(parts)}); "
                f"training on the other {len(train)} of the {total} frames given (--val-split none trains on all of them)")
    else:
        desc = f"no validation: every source has a single frame; training on all {total} frames given"
    return Split(train, val, desc, [])


# --- the torch dataset ---------------------------------------------------------------------
def make_target(mask: np.ndarray, confidence: np.ndarray, annotated: bool, lut: np.ndarray, *,
                min_confidence: float = 0.0, expert_weight: float = 1.0,
                confidence_weight: bool = True, class_weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Class ids -> model indices (uint8, 255 = ignore) and per-pixel weights (float32).

    Pixels with confidence below ``min_confidence`` become ignore; the weight is the
    confidence (``confidence_weight``) times ``expert_weight`` on annotated frames times the
    class's weight (``class_weight``, by model index); ignored pixels weigh 0.
    """
    index = lut[mask]
    target = np.where(index < 0, IGNORE_ID, index).astype(np.uint8)
    conf = confidence.astype(np.float32)
    if min_confidence > 0:
        target[conf < min_confidence] = IGNORE_ID
    weight = conf.copy() if confidence_weight else np.ones_like(conf)
    if annotated:
        weight *= float(expert_weight)
    if class_weight is not None:  # (K,) per model index
        weight *= class_weight[np.minimum(target, len(class_weight) - 1)]
    weight[target == IGNORE_ID] = 0.0
    return target, weight


class FrameDataset(torch.utils.data.Dataset):
    """Training items: normalised image (3,h,w), target indices (h,w) long, weights (h,w).

    Without ``transform`` an item's image is exactly what ``segment`` feeds the model for that
    frame at ``size`` (``contract.model_input``)."""

    def __init__(self, frames: list[Frame], classes: ClassMap, transform=None, *, min_confidence: float = 0.0,
                 expert_weight: float = 1.0, confidence_weight: bool = True,
                 class_weight: np.ndarray | None = None, size: tuple[int, int] | None = None) -> None:
        self.frames = frames
        self.size = size  # (W, H) every frame is resized to before augmentation; None: as stored
        self.lut = classes.id_to_index_lut()
        self.transform = transform
        self.kw = dict(min_confidence=min_confidence, expert_weight=expert_weight, confidence_weight=confidence_weight,
                       class_weight=class_weight)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        fr = self.frames[i]
        image, mask, confidence = fr.load(self.size)
        target, weight = make_target(mask, confidence, fr.annotated, self.lut, **self.kw)
        if self.transform is not None:
            out = self.transform(image=image, mask=target, weight=weight)
            image, target, weight = out["image"], out["mask"], out["weight"]
            weight = np.where(target == IGNORE_ID, 0.0, weight).astype(np.float32)
        return {
            "image": torch.from_numpy(normalize(image)),
            "target": torch.from_numpy(np.ascontiguousarray(target)).long(),
            "weight": torch.from_numpy(np.ascontiguousarray(weight, dtype=np.float32)),
        }


def parse_class_weights(text: str | dict | None, classes: ClassMap) -> np.ndarray | None:
    """``"0:0.1,5:2"`` (class id: weight; unnamed classes weigh 1) -> (K,) weights by model index."""
    if text is None or text == "" or text == {}:
        return None
    pairs = parse_id_pairs(text, float, "--class-weights", "id:weight", "0:0.1,5:2", TrainError)
    out = np.ones(classes.num_classes, dtype=np.float32)
    lut = classes.id_to_index_lut()
    for cid, w in pairs:
        if not 0 <= cid < 256 or lut[cid] < 0:
            raise TrainError(f"--class-weights: class id {cid} is not in the class table ({', '.join(map(str, classes.ids))})")
        if not (w >= 0 and np.isfinite(w)):
            raise TrainError(f"--class-weights: weight {w} of class {cid} must be a finite number >= 0")
        out[lut[cid]] = w
    return out
