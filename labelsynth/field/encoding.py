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

    def _lookup(self, x: torch.Tensor):
        """Corner indices (N, L, 8), per-axis fractions (N, L, 3) and the clamp mask (N, 3)."""
        n, L = x.shape[0], self.active_levels
        res, sizes, offsets, dense = self.resolutions[:L], self.table_sizes[:L], self.offsets[:L], self.dense[:L]
        u_raw = (x + 1.0) * 0.5
        inside = (u_raw > 0.0) & (u_raw < 1.0)
        u = u_raw.clamp(0.0, 1.0)
        pos = u[:, None, :] * res[None, :, None]  # (N, L, 3)
        base = torch.minimum(torch.floor(pos).detach(), res[None, :, None] - 1)
        frac = pos - base
        base = base.long()
        coord = torch.stack([base, base + 1], dim=-1)  # (N, L, 3, 2)
        stride = res.long() + 1
        mult = torch.where(
            dense[:, None],
            torch.stack([torch.ones_like(stride), stride, stride * stride], -1),
            torch.tensor(_PRIMES, device=x.device, dtype=torch.long)[None, :].expand(L, 3),
        )  # (L, 3): dense levels use a linear index, hashed levels xor of coordinate * prime
        parts = coord * mult[None, :, :, None]
        px, py, pz = parts[:, :, 0, :, None, None], parts[:, :, 1, None, :, None], parts[:, :, 2, None, None, :]
        idx = torch.where(dense[None, :, None, None, None], px + py + pz, px ^ py ^ pz)  # (N, L, 2, 2, 2)
        idx = torch.remainder(idx, sizes[None, :, None, None, None]) + offsets[None, :, None, None, None]
        return idx.reshape(n, L, 8), frac, inside

    def _pad(self, out: torch.Tensor) -> torch.Tensor:
        n, L = out.shape[0], self.active_levels
        out = out.reshape(n, -1)
        if L < self.levels:
            out = torch.cat([out, out.new_zeros(n, (self.levels - L) * self.features_per_level)], dim=-1)
        return out

    def forward(self, x: torch.Tensor, twice_differentiable: bool = False) -> torch.Tensor:
        """x: (N, 3) in [-1, 1]^3 (clamped) -> (N, levels * features).

        The default path has a hand-written backward (first derivatives with respect to x and
        the table: several times faster on CPU than autograd through the gathers). With
        ``twice_differentiable`` the same values come from plain autograd ops, which the
        eikonal loss needs for its second derivatives.
        """
        if twice_differentiable:
            return self._forward_autograd(x)
        return _HashInterp.apply(x, self.table, self)

    def _forward_autograd(self, x: torch.Tensor) -> torch.Tensor:
        n, L = x.shape[0], self.active_levels
        idx, frac, _ = self._lookup(x)
        w_axis = torch.stack([1.0 - frac, frac], dim=-1)  # (N, L, 3, 2)
        w = w_axis[:, :, 0, :, None, None] * w_axis[:, :, 1, None, :, None] * w_axis[:, :, 2, None, None, :]
        # index_select, not table[idx]: its backward is an index_add, several times faster on CPU.
        feats = self.table.index_select(0, idx.reshape(-1)).reshape(n, L, 8, self.features_per_level)
        return self._pad(torch.einsum("nlc,nlcf->nlf", w.reshape(n, L, 8), feats))


def _corner_weights(frac: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis weights (N, L, 3, 2) and trilinear corner weights (N, L, 8), x bit slowest."""
    w_axis = torch.stack([1.0 - frac, frac], dim=-1)
    w = w_axis[:, :, 0, :, None, None] * w_axis[:, :, 1, None, :, None] * w_axis[:, :, 2, None, None, :]
    return w_axis, w.reshape(*frac.shape[:2], 8)


class _HashInterp(torch.autograd.Function):
    """Trilinear hash-grid interpolation with an explicit first-order backward."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, table: torch.Tensor, enc: HashGridEncoding) -> torch.Tensor:
        n, L, F = x.shape[0], enc.active_levels, enc.features_per_level
        with torch.no_grad():
            idx, frac, inside = enc._lookup(x)
            w_axis, w = _corner_weights(frac)
            feats = table.index_select(0, idx.reshape(-1)).reshape(n, L, 8, F)
            out = torch.einsum("nlc,nlcf->nlf", w, feats)
        ctx.save_for_backward(idx, w_axis, w, feats, inside)
        ctx.enc = enc
        ctx.table_shape = table.shape
        return enc._pad(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        idx, w_axis, w, feats, inside = ctx.saved_tensors
        enc = ctx.enc
        n, L, _, F = feats.shape
        g = grad_out.reshape(n, enc.levels, F)[:, :L]  # (N, L, F)
        grad_x = grad_table = None
        if ctx.needs_input_grad[1]:
            contrib = (w[..., None] * g[:, :, None, :]).reshape(-1, F)
            grad_table = torch.zeros(ctx.table_shape, dtype=g.dtype, device=g.device)
            grad_table.index_add_(0, idx.reshape(-1), contrib)
        if ctx.needs_input_grad[0]:
            gf = torch.einsum("nlf,nlcf->nlc", g, feats).reshape(n, L, 2, 2, 2)  # d out / d w_c
            wx, wy, wz = w_axis[:, :, 0], w_axis[:, :, 1], w_axis[:, :, 2]  # (N, L, 2)
            dx = gf[:, :, 1] - gf[:, :, 0]  # (N, L, 2y, 2z)
            dy = gf[:, :, :, 1] - gf[:, :, :, 0]  # (N, L, 2x, 2z)
            dz = gf[:, :, :, :, 1] - gf[:, :, :, :, 0]  # (N, L, 2x, 2y)
            gx = (dx * wy[..., :, None] * wz[..., None, :]).sum((-1, -2))
            gy = (dy * wx[..., :, None] * wz[..., None, :]).sum((-1, -2))
            gz = (dz * wx[..., :, None] * wy[..., None, :]).sum((-1, -2))
            grad_pos = torch.stack([gx, gy, gz], dim=-1)  # (N, L, 3): d/d(pos) per level
            grad_x = (grad_pos * enc.resolutions[:L][None, :, None]).sum(1) * 0.5 * inside.to(g.dtype)
        return grad_x, grad_table, None
