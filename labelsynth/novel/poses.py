"""Novel camera poses around the captured path, and the test that keeps only well-seen ones.

A pose starts from a point on the captured path (between two neighbouring frames: position
interpolated, orientation slerped, the focal length of the first) and its target, the point
its optical axis meets the surface. It is then tilted about the target (orbiting it), moved
closer or farther along the axis, rolled about the axis, and zoomed. ``Spread`` bounds each
change; ``Spread.scaled(0)`` gives back the path itself.

A pose is kept only if, cast at low resolution onto the fitted surface, it shows about as much
surface as the real frames do and almost all of that surface was seen by some real frame;
the others are rejected and counted by reason (``PoseSample``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..cameras import Camera
from ..errors import LabelsynthError

REJECT_REASONS = ("empty", "unseen")


@dataclass(frozen=True)
class Spread:
    """How far novel poses stray from the captured path (each bound symmetric, drawn uniformly)."""

    along: float = 1.0  # fraction of the way to the next frame of the path
    tilt_deg: float = 15.0  # orbit about the target, in a random direction
    distance: float = 0.25  # distance to the target scaled within [1/(1+d), 1+d]
    roll_deg: float = 20.0  # roll about the optical axis
    focal: float = 0.2  # focal length scaled within [1/(1+f), 1+f]

    def scaled(self, k: float) -> "Spread":
        """Every bound times ``k`` (``along`` capped at 1)."""
        return Spread(min(1.0, self.along * k), self.tilt_deg * k, self.distance * k, self.roll_deg * k, self.focal * k)


SPREAD_KEYS = {"along": "along", "tilt": "tilt_deg", "distance": "distance", "roll": "roll_deg", "focal": "focal"}


def parse_spread(text: str | float | Spread | None) -> Spread:
    """``--spread``: a number that scales the default bounds (``1`` = defaults, ``0`` = the path
    itself), or ``key=value`` pairs over the defaults (``tilt=25,roll=0``; keys: along, tilt
    (degrees), distance, roll (degrees), focal)."""
    if text is None:
        return Spread()
    if isinstance(text, Spread):
        return text
    if isinstance(text, (int, float)):
        return _checked(Spread().scaled(float(text)), str(text))
    s = str(text).strip()
    if not s:
        raise LabelsynthError("--spread must not be empty (a number, or key=value pairs such as tilt=25,roll=0)")
    try:
        return _checked(Spread().scaled(float(s)), s)
    except ValueError:
        pass
    values = {}
    for part in filter(None, (p.strip() for p in s.split(","))):
        key, sep, val = part.partition("=")
        key = key.strip()
        if not sep or key not in SPREAD_KEYS:
            raise LabelsynthError(f"--spread {s!r}: expected a number or key=value pairs with keys "
                                  f"{', '.join(SPREAD_KEYS)} (e.g. tilt=25,roll=0)")
        try:
            values[SPREAD_KEYS[key]] = float(val)
        except ValueError:
            raise LabelsynthError(f"--spread {s!r}: {key}={val.strip()!r} is not a number") from None
    return _checked(replace(Spread(), **values), s)


def _checked(spread: Spread, text: str) -> Spread:
    for f in fields(spread):
        v = getattr(spread, f.name)
        if not (np.isfinite(v) and v >= 0):
            raise LabelsynthError(f"--spread {text!r}: {f.name} must be a finite number >= 0, got {v}")
    if spread.along > 1:
        raise LabelsynthError(f"--spread {text!r}: along must be at most 1 (the next frame), got {spread.along}")
    return spread


@dataclass
class PathPoint:
    """A real frame on the path: its unit-cube camera and the distance to its target."""

    camera: Camera
    target_distance: float


def path_points(cameras: list[Camera], caster) -> list[PathPoint]:
    """Each real camera with the distance at which its optical axis meets the surface (the
    median over the frames that hit it, for those whose axis misses)."""
    o = np.stack([c.center for c in cameras])
    d = np.stack([c.forward for c in cameras])
    hit, pts, _ = caster.first_hits(o, d)
    dist = np.linalg.norm(pts - o, axis=-1)
    fallback = float(np.median(dist[hit])) if hit.any() else 1.0
    return [PathPoint(c, float(dist[i]) if hit[i] else fallback) for i, c in enumerate(cameras)]


def sample_pose(rng: np.random.Generator, path: list[PathPoint], spread: Spread) -> Camera:
    """One novel camera (unit cube) near the path, drawn as the module docstring says."""
    n = len(path)
    i = int(rng.integers(n))
    j = i + 1 if i + 1 < n else max(i - 1, 0)
    t = float(rng.uniform(0.0, spread.along)) if j != i else 0.0
    a, b = path[i].camera, path[j].camera
    rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.c2w[:3, :3], b.c2w[:3, :3]])))([t]).as_matrix()[0]
    center = (1 - t) * a.center + t * b.center
    dist = (1 - t) * path[i].target_distance + t * path[j].target_distance
    forward = -rot[:, 2]
    target = center + dist * forward
    # tilt: orbit the camera about the target, axis perpendicular to the optical axis
    theta = np.deg2rad(spread.tilt_deg) * np.sqrt(rng.uniform())
    phi = rng.uniform(0, 2 * np.pi)
    axis = np.cos(phi) * rot[:, 0] + np.sin(phi) * rot[:, 1]
    tilt = Rotation.from_rotvec(theta * axis).as_matrix()
    scale = float(np.exp(rng.uniform(-1, 1) * np.log1p(spread.distance)))
    center = target + scale * (tilt @ (center - target))
    roll = Rotation.from_rotvec(np.deg2rad(rng.uniform(-1, 1) * spread.roll_deg) * np.array([0.0, 0, 1])).as_matrix()
    rot = tilt @ rot @ roll
    zoom = float(np.exp(rng.uniform(-1, 1) * np.log1p(spread.focal)))
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot, center
    return replace(a, c2w=c2w, fx=a.fx * zoom, fy=a.fy * zoom)


@dataclass
class PoseSample:
    """The kept cameras and what was rejected, by reason."""

    cameras: list[Camera]
    rejected: dict[str, int] = field(default_factory=lambda: {r: 0 for r in REJECT_REASONS})
    seen_fraction: list[float] = field(default_factory=list)  # per kept camera, at the test resolution
    surface_fraction: list[float] = field(default_factory=list)

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


def coverage(camera: Camera, caster, real, frames: list[int] | None = None, size: int = 64) -> tuple[float, float]:
    """(fraction of pixels on the surface, fraction of those some real frame sees) of a camera
    cast at about ``size`` pixels across (``real``: a ``views.RealFrames``)."""
    small = camera.scaled(size / max(camera.width, camera.height))
    o, d = small.rays()
    hit, pts, _ = caster.first_hits(o, d)
    if not hit.any():
        return 0.0, 0.0
    target = np.median(pts[hit], axis=0)
    frames = real.candidates(small, target) if frames is None else frames
    seen = real.lookup_points(pts[hit], small.center, frames).seen
    return float(hit.mean()), float(seen.float().mean())


def sample_poses(n: int, rng: np.random.Generator, path: list[PathPoint], spread: Spread, caster, real, *,
                 min_surface: float = 0.5, min_seen: float = 0.95, max_tries: int | None = None) -> PoseSample:
    """``n`` cameras near the path that pass the test; raises when ``max_tries`` (default 20 n)
    draws give fewer.

    ``min_surface``: a view must show at least this fraction of the surface the median real
    frame shows (else "empty": mostly empty space); ``min_seen``: at least this fraction of
    the surface it shows must be seen by a real frame (else "unseen").
    """
    real_surface = float(np.median([coverage(p.camera, caster, real)[0] for p in path]))
    out = PoseSample([])
    tries = 0
    max_tries = 20 * n if max_tries is None else max_tries
    while len(out.cameras) < n:
        if tries >= max_tries:
            raise LabelsynthError(
                f"only {len(out.cameras)} of {n} novel views passed the coverage test in {tries} draws "
                f"(rejected: {out.rejected['empty']} mostly empty, {out.rejected['unseen']} mostly unseen); "
                "try a smaller --spread"
            )
        tries += 1
        cam = sample_pose(rng, path, spread)
        surface, seen = coverage(cam, caster, real)
        if surface < min_surface * real_surface:
            out.rejected["empty"] += 1
        elif seen < min_seen:
            out.rejected["unseen"] += 1
        else:
            out.cameras.append(cam)
            out.seen_fraction.append(seen)
            out.surface_fraction.append(surface)
    return out
