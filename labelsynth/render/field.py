"""The fitted field: what ``expand`` learns from a capture, and nothing about how it is used.

Geometry (the SDF and its occupancy grid, frozen once the semantic stage starts) plus the
semantic head, with what gives them meaning: the class table, the scene normalisation (unit
cube <-> world), the recipe they were fitted with and what the geometry was fitted on
(``geometry.fingerprint``). ``renderer.FieldRenderer`` turns it into
masks (with any head: the report renders each left-out frame with its own);
``rundir.save_field`` / ``load_field`` persist it as ``field.pt``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from ..capture.model import SceneNormalization
from ..classes import ClassMap
from ..geometry.fingerprint import GeometryFingerprint
from ..geometry.sampling import OccupancyGrid
from ..geometry.sdf import SDFField
from ..recipe import Recipe
from ..semantics.head import SemanticHead
from ..semantics.training import make_semantic_head


@dataclass(frozen=True)
class SurfaceMesh:
    """The field's zero level set as ``render`` extracts it (marching cubes at ``resolution``
    cells per side, unit-cube coordinates). It depends on the frozen geometry alone, so
    field.pt keeps it and a relabel or a report rebuilt later does not extract it again."""

    resolution: int
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    normals: np.ndarray  # (V, 3)

    @classmethod
    def of(cls, mesh: trimesh.Trimesh, resolution: int) -> "SurfaceMesh":
        return cls(int(resolution), np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.vertex_normals))

    def mesh(self) -> trimesh.Trimesh:
        if not len(self.faces):
            return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, vertex_normals=self.normals, process=False)


@dataclass
class FittedField:
    """One capture's fitted field; ``head`` is None until the semantic stage has run
    (a geometry-only field). ``fitted_on``: what the geometry was fitted on (None for a
    field.pt from before fingerprints), so that it is reused only on the same inputs.
    ``surface``: the extracted surface, once rendered (``renderer.FieldRenderer.mesh``)."""

    sdf: SDFField
    grid: OccupancyGrid
    classes: ClassMap
    normalization: SceneNormalization
    recipe: Recipe
    head: SemanticHead | None = None
    fitted_on: GeometryFingerprint | None = None
    surface: SurfaceMesh | None = None

    @property
    def device(self) -> torch.device:
        return self.sdf.encoding.table.device

    def with_head(self, head: SemanticHead | None) -> "FittedField":
        """The same geometry with another head (the field is never changed in place)."""
        return dataclasses.replace(self, head=head)

    def new_head(self) -> SemanticHead:
        """A fresh, untrained head of the recipe's shape for this geometry and class table."""
        return make_semantic_head(self.sdf, self.classes, self.recipe.semantic)
