"""Stage 2 training: the semantic head on volume-rendered logits, geometry frozen and cached."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from ..cameras import Camera
from ..device import optimiser_options
from ..classes import ClassMap
from ..errors import LabelsynthError
from ..geometry.encoding import HashGridEncoding
from ..geometry.sampling import OccupancyGrid, march, neus_weights
from ..geometry.sdf import SDFField
from ..geometry.training import _camera_rays, _resize
from ..progress import make_progress
from .config import SemanticConfig
from .head import SemanticHead, class_weights

# Logit vector given to the part of a ray that leaves the region of interest unabsorbed:
# whatever lies beyond the surface band is background.
BACKGROUND_LOGIT = 10.0


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
    sdf: SDFField,
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
    fdim = sdf.cfg.feature_dim
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s : s + chunk], dirs[s : s + chunk]
        n = o.shape[0]
        samples = march(o, d, grid, steps=steps, perturb=False)
        pos = torch.zeros(n, k, 3, device=device)
        feat = torch.zeros(n, k, fdim, device=device)
        wk = torch.zeros(n, k, device=device)
        if samples.positions.shape[0] > 0:
            along = neus_weights(sdf, samples, 1.0, train=False)
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
    sdf: SDFField,
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
    device = sdf.encoding.table.device
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
                sdf, grid, torch.from_numpy(o).to(device), torch.from_numpy(d).to(device), steps, cfg.max_samples_per_ray
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


def make_semantic_head(sdf: SDFField, classes: ClassMap, cfg: SemanticConfig) -> SemanticHead:
    pos_enc = None
    if cfg.use_position:
        pos_enc = HashGridEncoding(
            levels=cfg.position_levels,
            features_per_level=2,
            log2_table=cfg.position_log2_table,
            base_resolution=16,
            max_resolution=cfg.position_max_resolution,
        )
    device = sdf.encoding.table.device
    return SemanticHead(sdf.cfg.feature_dim, classes.num_classes, cfg.hidden, cfg.dropout, pos_enc).to(device)


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


def _semantic_optimiser(params, cfg: SemanticConfig, iterations: int, device: torch.device):
    """Adam with the learning rate cosine-annealed from ``cfg.lr`` to ``cfg.lr * lr_final_factor``."""
    opt = torch.optim.Adam(params, lr=cfg.lr, betas=(cfg.adam_beta1, cfg.adam_beta2), eps=cfg.adam_eps,
                           **optimiser_options(device))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(iterations, 1), eta_min=cfg.lr * cfg.lr_final_factor)
    return opt, sched


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
    batch = min(cfg.rays_per_batch, len(baked))
    iterations = semantic_iterations(cfg, len(baked))
    opt, sched = _semantic_optimiser(head.parameters(), cfg, iterations, device)
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


def train_leave_one_out(
    make_head: Callable[[], SemanticHead],
    baked: BakedRays,
    classes: ClassMap,
    cfg: SemanticConfig,
    names: Sequence[str],
    *,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, SemanticHead]:
    """One fresh head per named frame, each trained without that frame's rays, all in one loop.

    What ``train_semantic`` on ``baked.without({name})`` does for each name in turn, but the
    heads share each step's batch (a head's loss skips the rays of its own frame) and, their
    position encodings having one layout, the encoding's index math: that and the batch are
    most of a step that is not the heads' own arithmetic. Each head has its own class
    weights (from the other frames' label counts) and its own Adam state (one optimiser over
    all heads is per parameter), and runs as many steps as the longest of the separate runs.
    """
    device = baked.positions.device
    frame_index = {n: i for i, n in enumerate(baked.frame_names)}
    missing = [n for n in names if n not in frame_index]
    if missing:
        raise LabelsynthError("leave-one-out: no baked rays for " + ", ".join(missing))
    heads = {}
    for name in names:
        torch.manual_seed(seed)  # every head starts where a separate refit's head would
        heads[name] = make_head().train()
    scheme = resolve_class_weighting(cfg.class_weighting, baked.expert_only)
    class_w, left_out, iterations = [], [], 0
    for name in names:
        j = frame_index[name]
        other = np.delete(baked.frame_class_counts, j, axis=0).sum(0)
        class_w.append(torch.from_numpy(class_weights(other, classes, cfg.background_weight,
                                                      cfg.tissue_weight_floor, scheme)).to(device))
        left_out.append(j)
        rays = int((baked.frame_of_ray != j).sum())
        iterations = max(iterations, semantic_iterations(cfg, rays))
    opt, sched = _semantic_optimiser([p for head in heads.values() for p in head.parameters()], cfg, iterations, device)
    gen = torch.Generator(device=device).manual_seed(seed + 1)
    batch = min(cfg.rays_per_batch, len(baked))
    bg_idx = classes.background_index
    with make_progress(progress) as bar:
        task = bar.add_task(f"leave-one-view-out: {len(heads)} heads", total=iterations, status="")
        for _ in range(iterations):
            _joint_step(heads, class_w, left_out, baked, batch, bg_idx, gen, opt)
            sched.step()
            bar.update(task, advance=1)
    for head in heads.values():
        head.eval()
    return heads


def _joint_step(heads: dict, class_w: list, left_out: list, baked: BakedRays, batch: int, bg_idx: int,
                gen: torch.Generator, opt: torch.optim.Optimizer) -> None:
    """One step of ``train_leave_one_out``: one batch, one position lookup, every head's loss."""
    first = next(iter(heads.values()))
    idx = torch.randint(0, len(baked), (batch,), device=baked.positions.device, generator=gen)
    pos, feat, w = baked.positions[idx], baked.features[idx], baked.weights[idx]
    labels, ray_w, frames = baked.labels[idx], baked.ray_weight[idx], baked.frame_of_ray[idx]
    lookup = first.position_encoding.lookup(pos.reshape(-1, 3)) if first.position_encoding is not None else None
    loss = 0.0
    for head, cw, j in zip(heads.values(), class_w, left_out):
        logits = rendered_logits(head, pos, feat, w, bg_idx, lookup)
        loss = loss + weighted_cross_entropy(logits, labels, cw, ray_w * (frames != j))
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()


def rendered_logits(
    head: SemanticHead, positions: torch.Tensor, features: torch.Tensor, weights: torch.Tensor, background_index: int,
    lookup=None,
) -> torch.Tensor:
    """Volume-rendered logits of K cached samples per ray; the unabsorbed rest is background.
    ``lookup``: the position encoding's lookup of ``positions`` (R*K points), when shared."""
    r, k, _ = positions.shape
    per_sample = head(features.reshape(r * k, -1), positions.reshape(r * k, 3), lookup).reshape(r, k, -1)
    logits = (weights[..., None] * per_sample).sum(1)
    rest = (1.0 - weights.sum(1)).clamp(0.0, 1.0)
    bg = torch.zeros(per_sample.shape[-1], device=positions.device)
    bg[background_index] = BACKGROUND_LOGIT
    return logits + rest[:, None] * bg[None, :]
