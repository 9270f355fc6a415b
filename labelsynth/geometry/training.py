"""Stage 1 training: fit the SDF and colour to the images (L1 photometric + eikonal)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from ..cameras import Camera
from ..device import optimiser_options
from ..progress import make_progress
from .sampling import (
    OccupancyGrid,
    accumulate,
    accumulate_scalar,
    march,
    neus_weights,
    ray_box,
)
from .config import GeometryConfig
from .sdf import SDFField

# A ray whose surface leaves less than this much light through shows no background.
BACKGROUND_VISIBLE = 1e-2


def _resize(img: np.ndarray, camera: Camera, interpolation: int) -> np.ndarray:
    if img.shape[1] == camera.width and img.shape[0] == camera.height:
        return img
    return cv2.resize(img, (camera.width, camera.height), interpolation=interpolation)


def _camera_rays(camera: Camera, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    o, d = camera.rays(pixels)
    return o.astype(np.float32), d.astype(np.float32)


def border_colour(images: Sequence[np.ndarray], fraction: float = 0.03) -> np.ndarray:
    """Median RGB (0-1) of the images' outer rim: the likeliest colour of what lies beyond
    the region of interest (a white or black backdrop, a table, skin around a wound)."""
    rims = []
    for img in images:
        b = max(1, int(round(fraction * min(img.shape[:2]))))
        rims += [img[:b].reshape(-1, 3), img[-b:].reshape(-1, 3), img[:, :b].reshape(-1, 3), img[:, -b:].reshape(-1, 3)]
    return np.median(np.concatenate(rims), axis=0) / 255.0


class RayBank:
    """Every pixel of every frame at the training scale, as rays and target colours."""

    def __init__(self, cameras: Sequence[Camera], images: Sequence[np.ndarray], device: torch.device) -> None:
        origins, dirs, rgbs, small = [], [], [], []
        for cam, img in zip(cameras, images):
            img = _resize(img, cam, cv2.INTER_AREA)
            small.append(img)
            o, d = _camera_rays(cam)
            origins.append(o)
            dirs.append(d)
            rgbs.append(img.reshape(-1, 3).astype(np.float32) / 255.0)
        self.origins = torch.from_numpy(np.concatenate(origins)).to(device)
        self.dirs = torch.from_numpy(np.concatenate(dirs)).to(device)
        self.rgb = torch.from_numpy(np.concatenate(rgbs)).to(device)
        self.device = device
        self.border_rgb = border_colour(small)
        self.mean_rgb = self.rgb.mean(0).cpu().numpy()  # what the images show on average

    def __len__(self) -> int:
        return self.origins.shape[0]

    def sample(self, n: int, generator: torch.Generator | None = None):
        idx = torch.randint(0, len(self), (n,), device=self.device, generator=generator)
        return self.origins[idx], self.dirs[idx], self.rgb[idx]


@dataclass
class GeometryStats:
    iterations: int
    seconds: float
    final_psnr: float
    mean_samples_per_ray: float
    inv_s: float
    occupancy: float


def render_rays_rgb(
    sdf: SDFField,
    grid: OccupancyGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    cos_anneal_ratio: float,
    steps: int,
    train: bool,
    opacity_grad: bool = True,
):
    """NeuS colour rendering of a batch of rays; returns rgb, opacity and the samples
    (``opacity_grad``: see ``neus_weights``)."""
    samples = march(origins, dirs, grid, steps=steps, perturb=train)
    n = origins.shape[0]
    far = ray_box(origins, dirs)[1]
    if samples.positions.shape[0] == 0:
        return sdf.get_background(dirs, origins, far), torch.zeros(n, device=origins.device), samples
    along = neus_weights(sdf, samples, cos_anneal_ratio, train=train, opacity_grad=opacity_grad)
    color = sdf.get_color(along.feature, F.normalize(along.gradient, dim=-1), samples.dirs)
    rgb = accumulate(color, along.weights, samples.ray_index, n)
    opacity = accumulate_scalar(along.weights, samples.ray_index, n)
    bg = sdf.get_background(dirs, origins, far, visible=(1.0 - opacity.detach()) > BACKGROUND_VISIBLE)
    rgb = rgb + (1.0 - opacity)[:, None] * bg
    return rgb, opacity, samples


def _band(cfg: GeometryConfig, sdf: SDFField) -> float:
    """Half-width of the sampled band around the surface: a few widths of NeuS's logistic density."""
    return min(cfg.occupancy_band / float(sdf.inv_s.detach()), cfg.occupancy_max_band)


def _geometry_optimiser(sdf: SDFField, cfg: GeometryConfig):
    """Adam over the hash table, the MLPs and the NeuS variance; linear warm-up, then exponential
    decay to ``lr * lr_final_factor`` (the hash table needs a large rate early and a small one late)."""
    params = [
        {"params": [sdf.encoding.table], "lr": cfg.lr},
        {"params": [p for n, p in sdf.named_parameters() if n != "encoding.table" and n != "variance"], "lr": cfg.lr},
        {"params": [sdf.variance], "lr": cfg.lr},
    ]
    opt = torch.optim.Adam(params, betas=(cfg.adam_beta1, cfg.adam_beta2), eps=cfg.adam_eps,
                           **optimiser_options(sdf.variance.device))
    gamma = cfg.lr_final_factor ** (1.0 / max(cfg.iterations, 1))
    warmup = max(cfg.warmup_iterations, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda it: min(1.0, (it + 1) / warmup) * gamma**it)
    return opt, sched


def _apply_schedules(sdf: SDFField, cfg: GeometryConfig, it: int) -> None:
    """Coarse to fine: switch on hash levels progressively, and raise the sharpness floor
    geometrically from ``inv_s_start`` to ``inv_s_end`` over the first ``inv_s_ramp`` of training."""
    sdf.encoding.set_active_levels(cfg.levels_start + it // max(cfg.levels_every, 1))
    ramp = min(1.0, it / max(cfg.inv_s_ramp * cfg.iterations, 1.0))
    sdf.inv_s_floor.fill_(cfg.inv_s_start * (cfg.inv_s_end / cfg.inv_s_start) ** ramp)


def _eikonal_loss(sdf: SDFField, positions: torch.Tensor, cfg: GeometryConfig, gen: torch.Generator) -> torch.Tensor:
    """|grad sdf| = 1 on a subset of the ray samples (near the surface, where it matters) plus
    random points of the cube (so the whole cube stays a distance function); these are the only
    points that pay for second derivatives."""
    pts = positions
    if pts.shape[0] > cfg.eikonal_samples:
        pick = torch.randint(0, pts.shape[0], (cfg.eikonal_samples,), device=pts.device, generator=gen)
        pts = pts[pick]
    rand_pts = torch.rand(cfg.eikonal_samples // 4, 3, device=pts.device, generator=gen) * 2 - 1
    _, _, eik_grad = sdf.sdf_and_gradient(torch.cat([pts, rand_pts]), create_graph=True)
    return ((eik_grad.norm(dim=-1) - 1.0) ** 2).mean()


def _next_ray_count(n_rays: int, n_samples: int, cfg: GeometryConfig) -> int:
    """Sample-count-driven batch: as the band tightens, more rays fit the same sample budget."""
    if n_samples == 0:
        return n_rays
    return int(min(cfg.max_rays, max(256, n_rays * 0.8 + 0.2 * n_rays * cfg.target_samples / n_samples)))


def _ema(previous: float, value: float, first: bool) -> float:
    """The progress bar's smoothed value (and the reported final PSNR): 5% per step."""
    return value if first else 0.95 * previous + 0.05 * value


def train_geometry(
    sdf: SDFField,
    bank: RayBank,
    cfg: GeometryConfig,
    *,
    seed: int = 0,
    progress: bool = True,
) -> tuple[OccupancyGrid, GeometryStats]:
    """Stage 1: fit SDF + colour to the images (L1 photometric + eikonal)."""
    device = bank.device
    torch.manual_seed(seed)
    gen = torch.Generator(device=device).manual_seed(seed)
    sdf.train()
    opt, sched = _geometry_optimiser(sdf, cfg)
    # backward to the parameters only: the samples' positions are leaves that need no gradient,
    # and asking for none lets the hash grid skip d/dx (HashGridEncoding.forward)
    params = [p for group in opt.param_groups for p in group["params"]]
    grid = OccupancyGrid(cfg.occupancy_resolution, device, margin=cfg.occupancy_margin, full_every=cfg.occupancy_full_every)
    n_rays = min(1024, cfg.max_rays)
    warmup_steps = int(round(cfg.opacity_warmup * cfg.iterations))
    psnr_ema, spr_ema, occ = 0.0, 0.0, 1.0
    t0 = time.time()
    with make_progress(progress) as bar:
        task = bar.add_task("geometry", total=cfg.iterations, status="")
        for it in range(cfg.iterations):
            _apply_schedules(sdf, cfg, it)
            if it % cfg.occupancy_every == 0:
                occ = grid.update(sdf.sdf_batched, _band(cfg, sdf))
            origins, dirs, target = bank.sample(n_rays, gen)
            cos_ratio = min(1.0, it / max(cfg.cos_anneal_iters, 1))
            rgb, _, samples = render_rays_rgb(sdf, grid, origins, dirs, cos_ratio, cfg.march_steps, train=True,
                                              opacity_grad=it >= warmup_steps)
            loss = F.l1_loss(rgb, target) + cfg.eikonal_weight * _eikonal_loss(sdf, samples.positions, cfg, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward(inputs=params)
            opt.step()
            sched.step()
            n_samples = samples.positions.shape[0]
            spr = n_samples / max(n_rays, 1)
            n_rays = _next_ray_count(n_rays, n_samples, cfg)
            with torch.no_grad():
                mse = F.mse_loss(rgb, target).item()
            psnr_ema = _ema(psnr_ema, -10 * math.log10(max(mse, 1e-10)), it == 0)
            spr_ema = _ema(spr_ema, spr, it == 0)
            bar.update(task, advance=1, status=f"psnr {psnr_ema:5.2f} rays {n_rays} spr {spr_ema:4.1f} s {float(sdf.inv_s.detach()):6.0f}")
    grid.update(sdf.sdf_batched, _band(cfg, sdf), jitter=False, full=True)
    sdf.eval()
    stats = GeometryStats(cfg.iterations, time.time() - t0, psnr_ema, spr_ema, float(sdf.inv_s.detach()), occ)
    return grid, stats
