"""The labelled surface: the field's mesh in world coordinates, coloured by class, with areas.

Clinicians want wound areas in mm², engineers want a mesh they can open in any viewer; both
come from the same extracted surface. Labels live on the vertices (the semantic head is
evaluated there), so a face whose vertices disagree is shared between their classes:
**each vertex owns one third of the area of every face it belongs to** (the barycentric
cell). This keeps class areas additive (they sum to the mesh area) and unbiased at class
boundaries, where a majority vote per face would always round towards one side.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..classes import ClassMap
from ..options import MeshFormat
from ..render.renderer import FieldRenderer
from ..rundir import MESH_STEM
from ..semantics.head import decide_labels

MESH_FORMATS = MeshFormat.choices()
WOUND_BED = "wound_bed"


@dataclass
class MeshAreas:
    """Per-class surface area of a labelled mesh in world units² (and mm² given a scale)."""

    by_class: dict[str, float]
    wound_bed: float
    total: float
    mm_per_unit: float | None = None
    vertex_counts: dict[str, int] = field(default_factory=dict)

    @property
    def mm2_by_class(self) -> dict[str, float] | None:
        if self.mm_per_unit is None:
            return None
        s = self.mm_per_unit**2
        return {k: v * s for k, v in self.by_class.items()}

    @property
    def wound_bed_mm2(self) -> float | None:
        return None if self.mm_per_unit is None else self.wound_bed * self.mm_per_unit**2

    def to_dict(self) -> dict:
        """JSON-ready: areas in scene units², plus mm² when a scale was given."""
        out: dict = {
            "units": "scene units^2",
            "by_class": dict(self.by_class),
            "wound_bed": self.wound_bed,
            "total": self.total,
            "vertex_counts": dict(self.vertex_counts),
            "mm_per_unit": self.mm_per_unit,
            "rule": "each vertex owns one third of every face it belongs to",
        }
        if self.mm_per_unit is not None:
            out["by_class_mm2"] = self.mm2_by_class
            out["wound_bed_mm2"] = self.wound_bed_mm2
            out["total_mm2"] = self.total * self.mm_per_unit**2
        return out


@dataclass
class MeshExport:
    """What ``export_labelled_mesh`` wrote."""

    paths: list[Path]
    areas: MeshAreas
    n_vertices: int
    n_faces: int

    def to_dict(self) -> dict:
        return {
            "files": [p.name for p in self.paths],
            "vertices": self.n_vertices,
            "faces": self.n_faces,
            "areas": self.areas.to_dict(),
        }


def class_areas(
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_ids: np.ndarray,
    classes: ClassMap,
    mm_per_unit: float | None = None,
) -> MeshAreas:
    """Area per class of a mesh whose vertices carry class ids (see the module docstring).

    ``vertices`` are in the units the areas should be in (world units for a scene mesh).
    """
    if mm_per_unit is not None and not (np.isfinite(mm_per_unit) and mm_per_unit > 0):
        raise ValueError(f"mm_per_unit must be a positive number, got {mm_per_unit}")
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    vertex_ids = np.asarray(vertex_ids).reshape(-1)
    if len(vertex_ids) != len(vertices):
        raise ValueError(f"{len(vertex_ids)} vertex labels for {len(vertices)} vertices")
    if len(faces):
        tri = vertices[faces]
        face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    else:
        face_area = np.zeros(0)
    by_class: dict[str, float] = {}
    counts: dict[str, int] = {}
    for c in classes.classes:
        own = (vertex_ids[faces] == c.id).sum(axis=1) if len(faces) else np.zeros(0)
        by_class[c.name] = float((face_area * own).sum() / 3.0)
        counts[c.name] = int((vertex_ids == c.id).sum())
    wb = classes.wound_bed_ids
    wound_bed = float(sum(by_class[classes.name_of(i)] for i in wb))
    return MeshAreas(by_class, wound_bed, float(face_area.sum()), mm_per_unit, counts)


def vertex_class_ids(view: FieldRenderer, vertices_unit: np.ndarray) -> np.ndarray:
    """Class id per vertex from the semantic head at the surface (unit-cube coordinates),
    decided by the same rule as the rendered masks."""
    if len(vertices_unit) == 0:
        return np.zeros(0, dtype=np.uint8)
    classes = view.field.classes
    probs = torch.softmax(view.logits_at(vertices_unit), dim=-1).cpu().numpy()
    return classes.index_to_id_lut()[decide_labels(probs, classes, view.config.decision)]


def labelled_mesh(vertices: np.ndarray, faces: np.ndarray, vertex_ids: np.ndarray, classes: ClassMap) -> trimesh.Trimesh:
    """A trimesh with RGBA vertex colours from the class table (ids outside it are grey)."""
    pal = np.asarray(classes.palette(), dtype=np.uint8).reshape(256, 3)
    rgba = np.concatenate([pal[np.asarray(vertex_ids, dtype=np.uint8)], np.full((len(vertex_ids), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=rgba, process=False)


def export_labelled_mesh(
    view: FieldRenderer,
    out_dir: str | Path,
    *,
    mesh_format: str = "ply",
    mm_per_unit: float | None = None,
    stem: str = MESH_STEM,
) -> MeshExport:
    """Write ``OUT/mesh.ply`` (always) and ``OUT/mesh.glb`` (``mesh_format="glb"``) in world units.

    PLY is always written because it is the format every mesh tool reads with vertex colours
    intact; GLB is added for web viewers and slide decks.
    """
    if mesh_format not in MESH_FORMATS:
        raise ValueError(f"mesh format must be one of {', '.join(MESH_FORMATS)}, not {mesh_format!r}")
    out_dir = Path(out_dir)
    classes = view.field.classes
    unit = view.mesh()
    v_unit = np.asarray(unit.vertices, dtype=np.float64)
    faces = np.asarray(unit.faces, dtype=np.int64)
    ids = vertex_class_ids(view, v_unit)
    v_world = view.field.normalization.to_world(v_unit) if len(v_unit) else v_unit
    mesh = labelled_mesh(v_world, faces, ids, classes)
    paths = [out_dir / f"{stem}.ply"]
    mesh.export(paths[0])
    if mesh_format == "glb":
        paths.append(out_dir / f"{stem}.glb")
        mesh.export(paths[1])
    areas = class_areas(v_world, faces, ids, classes, mm_per_unit)
    return MeshExport(paths, areas, len(v_world), len(faces))
