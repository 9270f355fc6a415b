"""Synthetic captures: readable, reproducible, and their truth is exact and view-consistent."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth.cameras import Camera
from labelsynth.cli import app
from labelsynth.errors import LabelsynthError
from labelsynth.evaluation.synth import AroundScene, SynthConfig, annotated_indices, background_image, synthesize

W, H, N = 160, 120, 8
AW, AH, AN = 64, 48, 8  # the all-around capture


@pytest.fixture(scope="module")
def synth_out(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "s"
    synthesize(out, SynthConfig(frames=N, annotated=3, width=W, height=H, seed=3), progress=False)
    return out


def _cameras(capture: Path) -> tuple[list[str], list[Camera]]:
    t = json.loads((capture / "transforms.json").read_text())
    names, cams = [], []
    for f in t["frames"]:
        names.append(Path(f["file_path"]).stem)
        cams.append(Camera(t["w"], t["h"], t["fl_x"], t["fl_y"], t["cx"], t["cy"], np.array(f["transform_matrix"])))
    return names, cams


def _gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.ndim == 2 and img.dtype == np.uint8, path
    return img


def _bed_dice(a: np.ndarray, b: np.ndarray) -> float:
    a, b = (a > 0) & (a < 255), (b > 0) & (b < 255)
    return float(2 * (a & b).sum() / max(1, a.sum() + b.sum()))


def test_layout_and_load_capture(synth_out: Path) -> None:
    cap, truth = synth_out / "capture", synth_out / "truth"
    t = json.loads((cap / "transforms.json").read_text())
    assert t["camera_model"] == "OPENCV" and (t["w"], t["h"]) == (W, H)
    assert len(t["frames"]) == N
    assert all((cap / f["file_path"]).is_file() for f in t["frames"])
    assert len(list((cap / "predictions").glob("*.png"))) == N
    assert len(list((truth).glob("*.png"))) == N
    assert len(list((truth / "depth").glob("*.npy"))) == N
    ann = sorted(p.stem for p in (cap / "annotations").glob("*.png"))
    assert ann == [f"frame_{i:03d}" for i in annotated_indices(N, 3)]
    scene = json.loads((truth / "scene.json").read_text())
    assert scene["seed"] == 3 and scene["class_areas"]["granulation"] > 0
    assert scene["layout"] == scene["config"]["layout"] == "one-sided" == SynthConfig().layout
    assert not (synth_out.parent / "s.partial").exists()

    from labelsynth.capture import load_capture

    capture = load_capture(cap)
    assert len(capture.frames) == N
    assert sum(f.annotation_path is not None for f in capture.frames) == 3
    assert all(f.prediction_path is not None for f in capture.frames)
    _, cams = _cameras(cap)
    for frame, cam in zip(capture.frames, cams):
        np.testing.assert_allclose(frame.camera.c2w, cam.c2w, atol=1e-9)
        assert frame.size == (W, H)


def _check_annotations_equal_truth(out: Path) -> None:
    anns = list((out / "capture" / "annotations").glob("*.png"))
    assert anns
    for p in anns:
        np.testing.assert_array_equal(_gray(p), _gray(out / "truth" / p.name))


def test_annotations_equal_truth(synth_out: Path) -> None:
    _check_annotations_equal_truth(synth_out)


def _check_truth_agrees_with_colour(out: Path, w: int, h: int, wound_in_every_frame: bool = True) -> None:
    names, _ = _cameras(out / "capture")
    bg = background_image(w, h)
    seen = set()
    for name in names:
        truth = _gray(out / "truth" / f"{name}.png")
        depth = np.load(out / "truth" / "depth" / f"{name}.npy")
        rgb = cv2.imread(str(out / "capture" / "images" / f"{name}.png"))[..., ::-1]
        assert depth.dtype == np.float32 and depth.shape == (h, w)
        assert set(np.unique(truth)) <= {0, 1, 2, 3, 4, 5}
        miss = ~np.isfinite(depth)
        assert np.all(truth[miss] == 0)
        np.testing.assert_array_equal(rgb[miss], bg[miss])
        assert np.all(depth[~miss] > 0)
        seen |= set(np.unique(truth).tolist())
        rgb = rgb.astype(float)
        gran, slough = rgb[truth == 1], rgb[truth == 2]
        assert len(gran) or not wound_in_every_frame
        if len(gran):
            assert gran[:, 0].mean() > gran[:, 1].mean() + 50  # red
        if len(slough) > 20:
            assert slough[:, 1].mean() > gran[:, 1].mean() + 40  # yellowish
    assert {0, 1, 2, 4} <= seen


def test_truth_agrees_with_colour(synth_out: Path) -> None:
    _check_truth_agrees_with_colour(synth_out, W, H)


def test_synth_scene_renders_the_written_frames(synth_out: Path) -> None:
    """Rebuilt from scene.json, the scene renders each frame's image, truth and depth exactly
    (novel views are scored against it)."""
    from labelsynth.evaluation.synth import SynthScene

    scene = SynthScene.from_truth(synth_out / "truth")
    names, cams = _cameras(synth_out / "capture")
    for i in (0, N - 1):
        rgb, truth, depth = scene.render(cams[i])
        np.testing.assert_array_equal(rgb, cv2.imread(str(synth_out / "capture" / "images" / f"{names[i]}.png"))[..., ::-1])
        np.testing.assert_array_equal(truth, _gray(synth_out / "truth" / f"{names[i]}.png"))
        np.testing.assert_array_equal(depth, np.load(synth_out / "truth" / "depth" / f"{names[i]}.npy"))


def test_the_caster_without_rescaling_finds_the_same_hits() -> None:
    """synth casts with ``render.surface.SurfaceCaster(rescale=False)`` (its captures depend on the
    exact float32 rays); the hits are those of the rescaled cast, to float32 rounding."""
    import trimesh

    from labelsynth.render.surface import SurfaceCaster

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    mesh.apply_translation([0.3, -0.2, 0.1])
    rng = np.random.default_rng(1)
    origins = rng.normal(size=(400, 3))
    origins = 2.0 * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    dirs = rng.uniform(-0.5, 0.9, size=(400, 3)) - origins  # some rays miss the sphere
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit, points, faces, _ = SurfaceCaster(mesh).cast(origins, dirs)
    hit_raw, points_raw, faces_raw, _ = SurfaceCaster(mesh, rescale=False).cast(origins, dirs)
    assert 0 < hit.sum() < len(hit)
    assert np.array_equal(hit_raw, hit)
    assert np.mean(faces_raw[hit] == faces[hit]) > 0.98  # a ray through an edge may pick either triangle
    np.testing.assert_allclose(points_raw[hit], points[hit], atol=1e-5)


def test_truth_is_consistent_across_views(synth_out: Path) -> None:
    _check_consistent_across_views(synth_out, [(0, 3), (1, 5), (2, 7), (4, 6)], min_checked=200)


def _check_consistent_across_views(out: Path, pairs: list[tuple[int, int]], min_checked: int) -> None:
    """Surface points seen inside a class region in view a, and visible in view b, have the same
    class in b (depth tells visibility)."""
    names, cams = _cameras(out / "capture")
    truth = [_gray(out / "truth" / f"{n}.png") for n in names]
    depth = [np.load(out / "truth" / "depth" / f"{n}.npy") for n in names]
    h, w = truth[0].shape

    def interior(t: np.ndarray) -> np.ndarray:
        """Pixels whose 5x5 neighbourhood has one class: away from any boundary."""
        k = np.ones((5, 5), np.uint8)
        return cv2.dilate(t, k) == cv2.erode(t, k)

    checked = agree = 0
    for a, b in pairs:
        ys, xs = np.nonzero(interior(truth[a]) & (truth[a] > 0))
        pix = np.stack([xs + 0.5, ys + 0.5], -1)
        o, d = cams[a].rays(pix)
        pts = o + d * depth[a][ys, xs, None]
        uv, _ = cams[b].project(pts)
        dist_b = np.linalg.norm(pts - cams[b].center, axis=-1)
        ub, vb = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (ub >= 0) & (vb >= 0) & (ub < w) & (vb < h)
        ub, vb, ys_, xs_, dist_b = ub[ok], vb[ok], ys[ok], xs[ok], dist_b[ok]
        visible = np.abs(depth[b][vb, ub] - dist_b) < 0.01 * dist_b
        inner_b = interior(truth[b])[vb, ub]
        sel = visible & inner_b
        checked += int(sel.sum())
        agree += int((truth[a][ys_[sel], xs_[sel]] == truth[b][vb[sel], ub[sel]]).sum())
    assert checked > min_checked
    assert agree / checked > 0.995


def _prediction_dice(out: Path) -> tuple[list[float], int]:
    names, _ = _cameras(out / "capture")
    dice, differ = [], 0
    for name in names:
        truth = _gray(out / "truth" / f"{name}.png")
        pred = _gray(out / "capture" / "predictions" / f"{name}.png")
        assert set(np.unique(pred)) <= {0, 1, 2, 3, 4, 5}
        differ += int(np.any(pred != truth))
        if (truth > 0).any():
            dice.append(_bed_dice(truth, pred))
    print(f"wound-bed Dice of predictions: mean {np.mean(dice):.3f}, min {np.min(dice):.3f}")
    return dice, differ


def test_predictions_good_but_imperfect(synth_out: Path) -> None:
    dice, differ = _prediction_dice(synth_out)
    assert differ == N
    assert 0.78 < np.mean(dice) < 0.97


def test_noise_zero_gives_exact_predictions(tmp_path: Path) -> None:
    out = tmp_path / "s"
    synthesize(out, SynthConfig(frames=3, annotated=1, width=64, height=48, noise=0.0), progress=False)
    for p in (out / "truth").glob("*.png"):
        np.testing.assert_array_equal(_gray(p), _gray(out / "capture" / "predictions" / p.name))


def test_reproducible_with_seed(tmp_path: Path) -> None:
    cfg = SynthConfig(frames=3, annotated=1, width=64, height=48, seed=11)
    a, b = tmp_path / "a", tmp_path / "b"
    synthesize(a, cfg, progress=False)
    synthesize(b, cfg, progress=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.suffix in (".png", ".npy", ".json"))
    assert len(files) >= 3 * 4
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = tmp_path / "c"
    synthesize(c, SynthConfig(frames=3, annotated=1, width=64, height=48, seed=12), progress=False)
    assert (a / "capture/images/frame_000.png").read_bytes() != (c / "capture/images/frame_000.png").read_bytes()


def test_refuses_existing_out(tmp_path: Path) -> None:
    out = tmp_path / "s"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    cfg = SynthConfig(frames=2, annotated=1, width=32, height=24)
    with pytest.raises(LabelsynthError, match="not empty"):
        synthesize(out, cfg, progress=False)
    assert (out / "keep.txt").exists()
    synthesize(out, cfg, force=True, progress=False)
    assert not (out / "keep.txt").exists() and (out / "capture" / "transforms.json").is_file()


def test_interrupted_run_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    from labelsynth.evaluation.synth import writer

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(writer, "predict_errors", boom)
    out = tmp_path / "s"
    with pytest.raises(KeyboardInterrupt):
        synthesize(out, SynthConfig(frames=2, annotated=1, width=32, height=24), progress=False)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_bad_config() -> None:
    with pytest.raises(LabelsynthError):
        SynthConfig(frames=1)
    with pytest.raises(LabelsynthError):
        SynthConfig(frames=4, annotated=5)
    with pytest.raises(LabelsynthError, match="layout"):
        SynthConfig(layout="sideways")


def test_cli_synth(tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "s"
    args = ["synth", str(out), "--frames", "3", "--annotated", "1", "--width", "48", "--height", "32"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert (out / "capture" / "transforms.json").is_file()
    res = runner.invoke(app, args)
    assert res.exit_code == 2
    assert "not empty" in res.output
    res = runner.invoke(app, args + ["--force", "--seed", "2"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, args + ["--force", "--layout", "all-around"])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "truth" / "scene.json").read_text())["layout"] == "all-around"
    res = runner.invoke(app, args + ["--force", "--layout", "sideways"])
    assert res.exit_code == 2 and "layout" in res.output


# ------------------------------------------------------------------------------------------
# the all-around layout: a wound wrapped around a limb, filmed in one turn around it
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def around_out(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("around") / "s"
    # seed 1: a band over about 70 % of the circumference (its ends and the gap are filmed too)
    synthesize(out, SynthConfig(frames=AN, annotated=2, width=AW, height=AH, seed=1, layout="all-around"),
               progress=False)
    return out


def _scene(out: Path) -> dict:
    return json.loads((out / "truth" / "scene.json").read_text())


def test_all_around_cameras_orbit_the_limb(around_out: Path) -> None:
    scene = _scene(around_out)
    assert scene["layout"] == "all-around" and scene["surface"]["kind"] == "limb"
    assert abs(scene["camera_path"]["sweep_deg"]) == 360
    axis = np.array(scene["surface"]["axis_point"])  # the limb's axis: this point, along x
    _, cams = _cameras(around_out / "capture")
    assert len(cams) == AN
    side = np.array([c.center - axis for c in cams])[:, 1:]  # where each camera is, around the axis
    ang = np.sort(np.arctan2(side[:, 0], side[:, 1]))
    unit = side / np.linalg.norm(side, axis=1, keepdims=True)
    assert np.linalg.norm(unit.mean(0)) < 0.3  # viewing directions spread all around
    assert np.max(np.diff(np.append(ang, ang[0] + 2 * np.pi))) < 2 * (2 * np.pi / AN)  # no big gap
    for c in cams:  # each optical axis passes through the limb's axis near the wound
        f = c.forward
        cross = np.cross(f, [1.0, 0, 0])
        miss = abs(np.dot(c.center - axis, cross)) / np.linalg.norm(cross)
        assert miss < 1e-6
        s = np.linalg.lstsq(np.stack([f, [-1.0, 0, 0]], 1), axis - c.center, rcond=None)[0]
        assert s[0] > 0 and abs(s[1]) < scene["surface"]["wound_radius"]


def test_all_around_wound_seen_from_all_sides(around_out: Path) -> None:
    scene = _scene(around_out)
    band = scene["surface"]["band"]
    assert 0.6 <= band["coverage"] <= 1.0 and not band["full_ring"]
    u_half = scene["surface"]["domain_uv_half"][0]
    names, cams = _cameras(around_out / "capture")
    with_wound = 0
    for name, cam in zip(names, cams):
        truth = _gray(around_out / "truth" / f"{name}.png")
        depth = np.load(around_out / "truth" / "depth" / f"{name}.npy")
        with_wound += int((truth > 0).mean() > 0.02)
        ys, xs = np.nonzero(np.isfinite(depth))
        o, d = cam.rays(np.stack([xs + 0.5, ys + 0.5], -1))
        pts = o + d * depth[ys, xs, None]
        assert np.abs(pts[:, 0]).max() < 0.5 * u_half  # the tube's open ends stay far out of view
        assert (~np.isfinite(depth)).any()  # the limb's outline shows (background beside it)
    assert with_wound >= 0.75 * AN


def test_all_around_truth(around_out: Path) -> None:
    _check_annotations_equal_truth(around_out)
    _check_truth_agrees_with_colour(around_out, AW, AH, wound_in_every_frame=False)
    _check_consistent_across_views(around_out, [(i, (i + 1) % AN) for i in range(AN)], min_checked=200)
    dice, differ = _prediction_dice(around_out)
    assert differ >= AN - 1 and 0.75 < np.mean(dice) < 0.99
    areas = _scene(around_out)["class_areas"]
    assert areas["granulation"] > areas["slough"] > 0 and areas["epithelial"] > 0


def test_all_around_region_of_interest(around_out: Path) -> None:
    """load_capture's region of interest holds the limb's section around the wound."""
    from labelsynth.capture import load_capture

    capture = load_capture(around_out / "capture")
    nrm = capture.normalization
    surf = _scene(around_out)["surface"]
    r, axis = surf["radius"], np.array(surf["axis_point"])
    assert np.linalg.norm(nrm.center - axis) < 0.2 * r
    pts = []
    for f in capture.frames:
        truth = _gray(around_out / "truth" / f"{f.name}.png")
        depth = np.load(around_out / "truth" / "depth" / f"{f.name}.npy")
        ys, xs = np.nonzero(truth > 0)
        o, d = f.camera.rays(np.stack([xs + 0.5, ys + 0.5], -1))
        pts.append(o + d * depth[ys, xs, None])
    pts = np.concatenate(pts)
    assert np.abs((pts - nrm.center) / nrm.scale).max() < 0.9  # every wound point seen
    th = np.linspace(-np.pi, np.pi, 37)
    for x in (pts[:, 0].min(), pts[:, 0].max()):  # the whole cross-section over the wound's extent
        rr = 1.05 * r * (1 + surf["taper"] * x)
        ring = np.stack([np.full_like(th, x), rr * np.sin(th), rr * np.cos(th) - r], -1)
        assert np.abs((ring - nrm.center) / nrm.scale).max() < 0.9


def test_all_around_continuous_across_the_seam() -> None:
    """Labels, colour and relief run on across v = +-pi*radius; the tube is closed there."""
    for seed in (0, 4):  # full rings: the wound crosses the seam
        scene = AroundScene(np.random.default_rng([seed, 0]), 384)
        assert scene.full_ring
        # the step from the last row (v) to the first is no larger than any step between rows
        # inside (a texture that is not periodic fails all four by far)
        lab = scene.labels
        rows = (lab[1:] != lab[:-1]).mean(1)  # texels changing class from one row to the next
        assert (lab[0] > 0).mean() > 0.1 and (lab[-1] != lab[0]).mean() <= rows.max()
        for tex in (scene.rho, scene.albedo, scene.height_geo):
            step = np.abs(np.diff(tex, axis=0)).reshape(len(tex) - 1, -1).mean(1)
            assert np.abs(tex[-1] - tex[0]).mean() <= step.max()
        uv = scene.vertex_uv
        first, last = np.isclose(uv[:, 1], -scene.v_half), np.isclose(uv[:, 1], scene.v_half)
        assert first.sum() == last.sum() > 0
        np.testing.assert_array_equal(scene.vertices[first], scene.vertices[last])


def test_all_around_reproducible_with_seed(tmp_path: Path) -> None:
    cfg = SynthConfig(frames=3, annotated=1, width=64, height=48, seed=11, layout="all-around")
    a, b = tmp_path / "a", tmp_path / "b"
    synthesize(a, cfg, progress=False)
    synthesize(b, cfg, progress=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 3 * 4
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = tmp_path / "c"
    synthesize(c, SynthConfig(frames=3, annotated=1, width=64, height=48, seed=12, layout="all-around"), progress=False)
    assert (a / "capture/images/frame_000.png").read_bytes() != (c / "capture/images/frame_000.png").read_bytes()
    one = tmp_path / "one"
    synthesize(one, SynthConfig(frames=3, annotated=1, width=64, height=48, seed=11), progress=False)
    assert (a / "capture/images/frame_000.png").read_bytes() != (one / "capture/images/frame_000.png").read_bytes()
