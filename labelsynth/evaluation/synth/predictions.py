"""Predictions that imitate a good but imperfect 2D segmenter, whose errors differ from view to
view (boundary offsets and jitter, slough taken for granulation, missed rims and small regions,
false blobs on skin), so that a multi-view method has something to fix.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import BACKGROUND, EPITHELIAL, GRANULATION, NECROTIC, SLOUGH, UNKNOWN, WOUND_CLASSES
from .textures import value_noise


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _smooth_field(rng: np.random.Generator, h: int, w: int, scale_px: float) -> np.ndarray:
    return value_noise(rng, (h, w), (max(1.0, h / scale_px), max(1.0, w / scale_px)))


@dataclass
class _ErrorDraws:
    """The random draws every error step shares, scaled to the frame (one per frame, in order)."""

    rng: np.random.Generator
    shape: tuple[int, int]  # (h, w)
    scale: float  # pixel magnitudes are given for 640-pixel-wide frames
    noise: float

    def radius(self, lo: float = 1.0, hi: float = 4.0) -> int:
        """A morphology radius in pixels, at least 1."""
        return int(max(1, round(self.rng.uniform(lo, hi) * self.scale * self.noise)))

    def smooth_field(self, scale_px: float) -> np.ndarray:
        """Smooth noise over the frame with features about ``scale_px`` pixels apart."""
        return _smooth_field(self.rng, *self.shape, scale_px)

    def partial(self, mask: np.ndarray, lo: float, hi: float) -> np.ndarray:
        """A random smooth part (fraction in [lo, hi]) of ``mask``."""
        if not mask.any():
            return mask
        f = self.smooth_field(25 * self.scale + 3)
        q = np.quantile(f[mask], 1 - self.rng.uniform(lo, hi))
        return mask & (f >= q)


def predict_errors(truth: np.ndarray, on_body: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """A plausible automatic segmentation of one frame: ``truth`` with view-specific errors.

    ``on_body`` marks pixels whose ray hit the body (false wound blobs go on skin there).
    ``noise`` scales every error (0 returns the truth).
    """
    lab = truth.copy()
    if noise <= 0:
        return lab
    draws = _ErrorDraws(rng, lab.shape, lab.shape[1] / 640.0, noise)
    p = min(1.0, noise)
    lab = _jitter_boundaries(lab, draws)
    _misjudge_outline(lab, draws)
    _misjudge_tissue_extents(lab, draws)
    _confuse_tissues(lab, draws, p)
    _miss_small_regions(lab, draws, p)
    _false_blobs(lab, truth, on_body, draws, p)
    return lab


def _jitter_boundaries(lab: np.ndarray, draws: _ErrorDraws) -> np.ndarray:
    """Wavy boundaries: a smooth random displacement field, nearest-neighbour resampling."""
    h, w = draws.shape
    amp = 3.5 * draws.scale * draws.noise
    dx = amp * draws.smooth_field(40 * draws.scale + 4)
    dy = amp * draws.smooth_field(40 * draws.scale + 4)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(lab, gx + dx, gy + dy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def _misjudge_outline(lab: np.ndarray, draws: _ErrorDraws) -> None:
    """The wound-bed outline drawn too big or too small (in place)."""
    bed = lab > 0
    r = draws.radius(2.0, 6.0)
    if draws.rng.random() < 0.5:
        grown = cv2.dilate(bed.astype(np.uint8), _disk(r)).astype(bool) & ~bed
        fill = cv2.dilate(lab, _disk(r))  # some neighbouring tissue id
        lab[grown] = fill[grown]
    else:
        lab[bed & ~cv2.erode(bed.astype(np.uint8), _disk(r)).astype(bool)] = BACKGROUND


def _misjudge_tissue_extents(lab: np.ndarray, draws: _ErrorDraws) -> None:
    """Each tissue grown or shrunk inside the bed, in random order (in place)."""
    bed = lab > 0
    for c in draws.rng.permutation(WOUND_CLASSES):
        m = lab == c
        if not m.any():
            continue
        r = draws.radius(1.0, 3.0)
        if draws.rng.random() < 0.5:
            lab[cv2.dilate(m.astype(np.uint8), _disk(r)).astype(bool) & bed] = c
        else:
            ring = m & ~cv2.erode(m.astype(np.uint8), _disk(r)).astype(bool)
            other = np.where(m, 0, lab).astype(np.uint8)
            fill = cv2.dilate(other, _disk(r + 1))
            lab[ring] = np.where(bed[ring], np.where(fill[ring] > 0, fill[ring], c), BACKGROUND)


def _confuse_tissues(lab: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """A missed stretch of edge and the tissue mix-ups a 2D segmenter makes, each in some views
    only (in place), so that views disagree and a multi-view vote can fix them."""
    rng = draws.rng
    # part of the wound edge missed (glare, shadow)
    if rng.random() < 0.35 * p:
        bed = lab > 0
        inner = cv2.erode(bed.astype(np.uint8), _disk(int(max(2, round(14 * draws.scale))))).astype(bool)
        lab[draws.partial(bed & ~inner, 0.2, 0.5)] = BACKGROUND
    # slough taken for granulation (fully or partly) in a good fraction of the views
    if rng.random() < 0.38 * p:
        lab[draws.partial(lab == SLOUGH, 0.5, 1.0)] = GRANULATION
    # granulation taken for slough in a few
    if rng.random() < 0.12 * p:
        lab[draws.partial(lab == GRANULATION, 0.08, 0.25)] = SLOUGH
    # necrotic taken for slough / granulation
    if rng.random() < 0.2 * p:
        lab[draws.partial(lab == NECROTIC, 0.4, 1.0)] = SLOUGH if rng.random() < 0.6 else GRANULATION
    # epithelial rim missed (part to skin, part to granulation)
    if rng.random() < 0.3 * p:
        lab[draws.partial(lab == EPITHELIAL, 0.4, 1.0)] = BACKGROUND if rng.random() < 0.6 else GRANULATION


def _miss_small_regions(lab: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """Small necrotic, unknown and slough regions taken for granulation now and then (in place)."""
    s = draws.scale
    for c in (NECROTIC, UNKNOWN, SLOUGH):
        m = (lab == c).astype(np.uint8)
        if not m.any():
            continue
        n_cc, cc, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        small = max(30 * s * s, 0.02 * max(1, int((lab > 0).sum())))
        for k in range(1, n_cc):
            if stats[k, cv2.CC_STAT_AREA] < small and draws.rng.random() < 0.5 * p:
                lab[cc == k] = GRANULATION


def _false_blobs(lab: np.ndarray, truth: np.ndarray, on_body: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """False-positive wound blobs on the skin in a few views (in place)."""
    rng, noise = draws.rng, draws.noise
    h, w = draws.shape
    if rng.random() < 0.25 * p:
        skin = on_body & (truth == BACKGROUND)
        ys, xs = np.nonzero(skin)
        for _ in range(int(rng.integers(1, 3))):
            if not len(ys):
                break
            k = rng.integers(len(ys))
            rx, ry = rng.uniform(0.015, 0.045) * w * np.sqrt(noise), rng.uniform(0.015, 0.045) * w * np.sqrt(noise)
            yy, xx = np.ogrid[:h, :w]
            wobble = 0.35 * _smooth_field(rng, h, w, 10 * draws.scale + 2)
            blob = ((xx - xs[k]) / rx) ** 2 + ((yy - ys[k]) / ry) ** 2 + wobble < 1.0
            lab[blob & skin] = GRANULATION if rng.random() < 0.7 else EPITHELIAL
