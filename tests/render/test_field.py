"""The saved field (conftest.tiny_expanded's field.pt) reloads and renders the masks it wrote,
also from a file saved before the outer background existed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from labelsynth.capture import load_capture
from labelsynth.render.field import SemanticField

# All tests using the shared tiny run go to one xdist worker, so it is fitted once.
pytestmark = pytest.mark.xdist_group("tiny_expanded")


def test_the_saved_field_re_renders_without_refitting(tiny_expanded):
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    sem = SemanticField.load(run.out / "field.pt", torch.device("cpu"))
    again = sem.render(cap.unit_cameras()[0]).mask
    saved = cv2.imread(str(run.out / "masks" / f"{cap.frames[0].name}.png"), cv2.IMREAD_UNCHANGED)
    assert (again == saved).mean() > 0.999


def test_a_field_saved_before_the_outer_background_still_loads(tiny_expanded, tmp_path):
    run = tiny_expanded
    state = torch.load(run.out / "field.pt", weights_only=False)
    state["sdf"] = {k: v for k, v in state["sdf"].items() if not k.startswith("outer.")}
    del state["recipe"]["geometry"]["sdf"]["background"], state["recipe"]["geometry"]["sdf"]["outer"]
    torch.save(state, tmp_path / "old.pt")
    sem = SemanticField.load(tmp_path / "old.pt", torch.device("cpu"))
    assert sem.sdf.outer is None and sem.recipe.geometry.sdf.background == "env"
    cam = load_capture(run.capture_dir).unit_cameras()[0]
    assert sem.render(cam).mask.shape == (cam.height, cam.width)


def test_the_embree_cast_agrees_with_trimesh_and_its_barycentric_coordinates_give_the_hit():
    import trimesh

    from labelsynth.render.surface import SurfaceCaster

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    rng = np.random.default_rng(0)
    origins = rng.normal(size=(400, 3))
    origins = 2.0 * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    targets = rng.uniform(-0.7, 0.7, size=(400, 3))  # some rays miss the sphere
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit, points, faces, bary = SurfaceCaster(mesh).cast(origins, dirs)
    from trimesh.ray.ray_pyembree import RayMeshIntersector  # trimesh's wrapper: float64 plane hits

    slow = RayMeshIntersector(mesh)
    loc, ray, tri = slow.intersects_location(origins, dirs, multiple_hits=False)
    expected = np.zeros(len(origins), bool)
    expected[ray] = True
    assert 0 < hit.sum() < len(hit)
    assert np.array_equal(hit, expected)
    assert np.array_equal(faces[ray], tri) and np.all(faces[~hit] == -1)
    assert np.abs(points[ray] - loc).max() < 1e-5
    assert np.allclose(bary[hit].sum(1), 1.0) and bary[hit].min() > -1e-5
    corners = mesh.vertices[mesh.faces[faces[hit]]]
    assert np.allclose(np.einsum("nk,nkd->nd", bary[hit], corners), points[hit])
