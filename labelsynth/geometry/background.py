"""What the rays meet after they leave the region of interest (the cube [-1, 1]^3).

Two models, chosen by ``geometry.background``:

- ``env``: a colour per viewing direction (an environment map at infinity, NeuS's choice for
  masked or plain backdrops). Exact for a white, black or far-away background; it cannot
  explain parallax, so a table or a room close behind the object must be explained by the
  SDF inside the cube, or by junk surfaces at the cube's walls.
- ``outer``: NeRF++'s idea, a small density-and-colour field over all space outside the cube,
  contracted into a shell (mip-NeRF 360's contraction in the max-norm: a point at max-norm
  ``r > 1`` maps to ``(2 - 1/r) x / r``), sampled uniformly in disparity from the cube's exit
  to infinity. Close background gets its own geometry, so the SDF need not grow any.

The outer field has no semantic head: whatever it explains is background.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from torch import nn
from torch.nn import functional as F

from ..config import Count, HashTableLog2, Range
from .encoding import HashGridEncoding, sh_deg2


@dataclass
class OuterConfig:
    """The NeRF beyond the unit cube (recipe section ``geometry.sdf.outer``)."""

    samples: Count = 16
    """Samples per ray, uniform in disparity between the cube's exit and infinity."""
    levels: Count = 8
    """Hash-grid levels."""
    log2_table: HashTableLog2 = 15
    """log2 of each level's hash-table size."""
    max_resolution: Annotated[int, Range(16)] = 256
    """Cells per side of the finest level (the coarsest has 16)."""
    hidden: Count = 32
    """Width of its network."""


def contract(x: torch.Tensor) -> torch.Tensor:
    """Max-norm contraction: the cube stays, all space outside maps into the shell 1 < r < 2."""
    r = x.abs().amax(-1, keepdim=True).clamp_min(1e-6)
    return torch.where(r <= 1.0, x, (2.0 - 1.0 / r) * x / r)


class OuterBackground(nn.Module):
    """A NeRF over contracted space outside the cube; what it leaves unabsorbed goes on to
    the environment colour (``SDFField.get_background``)."""

    def __init__(self, cfg: OuterConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or OuterConfig()
        self.encoding = HashGridEncoding(cfg.levels, 2, cfg.log2_table, 16, cfg.max_resolution)
        self.density_net = nn.Sequential(
            nn.Linear(self.encoding.output_dim, cfg.hidden), nn.ReLU(inplace=True), nn.Linear(cfg.hidden, 1 + 15)
        )
        self.color_net = nn.Sequential(nn.Linear(15 + 9, cfg.hidden), nn.ReLU(inplace=True), nn.Linear(cfg.hidden, 3))

    def initialise(self, logit: torch.Tensor) -> None:
        """Start transparent, coloured like the backdrop (``SDFField.initialise_background``)."""
        with torch.no_grad():
            self.density_net[-1].bias[0] = -4.0
            self.color_net[-1].bias.copy_(logit)

    def forward(self, origins: torch.Tensor, dirs: torch.Tensor, far: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour composited along the rays beyond ``far`` (their exit from the cube), and the
        transmittance left after them."""
        n, k = origins.shape[0], self.cfg.samples
        far = far.clamp_min(1e-3)[:, None]
        # disparity from 1/far down to (almost) 0, stratified when training
        u = torch.arange(k, device=origins.device, dtype=origins.dtype)[None, :]
        u = (u + (torch.rand(n, k, device=origins.device) if self.training else 0.5)) / k
        t = far / (1.0 - u * (1.0 - 1e-3))  # 1/t = (1/far) * (1 - u), last sample ~1000x far
        x = origins[:, None, :] + dirs[:, None, :] * t[..., None]
        xc = contract(x.reshape(-1, 3))
        h = self.density_net(self.encoding(xc * 0.5))
        sigma = F.softplus(h[:, 0] - 1.0).reshape(n, k)
        color = torch.sigmoid(self.color_net(torch.cat([h[:, 1:], sh_deg2(dirs).repeat_interleave(k, 0)], -1)))
        # distances in the contracted shell (thickness 1): the infinite tail stays finite
        xc = xc.reshape(n, k, 3)
        delta = torch.cat([(xc[:, 1:] - xc[:, :-1]).norm(dim=-1), (2.0 - xc[:, -1].abs().amax(-1, keepdim=True)).clamp_min(0)], 1)
        alpha = 1.0 - torch.exp(-sigma * delta)
        trans = torch.cumprod(torch.cat([torch.ones(n, 1, device=alpha.device), 1.0 - alpha + 1e-7], 1), 1)
        w = alpha * trans[:, :-1]
        return (w[..., None] * color.reshape(n, k, 3)).sum(1), trans[:, -1]
