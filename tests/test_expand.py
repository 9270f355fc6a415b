"""End to end on the shared tiny capture (conftest.tiny_expanded): outputs follow the contract,
the capture is untouched, and the fitted field recovers a two-class scene on unseen frames."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import cv2
import h5py
import numpy as np
import pytest
import torch

from labelsynth.capture import load_capture
from labelsynth.classes import ClassInfo, ClassMap
from labelsynth.errors import LabelsynthError
from labelsynth.evaluation.metrics import score_frames
from labelsynth.pipeline import expand, fit_semantics
from labelsynth.render.renderer import FieldRenderer
from labelsynth.rundir import load_field
from labelsynth.semantics.training import LabelledFrame

# All tests using the shared tiny run go to one xdist worker, so it is fitted once.
pytestmark = pytest.mark.xdist_group("tiny_expanded")

TWO_CLASSES = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "wound", (255, 0, 0), True)))


def _binary(mask: np.ndarray) -> np.ndarray:
    return np.where(mask == 255, 255, (mask > 0).astype(np.uint8)).astype(np.uint8)


def test_two_class_scene_is_recovered_on_unseen_frames(tiny_expanded):
    """Refit the semantic stage on the fitted geometry with binary masks of the good annotations."""
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    fitted = load_field(run.out / "field.pt", torch.device("cpu"))
    fitted = dataclasses.replace(fitted, classes=TWO_CLASSES, head=None)
    cams = cap.unit_cameras()
    frames = [
        LabelledFrame(cams[i], _binary(cap.load_annotation(i)), 1.0, f.name)
        for i, f in enumerate(cap.frames) if f.name in run.good
    ]
    fitted = fitted.with_head(fit_semantics(fitted, frames, progress=False).head)
    unseen = [i for i, f in enumerate(cap.frames) if f.annotation_path is None]
    assert len(unseen) == 4
    view = FieldRenderer(fitted)
    preds = [view.render(cams[i]).mask for i in unseen]
    truths = [_binary(cv2.imread(str(run.truth_dir / f"{cap.frames[i].name}.png"), cv2.IMREAD_UNCHANGED)) for i in unseen]
    scores = score_frames(preds, truths, TWO_CLASSES)
    dice = {row["class"]: row["dice"] for row in scores.table()}
    assert dice["wound_bed"] >= 0.9, scores.summary_line()


def test_outputs_follow_the_contract(tiny_expanded):
    run = tiny_expanded
    out, result = run.out, run.result
    masks = sorted((out / "masks").glob("*.png"))
    assert [p.stem for p in masks] == result.frames
    m = cv2.imread(str(masks[0]), cv2.IMREAD_UNCHANGED)
    assert m.shape == (72, 96) and m.dtype == np.uint8 and set(np.unique(m)) <= set(range(6))
    with h5py.File(out / "labels.h5") as f:
        assert f["images"].shape == (8, 72, 96, 3) and f["images"].dtype == np.uint8
        assert f["masks"].shape == (8, 72, 96) and f["confidence"].dtype == np.float16
        assert f["annotated"][:].sum() == 4
        assert f["masks"].chunks[0] == 1 and f["masks"].compression is not None
        assert np.array_equal(f["masks"][0], m)
    run_info = json.loads((out / "run.json").read_text())
    assert run_info["labels"] == "annotations" and run_info["recipe"]["name"] == "fast"
    # every phase timed, the report's own steps too (the speed issue's profile reads them)
    assert {"check", "geometry", "semantics", "render", "report"} <= set(run_info["seconds"])
    phases = run_info["report_seconds"]
    assert {"agreement", "leave_one_out", "pairwise", "mesh", "figures"} <= set(phases)
    assert phases["leave_one_out"] > 0 and sum(phases.values()) <= run_info["seconds"]["report"] + 1e-6
    assert (out / "field.pt").exists() and (out / "report.json").exists()
    assert not out.with_name(out.name + ".partial").exists()
    after = {p: p.read_bytes() for p in run.capture_dir.rglob("*") if p.is_file()}
    assert after == run.capture_bytes  # nothing in the capture folder changed


def test_existing_output_is_refused_and_interrupted_runs_leave_nothing(tiny_expanded, tmp_path, monkeypatch):
    run = tiny_expanded
    with pytest.raises(LabelsynthError, match="exists"):
        expand(run.capture_dir, run.out, recipe="fast", progress=False)

    import labelsynth.pipeline as pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "render_outputs", interrupted)
    out = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        expand(run.capture_dir, out, recipe="fast", progress=False,
               overrides=["geometry.iterations=2", "semantic.iterations=2", "render.mesh_resolution=32"])
    assert not out.exists() and not out.with_name("interrupted.partial").exists()


def test_bad_label_mode_is_a_clear_error(tiny_expanded, tmp_path):
    capture = tmp_path / "capture"
    shutil.copytree(tiny_expanded.capture_dir, capture)
    shutil.rmtree(capture / "predictions")
    with pytest.raises(LabelsynthError, match="needs automatic masks"):
        expand(capture, tmp_path / "o", labels="predictions", progress=False)
    with pytest.raises(LabelsynthError, match="--labels must be one of annotations, predictions, both, not 'everything'"):
        expand(tiny_expanded.capture_dir, tmp_path / "o", labels="everything", progress=False)


def test_cli_no_report_writes_masks_and_no_report(tiny_expanded, tmp_path):
    """`expand --no-report`: the masks, dataset, field and run.json, and neither report nor mesh."""
    from typer.testing import CliRunner

    from labelsynth.cli import app

    out = tmp_path / "masks_only"
    res = CliRunner().invoke(app, [
        "expand", str(tiny_expanded.capture_dir), "--out", str(out), "--recipe", "fast", "--device", "cpu",
        "--labels", "annotations", "--no-report", "--set", "geometry.iterations=4", "--set", "semantic.iterations=4",
        "--set", "semantic.min_epochs=0", "--set", "render.mesh_resolution=32",
    ])
    assert res.exit_code == 0, res.output
    assert len(list((out / "masks").glob("*.png"))) == 8
    for name in ("labels.h5", "field.pt", "run.json"):
        assert (out / name).is_file()
    assert not (out / "report.json").exists() and not (out / "mesh.ply").exists()
    run = json.loads((out / "run.json").read_text())
    assert "report" not in run["seconds"]
    # the summary names the geometry's training PSNR (a failed fit's sign), as run.json holds it
    assert f"geometry training PSNR {run['geometry']['final_psnr']:.1f} dB" in res.output


def test_leave_one_out_heads_are_fresh_heads_trained_for_a_fraction_of_the_steps(tiny_expanded):
    """report.loo_fraction: each left-out frame's head starts afresh (not the full head warm-started)
    and trains that fraction of the semantic stage's steps; the field is never changed."""
    from labelsynth.pipeline import labelled_frames, leave_one_out_heads_of
    from labelsynth.semantics.fit import scaled_config

    capture = load_capture(tiny_expanded.capture_dir)
    fitted = load_field(tiny_expanded.out / "field.pt", torch.device("cpu"))
    recipe = fitted.recipe
    frames = labelled_frames(capture, "annotations", recipe)
    full = fit_semantics(fitted, frames, progress=False)
    part = fit_semantics(fitted, [], exclude={tiny_expanded.good[0]}, baked=full.baked, progress=False,
                         steps_fraction=recipe.report.loo_fraction)
    assert full.stats.iterations == recipe.semantic.iterations
    assert part.stats.iterations == math.ceil(recipe.semantic.iterations * recipe.report.loo_fraction) < full.stats.iterations
    assert part.stats.rays < full.stats.rays and part.head is not full.head
    assert scaled_config(recipe.semantic, recipe.report.loo_fraction).iterations == part.stats.iterations
    head_before = fitted.head
    names = list(tiny_expanded.good[:2])
    heads = leave_one_out_heads_of(fitted, capture, "annotations", names, baked=full.baked)
    assert list(heads) == names and len({id(h) for h in heads.values()}) == 2
    assert fitted.head is head_before and all(h is not head_before for h in heads.values())
