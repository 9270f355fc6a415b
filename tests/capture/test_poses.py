"""pycolmap SfM on a synthetic capture recovers the true poses up to a similarity."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth.capture.poses import estimate_poses
from labelsynth.cli import app
from labelsynth.errors import LabelsynthError
from labelsynth.evaluation.poses import frame_poses, pose_errors
from labelsynth.evaluation.synth import SynthConfig, synthesize


@pytest.fixture(scope="module")
def synth_capture(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("poses") / "s"
    synthesize(out, SynthConfig(frames=14, annotated=2, width=320, height=240, seed=5), progress=False)
    return out / "capture"


def test_poses_match_truth_and_out_writes_elsewhere(synth_capture: Path, tmp_path: Path) -> None:
    before = sorted(p.relative_to(synth_capture) for p in synth_capture.rglob("*"))
    with pytest.raises(LabelsynthError, match="exists"):
        estimate_poses(synth_capture, progress=False)  # the synthetic capture has true poses
    out = tmp_path / "sfm"
    report = estimate_poses(synth_capture, out=out, progress=False)
    assert sorted(p.relative_to(synth_capture) for p in synth_capture.rglob("*")) == before
    assert report.output == out / "transforms.json" and report.output.is_file()
    assert (out / "points3D.ply").is_file()
    assert len(report.registered) == 14 and not report.unregistered
    assert "14/14" in report.summary()

    truth = json.loads((synth_capture / "transforms.json").read_text())
    est = json.loads(report.output.read_text())
    assert est["camera_model"] == "OPENCV" and (est["w"], est["h"]) == (320, 240)
    assert abs(est["fl_x"] / truth["fl_x"] - 1) < 0.02
    errors = pose_errors(frame_poses(truth), frame_poses(est))
    rot, centre = errors.rotation_deg, errors.centre
    print(f"SfM: rotation error median {np.median(rot):.3f} deg, centre error max {centre.max():.4f} of path size, "
          f"reprojection {report.mean_reprojection_error:.3f} px")
    assert np.median(rot) < 1.0
    assert centre.max() < 0.02
    with pytest.raises(LabelsynthError, match="exists"):
        estimate_poses(synth_capture, out=out, progress=False)


def test_fresh_capture_with_unregistrable_frame(synth_capture: Path, tmp_path: Path) -> None:
    cap = tmp_path / "cap"
    shutil.copytree(synth_capture / "images", cap / "images")
    noise = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    noise = cv2.GaussianBlur(noise, (0, 0), 3)
    cv2.imwrite(str(cap / "images" / "zz_noise.png"), noise)
    with pytest.warns(UserWarning, match="could not be registered"):
        report = estimate_poses(cap, progress=False)
    assert report.unregistered == ["zz_noise"]
    assert sorted(p.name for p in cap.iterdir()) == ["images", "transforms.json"]
    est = json.loads((cap / "transforms.json").read_text())
    assert len(est["frames"]) == 14 and all("zz_noise" not in f["file_path"] for f in est["frames"])

    from labelsynth.capture import load_capture

    assert len(load_capture(cap).frames) == 14
    # --force overwrites; without it the CLI refuses with one line
    runner = CliRunner()
    res = runner.invoke(app, ["poses", str(cap)])
    assert res.exit_code == 2 and "exists" in res.output


def test_input_errors(tmp_path: Path) -> None:
    with pytest.raises(LabelsynthError, match="no images"):
        estimate_poses(tmp_path, progress=False)
    (tmp_path / "images").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "images" / f"{i}.png"), np.zeros((32, 32, 3), np.uint8))
    with pytest.raises(LabelsynthError, match="at least 3"):
        estimate_poses(tmp_path, progress=False)
    cv2.imwrite(str(tmp_path / "images" / "2.png"), np.zeros((32, 32, 3), np.uint8))
    with pytest.raises(LabelsynthError, match="reconstruction failed"):
        estimate_poses(tmp_path, progress=False)
    assert not (tmp_path / "transforms.json").exists()
    with pytest.raises(LabelsynthError, match="matching"):
        estimate_poses(tmp_path, matching="vocab", progress=False)


def test_cli_poses_out(synth_capture: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["poses", str(synth_capture), "--out", str(tmp_path / "p.json"), "--matching", "sequential"])
    assert res.exit_code == 0, res.output
    assert "registered" in res.output
    assert (tmp_path / "p.json").is_file()
