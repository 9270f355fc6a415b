"""The two training stages of the paper: geometry from RGB, then semantics with geometry frozen."""

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
from ..classes import ClassMap
from ..errors import LabelsynthError
from ..progress import make_progress
from .config import GeometryConfig, SemanticConfig
from .encoding import HashGridEncoding
from .rendering import (
    OccupancyGrid,
    accumulate,
    accumulate_scalar,
    march,
    neus_weights,
    ray_box,
)
from .sdf import SDFField
from .semantic import SemanticHead, class_weights

# Logit vector given to the part of a ray that leaves the region of interest unabsorbed:
# whatever lies beyond the surface band is background.
BACKGROUND_LOGIT = 10.0
# A ray whose surface leaves less than this much light through shows no background.
BACKGROUND_VISIBLE = 1e-2


def pick_device(name: str = "auto") -> torch.device:
    """The one place a device is chosen: auto = CUDA when available, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise LabelsynthError("--device cuda was asked for but torch sees no CUDA device")
    if name not in {"cpu", "cuda"}:
        raise LabelsynthError(f"unknown device '{name}' (use auto, cpu or cuda)")
    return torch.device(name)


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
    field: SDFField,
    grid: OccupancyGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    cos_anneal_ratio: float,
    steps: int,
    train: bool,
):
    """NeuS colour rendering of a batch of rays; returns rgb, opacity and the samples."""
    samples = march(origins, dirs, grid, steps=steps, perturb=train)
    n = origins.shape[0]
    far = ray_box(origins, dirs)[1]
    if samples.positions.shape[0] == 0:
        return field.get_background(dirs, origins, far), torch.zeros(n, device=origins.device), samples
    along = neus_weights(field, samples, cos_anneal_ratio, train=train)
    color = field.get_color(along.feature, F.normalize(along.gradient, dim=-1), samples.dirs)
    rgb = accumulate(color, along.weights, samples.ray_index, n)
    opacity = accumulate_scalar(along.weights, samples.ray_index, n)
    bg = field.get_background(dirs, origins, far, visible=(1.0 - opacity.detach()) > BACKGROUND_VISIBLE)
    rgb = rgb + (1.0 - opacity)[:, None] * bg
    return rgb, opacity, samples


def _band(cfg: GeometryConfig, field: SDFField) -> float:
    """Half-width of the sampled band around the surface: a few widths of NeuS's logistic density."""
    return min(cfg.occupancy_band / float(field.inv_s.detach()), cfg.occupancy_max_band)


def train_geometry(
    field: SDFField,
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
    field.train()
    params = [
        {"params": [field.encoding.table], "lr": cfg.lr},
        {"params": [p for n, p in field.named_parameters() if n != "encoding.table" and n != "variance"], "lr": cfg.lr},
        {"params": [field.variance], "lr": cfg.lr},
    ]
    opt = torch.optim.Adam(params, betas=(cfg.adam_beta1, cfg.adam_beta2), eps=cfg.adam_eps)
    gamma = cfg.lr_final_factor ** (1.0 / max(cfg.iterations, 1))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda it: min(1.0, (it + 1) / max(cfg.warmup_iterations, 1)) * gamma**it  # warm-up, then exponential decay
    )
    grid = OccupancyGrid(cfg.occupancy_resolution, device, margin=cfg.occupancy_margin, full_every=cfg.occupancy_full_every)
    n_rays = min(1024, cfg.max_rays)
    psnr_ema, spr_ema, occ = 0.0, 0.0, 1.0
    t0 = time.time()
    with make_progress(progress) as bar:
        task = bar.add_task("geometry", total=cfg.iterations, status="")
        for it in range(cfg.iterations):
            field.encoding.set_active_levels(cfg.levels_start + it // max(cfg.levels_every, 1))
            ramp = min(1.0, it / max(cfg.inv_s_ramp * cfg.iterations, 1.0))
            field.inv_s_floor.fill_(cfg.inv_s_start * (cfg.inv_s_end / cfg.inv_s_start) ** ramp)
            if it % cfg.occupancy_every == 0:
                occ = grid.update(field.sdf_batched, _band(cfg, field))
            origins, dirs, target = bank.sample(n_rays, gen)
            cos_ratio = min(1.0, it / max(cfg.cos_anneal_iters, 1))
            rgb, opacity, samples = render_rays_rgb(
                field, grid, origins, dirs, cos_ratio, cfg.march_steps, train=True
            )
            loss = F.l1_loss(rgb, target)
            # Eikonal on a subset of ray samples (near the surface, where it matters) plus random
            # points of the cube (so the whole cube stays a distance function).
            pts = samples.positions
            if pts.shape[0] > cfg.eikonal_samples:
                pick = torch.randint(0, pts.shape[0], (cfg.eikonal_samples,), device=device, generator=gen)
                pts = pts[pick]
            rand_pts = torch.rand(cfg.eikonal_samples // 4, 3, device=device, generator=gen) * 2 - 1
            _, _, eik_grad = field.sdf_and_gradient(torch.cat([pts, rand_pts]), create_graph=True)
            loss = loss + cfg.eikonal_weight * ((eik_grad.norm(dim=-1) - 1.0) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            n_samples = samples.positions.shape[0]
            spr = n_samples / max(n_rays, 1)
            # Sample-count-driven batch: as the band tightens, more rays fit the same budget.
            if n_samples > 0:
                n_rays = int(min(cfg.max_rays, max(256, n_rays * 0.8 + 0.2 * n_rays * cfg.target_samples / n_samples)))
            with torch.no_grad():
                mse = F.mse_loss(rgb, target).item()
            psnr = -10 * math.log10(max(mse, 1e-10))
            psnr_ema = psnr if it == 0 else 0.95 * psnr_ema + 0.05 * psnr
            spr_ema = spr if it == 0 else 0.95 * spr_ema + 0.05 * spr
            bar.update(task, advance=1, status=f"psnr {psnr_ema:5.2f} rays {n_rays} spr {spr_ema:4.1f} s {float(field.inv_s.detach()):6.0f}")
    grid.update(field.sdf_batched, _band(cfg, field), jitter=False, full=True)
    field.eval()
    stats = GeometryStats(cfg.iterations, time.time() - t0, psnr_ema, spr_ema, float(field.inv_s.detach()), occ)
    return grid, stats


# --------------------------------------------------------------------------------------
# Semantic stage
# --------------------------------------------------------------------------------------


@dataclass
class LabelledFrame:
    """One frame's labels for the semantic stage; ``weight`` scales its rays' loss."""

    camera: Camera  # unit-cube coordinates, full resolution
    mask: np.ndarray  # (H, W) uint8 class ids, 255 ignore
    weight: float = 1.0
    name: str = ""
    expert: bool = False  # an expert annotation (exact) rather than an automatic prediction


@dataclass
class BakedRays:
    """Training rays of the semantic stage with their frozen-geometry samples (top-K by weight)."""

    positions: torch.Tensor  # (R, K, 3)
    features: torch.Tensor  # (R, K, F)
    weights: torch.Tensor  # (R, K)
    labels: torch.Tensor  # (R,) class index (not id)
    ray_weight: torch.Tensor  # (R,)
    frame_of_ray: torch.Tensor  # (R,) index into frame_names
    frame_names: list[str]
    frame_class_counts: np.ndarray  # (F, C) label pixels per frame and class index
    frame_expert: list[bool]  # per frame: an expert annotation?

    @property
    def expert_only(self) -> bool:
        """Every frame's labels are expert annotations (decides ``class_weighting: auto``)."""
        return bool(self.frame_expert) and all(self.frame_expert)

    def __len__(self) -> int:
        return self.labels.shape[0]

    @property
    def class_counts(self) -> np.ndarray:
        """(C,) label pixels per class over the used masks (the paper's N_y)."""
        return self.frame_class_counts.sum(0)

    def without(self, names: set[str]) -> "BakedRays":
        """The same rays minus those of the named frames: leave-one-out without re-baking."""
        keep_frames = [i for i, n in enumerate(self.frame_names) if n not in names]
        keep = torch.isin(self.frame_of_ray, torch.tensor(keep_frames, dtype=torch.long, device=self.frame_of_ray.device))
        remap = torch.full((len(self.frame_names),), -1, dtype=torch.long, device=self.frame_of_ray.device)
        remap[keep_frames] = torch.arange(len(keep_frames), device=remap.device)
        return BakedRays(
            self.positions[keep], self.features[keep], self.weights[keep], self.labels[keep], self.ray_weight[keep],
            remap[self.frame_of_ray[keep]], [self.frame_names[i] for i in keep_frames],
            self.frame_class_counts[keep_frames], [self.frame_expert[i] for i in keep_frames],
        )


@torch.no_grad()
def sample_frozen(
    field: SDFField,
    grid: OccupancyGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    steps: int,
    k: int,
    chunk: int = 8192,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each ray: its K highest-weight samples (positions, geometry features, weights).

    With geometry frozen, the rendering weights of a ray never change, so they are computed
    once; the semantic stage then only evaluates the head (the paper's Eq. 3, cached).
    """
    device = origins.device
    out_pos, out_feat, out_w = [], [], []
    fdim = field.cfg.feature_dim
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s : s + chunk], dirs[s : s + chunk]
        n = o.shape[0]
        samples = march(o, d, grid, steps=steps, perturb=False)
        pos = torch.zeros(n, k, 3, device=device)
        feat = torch.zeros(n, k, fdim, device=device)
        wk = torch.zeros(n, k, device=device)
        if samples.positions.shape[0] > 0:
            along = neus_weights(field, samples, 1.0, train=False)
            feature, w = along.feature, along.weights
            # Rank samples within each ray by weight: sort by (ray, -w) and take the first k.
            order = torch.argsort(samples.ray_index.double() * 4.0 - w.double().clamp(0, 1))
            ray_sorted = samples.ray_index[order]
            first = torch.ones_like(ray_sorted, dtype=torch.bool)
            first[1:] = ray_sorted[1:] != ray_sorted[:-1]
            start = torch.zeros(n, dtype=torch.long, device=device)
            start[ray_sorted[first]] = torch.nonzero(first).squeeze(-1)
            rank = torch.arange(len(order), device=device) - start[ray_sorted]
            keep = rank < k
            sel = order[keep]
            r, c = ray_sorted[keep], rank[keep]
            pos[r, c] = samples.positions[sel]
            feat[r, c] = feature[sel]
            wk[r, c] = w[sel]
        out_pos.append(pos)
        out_feat.append(feat)
        out_w.append(wk)
    return torch.cat(out_pos), torch.cat(out_feat), torch.cat(out_w)


def bake_semantic_rays(
    field: SDFField,
    grid: OccupancyGrid,
    frames: Sequence[LabelledFrame],
    classes: ClassMap,
    cfg: SemanticConfig,
    steps: int,
    *,
    seed: int = 0,
    progress: bool = True,
) -> BakedRays:
    """Rays of labelled pixels only: frames without labels contribute nothing (loss gating)."""
    rng = np.random.default_rng(seed)
    lut = classes.id_to_index_lut()
    device = field.encoding.table.device
    frame_counts = np.zeros((len(frames), classes.num_classes), dtype=np.int64)
    parts: list[tuple] = []
    with make_progress(progress) as bar:
        task = bar.add_task("baking rays", total=len(frames), status="")
        for fi, frame in enumerate(frames):
            cam = frame.camera.scaled(cfg.train_scale)
            mask = _resize(frame.mask, cam, cv2.INTER_NEAREST)
            idx = lut[mask.reshape(-1)]
            valid = np.nonzero(idx >= 0)[0]
            bar.advance(task)
            if valid.size == 0:
                continue
            frame_counts[fi] = np.bincount(idx[valid], minlength=classes.num_classes)
            if valid.size > cfg.max_rays_per_frame:
                valid = rng.choice(valid, cfg.max_rays_per_frame, replace=False)
            pixels = np.stack([valid % cam.width + 0.5, valid // cam.width + 0.5], -1)
            o, d = _camera_rays(cam, pixels)
            pos, feat, w = sample_frozen(
                field, grid, torch.from_numpy(o).to(device), torch.from_numpy(d).to(device), steps, cfg.max_samples_per_ray
            )
            labels = torch.from_numpy(idx[valid]).to(device)
            n = len(valid)
            parts.append((pos, feat, w, labels, torch.full((n,), float(frame.weight), device=device),
                          torch.full((n,), fi, dtype=torch.long, device=device)))
    if not parts:
        raise LabelsynthError("no labelled pixels: every annotation/prediction mask is empty or ignore")
    cat = [torch.cat([p[i] for p in parts]) for i in range(6)]
    names = [f.name or str(i) for i, f in enumerate(frames)]
    return BakedRays(*cat, frame_names=names, frame_class_counts=frame_counts,
                     frame_expert=[bool(f.expert) for f in frames])


def weighted_cross_entropy(
    logits: torch.Tensor, labels: torch.Tensor, class_w: torch.Tensor, ray_w: torch.Tensor
) -> torch.Tensor:
    """Paper Eq. 4: -w_y log p_y, normalised by the total weight (rays of weight 0 teach nothing)."""
    ce = F.cross_entropy(logits, labels, reduction="none")
    w = class_w[labels] * ray_w
    return (w * ce).sum() / w.sum().clamp_min(1e-8)


def make_semantic_head(field: SDFField, classes: ClassMap, cfg: SemanticConfig) -> SemanticHead:
    pos_enc = None
    if cfg.use_position:
        pos_enc = HashGridEncoding(
            levels=cfg.position_levels,
            features_per_level=2,
            log2_table=cfg.position_log2_table,
            base_resolution=16,
            max_resolution=cfg.position_max_resolution,
        )
    device = field.encoding.table.device
    return SemanticHead(field.cfg.feature_dim, classes.num_classes, cfg.hidden, cfg.dropout, pos_enc).to(device)


@dataclass
class SemanticStats:
    iterations: int
    seconds: float
    final_loss: float
    rays: int
    class_weights: list[float]
    class_weighting: str


def resolve_class_weighting(scheme: str, expert_only: bool) -> str:
    """``auto``: ``equal-tissue`` when every label is an expert annotation, else ``uniform``.

    Exact labels agree between views, so down-weighting background (the paper's 0.1) only
    keeps small classes from being swallowed by it. Predictions disagree at every boundary;
    there the same down-weighting grows the wound bed wherever a minority of views say so,
    and an unweighted loss learns the per-point majority instead (README, Benchmarks).
    """
    if scheme != "auto":
        return scheme
    return "equal-tissue" if expert_only else "uniform"


def semantic_iterations(cfg: SemanticConfig, rays: int) -> int:
    """``cfg.iterations``, raised so that the batches cover the labelled rays ``cfg.min_epochs`` times."""
    batch = max(min(cfg.rays_per_batch, rays), 1)
    return max(cfg.iterations, math.ceil(cfg.min_epochs * rays / batch))


def train_semantic(
    head: SemanticHead,
    baked: BakedRays,
    classes: ClassMap,
    cfg: SemanticConfig,
    *,
    seed: int = 0,
    progress: bool = True,
) -> SemanticStats:
    """Stage 2: weighted cross-entropy on volume-rendered logits, geometry frozen (cached)."""
    device = baked.positions.device
    torch.manual_seed(seed)
    gen = torch.Generator(device=device).manual_seed(seed + 1)
    scheme = resolve_class_weighting(cfg.class_weighting, baked.expert_only)
    cw = class_weights(baked.class_counts, classes, cfg.background_weight, cfg.tissue_weight_floor, scheme)
    class_w = torch.from_numpy(cw).to(device)
    opt = torch.optim.Adam(head.parameters(), lr=cfg.lr, betas=(cfg.adam_beta1, cfg.adam_beta2), eps=cfg.adam_eps)
    batch = min(cfg.rays_per_batch, len(baked))
    iterations = semantic_iterations(cfg, len(baked))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(iterations, 1), eta_min=cfg.lr * cfg.lr_final_factor)
    bg_idx = classes.background_index
    head.train()
    loss_ema = 0.0
    t0 = time.time()
    with make_progress(progress) as bar:
        task = bar.add_task("semantics", total=iterations, status="")
        for it in range(iterations):
            idx = torch.randint(0, len(baked), (batch,), device=device, generator=gen)
            logits = rendered_logits(head, baked.positions[idx], baked.features[idx], baked.weights[idx], bg_idx)
            loss = weighted_cross_entropy(logits, baked.labels[idx], class_w, baked.ray_weight[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            loss_ema = loss.item() if it == 0 else 0.95 * loss_ema + 0.05 * loss.item()
            bar.update(task, advance=1, status=f"loss {loss_ema:.4f}")
    head.eval()
    return SemanticStats(iterations, time.time() - t0, loss_ema, len(baked), cw.tolist(), scheme)


def rendered_logits(
    head: SemanticHead, positions: torch.Tensor, features: torch.Tensor, weights: torch.Tensor, background_index: int
) -> torch.Tensor:
    """Volume-rendered logits of K cached samples per ray; the unabsorbed rest is background."""
    r, k, _ = positions.shape
    per_sample = head(features.reshape(r * k, -1), positions.reshape(r * k, 3)).reshape(r, k, -1)
    logits = (weights[..., None] * per_sample).sum(1)
    rest = (1.0 - weights.sum(1)).clamp(0.0, 1.0)
    bg = torch.zeros(per_sample.shape[-1], device=positions.device)
    bg[background_index] = BACKGROUND_LOGIT
    return logits + rest[:, None] * bg[None, :]
