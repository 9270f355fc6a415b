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
from labelsynth.synth import SynthConfig, annotated_indices, background_image, synthesize

W, H, N = 160, 120, 8


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
    assert not list(synth_out.parent.glob(".s.partial-*"))

    from labelsynth.capture import load_capture

    capture = load_capture(cap)
    assert len(capture.frames) == N
    assert sum(f.annotation_path is not None for f in capture.frames) == 3
    assert all(f.prediction_path is not None for f in capture.frames)
    _, cams = _cameras(cap)
    for frame, cam in zip(capture.frames, cams):
        np.testing.assert_allclose(frame.camera.c2w, cam.c2w, atol=1e-9)
        assert frame.size == (W, H)


def test_annotations_equal_truth(synth_out: Path) -> None:
    for p in (synth_out / "capture" / "annotations").glob("*.png"):
        np.testing.assert_array_equal(_gray(p), _gray(synth_out / "truth" / p.name))


def test_truth_agrees_with_colour(synth_out: Path) -> None:
    names, _ = _cameras(synth_out / "capture")
    bg = background_image(W, H)
    seen = set()
    for name in names:
        truth = _gray(synth_out / "truth" / f"{name}.png")
        depth = np.load(synth_out / "truth" / "depth" / f"{name}.npy")
        rgb = cv2.imread(str(synth_out / "capture" / "images" / f"{name}.png"))[..., ::-1]
        assert depth.dtype == np.float32 and depth.shape == (H, W)
        assert set(np.unique(truth)) <= {0, 1, 2, 3, 4, 5}
        miss = ~np.isfinite(depth)
        assert np.all(truth[miss] == 0)
        np.testing.assert_array_equal(rgb[miss], bg[miss])
        assert np.all(depth[~miss] > 0)
        seen |= set(np.unique(truth).tolist())
        rgb = rgb.astype(float)
        gran, slough = rgb[truth == 1], rgb[truth == 2]
        assert len(gran) and gran[:, 0].mean() > gran[:, 1].mean() + 50  # red
        if len(slough) > 20:
            assert slough[:, 1].mean() > gran[:, 1].mean() + 40  # yellowish
    assert {0, 1, 2, 4} <= seen


def test_truth_is_consistent_across_views(synth_out: Path) -> None:
    names, cams = _cameras(synth_out / "capture")
    truth = [_gray(synth_out / "truth" / f"{n}.png") for n in names]
    depth = [np.load(synth_out / "truth" / "depth" / f"{n}.npy") for n in names]

    def interior(t: np.ndarray) -> np.ndarray:
        """Pixels whose 5x5 neighbourhood has one class: away from any boundary."""
        k = np.ones((5, 5), np.uint8)
        return cv2.dilate(t, k) == cv2.erode(t, k)

    checked = agree = 0
    for a, b in [(0, 3), (1, 5), (2, 7), (4, 6)]:
        ys, xs = np.nonzero(interior(truth[a]) & (truth[a] > 0))
        pix = np.stack([xs + 0.5, ys + 0.5], -1)
        o, d = cams[a].rays(pix)
        pts = o + d * depth[a][ys, xs, None]
        uv, _ = cams[b].project(pts)
        dist_b = np.linalg.norm(pts - cams[b].center, axis=-1)
        ub, vb = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (ub >= 0) & (vb >= 0) & (ub < W) & (vb < H)
        ub, vb, ys_, xs_, dist_b = ub[ok], vb[ok], ys[ok], xs[ok], dist_b[ok]
        visible = np.abs(depth[b][vb, ub] - dist_b) < 0.01 * dist_b
        inner_b = interior(truth[b])[vb, ub]
        sel = visible & inner_b
        checked += int(sel.sum())
        agree += int((truth[a][ys_[sel], xs_[sel]] == truth[b][vb[sel], ub[sel]]).sum())
    assert checked > 200
    assert agree / checked > 0.995


def test_predictions_good_but_imperfect(synth_out: Path) -> None:
    names, _ = _cameras(synth_out / "capture")
    dice, differ = [], 0
    for name in names:
        truth = _gray(synth_out / "truth" / f"{name}.png")
        pred = _gray(synth_out / "capture" / "predictions" / f"{name}.png")
        assert set(np.unique(pred)) <= {0, 1, 2, 3, 4, 5}
        differ += int(np.any(pred != truth))
        dice.append(_bed_dice(truth, pred))
    print(f"wound-bed Dice of predictions: mean {np.mean(dice):.3f}, min {np.min(dice):.3f}")
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
    import labelsynth.synth as synth_mod

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(synth_mod, "predict_errors", boom)
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
