"""Stage 1, geometry: an SDF and a colour field fitted to the images of a capture.

``encoding`` is the hash grid, ``sdf`` the distance + feature + colour model, ``background``
what lies beyond the region of interest, ``sampling`` marches rays through the occupancy grid
and turns the SDF into NeuS weights (the one weighting path), and ``training`` fits the whole
to the images (``RayBank`` + ``train_geometry``) as ``config.GeometryConfig`` (the recipe's
``geometry`` section) says. The semantic stage reads the frozen result.
"""

from .config import GeometryConfig
from .encoding import HashGridEncoding
from .sampling import OccupancyGrid, PackedSamples, RayWeights, march, neus_weights, ray_box
from .sdf import SDFConfig, SDFField
from .training import GeometryStats, RayBank, border_colour, render_rays_rgb, train_geometry

__all__ = [
    "GeometryConfig",
    "GeometryStats",
    "HashGridEncoding",
    "OccupancyGrid",
    "PackedSamples",
    "RayBank",
    "RayWeights",
    "SDFConfig",
    "SDFField",
    "border_colour",
    "march",
    "neus_weights",
    "ray_box",
    "render_rays_rgb",
    "train_geometry",
]
