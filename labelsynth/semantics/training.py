"""Stage 2 training: the semantic head on volume-rendered logits, geometry frozen and cached."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from ..cameras import Camera
from ..device import optimiser_options
from ..classes import ClassMap
from ..errors import LabelsynthError
from ..geometry.encoding import GridLookup, HashGridEncoding
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
    _lookups: "SampleLookups | None" = field(default=None, repr=False, compare=False)  # ``lookups``

    def lookups(self, encoding: HashGridEncoding | None, budget_bytes: float) -> "SampleLookups | None":
        """The position encoding's lookup of every sample that carries weight, made once for
        this encoding's layout (None: no encoding, or more samples than ``budget_bytes`` hold)."""
        if encoding is None:
            return None
        if self._lookups is not None and self._lookups.layout == (encoding.layout, encoding.active_levels):
            return self._lookups
        self._lookups = SampleLookups.build(self, encoding, budget_bytes)
        return self._lookups

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


@dataclass
class SampleLookups:
    """``HashGridEncoding.lookup`` of every baked sample that carries weight (table rows as
    int64, as the gathers want them), and where each (ray, slot) finds its row (-1: a slot of
    weight 0)."""

    layout: tuple  # (encoding layout, active levels) it was made for
    row_of_slot: torch.Tensor  # (R * K,) int64
    idx: torch.Tensor  # (S, L, 8) int64
    w: torch.Tensor  # (S, L, 8)
    inside: torch.Tensor  # (S, 3) bool

    @classmethod
    @torch.no_grad()
    def build(cls, baked: "BakedRays", encoding: HashGridEncoding, budget_bytes: float) -> "SampleLookups | None":
        flat = baked.weights.reshape(-1)
        live = torch.nonzero(flat > 0).squeeze(1)
        per_sample = encoding.active_levels * 8 * (8 + baked.weights.element_size()) + 3
        if live.numel() * per_sample + flat.numel() * 8 > budget_bytes:
            return None
        row = torch.full((flat.numel(),), -1, dtype=torch.long, device=flat.device)
        row[live] = torch.arange(live.numel(), device=flat.device)
        positions = baked.positions.reshape(-1, 3)
        parts = [encoding.lookup(positions[live[s : s + 65536]]) for s in range(0, live.numel(), 65536)]
        if not parts:
            return None
        return cls((encoding.layout, encoding.active_levels), row,
                   torch.cat([p.idx for p in parts]), torch.cat([p.w for p in parts]),
                   torch.cat([p.inside for p in parts]))

    def of(self, slots: torch.Tensor) -> GridLookup:
        """The lookup of the samples at these (ray * K + slot) positions, all carrying weight."""
        rows = self.row_of_slot.index_select(0, slots)
        layout, levels = self.layout
        return GridLookup(self.idx.index_select(0, rows), self.w.index_select(0, rows),
                          self.inside.index_select(0, rows), levels, layout)


@torch.no_grad()
def sample_frozen(
    sdf: SDFField,
    grid: OccupancyGrid,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    steps: int,
    k: int,
    chunk: int = 8192,
    min_weight: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For each ray: its K highest-weight samples (positions, geometry features, weights),
    highest first; a sample of weight below ``min_weight`` gets weight 0 (``rendered_logits``
    skips it).

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
            if min_weight > 0:
                wk = torch.where(wk >= min_weight, wk, torch.zeros((), device=device))
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
                sdf, grid, torch.from_numpy(o).to(device), torch.from_numpy(d).to(device), steps, cfg.max_samples_per_ray,
                min_weight=cfg.min_sample_weight,
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
    """``auto``: ``equal-tissue`` when every label is an expert annotation, else ``tissue-balanced``.

    Exact labels agree between views, so down-weighting background (the paper's 0.1) only
    keeps small classes from being swallowed by it. Predictions disagree at every boundary;
    there the same down-weighting grows the wound bed wherever a minority of views say so, so
    bed against background keeps the plain loss's per-point majority. Among the tissues,
    though, plain cross-entropy never learns a class on a few hundred pixels even where every
    view agrees on it (``unknown`` lost at 0.000 from predictions 0.88 right), so tissue weights
    fall with frequency (``tissue_power``; docs/benchmarks.md).
    """
    if scheme != "auto":
        return scheme
    return "equal-tissue" if expert_only else "tissue-balanced"


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
    cw = class_weights(baked.class_counts, classes, cfg.background_weight, cfg.tissue_weight_floor, scheme,
                       cfg.tissue_power)
    class_w = torch.from_numpy(cw).to(device)
    batch = min(cfg.rays_per_batch, len(baked))
    iterations = semantic_iterations(cfg, len(baked))
    opt, sched = _semantic_optimiser(head.parameters(), cfg, iterations, device)
    bg_idx = classes.background_index
    lookups = baked.lookups(head.position_encoding, cfg.lookup_cache_mb * 2**20)
    head.train()
    loss_ema = 0.0
    t0 = time.time()
    with make_progress(progress) as bar:
        task = bar.add_task("semantics", total=iterations, status="")
        for it in range(iterations):
            idx = torch.randint(0, len(baked), (batch,), device=device, generator=gen)
            live = LiveSamples.of(baked, idx)
            logits = rendered_logits(head, live, bg_idx, live.lookup(lookups, head.position_encoding))
            loss = weighted_cross_entropy(logits, baked.labels[idx], class_w, baked.ray_weight[idx])
            opt.zero_grad(set_to_none=True)
            if loss.requires_grad:  # else no ray of the batch met the surface: nothing for the head to learn
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
                                                      cfg.tissue_weight_floor, scheme, cfg.tissue_power)).to(device))
        left_out.append(j)
        rays = int((baked.frame_of_ray != j).sum())
        iterations = max(iterations, semantic_iterations(cfg, rays))
    opt, sched = _semantic_optimiser([p for head in heads.values() for p in head.parameters()], cfg, iterations, device)
    gen = torch.Generator(device=device).manual_seed(seed + 1)
    batch = min(cfg.rays_per_batch, len(baked))
    bg_idx = classes.background_index
    lookups = baked.lookups(next(iter(heads.values())).position_encoding, cfg.lookup_cache_mb * 2**20)
    with make_progress(progress) as bar:
        task = bar.add_task(f"leave-one-view-out: {len(heads)} heads", total=iterations, status="")
        for _ in range(iterations):
            _joint_step(heads, class_w, left_out, baked, batch, bg_idx, gen, opt, lookups)
            sched.step()
            bar.update(task, advance=1)
    for head in heads.values():
        head.eval()
    return heads


def _joint_step(heads: dict, class_w: list, left_out: list, baked: BakedRays, batch: int, bg_idx: int,
                gen: torch.Generator, opt: torch.optim.Optimizer, lookups: SampleLookups | None) -> None:
    """One step of ``train_leave_one_out``: one batch, one position lookup, every head's loss."""
    first = next(iter(heads.values()))
    idx = torch.randint(0, len(baked), (batch,), device=baked.positions.device, generator=gen)
    live = LiveSamples.of(baked, idx)
    labels, ray_w, frames = baked.labels[idx], baked.ray_weight[idx], baked.frame_of_ray[idx]
    lookup = live.lookup(lookups, first.position_encoding)
    loss = 0.0
    for head, cw, j in zip(heads.values(), class_w, left_out):
        logits = rendered_logits(head, live, bg_idx, lookup)
        loss = loss + weighted_cross_entropy(logits, labels, cw, ray_w * (frames != j))
    opt.zero_grad(set_to_none=True)
    if loss.requires_grad:  # as in train_semantic: a batch whose rays all missed the surface teaches nothing
        loss.backward()
        opt.step()


@dataclass
class LiveSamples:
    """The samples of a batch of rays that carry weight, flattened: the head is evaluated only
    there (a ray's dropped or padded slots have weight 0 and would add nothing)."""

    rays: int
    slots: torch.Tensor  # (M,) ray * K + slot, rays numbered as in BakedRays
    ray: torch.Tensor  # (M,) which ray of the batch
    positions: torch.Tensor  # (M, 3)
    features: torch.Tensor  # (M, F)
    weights: torch.Tensor  # (M,)
    rest: torch.Tensor  # (rays,) the part of each ray no sample absorbs

    @classmethod
    def of(cls, baked: BakedRays, rays: torch.Tensor) -> "LiveSamples":
        """The samples of ``baked``'s rays ``rays`` (a batch), weight 0 marking a slot without one;
        positions and features are gathered for the live samples only."""
        weights = baked.weights.index_select(0, rays)
        r, k = weights.shape
        flat = weights.reshape(-1)
        live = torch.nonzero(flat > 0).squeeze(1)
        ray = torch.div(live, k, rounding_mode="floor")
        slots = rays.index_select(0, ray) * k + (live - ray * k)
        return cls(r, slots, ray, baked.positions.reshape(-1, 3).index_select(0, slots),
                   baked.features.reshape(-1, baked.features.shape[-1]).index_select(0, slots),
                   flat.index_select(0, live), (1.0 - weights.sum(1)).clamp(0.0, 1.0))

    def lookup(self, lookups: SampleLookups | None, encoding: HashGridEncoding | None) -> GridLookup | None:
        """The position encoding's lookup of these samples: from ``lookups`` when made, else now."""
        if encoding is None:
            return None
        return lookups.of(self.slots) if lookups is not None else encoding.lookup(self.positions)


def rendered_logits(head: SemanticHead, samples: LiveSamples, background_index: int, lookup=None) -> torch.Tensor:
    """Volume-rendered logits (rays, C) of the cached samples; the unabsorbed rest is background.
    ``lookup``: the position encoding's lookup of ``samples.positions``, when shared."""
    classes = head.out.out_features
    logits = samples.weights.new_zeros(samples.rays, classes)
    if samples.ray.numel():
        per_sample = head(samples.features, samples.positions, lookup)
        logits = logits.index_add(0, samples.ray, samples.weights[:, None] * per_sample)
    bg = torch.zeros(classes, device=logits.device)
    bg[background_index] = BACKGROUND_LOGIT
    return logits + samples.rest[:, None] * bg[None, :]
