"""The numbers of the consistency report: agreement, leave-one-view-out, cross-view pairs, flags.

Why three measures:

- *agreement* (input mask vs the field's mask of the same frame) is cheap, but a frame that
  taught the field is partly compared with itself;
- *leave-one-view-out* refits the semantic stage without the frame (geometry reused) and
  asks whether the other views alone predict the expert's mask: the honest test of an
  annotation;
- *pairwise* consistency needs no field labels at all: each labelled frame's mask is carried
  onto the surface and compared with every other frame's mask where both see the same
  surface, so an annotator can see which two of their masks contradict each other.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera
from ..capture.model import Capture
from ..classes import IGNORE_ID, ClassMap
from ..classes import WOUND_BED
from ..metrics import Counts, frame_counts
from ..progress import track
from ..render.renderer import FieldRenderer
from ..semantics.head import SemanticHead

# Cross-view consistency
PAIR_MAX_SIDE = 160  # frames are cast at most this many pixels on their long side
DEPTH_TOLERANCE = 0.03  # unit-cube units (the cube is 2 wide): 1.5 % of the scene size...
DEPTH_TOLERANCE_PX = 2.0  # ...plus this many pixel footprints at the point's depth
MIN_SHARED_POINTS = 20  # fewer shared labelled points: the pair's Dice is undefined (null)

# Flagging (see ``flag_frames``)
MAD_K = 3.0
MAD_SCALE = 1.4826  # MAD -> standard deviation for a normal distribution
MIN_MARGIN = 0.05  # the threshold is at least this far above the median disagreement
ABS_FLOOR = 0.15  # never flag a disagreement (1 - Dice) below this
GROSS = 0.5  # with too few frames for statistics, flag only gross disagreement
MIN_GROUP = 3
CLASS_MIN_SHARE = 0.1  # a tissue class is checked where it covers >= 10 % of the wound bed...
CLASS_MIN_PIXELS = 16  # ...and at least this many pixels


def agreement(input_mask: np.ndarray, field_mask: np.ndarray, classes: ClassMap) -> dict[str, float]:
    """Dice per class and for the wound bed between an input mask (the reference) and the field's.

    Ignore pixels (255) of the input are left out. A class absent from both masks scores 1.0
    (they agree it is not there), following ``metrics.Counts``.
    """
    counts = frame_counts(field_mask, input_mask, classes)
    return {k: float(c.dice) for k, c in counts.items()}


def class_presence(mask: np.ndarray, classes: ClassMap) -> dict[str, int]:
    """Pixel count per class name and for the wound bed (ignore pixels not counted)."""
    hist = np.bincount(np.asarray(mask, dtype=np.int64).ravel(), minlength=256)
    out = {WOUND_BED: int(hist[classes.wound_bed_ids].sum())}
    for c in classes.classes:
        out[c.name] = int(hist[c.id])
    return out


# ------------------------------------------------------------------------------------------
# cross-view consistency of the inputs
# ------------------------------------------------------------------------------------------
@dataclass
class SurfaceLabels:
    """One frame's mask carried onto the surface at a reduced scale."""

    camera: Camera  # the reduced camera (unit coordinates)
    hit: np.ndarray  # (h, w) bool
    depth: np.ndarray  # (h, w) view depth of the hit (inf where no hit)
    label_img: np.ndarray  # (h, w) class ids where a labelled pixel hit the surface, else 255
    points: np.ndarray  # (n, 3) unit-cube hit points of labelled pixels
    labels: np.ndarray  # (n,) class ids of those points (no ignore)


def _reduced(camera: Camera, max_side: int) -> Camera:
    factor = min(1.0, max_side / max(camera.width, camera.height))
    return camera if factor >= 1.0 else camera.scaled(factor)


def surface_labels(caster, camera_unit: Camera, mask: np.ndarray, max_side: int = PAIR_MAX_SIDE) -> SurfaceLabels:
    """Cast a frame's pixels onto the surface and attach the mask's labels to the hit points."""
    cam = _reduced(camera_unit, max_side)
    hit, points, _ = caster.cast_camera(cam)
    small = cv2.resize(np.ascontiguousarray(mask), (cam.width, cam.height), interpolation=cv2.INTER_NEAREST).ravel()
    depth = np.full(len(hit), np.inf)
    if hit.any():
        depth[hit] = cam.project(points[hit])[1]
    keep = hit & (small != IGNORE_ID)
    label_img = np.where(keep, small, IGNORE_ID).astype(np.uint8).reshape(cam.height, cam.width)
    return SurfaceLabels(cam, hit.reshape(cam.height, cam.width), depth.reshape(cam.height, cam.width),
                         label_img, points[keep], small[keep].astype(np.uint8))


def _pair_counts(a: SurfaceLabels, b: SurfaceLabels, wound_ids: np.ndarray) -> tuple[Counts, int]:
    """(wound-bed counts, shared points): a's labelled points seen by b, a's labels as truth."""
    if len(a.points) == 0:
        return Counts(), 0
    cam = b.camera
    uv, depth = cam.project(a.points)
    u = np.floor(uv[:, 0]).astype(np.int64)
    v = np.floor(uv[:, 1]).astype(np.int64)
    inside = (depth > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    idx = np.nonzero(inside)[0]
    u, v, d = u[idx], v[idx], depth[idx]
    tol = DEPTH_TOLERANCE + DEPTH_TOLERANCE_PX * d / min(cam.fx, cam.fy)
    visible = b.hit[v, u] & (np.abs(b.depth[v, u] - d) < tol)
    idx, u, v = idx[visible], u[visible], v[visible]
    if len(idx) == 0:
        return Counts(), 0
    lb = b.label_img[v, u]
    ok = lb != IGNORE_ID
    la, lb = a.labels[idx[ok]], lb[ok]
    wa, wb = np.isin(la, wound_ids), np.isin(lb, wound_ids)
    return Counts(tp=int((wa & wb).sum()), fp=int((~wa & wb).sum()), fn=int((wa & ~wb).sum())), int(ok.sum())


def pairwise_consistency(
    caster,
    cameras_unit: Sequence[Camera],
    masks: Sequence[np.ndarray],
    classes: ClassMap,
    *,
    max_side: int = PAIR_MAX_SIDE,
    progress: bool = True,
) -> list[list[float | None]]:
    """Wound-bed Dice between every pair of labelled frames over the surface both see.

    Symmetric: the counts of i seen from j and j seen from i are pooled. The diagonal is 1;
    a pair sharing fewer than ``MIN_SHARED_POINTS`` labelled points is None (no overlap).
    """
    n = len(masks)
    surf = [surface_labels(caster, c, m, max_side) for c, m in track(list(zip(cameras_unit, masks)), "casting masks", enabled=progress)]
    wound_ids = np.asarray(classes.wound_bed_ids)
    mat: list[list[float | None]] = [[1.0 if i == j else None for j in range(n)] for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            counts_ij, shared_ij = _pair_counts(surf[i], surf[j], wound_ids)
            counts_ji, shared_ji = _pair_counts(surf[j], surf[i], wound_ids)
            if shared_ij + shared_ji < MIN_SHARED_POINTS:
                continue
            mat[i][j] = mat[j][i] = (counts_ij + counts_ji).dice
    return mat


# ------------------------------------------------------------------------------------------
# leave-one-view-out
# ------------------------------------------------------------------------------------------
def leave_one_out(
    view: FieldRenderer,
    capture: Capture,
    heads: Mapping[str, SemanticHead],
    *,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """The mask of each frame named in ``heads`` rendered by its own head, one trained
    without that frame."""
    cams = capture.unit_cameras()
    index = {n: i for i, n in enumerate(capture.names)}
    return {name: view.render(cams[index[name]], head).mask
            for name, head in track(list(heads.items()), "leave-one-view-out", enabled=progress)}


# ------------------------------------------------------------------------------------------
# flagging
# ------------------------------------------------------------------------------------------
@dataclass
class Check:
    """One frame's disagreement values to be judged: key -> 1 - Dice, and what was measured."""

    name: str
    group: str  # "loo" (annotated frames, leave-one-out) or "agreement" (the others)
    disagreement: dict[str, float]


def checked_keys(reference: np.ndarray, other: np.ndarray, classes: ClassMap) -> list[str]:
    """The wound bed, plus the tissue classes large enough in either mask to judge fairly.

    Small classes (a few pixels of necrosis) swing their Dice wildly from view to view and
    would flag good frames, so a class counts only where it covers ``CLASS_MIN_SHARE`` of
    the wound bed and ``CLASS_MIN_PIXELS`` pixels in the reference or the other mask.
    """
    keys = [WOUND_BED]
    pa, pb = class_presence(reference, classes), class_presence(other, classes)
    wb = classes.wound_bed_indices
    for i in wb:
        name = classes.classes[i].name
        for p in (pa, pb):
            if p[name] >= max(CLASS_MIN_PIXELS, CLASS_MIN_SHARE * p[WOUND_BED]):
                keys.append(name)
                break
    return keys


def _threshold(values: Sequence[float]) -> tuple[float, float]:
    """(median, threshold) of a robust outlier rule on disagreement values."""
    med = float(np.median(values))
    mad = float(np.median(np.abs(np.asarray(values) - med)))
    return med, med + max(MAD_K * MAD_SCALE * mad, MIN_MARGIN)


def flag_frames(checks: Sequence[Check]) -> dict[str, tuple[bool, str]]:
    """Which frames disagree clearly more than the others, and why.

    Per key (wound bed, each tissue class) and per group (annotated frames judged by their
    leave-one-out Dice; the other frames by their agreement with the field), a frame is
    flagged when ``1 - Dice > median + max(3 * 1.4826 * MAD, 0.05)`` over the group's frames
    and ``1 - Dice > 0.15``. A group of fewer than 3 frames borrows the values of all groups
    for its median and MAD; with fewer than 3 frames overall only ``1 - Dice > 0.5`` flags.
    The reason lists every key over its threshold, the largest excess first.
    """
    by_key_group: dict[tuple[str, str], list[float]] = {}
    by_key: dict[str, list[float]] = {}
    for c in checks:
        for k, d in c.disagreement.items():
            by_key_group.setdefault((k, c.group), []).append(d)
            by_key.setdefault(k, []).append(d)
    out: dict[str, tuple[bool, str]] = {}
    for c in checks:
        hits: list[tuple[float, str]] = []
        for k, d in c.disagreement.items():
            values = by_key_group[(k, c.group)]
            if len(values) < MIN_GROUP:
                values = by_key[k]
            if len(values) < MIN_GROUP:
                med, thr = float(np.median(values)), GROSS
            else:
                med, thr = _threshold(values)
            if d > thr and d > ABS_FLOOR:
                what = "LOO Dice" if c.group == "loo" else "agreement Dice"
                hits.append((d - thr, f"{k.replace('_', ' ')} {what} {1 - d:.2f} vs median {1 - med:.2f}"))
        hits.sort(key=lambda h: -h[0])
        out[c.name] = (bool(hits), "; ".join(r for _, r in hits))
    return out
