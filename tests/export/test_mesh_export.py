"""Labelled mesh export: colours survive a round trip, areas are right, mm² scale applies."""


import numpy as np
import pytest
import torch
import trimesh

from labelsynth.capture.model import SceneNormalization
from labelsynth.classes import ClassMap
from labelsynth.export.mesh import class_areas, export_labelled_mesh, labelled_mesh
from labelsynth.recipe import Recipe

CLASSES = ClassMap.default()
SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_unit_square_of_one_class_has_area_one():
    areas = class_areas(SQUARE_V, SQUARE_F, np.full(4, 1), CLASSES)
    assert areas.by_class["granulation"] == pytest.approx(1.0)
    assert areas.by_class["background"] == 0.0
    assert areas.wound_bed == pytest.approx(1.0)
    assert areas.total == pytest.approx(1.0)
    assert areas.mm2_by_class is None


def test_mm2_scaling():
    areas = class_areas(SQUARE_V * 2.0, SQUARE_F, np.full(4, 2), CLASSES, mm_per_unit=10.0)
    assert areas.by_class["slough"] == pytest.approx(4.0)
    assert areas.mm2_by_class["slough"] == pytest.approx(400.0)
    d = areas.to_dict()
    assert d["wound_bed_mm2"] == pytest.approx(400.0) and d["total_mm2"] == pytest.approx(400.0)
    with pytest.raises(ValueError):
        class_areas(SQUARE_V, SQUARE_F, np.full(4, 2), CLASSES, mm_per_unit=-1.0)


def test_mixed_faces_split_by_vertex_thirds():
    # vertices 0,1,2 granulation, 3 background: face (0,1,2) all granulation; face (0,2,3) two thirds.
    ids = np.array([1, 1, 1, 0])
    areas = class_areas(SQUARE_V, SQUARE_F, ids, CLASSES)
    assert areas.by_class["granulation"] == pytest.approx(0.5 + 0.5 * 2 / 3)
    assert areas.by_class["background"] == pytest.approx(0.5 / 3)
    assert sum(areas.by_class.values()) == pytest.approx(areas.total)


@pytest.mark.parametrize("ext", ["ply", "glb"])
def test_round_trip_keeps_vertex_colours(tmp_path, ext):
    ids = np.array([1, 2, 3, 0], dtype=np.uint8)
    mesh = labelled_mesh(SQUARE_V, SQUARE_F, ids, CLASSES)
    path = tmp_path / f"m.{ext}"
    mesh.export(path)
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.vertices) == 4 and len(back.faces) == 2
    # GLB may reorder nothing here, but match colours by position to be safe.
    order = [int(np.argmin(np.linalg.norm(back.vertices - v, axis=1))) for v in SQUARE_V]
    colours = np.asarray(back.visual.vertex_colors)[order, :3]
    np.testing.assert_array_equal(colours, CLASSES.colors[[1, 2, 3, 0]])


class _FakeField:
    """Just what export_labelled_mesh uses of a field's renderer: a unit-cube mesh, a head, a
    normalisation, a recipe."""

    def __init__(self):
        self.classes = CLASSES
        self.recipe = Recipe()
        self.config = self.recipe.render
        self.normalization = SceneNormalization(center=np.array([5.0, 0.0, 0.0]), scale=2.0)
        self.field = self  # the renderer's field
        self._mesh = trimesh.Trimesh(SQUARE_V * 0.5, SQUARE_F, process=False)

    def mesh(self):
        return self._mesh

    def logits_at(self, points):
        pts = torch.as_tensor(np.asarray(points, dtype=np.float32))
        logits = torch.zeros(len(pts), CLASSES.num_classes)
        logits[:, 1] = torch.where(pts[:, 0] < 0.25, 5.0, -5.0)  # left half granulation
        return logits


def test_export_labelled_mesh_world_units_and_files(tmp_path):
    exp = export_labelled_mesh(_FakeField(), tmp_path, mesh_format="glb", mm_per_unit=3.0)
    assert [p.name for p in exp.paths] == ["mesh.ply", "mesh.glb"]
    back = trimesh.load(tmp_path / "mesh.ply", process=False)
    # unit square of side 0.5 scaled by 2 around centre (5,0,0): side 1 in world units.
    np.testing.assert_allclose(back.vertices.min(0), [5.0, 0.0, 0.0])
    assert exp.areas.total == pytest.approx(1.0)
    assert exp.areas.by_class["granulation"] == pytest.approx(0.5)  # vertices 0 and 3 of 4
    assert exp.areas.to_dict()["total_mm2"] == pytest.approx(9.0)
    with pytest.raises(ValueError):
        export_labelled_mesh(_FakeField(), tmp_path, mesh_format="obj")
