"""Dice, recall, precision and IoU per class and for the wound bed: the one place they are
computed, for the report (agreement, leave-one-out, pairwise), training's validation and the
evaluation against truth.

The paper reports a class only over the population where the truth contains it (its Table 1:
"population sizes for wound bed, granulation and slough are 73, 41 and 31"), so a frame
without slough in its truth neither helps nor hurts the slough score. We follow that rule at
frame level: the mean of per-frame metrics over the frames whose truth contains the class,
with ``n`` = the size of that population. Pooled (micro) counts over all frames are kept
too, because they weigh large and small wounds by area instead of by frame.

Pixels whose truth is 255 (ignore) are excluded everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .classes import IGNORE_ID, WOUND_BED, ClassMap

METRICS = ("dice", "recall", "precision", "iou")


def _ratio(num: int, den: int, all_empty: bool) -> float:
    """num/den with the empty cases pinned down (see ``Counts``)."""
    if den > 0:
        return num / den
    return 1.0 if all_empty else 0.0


@dataclass(frozen=True)
class Counts:
    """Pixel confusion counts of one class (or the wound bed) against everything else.

    A zero denominator gives 1.0 when truth and prediction are both empty (perfect
    agreement on "nothing here") and 0.0 otherwise (e.g. precision of a class the
    prediction missed entirely). Aggregates never see the both-empty 1.0: such a frame is
    outside the class's population because its truth lacks the class.
    """

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0

    def __add__(self, other: "Counts") -> "Counts":
        return Counts(self.tp + other.tp, self.fp + other.fp, self.fn + other.fn, self.tn + other.tn)

    @property
    def present(self) -> bool:
        """Whether the truth contains the class: membership of the population."""
        return self.tp + self.fn > 0

    @property
    def predicted(self) -> bool:
        return self.tp + self.fp > 0

    @property
    def _empty(self) -> bool:
        return self.tp == 0 and self.fp == 0 and self.fn == 0

    @property
    def dice(self) -> float:
        return _ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn, self._empty)

    @property
    def recall(self) -> float:
        return _ratio(self.tp, self.tp + self.fn, self._empty)

    @property
    def precision(self) -> float:
        return _ratio(self.tp, self.tp + self.fp, self._empty)

    @property
    def iou(self) -> float:
        return _ratio(self.tp, self.tp + self.fp + self.fn, self._empty)

    def metrics(self) -> dict[str, float]:
        return {m: getattr(self, m) for m in METRICS}


def _check_pair(pred: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred)
    truth = np.asarray(truth)
    if pred.shape != truth.shape:
        raise ValueError(f"prediction shape {pred.shape} != truth shape {truth.shape}")
    if pred.ndim != 2:
        raise ValueError(f"masks must be 2-D class-id arrays, got shape {pred.shape}")
    for what, a in (("prediction", pred), ("truth", truth)):
        if a.size and (a.min() < 0 or a.max() > 255):
            raise ValueError(f"{what} has ids outside 0..255")
    return pred.astype(np.int64, copy=False), truth.astype(np.int64, copy=False)


def confusion_matrix(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """256x256 pixel counts ``[truth id, predicted id]`` over pixels whose truth is not ignore."""
    pred, truth = _check_pair(pred, truth)
    valid = truth != IGNORE_ID
    idx = truth[valid] * 256 + pred[valid]
    return np.bincount(idx, minlength=256 * 256).reshape(256, 256)


def _counts_for(conf: np.ndarray, ids: Sequence[int]) -> Counts:
    """Counts of the union of ``ids`` against all other ids, from a confusion matrix."""
    sel = np.zeros(256, dtype=bool)
    sel[list(ids)] = True
    tp = int(conf[np.ix_(sel, sel)].sum())
    fn = int(conf[sel, :].sum()) - tp
    fp = int(conf[:, sel].sum()) - tp
    tn = int(conf.sum()) - tp - fn - fp
    return Counts(tp, fp, fn, tn)


def frame_counts(pred: np.ndarray, truth: np.ndarray, classes: ClassMap) -> dict[str, Counts]:
    """Counts per class name, plus ``"wound_bed"`` (any wound-bed id vs the rest).

    A predicted 255 or an id outside the class map is simply "not that class": it is a
    false negative for the truth's class and a false positive for nobody.
    """
    if WOUND_BED in classes.names:
        raise ValueError(f"a class may not be named {WOUND_BED!r}: the name is reserved for the aggregate")
    conf = confusion_matrix(pred, truth)
    out = {WOUND_BED: _counts_for(conf, classes.wound_bed_ids)}
    for c in classes.classes:
        out[c.name] = _counts_for(conf, [c.id])
    return out


@dataclass
class Scores:
    """Per-frame counts and their aggregates for one method on one capture (or many)."""

    keys: list[str]
    frames: list[str]
    per_frame: list[dict[str, Counts]] = field(repr=False)

    def population(self, key: str) -> list[int]:
        """Indices of the frames whose truth contains ``key``."""
        return [i for i, fc in enumerate(self.per_frame) if fc[key].present]

    def mean(self, key: str) -> dict[str, float | int | None]:
        """Paper rule: per-frame metrics averaged over the population; None when it is empty."""
        pop = self.population(key)
        row: dict[str, float | int | None] = {}
        for m in METRICS:
            vals = [getattr(self.per_frame[i][key], m) for i in pop]
            row[m] = float(np.mean(vals)) if vals else None
        row["n"] = len(pop)
        return row

    def pooled(self, key: str) -> Counts:
        """Micro counts summed over all frames (including frames where the class is absent)."""
        total = Counts()
        for fc in self.per_frame:
            total = total + fc[key]
        return total

    def table(self, pooled: bool = False) -> list[dict]:
        """Rows ``{class, dice, recall, precision, iou, n}``, wound bed first.

        ``pooled=True`` gives micro metrics from summed counts instead (``n`` is still the
        population size, so the two tables line up). Metrics are None (JSON null) for a
        class no frame's truth contains.
        """
        rows = []
        for key in self.keys:
            if pooled:
                c = self.pooled(key)
                n = len(self.population(key))
                vals = c.metrics() if n else {m: None for m in METRICS}
                rows.append({"class": key, **vals, "n": n})
            else:
                rows.append({"class": key, **self.mean(key)})
        return rows

    def frame_table(self) -> list[dict]:
        """One row per (frame, key): the per-frame metrics and whether it is in the population."""
        rows = []
        for name, fc in zip(self.frames, self.per_frame):
            for key in self.keys:
                c = fc[key]
                rows.append(
                    {"frame": name, "class": key, **c.metrics(), "in_population": c.present,
                     "tp": c.tp, "fp": c.fp, "fn": c.fn}
                )
        return rows

    def summary_line(self, keys: Sequence[str] | None = None) -> str:
        """One line for logs: Dice/recall (n) per class with a population, wound bed first."""
        parts = []
        for row in self.table():
            if keys is not None and row["class"] not in keys:
                continue
            if keys is None and row["class"] == "background":
                continue
            label = row["class"].replace("_", " ")
            if row["n"] == 0:
                parts.append(f"{label}: -")
            else:
                parts.append(f"{label}: Dice {row['dice']:.3f} recall {row['recall']:.3f} (n={row['n']})")
        return " | ".join(parts)

    def to_dict(self) -> dict:
        """JSON-ready: mean and pooled tables plus per-frame rows."""
        return {"mean": self.table(), "pooled": self.table(pooled=True), "frames": self.frame_table()}


def score_frames(
    preds: Sequence[np.ndarray],
    truths: Sequence[np.ndarray],
    classes: ClassMap,
    names: Sequence[str] | None = None,
) -> Scores:
    """Score predicted masks against truth masks, frame by frame (same order in both lists)."""
    if len(preds) != len(truths):
        raise ValueError(f"{len(preds)} predictions but {len(truths)} truths")
    if names is None:
        names = [str(i) for i in range(len(preds))]
    elif len(names) != len(preds):
        raise ValueError(f"{len(names)} names for {len(preds)} frames")
    per_frame = [frame_counts(p, t, classes) for p, t in zip(preds, truths)]
    keys = [WOUND_BED, *classes.names]
    return Scores(keys=keys, frames=list(names), per_frame=per_frame)


def errors_far_from_edge(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None,
                         distance_px: float = 5.0) -> tuple[int, int]:
    """(wrong pixels, wrong pixels farther than ``distance_px`` from the true edge) of a binary mask.

    Boundary errors (a mask a pixel or two too wide) are what any segmentation makes; errors
    far from the edge are whole regions labelled wrong (a table taken for the object, a hole
    through it), the failures worth telling apart. The distance of a pixel to the true edge is
    its distance to the nearest pixel of the other side of ``truth`` (OpenCV's exact L2
    distance transform); ``valid`` (default all) limits what counts.
    """
    import cv2

    pred, truth = np.asarray(pred, dtype=bool), np.asarray(truth, dtype=bool)
    if pred.shape != truth.shape:
        raise ValueError(f"prediction {pred.shape} and truth {truth.shape} differ in shape")
    wrong = pred != truth
    if valid is not None:
        wrong &= np.asarray(valid, dtype=bool)
    n_wrong = int(wrong.sum())
    if n_wrong == 0 or truth.all() or not truth.any():
        return n_wrong, n_wrong  # no edge: every error is far from it
    to_edge = np.where(truth,
                       cv2.distanceTransform(truth.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                       cv2.distanceTransform((~truth).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    return n_wrong, int((wrong & (to_edge > distance_px)).sum())
