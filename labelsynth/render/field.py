"""The fitted field: what ``expand`` learns from a capture, and nothing about how it is used.

Geometry (the SDF and its occupancy grid, frozen once the semantic stage starts) plus the
semantic head, with what gives them meaning: the class table, the scene normalisation (unit
cube <-> world) and the recipe they were fitted with. ``renderer.FieldRenderer`` turns it into
masks (with any head: the report renders each left-out frame with its own);
``rundir.save_field`` / ``load_field`` persist it as ``field.pt``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from ..capture.model import SceneNormalization
from ..classes import ClassMap
from ..geometry.sampling import OccupancyGrid
from ..geometry.sdf import SDFField
from ..recipe import Recipe
from ..semantics.head import SemanticHead
from ..semantics.training import make_semantic_head


@dataclass
class FittedField:
    """One capture's fitted field; ``head`` is None until the semantic stage has run
    (a geometry-only field)."""

    sdf: SDFField
    grid: OccupancyGrid
    classes: ClassMap
    normalization: SceneNormalization
    recipe: Recipe
    head: SemanticHead | None = None

    @property
    def device(self) -> torch.device:
        return self.sdf.encoding.table.device

    def with_head(self, head: SemanticHead | None) -> "FittedField":
        """The same geometry with another head (the field is never changed in place)."""
        return dataclasses.replace(self, head=head)

    def new_head(self) -> SemanticHead:
        """A fresh, untrained head of the recipe's shape for this geometry and class table."""
        return make_semantic_head(self.sdf, self.classes, self.recipe.semantic)
