"""The geometry stage's knobs (recipe section ``geometry``); the networks' own configs sit beside
them (``sdf.SDFConfig``, ``background.OuterConfig``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from ..config import Count, Momentum, NonNegative, NonNegativeInt, OpenUnitInterval, Positive, Range
from .sdf import SDFConfig


@dataclass
class GeometryConfig:
    """Stage 1: fit the SDF and colour to the images (recipe section ``geometry``)."""

    iterations: Count = 1200
    """Optimiser steps."""
    train_scale: OpenUnitInterval = 0.25
    """Rays come from the images resized by this factor."""
    target_samples: Count = 16384
    """Samples per batch: the ray count adapts to hit it."""
    max_rays: Count = 4096
    """...but never more rays than this per batch."""
    lr: Positive = 1e-2
    """Peak learning rate."""
    lr_final_factor: OpenUnitInterval = 0.1
    """The learning rate decays exponentially to ``lr`` times this at the last step."""
    eikonal_weight: NonNegative = 0.05
    """Weight of |grad sdf| = 1, which keeps the field a distance function (the occupancy band
    and the mesh rely on it); NeuS's 0.1 smooths away detail the colour loss asks for within
    these few iterations (lego: training PSNR 24.2 -> 26.0 dB at 0.05; README, Captures of any
    shape)."""
    eikonal_samples: Count = 1024
    """Points per batch that pay for second derivatives."""
    cos_anneal_iters: NonNegativeInt = 300
    """Steps over which NeuS's cosine annealing reaches the true cosine."""
    inv_s_start: Positive = 20.0
    """The sharpness floor grows geometrically from this..."""
    inv_s_end: Positive = 400.0
    """...to this, over the first ``inv_s_ramp`` of training; the learned NeuS variance may go
    sharper still."""
    inv_s_ramp: OpenUnitInterval = 0.6
    """Fraction of training over which the sharpness floor ramps up."""
    march_steps: Count = 160
    """Samples along a ray through the unit cube before the occupancy grid skips empty ones."""
    occupancy_resolution: Annotated[int, Range(8, 512)] = 64
    """Cells per side of the occupancy grid."""
    occupancy_every: Count = 25
    """Steps between updates of the occupancy grid."""
    occupancy_band: Positive = 4.0
    """Band = occupancy_band / inv_s (NeuS sharpness), in unit-cube units..."""
    occupancy_max_band: Positive = 0.08
    """...but never wider than this."""
    occupancy_full_every: Count = 4
    """Every k-th update evaluates the whole grid..."""
    occupancy_margin: NonNegative = 0.1
    """...the others only cells whose last |sdf| was this close to the band."""
    levels_start: Count = 4
    """Progressive hash levels: start with this many..."""
    levels_every: Count = 100
    """...and add one every this many iterations."""
    adam_beta1: Momentum = 0.9
    """Adam over hash table, MLPs and the NeuS variance: the instant-ngp settings."""
    adam_beta2: Momentum = 0.99
    adam_eps: Positive = 1e-15
    opacity_warmup: Annotated[float, Range(0.0, 1.0, high_open=True)] = 0.0
    """Share of the first iterations in which the colour loss cannot change opacity (it reaches
    the SDF network only through the feature the colour head reads), so that the colour head
    learns before the surface can be given up. Where a backdrop the background model already
    explains fills most pixels, the loss's quickest descent is to make the whole surface
    transparent, and a surface gone from the cube never comes back: issue 31's table capture
    keeps its surface with 0.1 (3 of 3 seeds, training PSNR 16 -> 24 dB) though the object
    still forms only in part. Off by default: 0.1 costs the lego 0.023 foreground Dice
    (docs/benchmarks.md, Captures of any shape)."""
    warmup_iterations: NonNegativeInt = 50
    """The learning rate ramps linearly over these, then decays exponentially."""
    sdf: SDFConfig = field(default_factory=SDFConfig)
    """The SDF, colour and background networks."""
