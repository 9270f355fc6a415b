"""The semantic stage's knobs (recipe section ``semantic``) and the named choices it offers:
how classes are weighted in the loss, and how class probabilities become a label."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from ..config import Count, HashTableLog2, Momentum, NonNegative, OpenUnitInterval, Positive, UnitInterval

# "auto" is resolved per run by training.resolve_class_weighting (which labels are taught)
ClassWeighting = Literal["auto", "paper", "equal-tissue", "uniform", "inverse-sqrt", "inverse", "tissue-balanced"]
CLASS_WEIGHTINGS: tuple[str, ...] = get_args(ClassWeighting)

DecisionRule = Literal["wound-bed-first", "argmax"]
DECISION_RULES: tuple[str, ...] = get_args(DecisionRule)


@dataclass
class SemanticConfig:
    """Stage 2: the semantic head, geometry frozen (recipe section ``semantic``)."""

    iterations: Count = 800
    """Optimiser steps..."""
    rays_per_batch: Count = 4096
    min_epochs: NonNegative = 1.0
    """...but at least this many passes over the labelled rays: with every frame's predictions
    teaching there are millions of rays, and a head that has seen only part of them can miss a
    small class outright (README, Benchmarks: necrotic learned or lost by the seed)."""
    lr: Positive = 5e-3
    """Peak learning rate."""
    hidden: Count = 64
    """Width of the head."""
    dropout: Momentum = 0.5
    """Dropout before the last layer (the paper's 0.5)."""
    use_position: bool = True
    """A small hash grid of position beside the geometry feature."""
    position_levels: Count = 8
    position_log2_table: HashTableLog2 = 17
    position_max_resolution: Count = 512
    train_scale: OpenUnitInterval = 0.5
    """Label pixels are sampled at this image scale."""
    max_rays_per_frame: Count = 40000
    max_samples_per_ray: Count = 8
    """The K highest-weight samples of each ray that the head reads (baked once)."""
    min_sample_weight: UnitInterval = 1e-3
    """Of those, samples whose rendering weight is below this are dropped when baked (weight 0,
    the head never evaluated there). On the 50-frame wound they are half of the samples and
    carry 0.05% of the rendered weight, so the head's steps cost about half (docs/benchmarks.md,
    "Relabel and export"); 0 keeps every sample."""
    lookup_cache_mb: NonNegative = 1024.0
    """Memory (MiB) for the position encoding's grid lookups of every baked sample, computed
    once instead of at every step (the points never move); more samples than fit are looked up
    per step as before. Speed and memory only: the results are the same."""
    expert_weight: Positive = 4.0
    """With --labels both: weight of annotated frames against predictions."""
    class_weighting: ClassWeighting = "auto"
    """auto | paper | equal-tissue | uniform | inverse-sqrt | inverse | tissue-balanced (``head.class_weights``);
    auto = equal-tissue from expert annotations alone, tissue-balanced when predictions teach."""
    background_weight: NonNegative = 0.1
    """The paper and equal-tissue schemes: weight of background."""
    tissue_weight_floor: UnitInterval = 0.1
    """The paper scheme: w_y = floor + (1 - floor) * N_y / sum N (paper: 0.1 / 0.9)."""
    tissue_power: UnitInterval = 0.25
    """The tissue-balanced scheme: tissue weights proportional to N_y^-power (0: uniform;
    docs/benchmarks.md, "Class weights and the decision rule")."""
    adam_beta1: Momentum = 0.9
    """Adam, learning rate cosine-annealed from lr to lr * lr_final_factor."""
    adam_beta2: Momentum = 0.99
    adam_eps: Positive = 1e-15
    lr_final_factor: UnitInterval = 0.05
