"""The geometry field: a NeuS signed distance function with a colour head and a background.

Split as nerfstudio does: ``get_sdf`` gives geometry (distance and a feature vector, what the
semantic head reads), ``get_color`` the view-dependent appearance used only to fit geometry.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated, Literal

import torch
from torch import nn
from torch.nn import functional as F

from ..config import Count, HashTableLog2, OpenUnitInterval, Range
from .background import OuterBackground, OuterConfig
from .encoding import HashGridEncoding, sh_deg2


@dataclass
class SDFConfig:
    """The SDF, its colour head and the background (recipe section ``geometry.sdf``)."""

    levels: Count = 12
    """Hash-grid levels."""
    features_per_level: Count = 2
    log2_table: HashTableLog2 = 17
    """log2 of each level's hash-table size."""
    base_resolution: Count = 16
    """Cells per side of the coarsest level."""
    max_resolution: Count = 1024
    """Cells per side of the finest level."""
    hidden: Count = 64
    """Width of the SDF network."""
    feature_dim: Count = 15
    """Geometry feature handed to the colour and semantic heads."""
    color_hidden: Count = 64
    """Width of the colour network."""
    init_shape: Literal["auto", "sphere", "plane"] = "auto"
    """Shape the SDF starts as (``SDFField.initialise_shape``; auto: from the cameras)."""
    plane_normal: Literal["views", "camera-axes"] = "views"
    """Which way a plane start faces (``plane_normal``): views, the reverse of the mean viewing
    direction; camera-axes, square to every camera's x axis (upright cameras: the ground's, a
    table's normal), falling back to views where the axes do not fix it. On issue 31's table
    capture camera-axes forms the saturated top in more seeds but is better or worse than views
    depending on the schedule's length (docs/benchmarks.md, Real photographs), so views stays."""
    init_radius: OpenUnitInterval = 0.5
    """Sphere initialisation: radius in the unit cube."""
    init_variance: Annotated[float, Range(0.0, 2.0, low_open=True)] = 0.3
    """Initial NeuS sharpness: inv_s = exp(10 * variance)."""
    background: Literal["env", "outer"] = "outer"
    """env: a colour per direction beyond the cube; outer: also a NeRF over contracted space
    outside it (geometry.background), for a table or a room close behind the object."""
    outer: OuterConfig = field(default_factory=OuterConfig)
    """The outer NeRF (``background: outer``)."""

    def validate(self) -> None:
        """Relations between fields (``config.build_config`` calls it)."""
        if self.max_resolution < self.base_resolution:
            raise ValueError(f"max_resolution: {self.max_resolution} is below base_resolution {self.base_resolution}")


# A plane is a useful start only where the cameras see its front face squarely: beyond 60
# degrees from its normal a plane is foreshortened to less than half (cos 60 = 0.5) and a
# camera near 90 degrees sees it edge-on or from behind.
PLANE_MAX_VIEW_ANGLE_DEG = 60.0
PLANE_VIEW_QUANTILE = 0.9  # ...for this share of the cameras (a few stray frames may be oblique)


def _unit_directions(directions) -> tuple["np.ndarray", "np.ndarray"]:
    """Directions (the cameras' viewing directions or x axes) as unit vectors (N, 3), and their
    mean (not renormalised)."""
    import numpy as np

    dirs = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    return dirs, dirs.mean(0)


def choose_init_shape(view_dirs) -> str:
    """``plane`` when the cameras look from one side at a plane facing them, else ``sphere``.

    The plane's normal is the reverse of the mean viewing direction; it is chosen when 90%
    of the cameras look within ``PLANE_MAX_VIEW_ANGLE_DEG`` of it. The length of the mean
    direction alone does not tell: cameras spread over a hemisphere around an object (the
    NeRF-synthetic lego: 0.575) can average as far from zero as a phone's arc over a wound
    (0.80), yet some of them see any plane edge-on (lego: 92 degrees; the synthetic wound's
    arc: at most 45, a DTU scan's: 60 with 90% within 48).
    """
    import numpy as np

    dirs, mean = _unit_directions(view_dirs)
    norm = float(np.linalg.norm(mean))
    if norm < 1e-6:
        return "sphere"
    angles = np.degrees(np.arccos(np.clip(dirs @ (mean / norm), -1.0, 1.0)))
    return "plane" if float(np.quantile(angles, PLANE_VIEW_QUANTILE)) <= PLANE_MAX_VIEW_ANGLE_DEG else "sphere"


# Cameras are held upright: their x axes (image rows) lie parallel to the ground, to a table, to
# skin filmed squarely, so the one direction square to all of them is that surface's normal. It is
# trusted only where the x axes spread over a plane (a single sweep without turning leaves them
# parallel and the direction undetermined) and every camera sees the plane from its front side.
PLANE_AXES_MIN_SPREAD = 0.1  # the second-smallest eigenvalue of the x axes' scatter (of 1/2 at best)
PLANE_AXES_MAX_FLATNESS = 0.05  # the smallest, relative to the second: the axes lie in one plane
PLANE_AXES_MAX_VIEW_ANGLE_DEG = 75.0  # no camera sees the plane more obliquely than this


def plane_normal(view_dirs: Sequence, right_dirs: Sequence | None = None) -> "np.ndarray":
    """The unit normal of the plane the SDF starts as, towards the cameras.

    The direction square to every camera's x axis when those axes are known, spread and flat
    (see the constants above), else the reverse of the mean viewing direction. The mean viewing
    direction is off the surface's normal by the cameras' average tilt: a camera arc that looks
    down at a table from 35-55 degrees gives a plane tilted 43 degrees from the table, and a
    textureless table never tells the colour loss to turn it (issue 31).
    """
    import numpy as np

    dirs, mean = _unit_directions(view_dirs)
    mean = -mean / np.linalg.norm(mean)
    if right_dirs is None:
        return mean
    axes, _ = _unit_directions(right_dirs)
    values, vectors = np.linalg.eigh(axes.T @ axes / len(axes))
    if values[1] < PLANE_AXES_MIN_SPREAD or values[0] > PLANE_AXES_MAX_FLATNESS * values[1]:
        return mean
    normal = vectors[:, 0] if vectors[:, 0] @ mean > 0 else -vectors[:, 0]
    angles = np.degrees(np.arccos(np.clip(-dirs @ normal, -1.0, 1.0)))
    return normal if float(angles.max()) <= PLANE_AXES_MAX_VIEW_ANGLE_DEG else mean


def initial_surface_colour(init_shape: str, rim_rgb: Sequence[float], mean_rgb: Sequence[float]) -> Sequence[float]:
    """The colour the surface starts at: the images' rim colour (the background's start) for a
    plane, their mean colour for a sphere.

    A plane stands for what the cameras film from one side (skin around a wound, a table under
    an object): it crosses every ray through the box, and most pixels show what lies at the
    images' rim. Started at any other colour it explains those pixels worse than the background
    does, and the quickest descent of the colour loss is to make the whole plane transparent,
    over the object too (issue 31's tiny table: after 1000 steps no surface at all in 3 of 3
    seeds). At the rim's colour, transparency neither pays nor costs until the colour head has
    learnt something. A sphere around an object must be carved where the backdrop shows
    through, and the mean colour, darker or brighter than the rim, makes that pay at once
    (the lego with the rim's colour: foreground Dice 0.965 against 0.987).
    """
    return rim_rgb if init_shape == "plane" else mean_rgb


def _colour_logit(rgb) -> torch.Tensor:
    """The pre-sigmoid value of an RGB colour in 0-1 (kept off 0 and 1), for starting a head there."""
    import numpy as np

    c = np.clip(np.asarray(rgb, dtype=np.float64).reshape(3), 0.02, 0.98)
    return torch.as_tensor(np.log(c / (1.0 - c)), dtype=torch.float32)


class SDFField(nn.Module):
    """x in the unit cube -> signed distance (positive outside) and a geometry feature."""

    def __init__(self, cfg: SDFConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or SDFConfig()
        self.encoding = HashGridEncoding(
            cfg.levels, cfg.features_per_level, cfg.log2_table, cfg.base_resolution, cfg.max_resolution
        )
        in_dim = 3 + self.encoding.output_dim
        self.sdf_l0 = nn.Linear(in_dim, cfg.hidden)
        self.sdf_l1 = nn.Linear(cfg.hidden, 1 + cfg.feature_dim)
        self._geometric_init(in_dim)
        self.color_net = nn.Sequential(
            nn.Linear(cfg.feature_dim + 3 + 9, cfg.color_hidden),
            nn.ReLU(inplace=True),
            nn.Linear(cfg.color_hidden, cfg.color_hidden),
            nn.ReLU(inplace=True),
            nn.Linear(cfg.color_hidden, 3),
        )
        self.background = nn.Sequential(nn.Linear(9, 32), nn.ReLU(inplace=True), nn.Linear(32, 3))
        if cfg.background not in ("env", "outer"):
            raise ValueError(f"unknown background '{cfg.background}' (env or outer)")
        self.outer = OuterBackground(cfg.outer) if cfg.background == "outer" else None
        self.variance = nn.Parameter(torch.tensor(cfg.init_variance))

    def _geometric_init(self, in_dim: int) -> None:
        """SAL-style initialisation: the SDF starts as a sphere, so early rays meet a surface."""
        h = self.cfg.hidden
        nn.init.normal_(self.sdf_l0.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(h))
        nn.init.zeros_(self.sdf_l0.weight[:, 3:])
        nn.init.zeros_(self.sdf_l0.bias)
        nn.init.normal_(self.sdf_l1.weight, mean=math.sqrt(math.pi) / math.sqrt(h), std=1e-4)
        nn.init.constant_(self.sdf_l1.bias, -self.cfg.init_radius)
        with torch.no_grad():
            self.sdf_l1.weight[1:].normal_(0.0, 1.0 / math.sqrt(h))
            self.sdf_l1.bias[1:].zero_()

        self.register_buffer("inv_s_floor", torch.tensor(1.0), persistent=True)

    def initialise_shape(self, view_dirs: Sequence, right_dirs: Sequence | None = None) -> str:
        """Start from a shape the cameras can see: a plane facing them or a sphere.

        A phone filming a wound stays on one side of the body, and a plane through the
        region of interest, facing the cameras, is far closer to the truth than a sphere
        (from a sphere the surface has to travel half the cube: measured, wound-bed Dice
        0.31 instead of 0.98 with the fast recipe). Cameras around an object get the
        sphere. ``choose_init_shape`` decides; returns the shape chosen. ``right_dirs``: the
        cameras' x axes, which ``plane_normal: camera-axes`` reads (without them it faces the views).
        """
        import numpy as np

        dirs = np.asarray(view_dirs, dtype=np.float64)
        shape = self.cfg.init_shape
        if shape == "auto":
            shape = choose_init_shape(dirs)
        if shape == "plane":
            axes = right_dirs if self.cfg.plane_normal == "camera-axes" else None
            normal = torch.tensor(plane_normal(dirs, axes), dtype=torch.float32)  # towards the cameras
            with torch.no_grad():
                # softplus(z) - softplus(-z) = z: two hidden units make sdf = n . x exactly.
                self.sdf_l0.weight[:2].zero_()
                self.sdf_l0.weight[0, :3] = normal
                self.sdf_l0.weight[1, :3] = -normal
                self.sdf_l1.weight[0].normal_(0.0, 1e-4)
                self.sdf_l1.weight[0, 0] = 1.0
                self.sdf_l1.weight[0, 1] = -1.0
                self.sdf_l1.bias[0] = 0.0
        elif shape != "sphere":
            raise ValueError(f"unknown init_shape '{shape}' (auto, sphere or plane)")
        return shape

    def initialise_background(self, rgb) -> None:
        """Start the background at a colour (the images' border colour, see ``border_colour``).

        A background that starts grey must be learned while the surface forms; meanwhile
        the SDF can explain a white or dark backdrop faster by growing an opaque shell at
        the cube's walls, and rays that shell absorbs never teach the background again.
        Starting at the backdrop's colour removes that race.
        """
        logit = _colour_logit(rgb)
        with torch.no_grad():
            last = self.background[-1]
            last.weight.mul_(0.01)
            last.bias.copy_(logit)
        if self.outer is not None:
            self.outer.initialise(logit)

    def initialise_colour(self, rgb) -> None:
        """Start the surface's colour at a colour (``initial_surface_colour`` chooses it).

        The background starts at the colour of the images' rim; a surface that starts grey
        next to it explains every pixel worse than the background does, and the colour loss
        makes it transparent before its colour head has learnt anything (measured on a
        synthetic wound, ``synth --seed 101``: opacity 0.86 -> 0.01 in 30 steps, no surface
        left in the cube).
        """
        with torch.no_grad():
            self.color_net[-1].bias.copy_(_colour_logit(rgb))

    @property
    def inv_s(self) -> torch.Tensor:
        """NeuS sharpness: learned, but never below a scheduled floor (set by training)."""
        return torch.maximum(torch.exp(self.variance * 10.0), self.inv_s_floor).clamp(1.0, 1e5)

    def get_sdf(self, x: torch.Tensor, twice_differentiable: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,3) -> sdf (N,) and geometry feature (N, feature_dim)."""
        h = torch.cat([x, self.encoding(x, twice_differentiable)], dim=-1)
        h = F.softplus(self.sdf_l0(h), beta=100)
        out = self.sdf_l1(h)
        return out[:, 0], out[:, 1:]

    def sdf_and_gradient(
        self, x: torch.Tensor, create_graph: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """sdf, feature and d sdf / dx (exact, by autograd; ``create_graph`` for the eikonal loss)."""
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            sdf, feature = self.get_sdf(x, twice_differentiable=create_graph)
            (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=create_graph)
        return sdf, feature, grad

    def get_color(self, feature: torch.Tensor, normal: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """View-dependent colour: the wound is wet and shiny, so colour sees direction and normal."""
        return torch.sigmoid(self.color_net(torch.cat([feature, normal, sh_deg2(dirs)], dim=-1)))

    def get_background(self, dirs: torch.Tensor, origins: torch.Tensor | None = None,
                       far: torch.Tensor | None = None, visible: torch.Tensor | None = None) -> torch.Tensor:
        """Colour of what lies beyond the region of interest: the environment by direction,
        behind the outer field (from ``far``, the rays' exit from the cube) when there is one.

        ``visible`` (bool per ray) limits the outer field to rays the surface has not
        absorbed: behind skin or an opaque object it would cost time and change nothing.
        """
        env = torch.sigmoid(self.background(sh_deg2(dirs)))
        if self.outer is None:
            return env
        if visible is None:
            rgb, transmittance = self.outer(origins, dirs, far)
            return rgb + transmittance[:, None] * env
        out = env.clone()
        if bool(visible.any()):
            rgb, transmittance = self.outer(origins[visible], dirs[visible], far[visible])
            out[visible] = rgb + transmittance[:, None] * env[visible]
        return out

    @torch.no_grad()
    def sdf_batched(self, x: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        return torch.cat([self.get_sdf(x[i : i + chunk])[0] for i in range(0, len(x), chunk)])
