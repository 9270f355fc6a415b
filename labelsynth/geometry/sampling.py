"""Ray sampling and NeuS volume rendering with packed (variable-length) samples.

Speed comes from not sampling empty space: an occupancy grid derived from the SDF keeps
only the band around the surface, so a ray carries ~10-30 samples instead of hundreds
(instant-nsr-pl's trick, done here in plain PyTorch so it runs on CPU and CUDA alike).
Samples are packed: flat tensors plus the index of the ray each sample belongs to.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch.nn import functional as F


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, bound: float = 1.0, near_min: float = 0.05):
    """Entry and exit distances of rays in the cube [-bound, bound]^3 (exit <= entry: miss)."""
    safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (-bound - origins) / safe
    t1 = (bound - origins) / safe
    near = torch.minimum(t0, t1).amax(-1).clamp_min(near_min)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far


class OccupancyGrid:
    """A boolean grid over the unit cube marking cells near the SDF's zero level set."""

    def __init__(self, resolution: int = 64, device: torch.device | str = "cpu", *,
                 margin: float = 0.1, full_every: int = 4) -> None:
        self.resolution = resolution
        self.device = torch.device(device)
        self.occupied = torch.ones((resolution,) * 3, dtype=torch.bool, device=self.device)
        lin = (torch.arange(resolution, device=self.device, dtype=torch.float32) + 0.5) / resolution * 2 - 1
        self.centers = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
        self.voxel = 2.0 / resolution
        self.margin = margin
        self.full_every = max(1, int(full_every))
        self._sdf: torch.Tensor | None = None  # last |sdf| per cell, for partial updates
        self._updates = 0

    @torch.no_grad()
    def update(self, sdf_fn, band: float, jitter: bool = True, full: bool = False) -> float:
        """Mark cells whose |sdf| (at a jittered point) is within ``band`` plus a cell diagonal.

        Only every ``full_every``-th update evaluates every cell; the others re-evaluate the
        cells whose last |sdf| was within ``margin`` of the band, since a surface moves far
        less than ``margin`` (a tenth of the cube's half-size) in a few dozen steps and the
        rest of the cube cannot reach the band before the next full pass. Most of the cube
        is empty, so this skips most of the work.
        """
        slack = self.voxel * (0.87 if not jitter else 1.3)
        partial = not full and self._sdf is not None and self._updates % self.full_every != 0
        self._updates += 1
        pts = self.centers
        if partial:
            cells = torch.nonzero(self._sdf <= band + slack + self.margin).squeeze(-1)
            pts = pts[cells]
        if jitter:
            pts = pts + (torch.rand_like(pts) - 0.5) * self.voxel
        sdf = sdf_fn(pts).abs() if len(pts) else pts.new_zeros(0)
        if partial:
            self._sdf[cells] = sdf
        else:
            self._sdf = sdf
        # |sdf| <= band + the cell's half diagonal: the cell may hold a point within the band
        # (for a true distance function; the eikonal term keeps it one).
        self.occupied = (self._sdf <= band + slack).reshape((self.resolution,) * 3)
        return float(self.occupied.float().mean())

    def query(self, pts: torch.Tensor) -> torch.Tensor:
        idx = ((pts + 1) * 0.5 * self.resolution).long().clamp(0, self.resolution - 1)
        return self.occupied[idx[:, 0], idx[:, 1], idx[:, 2]]

    def state_dict(self) -> dict:
        return {"resolution": self.resolution, "occupied": self.occupied.cpu()}

    def load_state_dict(self, state: dict) -> None:
        self.occupied = state["occupied"].to(self.device)


@dataclass
class PackedSamples:
    """Samples of many rays, flattened; ``ray_index`` is sorted (ray-major, near to far)."""

    positions: torch.Tensor  # (S, 3)
    dirs: torch.Tensor  # (S, 3)
    deltas: torch.Tensor  # (S,) segment length each sample stands for
    ray_index: torch.Tensor  # (S,) long
    num_rays: int


def march(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    grid: OccupancyGrid,
    steps: int = 256,
    perturb: bool = True,
    bound: float = 1.0,
) -> PackedSamples:
    """Uniform steps through the cube, keeping only samples in occupied cells."""
    n = origins.shape[0]
    near, far = ray_box(origins, dirs, bound)
    hit = far > near
    step = (far - near).clamp_min(0) / steps  # per-ray step: every ray gets `steps` candidates
    offs = torch.arange(steps, device=origins.device, dtype=origins.dtype)[None, :]
    offs = offs + (torch.rand(n, steps, device=origins.device) if perturb else 0.5)
    t = near[:, None] + offs * step[:, None]  # (n, steps)
    pts = origins[:, None, :] + dirs[:, None, :] * t[..., None]
    keep = grid.query(pts.reshape(-1, 3)).reshape(n, steps) & hit[:, None]
    ray_index = torch.arange(n, device=origins.device)[:, None].expand(n, steps)[keep]
    return PackedSamples(
        positions=pts[keep],
        dirs=dirs[ray_index],
        deltas=step[:, None].expand(n, steps)[keep],
        ray_index=ray_index,
        num_rays=n,
    )


def neus_alpha(
    sdf: torch.Tensor,
    gradient: torch.Tensor,
    dirs: torch.Tensor,
    deltas: torch.Tensor,
    inv_s: torch.Tensor,
    cos_anneal_ratio: float,
) -> torch.Tensor:
    """NeuS opacity of each section from the SDF at its midpoint, with cosine annealing."""
    true_cos = (dirs * gradient).sum(-1)
    iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal_ratio) + F.relu(-true_cos) * cos_anneal_ratio)
    est_next = sdf + iter_cos * deltas * 0.5
    est_prev = sdf - iter_cos * deltas * 0.5
    prev_cdf = torch.sigmoid(est_prev * inv_s)
    next_cdf = torch.sigmoid(est_next * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


def composite_weights(alpha: torch.Tensor, ray_index: torch.Tensor, num_rays: int) -> torch.Tensor:
    """Volume-rendering weights T_i * alpha_i for packed samples (exclusive transmittance per ray)."""
    if alpha.numel() == 0:
        return alpha
    log_t = torch.log1p(-alpha.clamp(max=1.0 - 1e-6)).double()
    cum = torch.cumsum(log_t, 0)
    excl = cum - log_t  # sum over all earlier samples, including other rays
    first = torch.ones_like(ray_index, dtype=torch.bool)
    first[1:] = ray_index[1:] != ray_index[:-1]
    start_val = torch.zeros(num_rays, dtype=excl.dtype, device=excl.device)
    start_val[ray_index[first]] = excl[first]
    trans = torch.exp((excl - start_val[ray_index]).float())
    return alpha * trans


def accumulate(values: torch.Tensor, weights: torch.Tensor, ray_index: torch.Tensor, num_rays: int) -> torch.Tensor:
    """Sum of weight * value per ray: (S, C) -> (num_rays, C)."""
    out = torch.zeros(num_rays, values.shape[-1], device=values.device, dtype=values.dtype)
    return out.index_add(0, ray_index, values * weights[:, None])


def accumulate_scalar(weights: torch.Tensor, ray_index: torch.Tensor, num_rays: int) -> torch.Tensor:
    out = torch.zeros(num_rays, device=weights.device, dtype=weights.dtype)
    return out.index_add(0, ray_index, weights)


class _SDF(Protocol):
    inv_s: torch.Tensor

    def get_sdf(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...


@dataclass
class RayWeights:
    """What one pass of the SDF over packed samples gives: the NeuS weights and what they came from."""

    sdf: torch.Tensor  # (S,)
    feature: torch.Tensor  # (S, F) geometry feature (what the colour and semantic heads read)
    gradient: torch.Tensor  # (S, 3) d sdf / dx, first order, detached from the parameters
    weights: torch.Tensor  # (S,) T_i * alpha_i


def neus_weights(sdf_field: _SDF, samples: PackedSamples, cos_anneal_ratio: float, *, train: bool,
                 opacity_grad: bool = True) -> RayWeights:
    """The one place NeuS weights along packed rays are computed (RGB rendering, the semantic bake).

    The SDF gradient is first order and detached: second derivatives are paid only on the
    eikonal subset of a training step, which is where most of the time went when every
    sample carried them. With ``train`` the sdf and feature keep their graph (the colour
    loss reaches the SDF through them); otherwise they are detached. Without ``opacity_grad``
    the weights come from a detached sdf and sharpness: the loss then reaches the SDF network
    only through the feature the colour head reads (``GeometryConfig.opacity_warmup``).
    """
    with torch.enable_grad():
        x = samples.positions.detach().requires_grad_(True)
        sdf, feature = sdf_field.get_sdf(x)
        (grad,) = torch.autograd.grad(sdf.sum(), x, retain_graph=train)
    if not train:
        sdf, feature = sdf.detach(), feature.detach()
    sdf_for_alpha, inv_s = (sdf, sdf_field.inv_s) if opacity_grad else (sdf.detach(), sdf_field.inv_s.detach())
    alpha = neus_alpha(sdf_for_alpha, grad, samples.dirs, samples.deltas, inv_s, cos_anneal_ratio)
    return RayWeights(sdf, feature, grad, composite_weights(alpha, samples.ray_index, samples.num_rays))
