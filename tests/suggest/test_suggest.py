"""`labelsynth suggest` end to end on a tiny capture that dwells on one side of an object, then
`expand --geometry` from its output; every bad option or input is one line and leaves no OUT."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from labelsynth.cameras import Camera, look_at
from labelsynth.cli import app
from labelsynth.rundir import RunFolder, load_field
from labelsynth.suggest import default_out

from ..conftest import TINY_OVERRIDES
from ..scenes import make_object_capture, make_patch_capture

SIZE = 40
AZIMUTHS = [0, 12, 24, 36, 48, 60, 72, 200]  # seven frames on one side, the last one across
SET = [a for o in TINY_OVERRIDES for a in ("--set", o)]


def _cameras() -> list[Camera]:
    cams = []
    for i, a in enumerate(AZIMUTHS):
        el, az = np.radians((10.0, 35.0)[i % 2]), np.radians(a)
        eye = 2.2 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cams.append(Camera(SIZE, SIZE, 1.1 * SIZE, 1.1 * SIZE, SIZE / 2, SIZE / 2, look_at(eye, np.zeros(3))))
    return cams


@pytest.fixture(scope="module")
def suggested(tmp_path_factory):
    """One suggest run (one tiny geometry fit) shared by the tests of this module."""
    root = tmp_path_factory.mktemp("suggest")
    capture, truth = make_object_capture(root, frames=len(AZIMUTHS), size=SIZE, annotated=(1, 7), cameras=_cameras())
    before = {p: p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    out = root / "suggested"
    res = CliRunner().invoke(app, ["suggest", str(capture), "--annotate", "2", "--out", str(out), "--recipe", "fast",
                                   "--device", "cpu", *SET])
    assert res.exit_code == 0, res.output
    return capture, truth, out, res, before


def test_suggest_names_the_frames_that_show_most_and_keeps_the_geometry(suggested):
    capture, _, out, res, before = suggested
    data = json.loads((out / "suggest.json").read_text())
    names = [f["name"] for f in data["frames"]]
    assert len(names) == 2 and "view_07" in names  # the one frame of the far side
    assert data["spread"]["frames"] == ["view_02", "view_06"]  # both on the near side
    assert data["coverage"] > data["spread"]["coverage"] + 0.05
    assert data["frames"][0]["gain"] >= data["frames"][1]["gain"] > 0
    assert data["frames"][1]["coverage"] == pytest.approx(data["coverage"])
    assert len(data["coverage_by_k"]["suggested"]) == len(data["coverage_by_k"]["spread:k"]) == 6
    assert 0 < data["surface"]["seen"] <= data["surface"]["samples"]
    for name in names:
        assert name in res.stdout
    assert f"labelsynth expand {capture} --out OUT --geometry {out} --recipe fast --set geometry.iterations=250" \
        in res.stdout and data["expand"].startswith("labelsynth expand")
    # the geometry: a field without a head, with what it was fitted on
    fitted = load_field(RunFolder(out).field_path, torch.device("cpu"))
    assert fitted.head is None and fitted.fitted_on is not None
    assert sorted(fitted.fitted_on.images) == [f"view_{i:02d}" for i in range(8)]
    assert fitted.fitted_on.geometry["iterations"] == 250 and fitted.fitted_on.seed == 0
    sheet = cv2.imread(str(out / "suggest.png"))
    assert sheet is not None and sheet.shape[0] > 100 and sheet.shape[1] > 300
    assert not out.with_name(out.name + ".partial").exists()
    assert {p: p.read_bytes() for p in capture.rglob("*") if p.is_file()} == before  # the capture untouched


def test_expand_reuses_the_suggested_geometry(suggested, tmp_path):
    capture, _, out, _, _ = suggested
    res = CliRunner().invoke(app, ["expand", str(capture), "--out", str(tmp_path / "exp"), "--geometry", str(out),
                                   "--labels", "annotations", "--recipe", "fast", "--device", "cpu", "--no-report", *SET])
    assert res.exit_code == 0, res.output
    info = RunFolder(tmp_path / "exp").read_run()
    assert info.geometry_from == str(RunFolder(out).field_path.resolve())
    reused = load_field(RunFolder(tmp_path / "exp").field_path)
    assert reused.head is not None and reused.fitted_on == load_field(RunFolder(out).field_path).fitted_on
    # a changed seed is refused: that geometry was not fitted with it
    res = CliRunner().invoke(app, ["expand", str(capture), "--out", str(tmp_path / "seed1"), "--geometry", str(out),
                                   "--labels", "annotations", "--recipe", "fast", "--device", "cpu", "--seed", "1", *SET])
    assert res.exit_code == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "seed changed since the geometry in" in lines[0] and "(seed: 0 -> 1)" in lines[0], lines
    assert not (tmp_path / "seed1").exists() and not (tmp_path / "seed1.partial").exists()


def test_suggest_by_the_frame_objective(suggested, tmp_path):
    """--objective frames: the named frames are the frame objective's choice on the fitted surface,
    in greedy surface order, and suggest.json records the objective and both scores."""
    from labelsynth.capture import load_capture
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.suggest import CoverageConfig, surface_views

    capture = suggested[0]
    out = tmp_path / "frames"
    res = CliRunner().invoke(app, ["suggest", str(capture), "--annotate", "2", "--objective", "frames", "--out", str(out),
                                   "--recipe", "fast", "--device", "cpu", *SET])
    assert res.exit_code == 0, res.output
    data = json.loads((out / "suggest.json").read_text())
    assert data["objective"] == "frames" and len(data["coverage_by_k"]["suggested"]) == 6
    cap = load_capture(capture)
    view = FieldRenderer(load_field(RunFolder(out).field_path, torch.device("cpu")))
    views = surface_views(view.mesh(), cap.unit_cameras(), cap.names, CoverageConfig(), caster=view.caster(),
                          progress=False)
    choice = views.frame_choice(2)
    assert sorted(f["index"] for f in data["frames"]) == choice
    assert data["frame_score"] == pytest.approx(views.frame_score(choice))
    spread = [cap.names.index(n) for n in data["spread"]["frames"]]
    assert data["spread"]["frame_score"] == pytest.approx(views.frame_score(spread))
    assert data["coverage"] == pytest.approx(views.coverage(choice))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    capture, _ = make_patch_capture(tmp_path_factory.mktemp("small"), frames=4, size=24)
    return capture


BAD = [
    (["--annotate", "0"], "--annotate must be a whole number in 1..6, not 0"),
    (["--annotate", "7"], "--annotate must be a whole number in 1..6, not 7"),
    (["--annotate", "5"], "--annotate 5: {capture} has only 4 frames"),
    (["--annotate", "2", "--out", "{capture}/suggest"], "--out {capture}/suggest: inside the capture {capture}"),
    (["--annotate", "2", "--seed", "-1"], "--seed must be a whole number in 0..4294967295, not -1"),
    (["--annotate", "2", "--device", "tpu"], "--device must be one of auto, cpu, cuda, not 'tpu'"),
    (["--annotate", "2", "--objective", "pixels"], "--objective must be one of surface, frames, not 'pixels'"),
    (["--annotate", "2", "--recipe", "nope"], "--recipe 'nope': unknown recipe"),
    (["--annotate", "2", "--set", "geometry.iterations=-5"], "fast.yaml.geometry.iterations: -5 is not >= 1"),
    (["--annotate", "2", "--out", "{full}"], "{full}: output folder exists and is not empty"),
]


@pytest.mark.parametrize("args, message", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_bad_suggest_input_is_one_line_and_leaves_nothing(small, tmp_path, no_fitting, args, message):
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("x")
    names = {"capture": small, "full": full}
    args = [a.format(**names) for a in args]
    out = tmp_path / "out"
    if "--out" not in args:
        args += ["--out", str(out)]
    res = CliRunner().invoke(app, ["suggest", str(small), "--recipe", "fast", "--device", "cpu", *args])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"labelsynth: error: {message.format(**names)}"), lines
    assert not out.exists() and not out.with_name("out.partial").exists()
    assert not (small / "suggest").exists() and sorted(p.name for p in full.iterdir()) == ["keep.txt"]


def test_a_missing_capture_and_the_default_out(tmp_path, no_fitting):
    res = CliRunner().invoke(app, ["suggest", str(tmp_path / "nope"), "--annotate", "2"])
    assert res.exit_code == 2 and res.stderr.strip() == f"labelsynth: error: {tmp_path / 'nope'}: capture folder not found"
    assert not (tmp_path / "nope-suggest").exists() and not (tmp_path / "nope-suggest.partial").exists()
    assert default_out(tmp_path / "wound1") == (tmp_path / "wound1-suggest").resolve()
    assert default_out(f"{tmp_path / 'wound1'}/") == (tmp_path / "wound1-suggest").resolve()
