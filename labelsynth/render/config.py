"""The render stage's knobs (recipe section ``render``): how the fitted field becomes masks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from ..config import Count, Range
from ..semantics.config import DecisionRule


@dataclass
class RenderConfig:
    """Masks at full resolution from the fitted surface (``renderer.FieldRenderer``)."""

    mesh_resolution: Annotated[int, Range(8, 2048)] = 256
    """Cells per side of the marching-cubes grid over the unit cube."""
    subdivide: Annotated[int, Range(0, 4)] = 1
    """Midpoint subdivisions of the mesh before ray casting (4x faces each), so that its
    vertices, where the head is evaluated, lie ~1-2 px apart."""
    decision: DecisionRule = "wound-bed-first"
    """wound-bed-first | argmax: how class probabilities become a label (``semantics.head.decide_labels``)."""
    per_pixel: bool = False
    """Evaluate the head at every pixel's hit (slow) instead of at the mesh's vertices."""
    chunk: Count = 65536
    """Points per evaluation of the head (memory, not results)."""
