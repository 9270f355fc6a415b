"""Which frames of a video (or photos of a folder) to keep: sharp ones, spread over the video,
no two alike.

Two measures, each cheap enough to run on every decoded frame:

- **sharpness**: the variance of the Laplacian of the grey frame at the size it will be written
  (blur removes exactly the high frequencies the Laplacian keeps). It compares frames of one
  video; its absolute value depends on the scene, so the blur floor is relative to the video's
  own 90th percentile.
- **motion**: how far the camera has moved since the start, in image diagonals: the median
  displacement of corners tracked (pyramidal Lucas-Kanade, forward-backward checked) from a
  reference frame, which is replaced after a move of ``step``. A phone held still adds nothing,
  however long, since tremor and sensor noise never add up against a fixed reference.

The video is cut into equal stretches of time and the sharpest usable frame of each is kept;
a pick that barely moved from the previous one (a phone held still) is dropped, and the frames
it leaves free go where the kept frames are furthest apart along the camera's path.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

THUMB_SIDE = 320  # long side of the grey thumbnail that motion is tracked on
MIN_TRACKED = 12  # fewer tracked corners than this: the frame is not comparable with the reference
LOST_MOVE = 0.02  # motion counted for a frame that matches neither the reference nor the previous frame


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a uint8 grey image (higher = sharper)."""
    lap = cv2.Laplacian(gray, cv2.CV_16S)  # |kernel| sums to 8: 255*8 fits in int16
    std = cv2.meanStdDev(lap)[1]
    return float(std[0, 0] ** 2)


def resize_to(image: np.ndarray, max_side: int) -> np.ndarray:
    """``image`` with its long side at most ``max_side`` (area-averaged; never enlarged)."""
    h, w = image.shape[:2]
    scale = max_side / max(h, w)
    if scale >= 1.0:
        return image
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def thumbnail(gray: np.ndarray) -> np.ndarray:
    """The grey thumbnail motion is measured on."""
    return resize_to(gray, THUMB_SIDE)


class MotionTracker:
    """Cumulative camera motion along a video, in image diagonals (see the module docstring).

    ``step``: a displacement from the reference larger than this (a share of the diagonal)
    makes the current frame the new reference. A frame that cannot be compared with the
    reference (a blur smeared the corners, too few of them survived) is compared with the
    previous frame instead, which then becomes the reference; one that matches neither (a cut,
    a blank wall) counts as a move of ``LOST_MOVE``: never a near-duplicate.
    """

    def __init__(self, step: float = 0.005) -> None:
        self.step = step
        self._ref: np.ndarray | None = None
        self._pts: np.ndarray | None = None
        self._base = 0.0  # motion up to the reference frame
        self._prev: np.ndarray | None = None
        self._prev_position = 0.0
        self._position = 0.0

    def update(self, thumb: np.ndarray) -> float:
        """Feed the next frame's thumbnail; returns the motion from the first frame to it."""
        if self._ref is None:
            self._reset(thumb, 0.0)
        else:
            moved = self._displacement(thumb)
            if moved is None and self._prev is not self._ref:
                self._reset(self._prev, self._prev_position)  # go through the previous frame
                moved = self._displacement(thumb)
            if moved is None:
                self._reset(thumb, self._base + LOST_MOVE)
                position = self._base
            elif moved > self.step:
                self._reset(thumb, self._base + moved)
                position = self._base
            else:
                position = self._base + moved
            self._position = max(self._position, position)
        self._prev, self._prev_position = thumb, self._position
        return self._position

    def _reset(self, thumb: np.ndarray, position: float) -> None:
        self._ref, self._base = thumb, position
        self._pts = cv2.goodFeaturesToTrack(thumb, maxCorners=200, qualityLevel=0.01, minDistance=7)

    def _displacement(self, thumb: np.ndarray) -> float | None:
        """Median displacement of the reference's corners in ``thumb`` (share of the diagonal),
        or None when too few track there and back."""
        if self._pts is None or len(self._pts) < MIN_TRACKED or thumb.shape != self._ref.shape:
            return None
        lk = dict(winSize=(21, 21), maxLevel=3,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        fwd, st1, _ = cv2.calcOpticalFlowPyrLK(self._ref, thumb, self._pts, None, **lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(thumb, self._ref, fwd, None, **lk)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1)
        ok &= np.linalg.norm((back - self._pts).reshape(-1, 2), axis=1) < 1.0
        if ok.sum() < max(MIN_TRACKED, 0.25 * len(self._pts)):
            return None
        moved = np.linalg.norm((fwd - self._pts).reshape(-1, 2)[ok], axis=1)
        diagonal = float(np.hypot(*thumb.shape[:2]))
        return float(np.median(moved)) / diagonal


@dataclass
class Pick:
    """Which frames to keep, and why the others went."""

    chosen: list[int]  # positions into the measured frames, in order
    blurred: int  # frames below the blur floor (never candidates)
    near_duplicates: int = 0  # window picks dropped for having barely moved from the previous pick
    filled: int = 0  # frames added in the widest gaps after runs came out empty or duplicated


def usable_mask(sharp: np.ndarray, blur_floor: float) -> np.ndarray:
    """Frames at least ``blur_floor`` times as sharp as the 90th percentile of all of them."""
    sharp = np.asarray(sharp, dtype=np.float64)
    if sharp.size == 0:
        return np.zeros(0, dtype=bool)
    return sharp >= blur_floor * float(np.percentile(sharp, 90))


def pick_spread(sharp: np.ndarray, k: int, *, blur_floor: float, motion: np.ndarray | None = None,
                min_motion: float = 0.0) -> Pick:
    """Up to ``k`` frames: the sharpest usable frame in each of ``k`` equal runs of frames (time,
    or name order for photos). With ``motion`` (a video), a pick that moved less than
    ``min_motion`` (share of the diagonal) from the previous kept one is a near-duplicate and is
    dropped (the sharper of the two stays); runs left without a frame (only blurred ones, or a
    near-duplicate) are made up where the kept frames are furthest apart on the camera's path:
    the sharpest usable frame near the middle of the widest gap, at least ``min_motion`` from
    both ends, until ``k`` or none fits. Photos: all usable ones when there are at most ``k``."""
    sharp = np.asarray(sharp, dtype=np.float64)
    usable = usable_mask(sharp, blur_floor)
    blurred = int((~usable).sum())
    if motion is None and usable.sum() <= k:
        return Pick([int(i) for i in np.flatnonzero(usable)], blurred)
    picks = []
    for run in np.array_split(np.arange(len(sharp)), k):
        candidates = run[usable[run]]
        if candidates.size:
            picks.append(int(candidates[np.argmax(sharp[candidates])]))
    if motion is None:
        return Pick(picks, blurred)
    motion = np.asarray(motion, dtype=np.float64)
    kept: list[int] = []
    for i in picks:
        if kept and motion[i] - motion[kept[-1]] < min_motion:
            if sharp[i] > sharp[kept[-1]]:
                kept[-1] = i
            continue
        kept.append(i)
    duplicates = len(picks) - len(kept)
    filled = 0
    while len(kept) < k:
        extra = _fill_widest_gap(kept, sharp, motion, usable, min_motion)
        if extra is None:
            break
        kept = sorted([*kept, extra])
        filled += 1
    return Pick(kept, blurred, duplicates, filled)


def _fill_widest_gap(kept: list[int], sharp: np.ndarray, motion: np.ndarray, usable: np.ndarray,
                     min_motion: float) -> int | None:
    """The sharpest usable frame in the widest gap between kept frames (or the path's ends)
    that has room for one, preferring the middle half of the gap; None when none has room."""
    start, end = float(motion[0]), float(motion[-1])
    marks = [float(motion[i]) for i in kept]
    gaps = []  # (lo, hi, lo is a kept frame, hi is a kept frame)
    for lo, hi, lo_kept, hi_kept in zip([start, *marks], [*marks, end], [False] + [True] * len(marks),
                                        [True] * len(marks) + [False]):
        gaps.append((hi - lo, lo, hi, lo_kept, hi_kept))
    for _, lo, hi, lo_kept, hi_kept in sorted(gaps, reverse=True):
        room = usable.copy()
        room[kept] = False
        room &= motion >= lo + (min_motion if lo_kept else 0.0)
        room &= motion <= hi - (min_motion if hi_kept else 0.0)
        if not room.any():
            continue
        quarter = (hi - lo) / 4
        middle = room & (motion >= lo + quarter) & (motion <= hi - quarter)
        candidates = np.flatnonzero(middle if middle.any() else room)
        return int(candidates[np.argmax(sharp[candidates])])
    return None
