"""Multi-resolution hash-grid encoding (Instant-NGP) in plain PyTorch.

Written with gathers and products only, so autograd gives exact first *and* second
derivatives with respect to the input position (the eikonal loss differentiates the SDF
gradient), and it runs the same on CPU and CUDA. Coarse levels that fit are stored densely
(no hash collisions); finer ones are hashed into a table of ``2**log2_table`` entries.
"""

from __future__ import annotations

import functools
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
        out = out.reshape(n, L * self.features_per_level)  # explicit: n may be 0
        if L < self.levels:
            out = torch.cat([out, out.new_zeros(n, (self.levels - L) * self.features_per_level)], dim=-1)
        return out

    @torch.no_grad()
    def lookup(self, x: torch.Tensor) -> "GridLookup":
        """Where points fall in the grid: corner indices and trilinear weights, which depend only
        on the points and the grid's layout, not on the table. Encodings with the same layout
        (the report's leave-one-out heads) can share one lookup of the same points."""
        idx, frac, inside = self._lookup(x)
        return GridLookup(idx, _corner_weights(frac, self.corner_bits), inside, self.active_levels, self.layout)

    def forward(self, x: torch.Tensor, twice_differentiable: bool = False,
                lookup: "GridLookup | None" = None) -> torch.Tensor:
        """x: (N, 3) in [-1, 1]^3 (clamped) -> (N, levels * features).

        The default path has hand-written backwards (first derivatives with respect to x and
        the table: several times faster on CPU than autograd through the gathers). With
        ``twice_differentiable`` the same values come from plain autograd ops, which the
        eikonal loss needs for its second derivatives. ``lookup``: ``self.lookup(x)`` computed
        before (by this encoding or one with the same layout), to skip the index math.

        The derivatives with respect to x and to the table are two autograd nodes over one
        gather, so a backward pass pays only for what it asks: the SDF's normal
        (``autograd.grad`` to x) never scatters into the table, and the loss's backward to the
        parameters (``backward(inputs=...)``) never forms d/dx.
        """
        if twice_differentiable:
            return self._forward_autograd(x)
        if lookup is None:
            lookup = self.lookup(x)
        elif lookup.levels != self.active_levels or lookup.layout != self.layout:
            raise ValueError("the lookup was made for a hash grid of another layout")
        with torch.no_grad():
            feats = _gather_rows(self.table, lookup.idx.reshape(-1)).reshape(*lookup.w.shape, self.features_per_level)
            values = self._pad(torch.einsum("nlc,nlcf->nlf", lookup.w, feats))
        grad_on = torch.is_grad_enabled()
        to_x = grad_on and x.requires_grad
        to_table = grad_on and self.table.requires_grad
        if to_x and to_table:
            through_x = _PositionGrad.apply(x, values, feats, lookup, self)
            through_table = _TableGrad.apply(self.table, values, lookup, self)
            return through_x + (through_table - values)  # the same values; gradients reach both
        if to_x:
            return _PositionGrad.apply(x, values, feats, lookup, self)
        if to_table:
            return _TableGrad.apply(self.table, values, lookup, self)
        return values

    def _forward_autograd(self, x: torch.Tensor) -> torch.Tensor:
        n, L = x.shape[0], self.active_levels
        idx, frac, _ = self._lookup(x)
        w = _corner_weights(frac, self.corner_bits)
        # index_select, not table[idx]: its backward is an index_add, several times faster on CPU.
        feats = self.table.index_select(0, idx.reshape(-1)).reshape(n, L, 8, self.features_per_level)
        return self._pad(torch.einsum("nlc,nlcf->nlf", w.reshape(n, L, 8), feats))


def _corner_weights(frac: torch.Tensor, corner_bits: torch.Tensor) -> torch.Tensor:
    """Trilinear corner weights (N, L, 8), x bit slowest."""
    w_axis = torch.stack([1.0 - frac, frac], dim=-1)
    cx, cy, cz = corner_bits
    return w_axis[:, :, 0].index_select(2, cx) * w_axis[:, :, 1].index_select(2, cy) * w_axis[:, :, 2].index_select(2, cz)


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


@functools.lru_cache(maxsize=8)
def _edge_matrices(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The 12 cell edges as two (8, 12) matrices over the corners (x bit slowest): ``DIFF``
    takes the far corner minus the near one, ``SUM`` adds them. Along an edge the trilinear
    weight of the other two axes is the sum of its two corners' weights (the axis' own two
    weights add up to one), so d value / d position on each axis is a sum over its 4 edges
    of (difference of the corners' values) x (sum of their weights): two small matrix
    products instead of broadcasting 2 x 2 outer products, which is slow on CPU."""
    diff = torch.zeros(8, 12, device=device, dtype=dtype)
    total = torch.zeros(8, 12, device=device, dtype=dtype)
    for axis, bit in enumerate((4, 2, 1)):
        near = [c for c in range(8) if not c & bit]
        for k, c in enumerate(near):
            edge = axis * 4 + k
            diff[c + bit, edge], diff[c, edge] = 1.0, -1.0
            total[c + bit, edge] = total[c, edge] = 1.0
    return diff, total


@dataclass(frozen=True)
class GridLookup:
    """``HashGridEncoding.lookup``: per point and level, the 8 corners' table rows and weights."""

    idx: torch.Tensor  # (N, L, 8) rows of the table
    w: torch.Tensor  # (N, L, 8) trilinear corner weights
    inside: torch.Tensor  # (N, 3) not clamped (the gradient with respect to x is zero outside)
    levels: int
    layout: tuple  # HashGridEncoding.layout of the encoding that made it


class _PositionGrad(torch.autograd.Function):
    """The interpolated features as a function of x (the table held fixed); first order."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, values: torch.Tensor, feats: torch.Tensor, lookup: GridLookup,
                enc: HashGridEncoding) -> torch.Tensor:
        ctx.save_for_backward(feats, lookup.w, lookup.inside)
        ctx.enc = enc
        return values.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        feats, w, inside = ctx.saved_tensors
        enc = ctx.enc
        n, L, _, F = feats.shape
        g = grad_out.reshape(n, enc.levels, F)[:, :L]  # (N, L, F)
        gf = feats[..., 0] * g[:, :, None, 0]  # d out / d w_c, (N, L, 8); unrolled: F is 2
        for f in range(1, F):
            gf = gf + feats[..., f] * g[:, :, None, f]
        diff, total = _edge_matrices(feats.device, feats.dtype)
        per_edge = (gf @ diff) * (w @ total)  # (N, L, 12): axis-major, 4 edges each
        # sum over each axis' edges and the levels at once, scaled by each level's resolution
        # (d pos / d x = res / 2)
        scale = torch.zeros(L, 12, 3, device=feats.device, dtype=feats.dtype)
        for axis in range(3):
            scale[:, axis * 4 : axis * 4 + 4, axis] = enc.resolutions[:L, None] * 0.5
        grad_x = (per_edge.reshape(n, L * 12) @ scale.reshape(L * 12, 3)) * inside.to(g.dtype)
        return grad_x, None, None, None, None


class _TableGrad(torch.autograd.Function):
    """The interpolated features as a function of the table (x held fixed)."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, values: torch.Tensor, lookup: GridLookup,
                enc: HashGridEncoding) -> torch.Tensor:
        ctx.save_for_backward(lookup.idx, lookup.w)
        ctx.enc = enc
        ctx.rows = table.shape[0]
        return values.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        idx, w = ctx.saved_tensors
        enc = ctx.enc
        n, L, _ = w.shape
        F = enc.features_per_level
        g = grad_out.reshape(n, enc.levels, F)[:, :L]
        contrib = (w[..., None] * g[:, :, None, :]).reshape(-1, F)
        return _scatter_rows(contrib, idx.reshape(-1), ctx.rows), None, None, None


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
