"""Multi-resolution hash-grid encoding (Instant-NGP) in plain PyTorch.

Written with gathers and products only, so autograd gives exact first *and* second
derivatives with respect to the input position (the eikonal loss differentiates the SDF
gradient), and it runs the same on CPU and CUDA. Coarse levels that fit are stored densely
(no hash collisions); finer ones are hashed into a table of ``2**log2_table`` entries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

_PRIMES = (1, 2654435761, 805459861)
# The same primes as wrapped int32 (two's complement): products keep the same low bits.
_PRIME_Y = _PRIMES[1] - 2**32
_PRIME_Z = _PRIMES[2]


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
        self.layout = (base_resolution, max_resolution, tuple(sizes))  # what a shared lookup must match
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.long), persistent=False)
        self.register_buffer("dense", torch.tensor(dense, dtype=torch.bool), persistent=False)
        self.active_levels = levels
        # Corner c of a cell has bits (x, y, z) = (c >> 2, c >> 1, c) & 1: x slowest, matching
        # the (2, 2, 2) layout of the weights below.
        bits = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=torch.long)
        self.register_buffer("corner_bits", bits.T.contiguous(), persistent=False)
        self.n_dense = sum(dense)
        if any(dense[self.n_dense :]):
            raise ValueError("dense levels must come first")
        stride = torch.tensor(resolutions, dtype=torch.int64) + 1
        dense_off = bits[None, :, 0] + bits[None, :, 1] * stride[:, None] + bits[None, :, 2] * stride[:, None] ** 2
        self.register_buffer("dense_corner_offsets", dense_off.to(torch.int32), persistent=False)
        for size, is_dense in zip(sizes, dense):
            if not is_dense and size & (size - 1):
                raise ValueError("hashed tables must have a power-of-two size")
        self.register_buffer("hash_masks", torch.tensor([size - 1 for size in sizes], dtype=torch.int32), persistent=False)
        self.register_buffer("offsets32", torch.tensor(offsets[:-1], dtype=torch.int32), persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], features_per_level).uniform_(-init_scale, init_scale))

    @property
    def output_dim(self) -> int:
        return self.levels * self.features_per_level

    def set_active_levels(self, active: int) -> None:
        """Progressive training: levels >= ``active`` output zeros (and cost nothing)."""
        self.active_levels = int(max(1, min(active, self.levels)))

    def _lookup(self, x: torch.Tensor):
        """Corner indices (N, L, 8), per-axis fractions (N, L, 3) and the clamp mask (N, 3).

        Written for CPU speed: int32 arithmetic (only the low bits of the hash matter, and
        the tables are powers of two), dense and hashed levels computed apart, and 8-corner
        tensors built by gathering along a short last axis rather than 5-D broadcasting.
        """
        L = self.active_levels
        res = self.resolutions[:L]
        u_raw = (x + 1.0) * 0.5
        inside = (u_raw > 0.0) & (u_raw < 1.0)
        pos = u_raw.clamp(0.0, 1.0)[:, None, :] * res[None, :, None]  # (N, L, 3)
        base_f = torch.minimum(torch.floor(pos), res[None, :, None] - 1)
        frac = pos - base_f
        base = base_f.to(torch.int32)
        cx, cy, cz = self.corner_bits  # (8,) each: corner c has bits (cx, cy, cz)
        n_dense = min(self.n_dense, L)
        parts = []
        if n_dense:
            b = base[:, :n_dense]
            stride = (self.resolutions[:n_dense].to(torch.int32) + 1)[None, :]
            lin = b[..., 0] + b[..., 1] * stride + b[..., 2] * stride * stride  # (N, Ld)
            parts.append(lin[..., None] + self.dense_corner_offsets[:n_dense][None])
        if L > n_dense:
            b = base[:, n_dense:]
            hx = torch.stack([b[..., 0], b[..., 0] + 1], -1)
            hy = torch.stack([b[..., 1], b[..., 1] + 1], -1) * _PRIME_Y
            hz = torch.stack([b[..., 2], b[..., 2] + 1], -1) * _PRIME_Z
            h = hx.index_select(2, cx) ^ hy.index_select(2, cy) ^ hz.index_select(2, cz)  # (N, Lh, 8)
            parts.append(h & self.hash_masks[n_dense:L][None, :, None])
        idx = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        idx = (idx + self.offsets32[:L][None, :, None]).long()  # int64: index ops are much faster
        return idx, frac, inside

    def _pad(self, out: torch.Tensor) -> torch.Tensor:
        n, L = out.shape[0], self.active_levels
        out = out.reshape(n, -1)
        if L < self.levels:
            out = torch.cat([out, out.new_zeros(n, (self.levels - L) * self.features_per_level)], dim=-1)
        return out

    @torch.no_grad()
    def lookup(self, x: torch.Tensor) -> "GridLookup":
        """Where points fall in the grid: corner indices and trilinear weights, which depend only
        on the points and the grid's layout, not on the table. Encodings with the same layout
        (the report's leave-one-out heads) can share one lookup of the same points."""
        idx, frac, inside = self._lookup(x)
        w_axis, w = _corner_weights(frac, self.corner_bits)
        return GridLookup(idx, w_axis, w, inside, self.active_levels, self.layout)

    def forward(self, x: torch.Tensor, twice_differentiable: bool = False,
                lookup: "GridLookup | None" = None) -> torch.Tensor:
        """x: (N, 3) in [-1, 1]^3 (clamped) -> (N, levels * features).

        The default path has a hand-written backward (first derivatives with respect to x and
        the table: several times faster on CPU than autograd through the gathers). With
        ``twice_differentiable`` the same values come from plain autograd ops, which the
        eikonal loss needs for its second derivatives. ``lookup``: ``self.lookup(x)`` computed
        before (by this encoding or one with the same layout), to skip the index math.
        """
        if twice_differentiable:
            return self._forward_autograd(x)
        if lookup is None:
            lookup = self.lookup(x)
        elif lookup.levels != self.active_levels or lookup.layout != self.layout:
            raise ValueError("the lookup was made for a hash grid of another layout")
        return _HashInterp.apply(x, self.table, self, lookup)

    def _forward_autograd(self, x: torch.Tensor) -> torch.Tensor:
        n, L = x.shape[0], self.active_levels
        idx, frac, _ = self._lookup(x)
        _, w = _corner_weights(frac, self.corner_bits)
        # index_select, not table[idx]: its backward is an index_add, several times faster on CPU.
        feats = self.table.index_select(0, idx.reshape(-1)).reshape(n, L, 8, self.features_per_level)
        return self._pad(torch.einsum("nlc,nlcf->nlf", w.reshape(n, L, 8), feats))


def _corner_weights(frac: torch.Tensor, corner_bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis weights (N, L, 3, 2) and trilinear corner weights (N, L, 8), x bit slowest."""
    w_axis = torch.stack([1.0 - frac, frac], dim=-1)
    cx, cy, cz = corner_bits
    w = w_axis[:, :, 0].index_select(2, cx) * w_axis[:, :, 1].index_select(2, cy) * w_axis[:, :, 2].index_select(2, cz)
    return w_axis, w


def _gather_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table.index_select(0, index)`` without autograd; a row of two float32 features is read
    as one 8-byte word, which CPU gathers do several times faster than two-element rows."""
    if table.dtype == torch.float32 and table.shape[1] == 2 and table.is_contiguous():
        return table.view(torch.float64).reshape(-1).index_select(0, index).view(torch.float32).reshape(-1, 2)
    return table.index_select(0, index)


def _scatter_rows(values: torch.Tensor, index: torch.Tensor, rows: int) -> torch.Tensor:
    """``zeros(rows, F).index_add_(0, index, values)``, faster on CPU: a pair of float32
    features is added as one complex64 number (the same two float additions) in a single
    1-D scatter, which beats row-wise index_add_ and one float64 bincount per feature."""
    if values.dtype == torch.float32 and values.shape[1] == 2:
        pairs = values.contiguous().view(torch.complex64).reshape(-1)
        return torch.view_as_real(pairs.new_zeros(rows).scatter_add_(0, index, pairs))
    return values.new_zeros(rows, values.shape[1]).index_add_(0, index, values)


@dataclass(frozen=True)
class GridLookup:
    """``HashGridEncoding.lookup``: per point and level, the 8 corners' table rows and weights."""

    idx: torch.Tensor  # (N, L, 8) rows of the table
    w_axis: torch.Tensor  # (N, L, 3, 2) per-axis weights
    w: torch.Tensor  # (N, L, 8) trilinear corner weights
    inside: torch.Tensor  # (N, 3) not clamped (the gradient with respect to x is zero outside)
    levels: int
    layout: tuple  # HashGridEncoding.layout of the encoding that made it


class _HashInterp(torch.autograd.Function):
    """Trilinear hash-grid interpolation with an explicit first-order backward."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, table: torch.Tensor, enc: HashGridEncoding, lookup: GridLookup) -> torch.Tensor:
        n, L, F = x.shape[0], enc.active_levels, enc.features_per_level
        with torch.no_grad():
            idx, w_axis, w, inside = lookup.idx, lookup.w_axis, lookup.w, lookup.inside
            feats = _gather_rows(table, idx.reshape(-1)).reshape(n, L, 8, F)
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
            grad_table = _scatter_rows(contrib, idx.reshape(-1), ctx.table_shape[0])
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
        return grad_x, grad_table, None, None


def sh_deg2(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to degree 2 (9 values): a smooth code for view direction."""
    x, y, z = d.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, 0.28209479),
            -0.48860251 * y,
            0.48860251 * z,
            -0.48860251 * x,
            1.09254843 * x * y,
            -1.09254843 * y * z,
            0.31539157 * (2 * z * z - x * x - y * y),
            -1.09254843 * x * z,
            0.54627421 * (x * x - y * y),
        ],
        dim=-1,
    )
