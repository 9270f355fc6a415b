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
        self.active_levels = levels
        corners = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)
        self.register_buffer("corners", corners, persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], features_per_level).uniform_(-init_scale, init_scale))

    @property
    def output_dim(self) -> int:
        return self.levels * self.features_per_level

    def set_active_levels(self, active: int) -> None:
        """Progressive training: levels >= ``active`` output zeros (and cost nothing)."""
        self.active_levels = int(max(1, min(active, self.levels)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 3) in [-1, 1]^3 (clamped) -> (N, levels * features)."""
        n, L = x.shape[0], self.active_levels
        res, sizes, offsets, dense = (
            self.resolutions[:L], self.table_sizes[:L], self.offsets[:L], self.dense[:L]
        )
        u = ((x + 1.0) * 0.5).clamp(0.0, 1.0)
        pos = u[:, None, :] * res[None, :, None]  # (N, L, 3)
        base = torch.minimum(torch.floor(pos).detach(), res[None, :, None] - 1)
        frac = pos - base  # carries the gradient with respect to x
        base = base.long()
        # Per-axis corner weights (1-f, f) and corner coordinates (b, b+1): (N, L, 3, 2).
        w_axis = torch.stack([1.0 - frac, frac], dim=-1)
        coord = torch.stack([base, base + 1], dim=-1)
        # Dense levels: linear index; hashed levels: xor of coordinate * prime.
        stride = res.long() + 1
        mult = torch.where(
            dense[:, None],
            torch.stack([torch.ones_like(stride), stride, stride * stride], -1),
            torch.tensor(_PRIMES, device=x.device, dtype=torch.long)[None, :].expand(L, 3),
        )  # (L, 3)
        parts = coord * mult[None, :, :, None]  # (N, L, 3, 2)
        px = parts[:, :, 0, :, None, None]
        py = parts[:, :, 1, None, :, None]
        pz = parts[:, :, 2, None, None, :]
        idx = torch.where(dense[None, :, None, None, None], px + py + pz, px ^ py ^ pz)  # (N, L, 2, 2, 2)
        idx = torch.remainder(idx, sizes[None, :, None, None, None]) + offsets[None, :, None, None, None]
        w = w_axis[:, :, 0, :, None, None] * w_axis[:, :, 1, None, :, None] * w_axis[:, :, 2, None, None, :]
        feats = self.table[idx.reshape(n, -1)].reshape(n, L, 8, self.features_per_level)
        out = torch.einsum("nlc,nlcf->nlf", w.reshape(n, L, 8), feats).reshape(n, -1)
        if L < self.levels:
            out = torch.cat([out, out.new_zeros(n, (self.levels - L) * self.features_per_level)], dim=-1)
        return out
