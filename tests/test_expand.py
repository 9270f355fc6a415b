"""End to end on a tiny capture: the field recovers a two-class scene on frames it was not given."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from labelsynth.capture import load_capture
from labelsynth.errors import LabelsynthError
from labelsynth.metrics import score_frames
from labelsynth.pipeline import expand
from labelsynth.synth import SynthConfig, synthesize

TINY = [
    "geometry.iterations=250",
    "geometry.train_scale=1.0",
    "geometry.levels_every=25",
    "semantic.iterations=150",
    "semantic.train_scale=1.0",
    "render.mesh_resolution=128",
]
TWO_CLASSES = {"classes": [
    {"id": 0, "name": "background", "color": [0, 0, 0]},
    {"id": 1, "name": "wound", "color": [255, 0, 0], "wound_bed": True},
]}


def _binary(mask: np.ndarray) -> np.ndarray:
    return np.where(mask == 255, 255, (mask > 0).astype(np.uint8))


@pytest.fixture(scope="module")
def two_class_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("two_class")
    made = synthesize(root / "synth", SynthConfig(frames=8, annotated=3, width=96, height=72, seed=3), progress=False)
    capture = root / "capture"
    shutil.copytree(made.capture_dir, capture)
    shutil.rmtree(capture / "predictions")
    (capture / "classes.json").write_text(json.dumps(TWO_CLASSES))
    for p in (capture / "annotations").glob("*.png"):
        cv2.imwrite(str(p), _binary(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)))
    before = {p: p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    result = expand(capture, root / "out", recipe="fast", overrides=TINY, device="cpu", progress=False, report=False)
    return capture, made.truth_dir, result, before


def test_two_class_scene_is_recovered_on_unseen_frames(two_class_run):
    capture_dir, truth_dir, result, _ = two_class_run
    cap = load_capture(capture_dir)
    unseen = [n for n in result.frames if n not in result.annotated]
    assert len(unseen) == 5
    preds = [cv2.imread(str(result.out / "masks" / f"{n}.png"), cv2.IMREAD_UNCHANGED) for n in unseen]
    truths = [_binary(cv2.imread(str(Path(truth_dir) / f"{n}.png"), cv2.IMREAD_UNCHANGED)) for n in unseen]
    scores = score_frames(preds, truths, cap.classes, unseen)
    dice = {row["class"]: row["dice"] for row in scores.table()}
    assert dice["wound_bed"] >= 0.9, scores.summary_line()


def test_outputs_follow_the_contract(two_class_run):
    capture_dir, _, result, before = two_class_run
    out = result.out
    masks = sorted((out / "masks").glob("*.png"))
    assert [p.stem for p in masks] == result.frames
    m = cv2.imread(str(masks[0]), cv2.IMREAD_UNCHANGED)
    assert m.shape == (72, 96) and m.dtype == np.uint8 and set(np.unique(m)) <= {0, 1}
    with h5py.File(out / "labels.h5") as f:
        assert f["images"].shape == (8, 72, 96, 3) and f["images"].dtype == np.uint8
        assert f["masks"].shape == (8, 72, 96) and f["confidence"].dtype == np.float16
        assert f["annotated"][:].sum() == 3
        assert f["masks"].chunks[0] == 1 and f["masks"].compression is not None
    assert (out / "field.pt").exists() and (out / "run.json").exists()
    assert not out.with_name(out.name + ".partial").exists()
    # nothing in the capture folder changed
    after = {p: p.read_bytes() for p in Path(capture_dir).rglob("*") if p.is_file()}
    assert after == before


def test_existing_output_is_refused_and_interrupted_runs_leave_nothing(two_class_run, tmp_path, monkeypatch):
    capture_dir, _, result, _ = two_class_run
    with pytest.raises(LabelsynthError, match="exists"):
        expand(capture_dir, result.out, recipe="fast", progress=False, report=False)

    import labelsynth.pipeline as pipeline

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "render_outputs", boom)
    out = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        expand(capture_dir, out, recipe="fast", overrides=["geometry.iterations=2", "semantic.iterations=2",
               "render.mesh_resolution=32"], progress=False, report=False)
    assert not out.exists() and not out.with_name("interrupted.partial").exists()


def test_bad_label_mode_is_a_clear_error(two_class_run, tmp_path):
    capture_dir, *_ = two_class_run
    with pytest.raises(LabelsynthError, match="needs automatic masks"):
        expand(capture_dir, tmp_path / "o", labels="predictions", progress=False)
