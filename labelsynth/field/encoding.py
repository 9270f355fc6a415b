"""Multi-resolution hash-grid encoding (Instant-NGP) in plain PyTorch.

Written with gathers and products only, so autograd gives exact first *and* second
derivatives with respect to the input position (the eikonal loss differentiates the SDF
gradient), and it runs the same on CPU and CUDA. Coarse levels that fit are stored densely
(no hash collisions); finer ones are hashed into a table of ``2**log2_table`` entries.
"""

from __future__ import annotations

import math

import torch
from torch import nn

_PRIMES = (1, 2654435761, 805459861)


class HashGridEncoding(nn.Module):
    """Maps points in [-1, 1]^3 to ``levels * features_per_level`` features."""

    def __init__(
        self,
        levels: int = 12,
        features_per_level: int = 2,
        log2_table: int = 17,
        base_resolution: int = 16,
        max_resolution: int = 1024,
        init_scale: float = 1e-4,
    ) -> None:
        super().__init__()
        self.levels = levels
        self.features_per_level = features_per_level
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        resolutions, sizes, dense = [], [], []
        for level in range(levels):
            res = int(math.floor(base_resolution * growth**level))
            n_dense = (res + 1) ** 3
            table = min(n_dense, 2**log2_table)
            resolutions.append(res)
            sizes.append(table)
            dense.append(n_dense <= table)
        offsets = [0]
        for s in sizes:
            offsets.append(offsets[-1] + s)
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        self.register_buffer("table_sizes", torch.tensor(sizes, dtype=torch.long), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.long), persistent=False)
        self.register_buffer("dense", torch.tensor(dense, dtype=torch.bool), persistent=False)
        self.register_buffer("level_mask", torch.ones(levels), persistent=False)
        corners = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)
        self.register_buffer("corners", corners, persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], features_per_level).uniform_(-init_scale, init_scale))

    @property
    def output_dim(self) -> int:
        return self.levels * self.features_per_level

    def set_active_levels(self, active: int) -> None:
        """Progressive training: zero the features of levels >= ``active`` (coarse to fine)."""
        self.level_mask.copy_((torch.arange(self.levels, device=self.level_mask.device) < active).float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 3) in [-1, 1]^3 (clamped) -> (N, levels * features)."""
        n = x.shape[0]
        u = ((x + 1.0) * 0.5).clamp(0.0, 1.0)
        pos = u[:, None, :] * self.resolutions[None, :, None]  # (N, L, 3)
        base = torch.minimum(torch.floor(pos).detach(), self.resolutions[None, :, None] - 1)
        frac = pos - base  # carries the gradient with respect to x
        base = base.long()
        # Per-axis corner weights (1-f, f) and corner coordinates (b, b+1): (N, L, 3, 2).
        w_axis = torch.stack([1.0 - frac, frac], dim=-1)
        coord = torch.stack([base, base + 1], dim=-1)
        # Dense levels: linear index; hashed levels: xor of coordinate * prime.
        mult = torch.where(
            self.dense[:, None],
            torch.stack([torch.ones_like(self.table_sizes), self.resolutions.long() + 1, (self.resolutions.long() + 1) ** 2], -1),
            torch.tensor(_PRIMES, device=x.device, dtype=torch.long)[None, :].expand(self.levels, 3),
        )  # (L, 3)
        parts = coord * mult[None, :, :, None]  # (N, L, 3, 2)
        px = parts[:, :, 0, :, None, None]
        py = parts[:, :, 1, None, :, None]
        pz = parts[:, :, 2, None, None, :]
        dense_mask = self.dense[None, :, None, None, None]
        idx = torch.where(dense_mask, px + py + pz, px ^ py ^ pz)  # (N, L, 2, 2, 2)
        idx = torch.remainder(idx, self.table_sizes[None, :, None, None, None]) + self.offsets[None, :, None, None, None]
        w = w_axis[:, :, 0, :, None, None] * w_axis[:, :, 1, None, :, None] * w_axis[:, :, 2, None, None, :]
        feats = self.table[idx.reshape(n, -1)].reshape(n, self.levels, 8, self.features_per_level)
        out = torch.einsum("nlc,nlcf->nlf", w.reshape(n, self.levels, 8), feats) * self.level_mask[None, :, None]
        return out.reshape(n, -1)
