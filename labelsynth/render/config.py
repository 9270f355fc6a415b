"""The render stage's knobs (recipe section ``render``): how the fitted field becomes masks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from ..config import Count, Positive, Range, UnitInterval
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
    unseen_confidence: UnitInterval = 0.25
    """Confidence (labels.h5) at most this where the pixel's surface no teaching frame saw
    (``support.SurfaceSupport``): the head's class there is a guess from its neighbours, not
    something a mask said. Below 1/classes it also reads lower than any label the head gives
    a seen pixel. 1.0 leaves the confidence as the head gives it."""
    support_tolerance_px: Positive = 2.0
    """A surface point counts as seen by a teaching frame when it lies no deeper than the
    frame's own first hit at its pixel plus this many pixels' footprint at that depth."""
    support_size: Annotated[int, Range(16, 8192)] = 512
    """Longest side of the teaching frames' depth maps (smaller frames are cast as they are)."""
    chunk: Count = 65536
    """Points per evaluation of the head (memory, not results)."""
