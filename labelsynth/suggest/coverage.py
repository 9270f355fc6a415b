"""Which frames together show the most of the fitted surface: greedy coverage.

Points are sampled uniformly by area on the fitted surface (the geometry stage's mesh). A frame
sees a point when the point projects into the image, faces the camera and the first surface hit
of the ray from the camera centre towards it is the point itself (cast with ``render.surface``).
How well it sees it: the projected pixel density along the surface, ``f * cos(angle) / depth``
(pixels per unit of surface length, foreshortening included). A point counts fully when a
chosen frame sees it at least as well as ``reference_quantile`` of the points are seen by their
best frame (close and square), proportionally less when seen from far or at a grazing angle, and
once only: at the best view any chosen frame has of it. The score of a set of frames is the
mean of that over the points some frame of the capture sees, divided by the same for all frames
(1 = the chosen frames show everything the video shows as well as the video does). It is a
facility-location function (monotone, submodular), so adding the frame of largest marginal gain,
K times, is within 1 - 1/e of the best K-subset.

A second objective scores frames rather than surface (``objective="frames"``): teacher i serves
frame j by the share of j's view of the surface that i sees at least as well,
``sum_p min(q_i(p), q_j(p)) / sum_p q_j(p)``, and a choice scores the mean over the frames of their
best teacher's share. It asks that every frame have one teacher that saw what it sees, where the
surface objective may be satisfied by teachers each seeing a part of a frame's view. Greedy, then
single swaps until none helps (greedy alone can end below ``spread:K``); its K-choice is not the
first K of its (K+1)-choice.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
import trimesh

from ..cameras import Camera
from ..errors import LabelsynthError
from ..progress import track
from ..render.surface import SurfaceCaster


@dataclass
class CoverageConfig:
    """How the surface is sampled and how a frame's view of a point is weighed."""

    samples: int = 20000
    """Points sampled uniformly by area on the fitted surface."""
    reference_quantile: float = 0.5
    """A chosen frame's view of a point counts fully when its pixel density reaches this
    quantile of every point's best view (0.5: the median point's best view)."""
    occlusion_tolerance: float = 2e-3
    """A ray's first hit within this fraction of the surface's bounding-box diagonal before the
    point still counts as the point (the sample lies on a triangle; Embree casts in float32)."""
    seed: int = 0
    """Seed of the surface samples."""
    colour_neighbours: int = 32
    """``appearance_weights``: a sample's colour density is read at its k-th nearest colour."""
    colour_floor: float = 1.0
    """``appearance_weights``: colour distances below this (CIELAB units) count as this, so a
    surface of one exact colour (a synthetic skin, a saturated patch) keeps a weight."""
    weight_cap: float = 8.0
    """``appearance_weights``: no sample counts more than this many times the median sample."""


@dataclass
class Pick:
    """One chosen frame: its gain is the share of the surface's score it added when chosen."""

    name: str
    index: int
    gain: float
    coverage: float
    """The chosen frames' coverage up to and including this one."""


@dataclass
class SurfaceViews:
    """How well every frame sees every surface sample (``quality``, frames x samples, in [0, 1])."""

    names: list[str]
    points: np.ndarray
    """(N, 3) samples in the unit cube."""
    normals: np.ndarray
    """(N, 3) outward unit normals."""
    quality: np.ndarray
    """(F, N) float32: 0 = unseen, 1 = seen close and square (see the module docstring)."""
    reference: float
    """Pixel density that counts fully (``CoverageConfig.reference_quantile``)."""
    weights: np.ndarray | None = None
    """(N,) how much each sample counts in the surface objective (None: all alike; see
    ``appearance_weights``)."""
    total: float = field(init=False)
    _shares: np.ndarray | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        self.total = float(self._weighted(self.quality.max(axis=0)).sum()) if len(self.quality) else 0.0

    def _weighted(self, values: np.ndarray) -> np.ndarray:
        return values if self.weights is None else values * self.weights

    def weighted(self, weights: np.ndarray | None) -> "SurfaceViews":
        """The same views with the samples weighted by ``weights`` (N,) in the surface objective."""
        return SurfaceViews(self.names, self.points, self.normals, self.quality, self.reference,
                            None if weights is None else np.asarray(weights, dtype=np.float32))

    @property
    def seen(self) -> np.ndarray:
        """(N,) samples some frame sees."""
        return self.quality.max(axis=0) > 0

    def coverage(self, indices: list[int]) -> float:
        """The share of what all frames show that these frames show (0..1)."""
        if not indices or self.total <= 0:
            return 0.0
        return float(self._weighted(self.quality[list(indices)].max(axis=0)).sum() / self.total)

    def greedy(self, k: int, *, first: list[int] | None = None, among: list[int] | None = None) -> list[Pick]:
        """``k`` frames, each the one that adds most to those before it (ties: the earlier frame).
        ``first``: frames taken as already chosen (their picks are not returned); ``among``: the
        only frames it may choose (default: all)."""
        pool = len(self.names) if among is None else len(among)
        if not 1 <= k <= pool:
            raise LabelsynthError(f"cannot choose {k} of {pool} frames")
        total = self.total if self.total > 0 else 1.0
        chosen = list(first or [])
        picks: list[Pick] = []
        for i, gain in greedy_facility(self._weighted(self.quality), k, chosen=first or [], among=among):
            chosen.append(i)
            picks.append(Pick(self.names[i], i, float(max(gain, 0.0) / total), self.coverage(chosen)))
        return picks

    def teacher_shares(self) -> np.ndarray:
        """(F, F): [i, j] = the share of frame j's view of the surface that frame i sees as well (each
        sample counted by its ``weights``, when set)."""
        if self._shares is None:
            q = self.quality.astype(np.float64)
            own = np.maximum(self._weighted(q).sum(axis=1), 1e-12)
            self._shares = np.stack([self._weighted(np.minimum(q[i][None], q)).sum(axis=1) / own
                                     for i in range(len(q))])
        return self._shares

    def frame_score(self, indices: list[int]) -> float:
        """Mean over the frames of the share of their view that their best teacher in ``indices`` sees."""
        return float(self.teacher_shares()[list(indices)].max(axis=0).mean()) if indices else 0.0

    def frame_choice(self, k: int) -> list[int]:
        """``k`` frames by the frame objective: greedy, then single swaps while one raises the score
        (a local optimum; sorted by index)."""
        if not 1 <= k <= len(self.names):
            raise LabelsynthError(f"cannot choose {k} of {len(self.names)} frames")
        shares = self.teacher_shares()
        chosen = [i for i, _ in greedy_facility(shares, k)]
        score, improved = self.frame_score(chosen), True
        while improved:
            improved = False
            for slot in range(k):
                for c in range(len(shares)):
                    if c in chosen:
                        continue
                    trial = chosen[:slot] + [c] + chosen[slot + 1:]
                    trial_score = self.frame_score(trial)
                    if trial_score > score + 1e-12:
                        chosen, score, improved = trial, trial_score, True
        return sorted(chosen)

    def ordered(self, indices: list[int]) -> list[Pick]:
        """``indices`` as picks in the order greedy surface coverage would take them among themselves
        (each one's gain: the surface it adds to those before it)."""
        return self.greedy(len(indices), among=list(indices))

    def curve(self, orders: list[list[int]]) -> list[float]:
        """Coverage of each index list (e.g. spread:k for k = 1..6)."""
        return [self.coverage(o) for o in orders]


def greedy_facility(values: np.ndarray, k: int, *, chosen: list[int] = (), among: list[int] | None = None
                    ) -> list[tuple[int, float]]:
    """Greedy maximisation of sum_columns max_(chosen rows) ``values`` (a facility location): ``k``
    rows, each the one of largest gain over ``chosen`` and those before it (ties: the earlier row),
    from ``among`` (default: every row). Returns (row, gain) in order of choice."""
    chosen = list(chosen)
    best = values[chosen].max(axis=0) if chosen else np.zeros(values.shape[1], values.dtype)
    out: list[tuple[int, float]] = []
    for _ in range(k):
        gains = np.maximum(values, best[None]).sum(axis=1, dtype=np.float64) - best.sum(dtype=np.float64)
        gains[chosen] = -np.inf
        if among is not None:
            gains[np.setdiff1d(np.arange(len(gains)), among)] = -np.inf
        i = int(np.argmax(gains))
        chosen.append(i)
        best = np.maximum(best, values[i])
        out.append((i, float(gains[i])))
    return out


def sample_surface(mesh: trimesh.Trimesh, cfg: CoverageConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N,3), outward normals (N,3), face index (N,)) uniform by area."""
    if len(mesh.faces) == 0:
        raise LabelsynthError("the fitted surface is empty (the geometry stage found no surface in the scene box)")
    points, faces = trimesh.sample.sample_surface(mesh, cfg.samples, seed=cfg.seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[faces], dtype=np.float64), faces


def pixel_density(camera: Camera) -> float:
    """Pixels per unit length at unit depth (the geometric mean of the focal lengths)."""
    return float(np.sqrt(camera.fx * camera.fy))


def view_density(points: np.ndarray, normals: np.ndarray, camera: Camera, caster: SurfaceCaster,
                 tolerance: float) -> np.ndarray:
    """(N,) projected pixel density ``f cos(angle) / depth`` of ``camera`` at each point, 0
    where it does not see the point (outside the image, facing away, or hidden)."""
    out = np.zeros(len(points))
    if not len(points):
        return out
    pix, depth = camera.project(points)
    inside = (depth > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < camera.width) & (pix[:, 1] >= 0) & (pix[:, 1] < camera.height)
    offset = points - camera.center
    dist = np.linalg.norm(offset, axis=1)
    dirs = offset / np.maximum(dist, 1e-12)[:, None]
    cos = -np.einsum("nd,nd->n", dirs, normals)
    idx = np.nonzero(inside & (cos > 0))[0]
    if not len(idx):
        return out
    hit, hits, _ = caster.first_hits(np.broadcast_to(camera.center, (len(idx), 3)).copy(), dirs[idx])
    reach = np.linalg.norm(hits - camera.center, axis=1)
    visible = hit & (reach >= dist[idx] - tolerance)
    keep = idx[visible]
    out[keep] = pixel_density(camera) * cos[keep] / depth[keep]
    return out


def surface_views(mesh: trimesh.Trimesh, cameras: list[Camera], names: list[str], cfg: CoverageConfig | None = None,
                  *, caster: SurfaceCaster | None = None, progress: bool = True) -> SurfaceViews:
    """Every frame's view of every surface sample (``cameras`` in the mesh's coordinates)."""
    cfg = cfg or CoverageConfig()
    points, normals, _ = sample_surface(mesh, cfg)
    caster = caster or SurfaceCaster(mesh)
    tolerance = cfg.occlusion_tolerance * float(np.linalg.norm(np.ptp(points, axis=0)))
    density = np.stack([view_density(points, normals, cam, caster, tolerance)
                        for cam in track(cameras, "surface seen by each frame", enabled=progress)])
    best = density.max(axis=0)
    if not np.any(best > 0):
        raise LabelsynthError("no frame sees the fitted surface (are the cameras and the surface in the same place?)")
    reference = float(np.quantile(best[best > 0], cfg.reference_quantile))
    quality = np.minimum(density / reference, 1.0).astype(np.float32)
    return SurfaceViews(list(names), points, normals, quality, reference)


def surface_colours(views: SurfaceViews, cameras: list[Camera], load_image: Callable[[int], np.ndarray], *,
                    blur: int = 5, progress: bool = True) -> np.ndarray:
    """(N, 3) float32 RGB in [0, 1] of each sample, read (box-blurred over ``blur`` pixels, so noise
    and JPEG blocks do not make a colour) in the frame that sees it best; NaN where no frame does."""
    best = views.quality.argmax(axis=0)
    seen = views.seen
    colours = np.full((len(views.points), 3), np.nan, np.float32)
    for f in track(sorted(set(best[seen].tolist())), "colour of the surface", enabled=progress):
        idx = np.nonzero(seen & (best == f))[0]
        image = cv2.blur(load_image(f), (blur, blur)) if blur > 1 else load_image(f)
        pix, _ = cameras[f].project(views.points[idx])
        h, w = image.shape[:2]
        cols = np.clip(np.floor(pix[:, 0]).astype(np.int64), 0, w - 1)
        rows = np.clip(np.floor(pix[:, 1]).astype(np.int64), 0, h - 1)
        colours[idx] = image[rows, cols, :3].astype(np.float32) / 255.0
    return colours


def appearance_weights(colours: np.ndarray, cfg: CoverageConfig | None = None) -> np.ndarray:
    """(N,) weight of each sample by how rare its colour is on the surface: the inverse square root
    of its colour density (from the distance to its k-th nearest colour in CIELAB, lightness
    halved so that shading counts less than hue), median 1, capped at ``weight_cap``; 0 where it
    has no colour. Why: labels carry well across a surface of one appearance, and the frames an
    annotator must see are those that show the rare ones (small tissues, parts of another colour)."""
    from scipy.spatial import cKDTree

    cfg = cfg or CoverageConfig()
    weights = np.zeros(len(colours), np.float32)
    have = np.isfinite(colours).all(axis=1)
    n = int(have.sum())
    if n < 2:
        weights[have] = 1.0
        return weights
    lab = cv2.cvtColor(colours[have].reshape(-1, 1, 3).astype(np.float32), cv2.COLOR_RGB2Lab).reshape(-1, 3)
    lab[:, 0] *= 0.5
    k = min(cfg.colour_neighbours, n - 1)
    dist, _ = cKDTree(lab).query(lab, k=k + 1)  # the first neighbour is the sample itself
    radius = np.maximum(dist[:, -1], cfg.colour_floor)
    rarity = radius ** 1.5  # density ~ k / r^3: its inverse square root
    rarity /= np.median(rarity)
    weights[have] = np.minimum(rarity, cfg.weight_cap)
    return weights
