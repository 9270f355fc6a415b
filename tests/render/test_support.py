"""Surface no teaching frame saw (issue 31): found on an exact mesh, capped on a fitted field and
in labels.h5, reported; and a real photograph's hard parts in a tiny capture (white textureless
table, saturated top, dark backdrop) fitted without a hole and without the backdrop labelled
object (fails on today's field: marked xfail with what was measured)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from labelsynth.cameras import Camera, look_at
from labelsynth.classes import IGNORE_ID
from labelsynth.render.config import RenderConfig
from labelsynth.render.support import SurfaceSupport
from labelsynth.render.surface import SurfaceCaster

from ..conftest import TINY_OVERRIDES
from ..scenes import make_table_capture, table_scene, table_scores, table_truth_hits


def _camera(az_deg: float, el_deg: float = 40.0, size: int = 64) -> Camera:
    az, el = np.radians(az_deg), np.radians(el_deg)
    eye = 2.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Camera(size, size, 1.1 * size, 1.1 * size, size / 2, size / 2, look_at(eye, np.array([0.0, 0.0, 0.3])))


def test_support_on_an_exact_surface():
    obj, table = table_scene()
    mesh = trimesh.util.concatenate([obj, table])
    caster = SurfaceCaster(mesh)
    teachers = [_camera(-40.0), _camera(-10.0)]  # both on the +x side of the object
    labelled = [np.zeros((c.height, c.width), np.uint8) for c in teachers]
    support = SurfaceSupport(caster, teachers, labelled, RenderConfig())

    # surface points, each found by a ray onto it: the box's +x face (towards the teachers), its
    # -x face (turned away from them) and the table just behind the box (hidden by it)
    hit, points, faces, _ = caster.cast(np.array([[2.0, 0, 0.2], [-2.0, 0, 0.2], [-0.45, 0, 2.0]]),
                                        np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, 0, -1.0]]))
    assert hit.all() and np.allclose(points, [[0.35, 0, 0.2], [-0.35, 0, 0.2], [-0.45, 0, 0]], atol=1e-6)
    for cam in teachers:  # the premise: the box hides the table point from every teacher
        d = points[2] - cam.center
        loc, _, _ = mesh.ray.intersects_location(cam.center[None], (d / np.linalg.norm(d))[None], multiple_hits=False)
        assert np.linalg.norm(loc[0] - points[2]) > 0.1
    assert support.seen(points, faces).tolist() == [True, False, False]

    # every pixel a teacher sees of the surface is seen by it
    for cam in teachers:
        hit, pts, fcs, _ = caster.cast(*cam.rays())
        assert hit.any() and not support.unseen(hit, pts, fcs).any()
    # a view from the other side sees surface the teachers did not
    hit, pts, fcs, _ = caster.cast(*_camera(150.0).rays())
    assert 0.05 < support.unseen(hit, pts, fcs).mean() < hit.mean()

    # a pixel the teacher's mask leaves unlabelled (ignore) did not teach: nothing seen
    ignored = SurfaceSupport(caster, teachers, [np.full_like(m, IGNORE_ID) for m in labelled], RenderConfig())
    assert not ignored.seen(points, faces).any()


@pytest.mark.xdist_group("tiny_expanded")
def test_render_caps_confidence_where_no_teaching_frame_saw(tiny_expanded):
    """On a fitted field: with one teaching frame, surface outside its view is unseen and capped;
    its own pixels are all seen and keep the head's confidence."""
    from labelsynth.capture import load_capture
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    cap = load_capture(tiny_expanded.capture_dir)
    view = FieldRenderer(RunFolder(tiny_expanded.out).load_field())
    cams = cap.unit_cameras()
    teacher = cap.names.index(tiny_expanded.good[0])
    mask = cap.load_annotation(teacher)
    support = view.support([cams[teacher]], [mask])
    cap_value = view.config.unseen_confidence

    own = view.render(cams[teacher], support=support)
    assert own.hit.any() and not own.unseen.any()
    outside_total = 0
    for i, cam in enumerate(cams):
        plain = view.render(cam)
        r = view.render(cam, support=support, keep_points=True)
        assert np.array_equal(r.mask, plain.mask)  # labels unchanged, only their confidence
        uv, z = cams[teacher].project(r.points[r.hit])
        outside = np.zeros_like(r.hit)
        outside[r.hit] = (z <= 0) | (uv[:, 0] < 0) | (uv[:, 1] < 0) | (uv[:, 0] >= cam.width) | (uv[:, 1] >= cam.height)
        outside_total += int(outside.sum())
        assert r.unseen[outside].all()  # surface the teacher never looked at
        assert (r.confidence[r.unseen] <= cap_value + 1e-6).all()
        np.testing.assert_allclose(r.confidence[~r.unseen], plain.confidence[~r.unseen])
        assert not r.unseen[~r.hit].any()  # a ray that meets no surface is background, not unseen
        assert r.unseen_share == pytest.approx(r.unseen.mean())
    assert outside_total > 0  # the premise: other frames see surface outside the teacher's view


@pytest.mark.xdist_group("tiny_expanded")
def test_expand_writes_capped_confidence_and_reports_unseen_share(tiny_expanded):
    from labelsynth.capture import load_capture
    from labelsynth.export.labels_h5 import LabelsReader
    from labelsynth.pipeline import teaching_support, unseen_shares
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    run = RunFolder(tiny_expanded.out)
    cap = load_capture(tiny_expanded.capture_dir)
    view = FieldRenderer(run.load_field())
    support = teaching_support(view, cap, "annotations")
    report = json.loads(run.report_json.read_text())
    by_name = {f["name"]: f for f in report["frames"]}
    shares = unseen_shares(view, cap, "annotations")
    assert report["summary"]["unseen_confidence"] == view.config.unseen_confidence
    assert report["summary"]["max_unseen_share"] == pytest.approx(max(shares.values()))
    cams = cap.unit_cameras()
    with LabelsReader(run.labels_path) as reader:
        for i, name in enumerate(cap.names):
            r = view.render(cams[i], support=support)
            _, _, conf = reader.read(i)
            np.testing.assert_allclose(np.asarray(conf, np.float32), r.confidence, atol=1e-3)
            assert by_name[name]["unseen_share"] == pytest.approx(r.unseen_share) == pytest.approx(shares[name])
            if cap.frames[i].annotation_path is not None:
                assert by_name[name]["unseen_share"] < 0.02  # what a frame taught, it saw
    assert "unseen surface" in run.report_html.read_text()


@pytest.fixture(scope="module")
def table_run(tmp_path_factory):
    from labelsynth.pipeline import expand

    root = tmp_path_factory.mktemp("table")
    capture, truth = make_table_capture(root)
    expand(capture, root / "out", labels="annotations", recipe="fast", device="cpu", overrides=TINY_OVERRIDES,
           progress=False, report=False)
    return capture, truth, root / "out"


@pytest.mark.xdist_group("table")
def test_table_capture_keeps_its_surface_over_the_object(table_run):
    """Issue 31's race: the background explains the white table at once, and the quickest descent
    of the colour loss is then a transparent box, over the object too; a surface gone from the box
    never returns (before the plane started at the rim's colour: mean opacity 0.13 over the
    object's pixels after 250 steps, no fitted hit within 0.1 of the object). The geometry stage's
    own rendering must stay opaque where the object is."""
    import torch

    from labelsynth.geometry.training import render_rays_rgb
    from labelsynth.rundir import RunFolder

    capture_dir, _, out = table_run
    cap, hits = table_truth_hits(capture_dir)
    run = RunFolder(out)
    assert run.read_run().geometry["init_shape"] == "plane"  # the premise
    fitted = run.load_field()
    opacities = []
    for cam, (_, _, on_obj) in zip(cap.unit_cameras(), hits):
        o, d = (torch.as_tensor(a[on_obj], dtype=torch.float32) for a in cam.rays())
        with torch.no_grad():
            _, opacity, _ = render_rays_rgb(fitted.sdf, fitted.grid, o, d, 1.0, fitted.recipe.geometry.march_steps,
                                            train=False)
        opacities.append(opacity.numpy())
    opacity = np.concatenate(opacities)
    assert len(opacity) > 1000
    assert opacity.mean() > 0.8, f"mean opacity over the object's pixels: {opacity.mean():.2f}"


# Measured 2026-12-03 on this tree: the fast recipe at the tests' size forms no object on this
# capture (training PSNR 15.6 dB; 0 of 971 rays through the saturated top meet it, every fitted
# hit lies 0.15-1.2 units from the true surface). 2026-12-07, with the plane starting at the rim's
# colour (the surface is kept, the test above): still 0/971 after these 250 steps (506 of the
# object's other 2040 rays within 0.1, foreground Dice 0.73); with 1000 steps 950, 838, 0, 213 and 0
# of 971 over seeds 0-4 (the tree before, seeds 0-2: no surface at all in each). Issue 31's geometry work must
# make it pass; strict, so that the marker goes when it does. `benchmarks/bench_table.py` reproduces
# these counts over seeds; a plane normal from the cameras' x axes forms the top in 5 of 5 seeds at
# 1000 steps but halves some seeds' Dice (docs/benchmarks.md), so it is not what makes this pass.
@pytest.mark.xdist_group("table")
@pytest.mark.xfail(strict=True, reason="issue 31: the field forms no surface under the saturated top on "
                                        "a white table before a dark backdrop (measured: 0/971 rays meet it)")
def test_textureless_saturated_patch_has_no_hole_and_backdrop_stays_background(table_run):
    capture_dir, _, out = table_run
    counts = table_scores(capture_dir, out)
    white, white_hit, backdrop, backdrop_object = (counts[k] for k in ("top", "top_hit", "backdrop", "backdrop_object"))
    assert white > 100 and backdrop > 100  # the premise: every view sees the white top, some the backdrop
    assert white_hit / white > 0.9, f"rays through the saturated top: {white_hit}/{white} meet it"
    assert backdrop_object / backdrop < 0.05, f"backdrop labelled object: {backdrop_object}/{backdrop}"
