"""Choosing the region of interest: the cube the field models, in world coordinates.

The field lives in [-1, 1]^3; ``SceneNormalization`` maps world coordinates into it. The
cube must hold what the cameras look at (a wound and the skin around it, or an object) and
need not hold the cameras themselves: the field samples only inside the cube.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..cameras import Camera
from .model import SceneNormalization

FOOTPRINT_MARGIN = 1.2
# The cube reaches as far as this share of the cameras' axes stray from the centre (a few
# stray frames may look elsewhere); the same share as the initial shape's view test.
AIM_QUANTILE = 0.9
OUTLIER_FACTOR = 5.0
MIN_POINTS = 10


def region_of_interest(cameras: Sequence[Camera], points: np.ndarray | None = None) -> SceneNormalization:
    """The centre and half-size of the region the cameras look at.

    Centre:
      1. Without points: the least-squares point closest to all optical axes (where the
         cameras converge: the object of an object-centric capture, the wound of a phone
         capture that keeps the wound in view). If the axes are (nearly) parallel, or the
         point lies behind the cameras, it is undefined; then the centre is the mean camera
         centre moved along the mean viewing direction by twice the cameras' spread (a
         guess, since parallel axes carry no depth; the half-size then grows to at least
         that depth so that the cube reaches from the cameras to twice as far).
      2. With SfM points: the per-axis median of the points seen inside at least 2 views
         (at least 1 if too few qualify; the axes centre if still too few). SfM points lie
         on the surface, so they beat any guess from the axes, and the median ignores
         stray background points.
    Half-size: the half-width of an image's footprint at the centre (median camera distance
    to the centre x max(tan half-FOV x, tan half-FOV y)) x 1.2, plus how far from the centre
    the cameras aim (``_aim_offsets``: where each optical axis passes the centre's depth; the
    90th percentile) beyond the 0.2 footprint the margin already adds; and, when points are
    given, at least the 95th percentile of their distances to the centre after dropping
    points farther than 5x the median distance.
    Cameras that converge on the centre (an object filmed all around, a phone aimed at a
    wound) aim at it, so the cube is one footprint; cameras close to a large object, each
    aimed at a different part of it (a building that fills every view), see that much
    further, and a cube of one footprint would leave what they see outside it, where the
    field can only call it background.
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("region_of_interest needs at least one camera")
    centres = np.array([c.center for c in cameras])
    forwards = np.array([c.forward for c in cameras])

    centre, guessed_depth = _axes_centre(centres, forwards)
    kept = _visible_points(cameras, points)
    if kept is not None:
        centre = np.median(kept, axis=0)

    dist = np.linalg.norm(centres - centre, axis=1)
    d_med = float(np.median(dist))
    tan_half = float(np.median([max(0.5 * c.width / c.fx, 0.5 * c.height / c.fy) for c in cameras]))
    footprint = d_med * tan_half
    # the footprint's margin already covers axes that miss the centre by less than it
    stray = float(np.quantile(_aim_offsets(centres, forwards, centre), AIM_QUANTILE))
    half = footprint * FOOTPRINT_MARGIN + max(0.0, stray - footprint * (FOOTPRINT_MARGIN - 1.0))

    if kept is None and guessed_depth is not None:
        half = max(half, guessed_depth)  # depth unknown: reach from the cameras to twice the guess
    if kept is not None:
        r = np.linalg.norm(kept - centre, axis=1)
        r_med = float(np.median(r))
        if r_med > 0:
            r = r[r <= OUTLIER_FACTOR * r_med]
        if len(r):
            half = max(half, float(np.percentile(r, 95)))

    if not np.isfinite(half) or half <= 1e-9:
        spread = float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1))) if len(cameras) > 1 else 0.0
        half = spread if spread > 1e-9 else 1.0
    return SceneNormalization(center=np.asarray(centre, dtype=np.float64), scale=float(half))


def _aim_offsets(centres: np.ndarray, forwards: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Per camera (centres and unit viewing directions, (N, 3) each), the max-norm distance from
    ``centre`` of the point where its optical axis reaches the centre's depth: zero for cameras
    aimed at the centre."""
    depths = np.einsum("ni,ni->n", centre - centres, forwards).clip(min=0.0)
    return np.abs(centres + depths[:, None] * forwards - centre).max(axis=1)


def _axes_centre(centres: np.ndarray, forwards: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Least-squares intersection of the optical axes, and None; or, when it is undefined,
    a point guessed along the mean viewing direction and the guessed depth."""
    n = len(centres)
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]  # (N,3,3)
    A = projectors.sum(0)
    b = np.einsum("nij,nj->i", projectors, centres)
    eig = np.linalg.eigvalsh(A)
    if n >= 2 and eig[0] > 1e-3 * n:  # >~2 degrees of RMS angle between the axes
        x = np.linalg.solve(A, b)
        depths = np.einsum("ni,ni->n", x - centres, forwards)
        if np.median(depths) > 0:
            return x, None
    mean_forward = forwards.mean(0)
    norm = np.linalg.norm(mean_forward)
    mean_forward = mean_forward / norm if norm > 1e-9 else forwards[0]
    spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1))) if n > 1 else 0.0
    depth = 2.0 * spread if spread > 1e-9 else 1.0
    return centres.mean(0) + depth * mean_forward, depth


def _visible_points(cameras: list[Camera], points: np.ndarray | None) -> np.ndarray | None:
    """Finite points seen inside >= 2 views (>= 1 if too few), or None if too few either way."""
    if points is None:
        return None
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < MIN_POINTS:
        return None
    views = np.zeros(len(pts), dtype=np.int64)
    for cam in cameras:
        # Pinhole projection is enough to count views and avoids distortion blow-ups far
        # outside the image for points behind or beside the camera.
        p_cam = (pts - cam.center) @ cam.c2w[:3, :3]  # OpenGL camera axes
        depth = -p_cam[:, 2]
        ok = depth > 1e-9
        safe = np.where(ok, depth, 1.0)
        u = cam.fx * p_cam[:, 0] / safe + cam.cx
        v = -cam.fy * p_cam[:, 1] / safe + cam.cy
        views += ok & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
    for need in (2, 1):
        kept = pts[views >= need]
        if len(kept) >= MIN_POINTS:
            return kept
    return None
