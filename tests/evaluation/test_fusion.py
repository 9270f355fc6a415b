"""The 3D/2D vote on tiny meshes whose answer is known."""

import numpy as np
import pytest
import trimesh

from labelsynth.cameras import Camera, look_at
from labelsynth.capture.model import SceneNormalization
from labelsynth.classes import ClassMap
from labelsynth.errors import LabelsynthError
from labelsynth.evaluation.fusion import fuse_labels, load_mesh_unit, render_labels, view_votes
from labelsynth.render.surface import SurfaceCaster

CLASSES = ClassMap.default()
SIZE = 64


def grid_square(half: float, z: float, cells: int = 8) -> trimesh.Trimesh:
    """A flat square in the plane z=const, normal +z, split into cells x cells x 2 triangles."""
    lin = np.linspace(-half, half, cells + 1)
    xx, yy = np.meshgrid(lin, lin, indexing="ij")
    verts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], -1)
    idx = np.arange(verts.shape[0]).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return trimesh.Trimesh(vertices=verts, faces=faces, process=False)


def camera_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), size=SIZE) -> Camera:
    # focal = size: half-FOV tan 0.5, so at distance 2 the view spans +-1
    return Camera(size, size, float(size), float(size), size / 2, size / 2, look_at(eye, target, up))


def camera_at_angle(deg: float, dist: float = 2.0) -> Camera:
    """A camera at ``deg`` from the +z normal of the plane z=0, looking at the origin."""
    t = np.deg2rad(deg)
    return camera_at((dist * np.sin(t), 0.0, dist * np.cos(t)))


def full(cls_id: int) -> np.ndarray:
    return np.full((SIZE, SIZE), cls_id, dtype=np.uint8)


def test_squarely_seen_label_wins_over_grazing_view():
    mesh = grid_square(0.5, 0.0)
    cams = {"square": camera_at_angle(0.0), "grazing": camera_at_angle(65.0)}
    fused = fuse_labels(mesh, cams, {"square": full(1), "grazing": full(2)}, CLASSES, cutoff_deg=75)
    assert fused.views == 2
    # both views voted, each for its own class...
    assert fused.votes[:, 1].sum() > 0 and fused.votes[:, 2].sum() > 0
    # ...and the square view wins on every face
    assert set(fused.face_labels.tolist()) == {CLASSES.index_of(1)}


def test_view_beyond_cutoff_does_not_vote():
    mesh = grid_square(0.5, 0.0)
    cams = {"grazing": camera_at_angle(80.0)}
    fused = fuse_labels(mesh, cams, {"grazing": full(2)}, CLASSES, cutoff_deg=75)
    assert fused.views == 0 and not fused.votes.any()
    assert (fused.face_labels == CLASSES.background_index).all()
    # a wider cut-off lets the same view vote
    wide = fuse_labels(mesh, cams, {"grazing": full(2)}, CLASSES, cutoff_deg=85)
    assert wide.votes[:, 2].sum() > 0 and not np.delete(wide.votes, 2, axis=1).any()


def test_grazing_weight_is_cosine():
    """One view's vote per vertex is |cos| times its pixel coverage: a 60 degree view of the same
    square gives half the weight per pixel of a square view."""
    mesh = grid_square(0.5, 0.0)
    caster = SurfaceCaster(mesh)
    v0 = view_votes(caster, camera_at_angle(0.0), full(1), CLASSES, stride=1)
    v60 = view_votes(caster, camera_at_angle(60.0), full(1), CLASSES, stride=1)
    # pixels per unit area also shrink with cos, so the totals go as cos^2 (up to perspective)
    ratio = v60.sum() / v0.sum()
    assert 0.15 < ratio < 0.35


def test_ignore_and_unknown_ids_do_not_vote():
    mesh = grid_square(0.5, 0.0)
    mask = full(255)
    mask[:, : SIZE // 2] = 77  # not in the class map
    fused = fuse_labels(mesh, {"a": camera_at_angle(0.0)}, {"a": mask}, CLASSES)
    assert not fused.votes.any()


def test_occluded_surface_gets_no_votes_from_views_that_cannot_see_it():
    front = grid_square(0.3, 0.5, cells=4)  # nearer the top camera
    back = grid_square(1.0, 0.0, cells=8)
    mesh = trimesh.util.concatenate([front, back])
    nf = len(front.vertices)
    top = camera_at((0.0, 0.0, 3.0))
    below = camera_at((0.0, 0.0, -3.0))
    fused = fuse_labels(mesh, {"top": top, "below": below}, {"top": full(1), "below": full(2)}, CLASSES,
                        fill_iterations=0)
    v = fused.votes
    # the front square is hidden from below by the back square: no class-2 votes at all
    assert v[:nf, 1].sum() > 0 and v[:nf, 2].sum() == 0
    # the centre of the back square is hidden from the top camera by the front square
    centre = nf + np.argmin(np.linalg.norm(back.vertices[:, :2], axis=1))
    assert v[centre, 1] == 0 and v[centre, 2] > 0
    # its rim is seen by both
    corner = nf + np.argmax(back.vertices[:, 0] + back.vertices[:, 1])
    assert v[corner, 1] > 0 and v[corner, 2] > 0


def _plane_hits(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """x and y where each pixel's ray meets the plane z=0 (row-major, reshaped to the image)."""
    o, d = cam.rays()
    t = -o[:, 2] / d[:, 2]
    p = o + t[:, None] * d
    return p[:, 0].reshape(cam.height, cam.width), p[:, 1].reshape(cam.height, cam.width)


def test_render_back_labels_in_the_right_pixels_and_background_on_misses():
    mesh = grid_square(0.5, 0.0)
    cam = camera_at_angle(0.0)
    x, y = _plane_hits(cam)
    label = np.where(x < 0, 1, 2).astype(np.uint8)  # left half granulation, right half slough
    other = camera_at_angle(30.0)
    xo, _ = _plane_hits(other)
    fused = fuse_labels(mesh, {"a": cam, "b": other}, {"a": label, "b": np.where(xo < 0, 1, 2).astype(np.uint8)},
                        CLASSES, stride=2)
    # render into a third, unseen view and into the first one
    for view in (cam, camera_at_angle(-20.0)):
        out = render_labels(fused, view)
        vx, vy = _plane_hits(view)
        inside = (np.abs(vx) <= 0.5) & (np.abs(vy) <= 0.5)
        assert out.shape == (SIZE, SIZE) and out.dtype == np.uint8
        assert (out[~inside] == 0).all()  # rays that miss the square are background
        clear = inside & (np.abs(vx) > 0.15) & (np.abs(vx) < 0.45) & (np.abs(vy) < 0.45)
        assert (out[clear & (vx < 0)] == 1).all()
        assert (out[clear & (vx > 0)] == 2).all()


def test_empty_mesh_renders_background():
    empty = trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    cam = camera_at_angle(0.0)
    fused = fuse_labels(empty, {"a": cam}, {"a": full(1)}, CLASSES)
    assert (render_labels(fused, cam) == 0).all()


def test_errors():
    mesh = grid_square(0.5, 0.0)
    cam = camera_at_angle(0.0)
    with pytest.raises(LabelsynthError, match="no camera"):
        fuse_labels(mesh, {}, {"a": full(1)}, CLASSES)
    with pytest.raises(LabelsynthError, match="cut-off"):
        fuse_labels(mesh, {"a": cam}, {"a": full(1)}, CLASSES, cutoff_deg=120)
    with pytest.raises(ValueError, match="does not match"):
        fuse_labels(mesh, {"a": cam}, {"a": np.zeros((3, 3), np.uint8)}, CLASSES)


def test_load_mesh_unit_maps_world_to_unit(tmp_path):
    mesh = grid_square(0.5, 0.0)
    norm = SceneNormalization(center=np.array([1.0, 2.0, 3.0]), scale=2.0)
    world = trimesh.Trimesh(vertices=norm.to_world(mesh.vertices), faces=mesh.faces, process=False)
    path = tmp_path / "scene.ply"
    world.export(path)
    unit = load_mesh_unit(path, norm)
    assert np.allclose(unit.vertices, mesh.vertices, atol=1e-5)
    with pytest.raises(LabelsynthError, match="not found"):
        load_mesh_unit(tmp_path / "missing.ply", norm)


def test_unvoted_vertices_take_their_voted_neighbours_label_but_unseen_islands_stay_empty():
    from labelsynth.evaluation.fusion import _fill_unvoted

    square = grid_square(0.5, 0.0, cells=4)
    island = grid_square(0.1, 1.0, cells=1)
    mesh = trimesh.util.concatenate([square, island])
    votes = np.zeros((len(mesh.vertices), CLASSES.num_classes))
    votes[: len(square.vertices), 2] = 1.0
    centre = int(np.argmin(np.linalg.norm(square.vertices, axis=1)))
    votes[centre] = 0.0
    filled = _fill_unvoted(mesh, votes, iterations=2)
    assert filled[centre].argmax() == 2 and 0 < filled[centre].sum() < 1e-3  # fills, never outvotes
    assert not filled[len(square.vertices):].any()
    assert np.array_equal(filled[: len(square.vertices)][np.arange(len(square.vertices)) != centre],
                          votes[: len(square.vertices)][np.arange(len(square.vertices)) != centre])
