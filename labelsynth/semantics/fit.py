"""The semantic stage as two calls on frozen geometry: fit a head, and the leave-one-out heads.

Both return new heads and leave everything they are given as it was; which head renders what
is the caller's business (``render.renderer.FieldRenderer.render(camera, head)``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..classes import ClassMap
from ..errors import LabelsynthError
from ..geometry.sampling import OccupancyGrid
from ..geometry.sdf import SDFField
from .config import SemanticConfig
from .head import SemanticHead
from .training import (
    BakedRays,
    LabelledFrame,
    SemanticStats,
    bake_semantic_rays,
    make_semantic_head,
    train_leave_one_out,
    train_semantic,
)


@dataclass
class HeadFit:
    """A trained head, its statistics, and the baked rays it learnt from (reusable by refits)."""

    head: SemanticHead
    stats: SemanticStats
    baked: BakedRays


def scaled_config(cfg: SemanticConfig, fraction: float) -> SemanticConfig:
    """``cfg`` with its steps and epochs scaled by ``fraction`` (the report's refits)."""
    if fraction == 1.0:
        return cfg
    return dataclasses.replace(cfg, iterations=max(1, math.ceil(cfg.iterations * fraction)),
                               min_epochs=cfg.min_epochs * fraction)


def fit_head(
    sdf: SDFField,
    grid: OccupancyGrid,
    classes: ClassMap,
    cfg: SemanticConfig,
    march_steps: int,
    frames: Sequence[LabelledFrame],
    *,
    baked: BakedRays | None = None,
    exclude: set[str] = frozenset(),
    seed: int = 0,
    progress: bool = True,
    steps_fraction: float = 1.0,
) -> HeadFit:
    """A fresh head trained on the frozen geometry from ``frames`` (baked here), or from
    ``baked`` rays of an earlier fit (``frames`` then unused) without the frames in ``exclude``.

    ``steps_fraction`` scales the head's steps and epochs. The returned ``baked`` are all the
    rays (``exclude`` not applied), so a later refit can leave out other frames.
    """
    if baked is None:
        baked = bake_semantic_rays(sdf, grid, frames, classes, cfg, march_steps, seed=seed, progress=progress)
    taught = baked.without(set(exclude)) if exclude else baked
    if exclude and len(taught) == 0:
        raise LabelsynthError("no labelled pixels left after leaving out " + ", ".join(sorted(exclude)))
    cfg = scaled_config(cfg, steps_fraction)
    head = make_semantic_head(sdf, classes, cfg)
    stats = train_semantic(head, taught, classes, cfg, seed=seed, progress=progress)
    return HeadFit(head, stats, baked)


def leave_one_out_heads(
    sdf: SDFField,
    classes: ClassMap,
    cfg: SemanticConfig,
    baked: BakedRays,
    names: Sequence[str],
    *,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, SemanticHead]:
    """For each named frame, a fresh head trained (by ``cfg``) without that frame's rays.

    The frames that taught are trained together (``training.train_leave_one_out``: one batch
    and one position lookup per step for all of them); a named frame that taught nothing gets
    a head trained alone on every ray. A frame whose absence leaves no labelled ray is a
    one-line error.
    """
    index = {n: i for i, n in enumerate(baked.frame_names)}
    per_frame = torch.bincount(baked.frame_of_ray, minlength=len(baked.frame_names))
    for name in names:
        if name in index and int(per_frame[index[name]]) == len(baked):
            raise LabelsynthError(f"no labelled pixels left after leaving out {name}")
    together = [n for n in names if n in index]
    heads: dict[str, SemanticHead] = {}
    if together:
        heads = train_leave_one_out(lambda: make_semantic_head(sdf, classes, cfg), baked, classes, cfg, together,
                                    seed=seed, progress=progress)
    for name in names:
        if name not in heads:
            head = make_semantic_head(sdf, classes, cfg)
            train_semantic(head, baked, classes, cfg, seed=seed, progress=False)
            heads[name] = head
    return {n: heads[n] for n in names}
