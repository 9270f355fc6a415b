"""Sources -> frames: labels.h5 files written by ``expand`` and capture folders (their
``annotations/`` only), one class table for all, and the validation split by capture.

Frames are held in memory as uint8 images, uint8 class-id masks and float16 confidence
(150 frames at 640x480 are ~200 MB); ``train`` never writes into a source.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from ..classes import IGNORE_ID, ClassMap, parse_id_pairs
from ..errors import LabelsynthError

LABELS_DATASETS = ("images", "masks", "confidence", "annotated", "frame_names")
HOLDOUT_FRACTION = 0.2  # of each source's frames, a contiguous block, when no source is held out


class TrainError(LabelsynthError, ValueError):
    """A source, option or checkpoint that ``train`` cannot use (one line, names the file)."""


@dataclass
class Source:
    """The frames of one labels.h5 or one capture folder."""

    path: Path
    kind: str  # "labels" | "capture"
    classes: ClassMap
    names: list[str]
    images: list[np.ndarray]  # (H,W,3) uint8 RGB
    masks: list[np.ndarray]  # (H,W) uint8 class ids, 255 = ignore
    confidence: list[np.ndarray]  # (H,W) float16 in [0,1]
    annotated: np.ndarray  # (N,) bool

    @property
    def name(self) -> str:
        """The capture's name: the folder, or the folder holding labels.h5."""
        if self.kind == "labels" and self.path.name == "labels.h5":
            return self.path.parent.name
        return self.path.stem if self.kind == "labels" else self.path.name

    def __len__(self) -> int:
        return len(self.names)


@dataclass
class Frame:
    """One training or validation frame (views into its source's arrays)."""

    image: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    annotated: bool
    source: str
    name: str


@dataclass
class Split:
    train: list[Frame]
    val: list[Frame]
    description: str  # one line for the log and train.json
    val_sources: list[str] = field(default_factory=list)


# --- reading sources -----------------------------------------------------------------------
def _str(v: Any) -> str:
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def load_labels_h5(path: Path, only_annotated: bool = False) -> Source:
    """A labels.h5 written by ``expand``: checked for its format, version and datasets."""
    from ..export.dataset import FORMAT, FORMAT_VERSION, classes_from_attrs

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise TrainError(f"{path}: not a readable HDF5 file ({exc})") from None
    with f:
        fmt = _str(f.attrs.get("format", ""))
        if fmt != FORMAT:
            raise TrainError(f"{path}: not a labelsynth labels.h5 (format {fmt!r}, expected {FORMAT!r})")
        version = int(f.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            raise TrainError(f"{path}: labels.h5 format version {version}; this labelsynth reads version {FORMAT_VERSION}")
        missing = [d for d in LABELS_DATASETS if d not in f]
        if missing:
            raise TrainError(f"{path}: labels.h5 lacks the datasets {missing}")
        try:
            classes = classes_from_attrs(f.attrs)
        except (LabelsynthError, KeyError, ValueError) as exc:
            raise TrainError(f"{path}: unusable class table ({str(exc).splitlines()[0]})") from None
        annotated = f["annotated"][()].astype(bool)
        keep = np.flatnonzero(annotated) if only_annotated else np.arange(len(annotated))
        if keep.size == 0:
            raise TrainError(f"{path}: no annotated frames (--only-annotated)")
        names = [str(s) for s in f["frame_names"].asstr()[()]]
        images = [f["images"][i] for i in keep]
        masks = [f["masks"][i] for i in keep]
        confidence = [f["confidence"][i].astype(np.float16) for i in keep]
    return Source(path, "labels", classes, [names[i] for i in keep], images, masks, confidence, annotated[keep])


def load_capture_source(path: Path) -> Source:
    """A capture folder's expert annotations (``annotations/``): the sparse baseline."""
    from ..capture import load_capture

    capture = load_capture(path)
    indices = [i for i, f in enumerate(capture.frames) if f.annotation_path is not None]
    if not indices:
        raise TrainError(f"{path / 'annotations'}: the capture has no annotations to train from")
    images, masks, conf = [], [], []
    for i in indices:
        image = capture.load_image(i)
        mask = capture.load_annotation(i)
        images.append(image)
        masks.append(mask)
        conf.append(np.ones(mask.shape, dtype=np.float16))
    names = [capture.frames[i].name for i in indices]
    return Source(path, "capture", capture.classes, names, images, masks, conf, np.ones(len(indices), dtype=bool))


def load_source(path: str | Path, only_annotated: bool = False) -> Source:
    path = Path(path)
    if path.is_dir():
        return load_capture_source(path)
    if path.is_file():
        return load_labels_h5(path, only_annotated)
    raise TrainError(f"{path}: no such labels.h5 or capture folder")


def load_sources(paths: list[str | Path], only_annotated: bool = False) -> tuple[list[Source], ClassMap]:
    """Every source, and the one class table they share (a clear error naming the odd file)."""
    if not paths:
        raise TrainError("give at least one SOURCE (a labels.h5 or a capture folder)")
    seen: dict[Path, str | Path] = {}
    for p in paths:
        key = Path(p).resolve()
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
    return [
        Frame(source.images[i], source.masks[i], source.confidence[i], bool(source.annotated[i]), source.name,
              source.names[i])
        for i in indices
    ]


def _matches(source: Source, key: str) -> bool:
    key_path = Path(key)
    return key in (source.name, str(source.path)) or (key_path.exists() and key_path.resolve() == source.path.resolve())


def split_by_capture(sources: list[Source], val_captures: list[str] | None = None) -> Split:
    """Validation by capture, never by frame (frames of one video are near-duplicates).

    ``val_captures`` names the held-out sources (name or path); with none named and 3+
    sources the last one is held out; otherwise every source keeps its last contiguous
    block of frames (``HOLDOUT_FRACTION``, at least one frame of any source with two or more)
    for validation, which the description says.
    """
    if val_captures:
        held = []
        for key in val_captures:
            hits = [s for s in sources if _matches(s, key)]
            if not hits:
                raise TrainError(f"--val-captures {key!r}: not one of the sources ({', '.join(str(s.path) for s in sources)})")
            held.extend(h for h in hits if h not in held)
    elif len(sources) >= 3:
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
        return Split(train, val, desc, [str(s.path) for s in held])
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
        desc = ("too few captures to hold one out: validation on the last contiguous block of frames of each "
                f"({'; '.join(parts)})")
    else:
        desc = "no validation: every source has a single frame"
    return Split(train, val, desc, [])


# --- the torch dataset ---------------------------------------------------------------------
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def normalize_image(image: np.ndarray) -> torch.Tensor:
    """(H,W,3) uint8 RGB -> (3,H,W) float, ImageNet mean/std: what ``segment`` feeds the model."""
    x = (image.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))


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
    """Training items: normalised image (3,h,w), target indices (h,w) long, weights (h,w)."""

    def __init__(self, frames: list[Frame], classes: ClassMap, transform=None, *, min_confidence: float = 0.0,
                 expert_weight: float = 1.0, confidence_weight: bool = True,
                 class_weight: np.ndarray | None = None) -> None:
        self.frames = frames
        self.lut = classes.id_to_index_lut()
        self.transform = transform
        self.kw = dict(min_confidence=min_confidence, expert_weight=expert_weight, confidence_weight=confidence_weight,
                       class_weight=class_weight)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        fr = self.frames[i]
        target, weight = make_target(fr.mask, fr.confidence, fr.annotated, self.lut, **self.kw)
        image = fr.image
        if self.transform is not None:
            out = self.transform(image=image, mask=target, weight=weight)
            image, target, weight = out["image"], out["mask"], out["weight"]
            weight = np.where(target == IGNORE_ID, 0.0, weight).astype(np.float32)
        return {
            "image": normalize_image(image),
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
