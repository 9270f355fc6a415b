"""The paper's robustness perturbations of class-id masks (its Table 2).

- erosion-dilation: per frame, erode or dilate the wound (radius 3 px) at random, which is what
  an under- or over-confident 2D segmenter looks like: the boundary between wound and
  background moves, the boundaries between tissue classes stay put.
- jitter: pixels within 3 px of a class boundary flip to a label found nearby.
- half-frames: every other frame (50 -> 25).

Ignore pixels (255) stay ignore and never spread. Everything is deterministic by seed; per
frame the random stream comes from (seed, frame name), so a frame is perturbed the same way
whatever else is in the set.

Why not ``albumentations.Morphological``: it runs grey-level erode/dilate (min/max filters) on
the id image, so a dilation lets the highest id win every contact between classes and an
erosion lets the lowest win, including background eating tissue at inner boundaries. We need
per-class behaviour, so we use exact Euclidean distance transforms from OpenCV instead; a
pixel moves when it is within ``radius`` (Euclidean, inclusive) of the other side, i.e. a disk
structuring element of that radius.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from ..capture.masks import as_id_mask
from ..classes import BACKGROUND_ID, IGNORE_ID
from ..errors import RecipeError

PERTURBATIONS = ("none", "erosion-dilation", "jitter", "half-frames")

_FAR = np.float32(1e9)




def _distance_to(region: np.ndarray) -> np.ndarray:
    """Euclidean distance of every pixel to the nearest pixel of ``region`` (bool)."""
    if not region.any():
        return np.full(region.shape, _FAR, dtype=np.float32)
    # distanceTransform measures the distance to the nearest zero pixel.
    return cv2.distanceTransform((~region).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def erode(mask: np.ndarray, radius: int = 3) -> np.ndarray:
    """Shrink the wound: pixels within ``radius`` of background become background.

    Only background pulls the boundary in: tissue/tissue boundaries, ignore pixels and the
    image border do not (they are not wound boundaries).
    """
    mask = as_id_mask(mask)
    out = mask.copy()
    dist = _distance_to(mask == BACKGROUND_ID)
    out[(dist <= radius + 1e-4) & (mask != BACKGROUND_ID) & (mask != IGNORE_ID)] = BACKGROUND_ID
    return out


def dilate(mask: np.ndarray, radius: int = 3, rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Grow the wound: background within ``radius`` of a class takes the nearest class.

    Each non-background class grows into background only. Where two classes reach the same
    pixel the nearer one wins and exact ties are broken at random, never by id order.
    """
    mask = as_id_mask(mask)
    rng = _rng(rng)
    best = np.full(mask.shape, _FAR, dtype=np.float32)
    label = np.full(mask.shape, BACKGROUND_ID, dtype=np.uint8)
    ids = [int(i) for i in np.unique(mask) if i not in (BACKGROUND_ID, IGNORE_ID)]
    # Distances are square roots of integers, distinct ones differ by far more than 1e-3,
    # so a tiny random offset only reorders exact ties.
    for cid in ids:
        d = _distance_to(mask == cid) + rng.uniform(0.0, 1e-3, size=mask.shape).astype(np.float32)
        closer = d < best
        best[closer] = d[closer]
        label[closer] = cid
    grow = (mask == BACKGROUND_ID) & (best <= radius + 2e-3)
    out = mask.copy()
    out[grow] = label[grow]
    return out


def erode_dilate(
    mask: np.ndarray, radius: int = 3, rng: np.random.Generator | int | None = None
) -> np.ndarray:
    """The paper's Erosion-Dilation case: erosion or dilation with probability 1/2 each."""
    rng = _rng(rng)
    if rng.random() < 0.5:
        return erode(mask, radius)
    return dilate(mask, radius, rng)


def disk_offsets(radius: int) -> np.ndarray:
    """(K, 2) integer (dy, dx) offsets with dy^2 + dx^2 <= radius^2, centre included."""
    r = int(radius)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    keep = dy**2 + dx**2 <= r * r
    return np.stack([dy[keep], dx[keep]], axis=1)


def _disk_kernel(radius: int) -> np.ndarray:
    r = int(radius)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    return (dy**2 + dx**2 <= r * r).astype(np.uint8)


def boundary_band(mask: np.ndarray, band: int = 3) -> np.ndarray:
    """Pixels (not ignore) that have a different, non-ignore label within ``band`` px."""
    mask = as_id_mask(mask)
    disk = _disk_kernel(band)
    near = np.zeros(mask.shape, dtype=np.uint8)
    for cid in np.unique(mask):
        if cid == IGNORE_ID:
            continue
        near += cv2.dilate((mask == cid).astype(np.uint8), disk, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return (near >= 2) & (mask != IGNORE_ID)


def boundary_jitter(
    mask: np.ndarray, band: int = 3, rng: np.random.Generator | int | None = None, p: float = 0.5
) -> np.ndarray:
    """The paper's Jittering case: random flips near class boundaries.

    Each pixel of the boundary band (see ``boundary_band``) is picked with probability ``p``
    and takes the label of a pixel drawn uniformly from the disk of radius ``band`` around it
    (in the unperturbed mask). So labels only ever come from within ``band`` px, a pick can
    land on its own class (no change), and a draw that falls on ignore or off the image
    leaves the pixel as it was.
    """
    mask = as_id_mask(mask)
    rng = _rng(rng)
    h, w = mask.shape
    ys, xs = np.nonzero(boundary_band(mask, band))
    pick = rng.random(ys.size) < p
    ys, xs = ys[pick], xs[pick]
    disk = disk_offsets(band)
    offs = disk[rng.integers(0, len(disk), size=ys.size)]
    qy, qx = ys + offs[:, 0], xs + offs[:, 1]
    inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
    ys, xs, qy, qx = ys[inside], xs[inside], qy[inside], qx[inside]
    new = mask[qy, qx]
    ok = new != IGNORE_ID
    out = mask.copy()
    out[ys[ok], xs[ok]] = new[ok]
    return out


def half_frames(names: Sequence[str]) -> list[str]:
    """Every other frame, starting with the first: 50 -> 25, 7 -> 4 (ceil(N/2)).

    Order is kept as given (capture order), so the kept frames are spread evenly over the
    video the way the paper halves 50 frames to 25.
    """
    return list(names)[::2]


def _frame_rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode("utf-8"))]))


def apply_perturbation(name: str, masks: Mapping[str, np.ndarray], seed: int = 0) -> dict[str, np.ndarray]:
    """Apply a named perturbation to ``{frame name: mask}``; returns a new dict in the same order.

    Names: ``none``, ``erosion-dilation``, ``jitter``, ``half-frames`` (which drops entries
    instead of changing masks). Radii are the paper's 3 px. An unknown name is a RecipeError.
    """
    key = str(name).strip().lower().replace("_", "-")
    if key == "none":
        return {k: np.array(v, copy=True) for k, v in masks.items()}
    if key == "half-frames":
        return {k: np.array(masks[k], copy=True) for k in half_frames(list(masks))}
    if key == "erosion-dilation":
        return {k: erode_dilate(v, 3, _frame_rng(seed, k)) for k, v in masks.items()}
    if key == "jitter":
        return {k: boundary_jitter(v, 3, _frame_rng(seed, k)) for k, v in masks.items()}
    raise RecipeError(f"unknown perturbation {name!r}; choose one of {', '.join(PERTURBATIONS)}")
