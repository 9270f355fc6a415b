"""`labelsynth augment` on the tiny expanded capture: files, exact poses, unseen pixels, rejections, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch

from labelsynth.errors import LabelsynthError

VIEWS = 5


def _copy_out(tiny, dest: Path) -> Path:
    """The fixture's OUT without its report (field.pt, run.json, labels.h5, masks/): augment writes
    OUT/augment, and the fixture's OUT is shared with other tests."""
    dest.mkdir(parents=True)
    for name in ("field.pt", "run.json", "labels.h5"):
        shutil.copy2(tiny.out / name, dest / name)
    shutil.copytree(tiny.out / "masks", dest / "masks")
    return dest


@pytest.fixture(scope="module")
def augmented(tiny_expanded, tmp_path_factory):
    from labelsynth.novel import augment

    out = _copy_out(tiny_expanded, tmp_path_factory.mktemp("augment") / "out")
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    result = augment(out, VIEWS, seed=3, device="cpu", progress=False)
    return out, result, before


@pytest.fixture(scope="module")
def real_frames(tiny_expanded):
    from types import SimpleNamespace

    from labelsynth.novel.views import RealFrames
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    run = RunFolder(tiny_expanded.out)
    _, cap = run.open_capture()
    ex = SimpleNamespace(capture=cap, view=FieldRenderer(run.load_field(torch.device("cpu"))))
    images = [cap.load_image(i) for i in range(len(cap))]
    return ex, RealFrames(ex.view, cap.unit_cameras(), images), images


def _psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64))[where]
    return float(10 * np.log10(255.0**2 / max(np.mean(d**2), 1e-10)))


def test_writes_the_documented_files(augmented, tiny_expanded):
    from labelsynth.export import LabelsDataset
    from labelsynth.train.data import load_labels_h5

    out, result, before = augmented
    aug = out / "augment"
    assert result.out == aug and result.views == VIEWS
    # nothing but OUT/augment was added or changed in OUT; no partial left; the capture untouched
    assert sorted(p.relative_to(out) for p in out.rglob("*") if not p.is_relative_to(aug)) == before
    assert not (out / "augment.partial").exists()
    for p, data in tiny_expanded.capture_bytes.items():
        assert p.read_bytes() == data
    names = [f"novel_{k:04d}" for k in range(VIEWS)]
    for sub in ("images", "masks", "valid"):
        assert sorted(p.stem for p in (aug / sub).glob("*.png")) == names
    with h5py.File(out / "labels.h5", "r") as f:
        real_names = [str(s) for s in f["frame_names"].asstr()[()]]
        real_attrs = set(f.attrs)
        real_images = f["images"][()]
    with h5py.File(aug / "augment.h5", "r") as f:
        assert {"images", "masks", "confidence", "annotated", "frame_names"} <= set(f)
        assert real_attrs <= set(f.attrs)
        n = VIEWS + len(real_names)
        assert f["novel"][()].tolist() == [True] * VIEWS + [False] * len(real_names)
        assert f["c2w"].shape == (n, 4, 4) and f["intrinsics"].shape == (n, 8)
        assert [str(s) for s in f["frame_names"].asstr()[()]] == names + real_names
        np.testing.assert_array_equal(f["images"][VIEWS:], real_images)
        valid, masks, images = f["valid"][()], f["masks"][()], f["images"][()]
        assert not f["annotated"][:VIEWS].any()
    # the PNGs are the h5's frames; unseen pixels are ignore (255) with colour 0, nothing else is
    for k, name in enumerate(names):
        png_mask = cv2.imread(str(aug / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(png_mask, masks[k])
        np.testing.assert_array_equal(cv2.imread(str(aug / "valid" / f"{name}.png"), cv2.IMREAD_UNCHANGED) > 0, valid[k])
        assert (masks[k][~valid[k]] == 255).all() and (masks[k][valid[k]] != 255).all()
        assert (images[k][~valid[k]] == 0).all()
        assert valid[k].mean() > 0.5
    # LabelsDataset and train read it unchanged
    ds = LabelsDataset(aug / "augment.h5")
    assert len(ds) == VIEWS + len(real_names) and ds[0]["image"].shape == (3, 72, 96)
    src = load_labels_h5(aug / "augment.h5")
    assert len(src) == len(ds)
    summary = json.loads((aug / "augment.json").read_text())
    assert summary["views"] == VIEWS and summary["rejected"] == result.rejected
    assert len(summary["cameras"]) == VIEWS


def test_cameras_are_in_the_captures_world(augmented, real_frames):
    """augment.h5's real-frame cameras are the capture's own; a novel camera maps back to a unit
    camera whose mask is the one written."""
    from labelsynth.cameras import Camera

    ex, _, _ = real_frames
    out, _, _ = augmented
    with h5py.File(out / "augment" / "augment.h5", "r") as f:
        c2w, intr, masks, valid = f["c2w"][()], f["intrinsics"][()], f["masks"][()], f["valid"][()]
    for i, frame in enumerate(ex.capture.frames):
        np.testing.assert_allclose(c2w[VIEWS + i], frame.camera.c2w)
    cam0 = ex.capture.frames[0].camera
    novel = ex.capture.normalization.camera_to_unit(Camera(cam0.width, cam0.height, *intr[0][:4], c2w[0], *intr[0][4:]))
    r = ex.view.render(novel)
    np.testing.assert_array_equal(r.mask[valid[0]], masks[0][valid[0]])


def test_real_pose_reproduces_the_frame(real_frames, tiny_expanded):
    from labelsynth.novel.views import render_view

    ex, real, images = real_frames
    cams = ex.capture.unit_cameras()
    for i in (0, len(cams) - 1):
        v = render_view(ex.view, real, cams[i])
        assert v.valid_fraction > 0.99
        assert _psnr(v.image, images[i], v.valid) > 45.0
        expand_mask = cv2.imread(str(tiny_expanded.out / "masks" / f"{ex.capture.frames[i].name}.png"),
                                 cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(v.mask[v.valid], expand_mask[v.valid])
    # left out, the frame is rebuilt from its neighbours: close, not exact
    v = render_view(ex.view, real, cams[3], exclude={3})
    assert 20.0 < _psnr(v.image, images[3], v.valid) < 45.0


def test_unseen_pixels_are_ignore(real_frames):
    """With frame 0 as the only source, frame 5's pixels whose surface point falls outside
    frame 0's picture are not valid: mask 255, colour 0; those frame 0 sees keep the field's label."""
    from labelsynth.novel.views import RealFrames, render_view

    ex, real, images = real_frames
    cams = ex.capture.unit_cameras()
    only0 = RealFrames(ex.view, cams[:1], images[:1], depth=[real.depth_map(cams[0])])
    v = render_view(ex.view, only0, cams[5])
    r = ex.view.render(cams[5], keep_points=True)
    pix, z = cams[0].project(r.points.reshape(-1, 3))
    outside = ((pix[:, 0] < 0) | (pix[:, 0] >= cams[0].width) | (pix[:, 1] < 0) | (pix[:, 1] >= cams[0].height)
               | (z <= 0)).reshape(r.mask.shape) & r.hit
    assert outside.sum() > 50  # the test means something
    assert not v.valid[outside].any()
    assert (v.mask[~v.valid] == 255).all() and (v.image[~v.valid] == 0).all()
    np.testing.assert_array_equal(v.mask[v.valid], r.mask[v.valid])
    assert 0.2 < v.valid_fraction < 1.0


def test_rejected_views_are_counted(real_frames):
    from labelsynth.novel.poses import Spread, path_points, sample_poses

    ex, real, _ = real_frames
    caster = ex.view.render_caster()
    path = path_points(ex.capture.unit_cameras(), caster)
    wild = Spread(tilt_deg=75.0, distance=3.0, roll_deg=180.0, focal=1.0)
    s = sample_poses(4, np.random.default_rng(0), path, wild, caster, real, max_tries=200)
    assert len(s.cameras) == 4 and s.rejected_total > 0
    assert set(s.rejected) == {"empty", "unseen"}
    assert all(v >= 0.95 for v in s.seen_fraction)
    with pytest.raises(LabelsynthError, match=r"only \d+ of 50 novel views passed .*rejected: \d+ mostly empty"):
        sample_poses(50, np.random.default_rng(0), path, wild, caster, real, max_tries=20)
    # the same seed gives the same poses
    a = sample_poses(2, np.random.default_rng(7), path, Spread(), caster, real)
    b = sample_poses(2, np.random.default_rng(7), path, Spread(), caster, real)
    np.testing.assert_array_equal(a.cameras[0].c2w, b.cameras[0].c2w)


def test_zero_spread_gives_the_path_back():
    from labelsynth.cameras import Camera, look_at
    from labelsynth.novel.poses import PathPoint, Spread, sample_pose

    cams = [Camera(64, 48, 50, 50, 32, 24, look_at(np.array([x, -2.0, 1.0]), np.zeros(3))) for x in (-1.0, 0.0, 1.0)]
    path = [PathPoint(c, 2.4) for c in cams]
    rng = np.random.default_rng(0)
    for _ in range(5):
        cam = sample_pose(rng, path, Spread().scaled(0.0))
        assert min(np.abs(cam.c2w - c.c2w).max() for c in cams) < 1e-9
        assert cam.fx == 50
    moved = sample_pose(np.random.default_rng(1), path, Spread())
    assert min(np.abs(moved.c2w - c.c2w).max() for c in cams) > 1e-3


def test_parse_spread():
    from labelsynth.novel.poses import Spread, parse_spread

    assert parse_spread(None) == Spread()
    assert parse_spread("0") == Spread(0, 0, 0, 0, 0)
    assert parse_spread("2").tilt_deg == 30.0
    s = parse_spread("tilt=25, roll=0")
    assert s.tilt_deg == 25.0 and s.roll_deg == 0.0 and s.distance == Spread().distance
    for bad, msg in (("spin=3", "expected a number or key=value"), ("tilt=x", "not a number"),
                     ("roll=-1", "must be a finite number >= 0"), ("along=2", "at most 1")):
        with pytest.raises(LabelsynthError, match=msg):
            parse_spread(bad)


def test_bad_inputs_are_one_line_errors(tiny_expanded, tmp_path):
    from labelsynth.novel import AugmentError, augment
    from labelsynth.rundir import RunFolderError

    out = _copy_out(tiny_expanded, tmp_path / "out")
    with pytest.raises(LabelsynthError, match=r"--views must be a whole number in 1\.\.100000, not 0"):
        augment(out, 0, progress=False)
    with pytest.raises(RunFolderError, match="not found"):
        augment(tmp_path / "nowhere", 2, progress=False)
    partial = tmp_path / "half.partial"
    partial.mkdir()
    with pytest.raises(RunFolderError, match="not finished"):
        augment(tmp_path / "half", 2, progress=False)
    with pytest.raises(RunFolderError, match="unfinished expand"):
        augment(partial, 2, progress=False)
    nofield = _copy_out(tiny_expanded, tmp_path / "nofield")
    (nofield / "field.pt").unlink()
    with pytest.raises(RunFolderError, match=r"field\.pt: not found"):
        augment(nofield, 2, progress=False)
    moved = _copy_out(tiny_expanded, tmp_path / "moved")
    run = json.loads((moved / "run.json").read_text())
    run["capture"] = str(tmp_path / "gone" / "capture")
    (moved / "run.json").write_text(json.dumps(run))
    with pytest.raises(RunFolderError, match=r"gone/capture: the capture named in .*run\.json was not found"):
        augment(moved, 2, progress=False)
    (out / "augment").mkdir()
    (out / "augment" / "keep.txt").write_text("x")
    with pytest.raises(LabelsynthError, match="exists and is not empty"):
        augment(out, 2, progress=False)
    assert (out / "augment" / "keep.txt").read_text() == "x"
    for err in (AugmentError, RunFolderError):
        assert issubclass(err, LabelsynthError)


def test_cli_augment_errors(tiny_expanded, tmp_path):
    from typer.testing import CliRunner

    from labelsynth.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["augment", str(tmp_path / "nowhere"), "--views", "3"])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "nowhere: not found" in lines[0]
    res = runner.invoke(app, ["augment", str(tiny_expanded.out), "--views", "0"])
    assert res.exit_code != 0
