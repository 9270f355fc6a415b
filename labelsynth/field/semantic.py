"""The semantic head, its class weights, and the wound-bed aggregation (paper, Method).

Semantics are view-independent (Semantic-NeRF): the head reads the frozen geometry feature
(and optionally a position encoding), never the view direction.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..classes import ClassMap
from .encoding import HashGridEncoding


class SemanticHead(nn.Module):
    """geometry feature (+ position code) -> per-class logits, dropout before the last layer."""

    def __init__(
        self,
        feature_dim: int,
        num_classes: int,
        hidden: int = 64,
        dropout: float = 0.5,
        position_encoding: HashGridEncoding | None = None,
    ) -> None:
        super().__init__()
        self.position_encoding = position_encoding
        in_dim = feature_dim + (position_encoding.output_dim if position_encoding is not None else 0)
        self.body = nn.Sequential(
            nn.Linear(in_dim, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
        )
        self.dropout = nn.Dropout(dropout)
        self.out = nn.Linear(hidden, num_classes)

    def forward(self, feature: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        h = feature
        if self.position_encoding is not None:
            h = torch.cat([h, self.position_encoding(positions)], dim=-1)
        return self.out(self.dropout(self.body(h)))


def class_weights(
    pixel_counts: np.ndarray, classes: ClassMap, background_weight: float = 0.1, floor: float = 0.1
) -> np.ndarray:
    """The paper's weighted-CE weights, indexed like ``classes``.

    Background gets ``background_weight`` (0.1); every other class y gets
    ``floor + (1 - floor) * N_y / sum_n N_n`` with N counted over the training masks and the
    sum over the non-background classes (paper: 0.1 + 0.9 * N_y / sum N).
    """
    counts = np.asarray(pixel_counts, dtype=np.float64)
    weights = np.zeros(classes.num_classes, dtype=np.float64)
    bg = classes.background_index
    tissue = [i for i in range(classes.num_classes) if i != bg]
    total = counts[tissue].sum()
    for i in tissue:
        weights[i] = floor + (1.0 - floor) * (counts[i] / total if total > 0 else 0.0)
    weights[bg] = background_weight
    return weights.astype(np.float32)


def wound_bed_logits(logits: torch.Tensor, classes: ClassMap) -> torch.Tensor:
    """(..., C) class logits -> (..., 2) [background, wound bed] with the bed as log-sum-exp."""
    bed = torch.logsumexp(logits[..., classes.wound_bed_indices], dim=-1)
    return torch.stack([logits[..., classes.background_index], bed], dim=-1)


def wound_bed_probability(logits: torch.Tensor, classes: ClassMap) -> torch.Tensor:
    """Probability of the wound bed: softmax of the aggregated logit against background."""
    return torch.softmax(wound_bed_logits(logits, classes), dim=-1)[..., 1]
