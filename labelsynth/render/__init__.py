"""The fitted field rendered into per-frame masks.

``field`` is ``SemanticField`` (geometry + head + what it takes to reload and render it:
``field.pt``) and its per-frame ``FrameRender``; ``surface`` extracts the SDF's zero level
set and casts camera rays onto it.
"""

from .field import FrameRender, SemanticField
from .surface import SurfaceCaster, extract_mesh

__all__ = ["FrameRender", "SemanticField", "SurfaceCaster", "extract_mesh"]
