"""Camera paths: a hand-held arc above the wound (one-sided) and one turn around the limb
(all-around), each with smooth random wobbles in distance, elevation or tilt, and roll.

A path returns its cameras and the summary ``scene.json`` records as ``camera_path``. Phone-like
changes along the path (``PathChanges``: the distance to the wound and the focal length, the
``distance_change`` and ``zoom`` options) multiply the path's own distance and focal length frame
by frame; they come from their own random stream (``layouts``), so a path without them is the
path it always was. What a path could vary further (uneven speed) belongs here too.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ...cameras import Camera, look_at
from .config import SynthConfig

if TYPE_CHECKING:
    from .around import AroundScene
    from .scene import OneSidedScene


def smooth_curve(rng: np.random.Generator, t: np.ndarray, freqs: tuple[float, ...]) -> np.ndarray:
    """A smooth random curve in about [-1, 1] over t in [0, 1] (sum of a few sines)."""
    out = np.zeros_like(t)
    total = 0.0
    for f in freqs:
        a = rng.uniform(0.5, 1.0)
        out += a * np.sin(2 * np.pi * f * rng.uniform(0.8, 1.2) * t + rng.uniform(0, 2 * np.pi))
        total += a
    return out / total


class PathChanges(NamedTuple):
    """Per-frame factors on a path's distance to its aim point and on its focal length."""

    distance: np.ndarray  # (N,)
    focal: np.ndarray  # (N,)

    def info(self) -> dict:
        """What scene.json's ``camera_path`` adds (nothing when the path is unchanged)."""
        out = {}
        if np.ptp(self.distance) > 0:
            out["distance_factor"] = [float(self.distance.min()), float(self.distance.max())]
        if np.ptp(self.focal) > 0:
            out["focal_factor"] = [float(self.focal.min()), float(self.focal.max())]
        return out


def path_changes(rng: np.random.Generator, cfg: SynthConfig) -> PathChanges | None:
    """The ``distance_change`` and ``zoom`` factors of every frame (None when both are off): smooth
    curves between 1/(1+x) and 1+x, i.e. x in log space, so moving in and out are alike."""
    if not (cfg.distance_change or cfg.zoom):
        return None
    t = np.linspace(0.0, 1.0, cfg.frames)
    distance = (1.0 + cfg.distance_change) ** smooth_curve(rng, t, (0.7, 1.5))
    focal = (1.0 + cfg.zoom) ** smooth_curve(rng, t, (0.6, 1.3))
    return PathChanges(distance, focal)


def _apply(changes: PathChanges | None, dist: np.ndarray, fx: float) -> tuple[np.ndarray, np.ndarray]:
    """The path's distances and per-frame focal lengths after ``changes``."""
    if changes is None:
        return dist, np.full(len(dist), fx)
    return dist * changes.distance, fx * changes.focal


def hand_held_path(rng: np.random.Generator, scene: OneSidedScene, cfg: SynthConfig,
                   changes: PathChanges | None = None) -> tuple[list[Camera], dict]:
    """A hand-held phone path: an arc above the wound with varying elevation, distance and roll."""
    hfov = np.deg2rad(rng.uniform(55, 65))
    fx = cfg.width / (2 * np.tan(hfov / 2))
    frac = rng.uniform(0.25, 0.35)  # wound diameter / image width at the typical distance
    d0 = 2 * scene.wound_radius / (frac * 2 * np.tan(hfov / 2))
    n = cfg.frames
    t = np.linspace(0.0, 1.0, n)
    sweep = np.deg2rad(rng.uniform(200, 300)) * (1 if rng.random() < 0.5 else -1)
    az = rng.uniform(0, 2 * np.pi) + sweep * t + 0.08 * smooth_curve(rng, t, (1.7, 3.1))
    el_lo, el_hi = np.deg2rad(35), np.deg2rad(80)
    el_curve = 0.5 + 0.5 * smooth_curve(rng, t, (0.8, 1.3, 2.2))
    el_curve = (el_curve - el_curve.min()) / max(1e-6, np.ptp(el_curve))
    el = el_lo + (el_hi - el_lo) * (0.05 + 0.9 * el_curve)
    dist = d0 * (1 + 0.2 * smooth_curve(rng, t, (0.9, 1.9)))
    roll = np.deg2rad(6) * smooth_curve(rng, t, (1.1, 2.7))
    dist, focal = _apply(changes, dist, fx)
    jit = 0.15 * scene.wound_radius
    tx, ty = jit * smooth_curve(rng, t, (1.3, 2.9)), jit * smooth_curve(rng, t, (1.6, 3.3))
    c0 = scene.center
    normal, t1, t2 = np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    cams = []
    for i in range(n):
        eye = c0 + dist[i] * (np.cos(el[i]) * (np.cos(az[i]) * t1 + np.sin(az[i]) * t2) + np.sin(el[i]) * normal)
        target = c0 + tx[i] * t1 + ty[i] * t2
        c2w = look_at(eye, target, up=normal)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        c2w[:3, :3] = c2w[:3, :3] @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        cams.append(Camera(cfg.width, cfg.height, focal[i], focal[i], cfg.width / 2, cfg.height / 2, c2w))
    info = {"hfov_deg": float(np.rad2deg(hfov)), "typical_distance": float(d0),
            "elevation_deg": [float(np.rad2deg(el.min())), float(np.rad2deg(el.max()))],
            "distance": [float(dist.min()), float(dist.max())], "sweep_deg": float(np.rad2deg(sweep))}
    return cams, {**info, **(changes.info() if changes else {})}


UNEVEN_DWELL = 0.75
"""``all-around-uneven``: the share of the frames spent on the first third of the turn..."""
UNEVEN_SHARE = 1 / 3
"""...which is this share of the turn; the rest is passed in a quarter of the frames."""


def turn_progress(t: np.ndarray, cfg: SynthConfig) -> np.ndarray:
    """How far round the turn each frame is (0..1 at times ``t`` in [0, 1)): even for
    ``all-around``; for ``all-around-uneven`` the camera dwells on one side of the limb (the first
    ``UNEVEN_SHARE`` of the turn takes ``UNEVEN_DWELL`` of the frames) and passes the other side
    quickly, the speed changing smoothly (a logistic step over about 5% of the video). No random
    draw, so the scene and the wobbles are those of ``all-around`` with the same seed."""
    if cfg.layout != "all-around-uneven":
        return t
    slow, fast = UNEVEN_SHARE / UNEVEN_DWELL, (1 - UNEVEN_SHARE) / (1 - UNEVEN_DWELL)
    fine = np.linspace(0.0, 1.0, 4001)
    speed = slow + (fast - slow) / (1 + np.exp(-(fine - UNEVEN_DWELL) / 0.012))
    done = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2)])
    return np.interp(t, fine, done / done[-1])


def orbit_path(rng: np.random.Generator, scene: AroundScene, cfg: SynthConfig,
               changes: PathChanges | None = None) -> tuple[list[Camera], dict]:
    """An all-around path: one turn around the limb's axis (world x), always aimed at the axis
    near the wound, with smooth random wobbles in distance, position along the axis, tilt
    (looking a little along the limb) and roll. The axis runs across the image."""
    hfov = np.deg2rad(rng.uniform(55, 65))
    tan = np.tan(hfov / 2)
    fx = cfg.width / (2 * tan)
    r, R = scene.radius, scene.wound_radius
    # distance from the axis: the limb's outline takes 75-95 % of the image height, so the band
    # runs through the frame and the limb's sides show; the region of interest (about the image
    # footprint at the axis) then holds the limb's cross-section with room to spare
    vhalf = np.arctan(tan * cfg.height / cfg.width)
    d0 = float(r / np.sin(rng.uniform(0.75, 0.95) * vhalf))
    n = cfg.frames
    t = np.arange(n) / n
    turn = 2 * np.pi * (1 if rng.random() < 0.5 else -1)
    theta = rng.uniform(-np.pi, np.pi) + turn * turn_progress(t, cfg) + 0.08 * smooth_curve(rng, t, (1.7, 3.1))
    dist = d0 * (1 + 0.12 * smooth_curve(rng, t, (0.9, 1.9)))
    along = 0.5 * R * smooth_curve(rng, t, (0.7, 1.6))  # aim point along the axis
    tilt = np.deg2rad(rng.uniform(5, 15)) * smooth_curve(rng, t, (0.8, 1.7))
    roll = np.deg2rad(6) * smooth_curve(rng, t, (1.1, 2.7))
    dist, focal = _apply(changes, dist, fx)
    x_axis = np.array([1.0, 0, 0])
    cams = []
    for i in range(n):
        radial = np.array([0.0, np.sin(theta[i]), np.cos(theta[i])])
        tangent = np.array([0.0, np.cos(theta[i]), -np.sin(theta[i])])
        target = scene.axis_point + along[i] * x_axis
        eye = target + dist[i] * (np.cos(tilt[i]) * radial + np.sin(tilt[i]) * x_axis)
        c2w = look_at(eye, target, up=tangent)  # image right = +x (the axis)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        c2w[:3, :3] = c2w[:3, :3] @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        cams.append(Camera(cfg.width, cfg.height, focal[i], focal[i], cfg.width / 2, cfg.height / 2, c2w))
    info = {"kind": "orbit", "axis": "x", "hfov_deg": float(np.rad2deg(hfov)), "typical_distance": float(d0),
            "distance": [float(dist.min()), float(dist.max())],
            "tilt_deg": [float(np.rad2deg(tilt.min())), float(np.rad2deg(tilt.max()))],
            "along_axis": [float(along.min()), float(along.max())], "sweep_deg": float(np.rad2deg(turn)),
            "start_angle_deg": float(np.rad2deg(theta[0]))}
    return cams, {**info, **(changes.info() if changes else {})}
