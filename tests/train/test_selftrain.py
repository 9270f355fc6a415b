"""``labelsynth selftrain`` and ``capture.view`` on tiny captures: each round segments with the
previous round's model, fuses (or not) what it was asked to, trains on exactly that, scores the
held-out captures, and never writes into a capture; a rerun continues instead of redoing."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from labelsynth.capture import load_capture
from labelsynth.capture.view import capture_view
from labelsynth.classes import ClassMap
from labelsynth.cli import app
from labelsynth.errors import CaptureError
from labelsynth.export.labels_h5 import LabelsReader
from labelsynth.train import TrainConfig
from labelsynth.train import selftrain as st
from labelsynth.train.selftrain import SelfTrainConfig, SelfTrainError, selftrain

from ..conftest import TINY_EXPAND

W, H = 48, 36
TINY_TRAIN = dict(steps=2, batch_size=2, crop=32, eval_every=1, device="cpu")


class Redness(torch.nn.Module):
    """A real (if crude) segmenter: granulation where the pixel is much redder than green."""

    def forward(self, pixel_values):
        red = pixel_values[:, 0] * 0.229 - pixel_values[:, 1] * 0.224 + 0.029  # r - g in 0..1 units
        logits = torch.zeros(pixel_values.shape[0], 6, *pixel_values.shape[2:])
        logits[:, 0] = 0.25
        logits[:, 1] = red
        return logits


def _log(msg: str) -> None:
    import time
    print(time.strftime("%H:%M:%S"), msg, flush=True)


def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    from labelsynth.evaluation.synth import SynthConfig, synthesize
    from labelsynth.train.export_onnx import export_onnx

    root = tmp_path_factory.mktemp("selftrain")
    out = {}
    for name, seed, frames, annotated in (("cap", 1, 4, 1), ("cap2", 2, 3, 1), ("held", 3, 3, 3)):
        out[name] = synthesize(root / name, SynthConfig(frames=frames, annotated=annotated, width=W, height=H,
                                                        seed=seed), progress=False).capture_dir
    out["m0"] = export_onnx(Redness(), root / "m0.onnx", ClassMap.default(), (W, H))
    out["root"] = root
    return out


def _spy_segment(monkeypatch) -> list[tuple[Path, Path]]:
    from labelsynth.train import segment

    calls: list[tuple[Path, Path]] = []
    real = segment.segment_capture

    def spy(capture, model, out_dir, **kw):
        calls.append((Path(capture), Path(model)))
        return real(capture, model, out_dir, **kw)

    monkeypatch.setattr(segment, "segment_capture", spy)
    return calls


# --- capture.view --------------------------------------------------------------------------------
def test_capture_view_has_the_frames_and_only_the_masks_given(data, tmp_path):
    cap = data["cap"]
    before = _files(cap)
    truth = cap.parent / "truth"
    view = capture_view(cap, tmp_path / "v", annotations={"frame_002": truth / "frame_002.png"},
                        predictions=cap / "predictions")
    loaded = load_capture(view)
    assert loaded.names == load_capture(cap).names
    assert [f.name for f in loaded.frames if f.annotation_path is not None] == ["frame_002"]
    assert all(f.prediction_path is not None for f in loaded.frames)
    np.testing.assert_array_equal(loaded.load_annotation(2), cv2.imread(str(truth / "frame_002.png"), cv2.IMREAD_UNCHANGED))
    plain = load_capture(capture_view(cap, tmp_path / "w"))  # no masks at all
    assert not plain.has_annotations and not plain.has_predictions
    kept = load_capture(capture_view(cap, tmp_path / "k", keep_annotations=True))
    assert kept.has_annotations and not kept.has_predictions
    assert _files(cap) == before  # the capture is only read
    with pytest.raises(CaptureError, match="inside"):
        capture_view(cap, cap / "sub")
    with pytest.raises(CaptureError, match="not a capture"):
        capture_view(tmp_path, tmp_path / "x")


# --- the loop ------------------------------------------------------------------------------------
def test_two_rounds_with_both(data, tmp_path, monkeypatch):
    calls = _spy_segment(monkeypatch)
    before = _files(data["cap"])
    out = tmp_path / "st"
    cfg = SelfTrainConfig(rounds=2, labels="both", recipe="fast", overrides=TINY_EXPAND, device="cpu",
                          train=TrainConfig(**TINY_TRAIN))
    result = selftrain([data["cap"]], data["m0"], out, cfg, holdout=[data["held"]], progress=False, log=_log)

    # round 1 segments with M0, round 2 with round 1's model; each round scores the held-out capture
    by_capture = [(c, m) for c, m in calls if c == data["cap"]]
    assert by_capture == [(data["cap"], data["m0"]), (data["cap"], out / "round1" / "model" / "model.onnx")]
    assert [r.round for r in result.rounds] == [0, 1, 2]
    assert all(r.dice("wound_bed") is not None for r in result.rounds)
    for r in (1, 2):
        masks = sorted(p.stem for p in (out / f"round{r}" / "predictions" / "capture").glob("*.png"))
        assert masks == load_capture(data["cap"]).names  # every frame segmented
        reader = LabelsReader(out / f"round{r}" / "expanded" / "capture" / "labels.h5")
        assert len(reader) == 4 and reader.annotated.tolist() == [False, False, True, False]  # 'both': the expert frame
        run = json.loads((out / f"round{r}" / "expanded" / "capture" / "run.json").read_text())
        assert run["labels"] == "both"
        report = json.loads((out / f"round{r}" / "model" / "train.json").read_text())
        assert report["sources"] == [str(out / f"round{r}" / "expanded" / "capture" / "labels.h5"), str(data["held"])]
        assert report["split"]["train_frames"] == 4 and report["split"]["val_sources"] == [str(data["held"])]
    state = json.loads((out / "selftrain.json").read_text())
    assert len(state["rounds"]) == 3 and "| 2 |" in state["table"]
    best = result.best()
    assert best.mean_dice == max(r.mean_dice for r in result.rounds)
    assert state["best"] == {"round": best.round, "model": best.model, "mean_dice": best.mean_dice}
    assert f"best on the held-out captures: round {best.round}" in result.summary()
    assert _files(data["cap"]) == before  # predictions went into the loop's own view, not the capture

    # a rerun with the same settings continues: nothing is segmented, expanded or trained again
    calls.clear()
    monkeypatch.setattr(st, "_expand", lambda *a, **k: pytest.fail("expanded again"))
    again = selftrain([data["cap"]], data["m0"], out, cfg, holdout=[data["held"]], progress=False, log=lambda m: None)
    assert calls == [] and [r.dice("wound_bed") for r in again.rounds] == [r.dice("wound_bed") for r in result.rounds]
    other = SelfTrainConfig(rounds=2, labels="predictions", recipe="fast", overrides=TINY_EXPAND, device="cpu",
                            train=TrainConfig(**TINY_TRAIN))
    with pytest.raises(SelfTrainError, match="other settings"):
        selftrain([data["cap"]], data["m0"], out, other, holdout=[data["held"]], progress=False, log=lambda m: None)


def test_raw_trains_on_the_masks_themselves(data, tmp_path, monkeypatch):
    monkeypatch.setattr(st, "_expand", lambda *a, **k: pytest.fail("raw must not expand"))
    out = tmp_path / "raw"
    cfg = SelfTrainConfig(rounds=1, labels="raw", device="cpu", train=TrainConfig(**TINY_TRAIN, val_split="none"))
    selftrain([data["cap"], data["cap2"]], data["m0"], out, cfg, progress=False, log=lambda m: None)
    for name, n in (("capture", 4), ("capture-2", 3)):
        reader = LabelsReader(out / "round1" / "labels" / f"{name}.h5")
        assert len(reader) == n and not reader.annotated.any()  # the expert frame did not teach here
        view = load_capture(out / "round1" / "captures" / name)
        assert not view.has_annotations
        for i in range(n):
            _, mask, conf = reader.read(i)
            np.testing.assert_array_equal(mask, view.load_prediction(i))
            assert np.all(conf == 1)
    report = json.loads((out / "round1" / "model" / "train.json").read_text())
    assert report["split"]["train_frames"] == 7 and report["split"]["val_frames"] == 0


def test_warm_start_reads_the_previous_rounds_weights(data, tmp_path, monkeypatch):
    """--warm-start: round 1 trains from the checkpoint beside M0, round 2 from round 1's."""
    from labelsynth.train import train

    m0_dir = tmp_path / "m0"
    train([data["cap"]], m0_dir, TrainConfig(**TINY_TRAIN, only_annotated=True), progress=False, log=lambda m: None)
    out = tmp_path / "warm"
    cfg = SelfTrainConfig(rounds=2, labels="raw", device="cpu", warm_start=True,
                          train=TrainConfig(**TINY_TRAIN, val_split="none"))
    selftrain([data["cap2"]], m0_dir / "model.onnx", out, cfg, progress=False, log=lambda m: None)
    for r, start in ((1, m0_dir), (2, out / "round1" / "model")):
        report = json.loads((out / f"round{r}" / "model" / "train.json").read_text())
        assert report["arguments"]["init"] == str(start / "checkpoint.pt")
    res = CliRunner().invoke(app, ["selftrain", str(data["cap"]), "--model", str(data["m0"]), "--out",
                                   str(tmp_path / "o4"), "--warm-start"])
    assert res.exit_code == 2 and "--warm-start needs the checkpoint.pt" in res.output, res.output
    assert not (tmp_path / "o4").exists()


def test_accumulate_trains_each_round_on_every_rounds_labels(data, tmp_path):
    """--accumulate: round 2 trains on round 1's labels and its own (the same frames twice, from
    two models' masks); without it, on its own only (test_two_rounds_with_both)."""
    out = tmp_path / "acc"
    cfg = SelfTrainConfig(rounds=2, labels="raw", device="cpu", accumulate=True,
                          train=TrainConfig(**TINY_TRAIN, val_split="none"))
    selftrain([data["cap2"]], data["m0"], out, cfg, progress=False, log=lambda m: None)
    for r, rounds in ((1, [1]), (2, [1, 2])):
        report = json.loads((out / f"round{r}" / "model" / "train.json").read_text())
        assert report["sources"] == [str(out / f"round{q}" / "labels" / "capture.h5") for q in rounds]
        assert report["split"]["train_frames"] == 3 * len(rounds)


def test_agreed_labels_keep_only_the_pixels_both_rounds_gave_the_same_class(tmp_path):
    """agreed_labels_h5: round R's class where round R-1's is the same, else ignore with confidence 0;
    images, confidences and expert flags otherwise as round R's."""
    from labelsynth.export import write_labels_h5

    rng = np.random.default_rng(0)
    classes = ClassMap.default()
    images = rng.integers(0, 256, (2, 5, 6, 3), dtype=np.uint8)
    before = rng.choice([0, 1, 3], (2, 5, 6)).astype(np.uint8)
    now = np.where(rng.random((2, 5, 6)) < 0.5, before, rng.choice([0, 2], (2, 5, 6))).astype(np.uint8)
    conf = rng.uniform(0.3, 1.0, (2, 5, 6)).astype(np.float32)
    kw = dict(images=images, frame_names=["a", "b"], classes=classes)
    write_labels_h5(tmp_path / "r1.h5", masks=before, **kw)
    write_labels_h5(tmp_path / "r2.h5", masks=now, confidence=conf, annotated=[True, False], **kw)
    st.agreed_labels_h5(tmp_path / "r2.h5", tmp_path / "r1.h5", tmp_path / "agreed.h5")
    reader = LabelsReader(tmp_path / "agreed.h5")
    assert reader.frame_names == ["a", "b"] and reader.annotated.tolist() == [True, False]
    same = now == before
    assert same.any() and (~same).any()
    for i in range(2):
        image, mask, c = (np.asarray(x) for x in reader.read(i))
        np.testing.assert_array_equal(image, images[i])
        np.testing.assert_array_equal(mask, np.where(same[i], now[i], 255))
        np.testing.assert_allclose(c, np.where(same[i], conf[i], 0.0), atol=1e-3)  # float16 storage
    write_labels_h5(tmp_path / "other.h5", masks=before, images=images, frame_names=["a", "c"], classes=classes)
    with pytest.raises(SelfTrainError, match="not the same frames"):
        st.agreed_labels_h5(tmp_path / "r2.h5", tmp_path / "other.h5", tmp_path / "x.h5")


def test_agree_trains_round_two_on_the_labels_round_one_agrees_with(data, tmp_path):
    """--agree: round 1 trains on its labels as they are; round 2 on its own labels where round 1's
    give the same class (round2/agreed/), and says so in selftrain.json."""
    out = tmp_path / "agree"
    cfg = SelfTrainConfig(rounds=2, labels="raw", device="cpu", agree=True,
                          train=TrainConfig(**TINY_TRAIN, val_split="none"))
    selftrain([data["cap2"]], data["m0"], out, cfg, progress=False, log=lambda m: None)
    labels = {r: out / f"round{r}" / "labels" / "capture.h5" for r in (1, 2)}
    agreed = out / "round2" / "agreed" / "capture.h5"
    sources = {r: json.loads((out / f"round{r}" / "model" / "train.json").read_text())["sources"] for r in (1, 2)}
    assert sources == {1: [str(labels[1])], 2: [str(agreed)]} and not (out / "round1" / "agreed").exists()
    r1, r2, kept = LabelsReader(labels[1]), LabelsReader(labels[2]), LabelsReader(agreed)
    for i in range(len(kept)):
        m1, m2, mk = (np.asarray(reader.read(i)[1]) for reader in (r1, r2, kept))
        np.testing.assert_array_equal(mk, np.where(m1 == m2, m2, 255))
    assert json.loads((out / "selftrain.json").read_text())["settings"]["config"]["agree"] is True


def test_cross_fit_segments_each_capture_with_a_teacher_that_never_learnt_its_labels(data, tmp_path, monkeypatch):
    """--cross-fit: round 1 segments with M0 as always; round 2 segments capture 1 with a teacher
    trained on capture 2's round-1 labels only and capture 2 with one trained on capture 1's, and
    trains round 2's model on both round-2 labellings."""
    calls = _spy_segment(monkeypatch)
    out = tmp_path / "cross"
    cfg = SelfTrainConfig(rounds=2, labels="raw", device="cpu", cross_fit=True,
                          train=TrainConfig(**TINY_TRAIN, val_split="none"))
    selftrain([data["cap"], data["cap2"]], data["m0"], out, cfg, progress=False, log=lambda m: None)
    labels = {r: [out / f"round{r}" / "labels" / f"{n}.h5" for n in ("capture", "capture-2")] for r in (1, 2)}
    folds = [out / "round2" / "teachers" / f"fold{f}" for f in (1, 2)]
    assert calls == [(data["cap"], data["m0"]), (data["cap2"], data["m0"]),
                     (data["cap"], folds[0] / "model.onnx"), (data["cap2"], folds[1] / "model.onnx")]
    for fold, taught in zip(folds, (labels[1][1], labels[1][0])):
        assert json.loads((fold / "train.json").read_text())["sources"] == [str(taught)]
    assert json.loads((out / "round2" / "model" / "train.json").read_text())["sources"] == [str(p) for p in labels[2]]
    assert not (out / "round1" / "teachers").exists()  # M0 never saw these captures' labels
    assert json.loads((out / "selftrain.json").read_text())["settings"]["config"]["cross_fit"] is True


def test_cross_fit_needs_two_captures_and_no_warm_start(data, tmp_path):
    runner = CliRunner()
    base = ["selftrain", str(data["cap"]), "--model", str(data["m0"]), "--cross-fit"]
    for extra, needle in (([], "--cross-fit needs at least 2 captures"),
                          ([str(data["cap2"]), "--warm-start"], "--cross-fit with --warm-start")):
        res = runner.invoke(app, [*base, *extra, "--out", str(tmp_path / "o")])
        errors = [ln for ln in res.output.splitlines() if ln.startswith("labelsynth: error:")]
        assert res.exit_code == 2 and len(errors) == 1 and needle in errors[0], res.output
        assert not (tmp_path / "o").exists()


def test_bad_input_is_one_line(data, tmp_path):
    runner = CliRunner()
    base = ["selftrain", str(data["cap"]), "--model", str(data["m0"]), "--out", str(tmp_path / "o")]
    cases = [
        (["--holdout", str(data["cap"])], "cannot also be trained on"),
        (["--labels", "guess"], "--labels"),
        (["--model", str(tmp_path / "none.onnx")], "model file not found"),
        (["--holdout", str(tmp_path)], "no camera poses"),
    ]
    for extra, needle in cases:
        res = runner.invoke(app, [*base, *extra])
        assert res.exit_code == 2, res.output
        errors = [ln for ln in res.output.splitlines() if ln.startswith("labelsynth: error:")]
        assert len(errors) == 1 and needle in errors[0], res.output
    no_expert = load_capture(capture_view(data["cap"], tmp_path / "bare"))
    assert not no_expert.has_annotations
    res = runner.invoke(app, ["selftrain", str(tmp_path / "bare"), "--model", str(data["m0"]), "--out",
                              str(tmp_path / "o2"), "--labels", "both"])
    assert res.exit_code == 2 and "needs expert frames" in res.output
    res = runner.invoke(app, ["selftrain", str(data["cap"]), "--model", str(data["m0"]), "--out", str(tmp_path / "o3"),
                              "--holdout", str(tmp_path / "bare")])
    assert res.exit_code == 2 and "needs annotations" in res.output


def test_the_best_round_is_named_not_assumed_to_be_the_last(tmp_path):
    def row(r, mean):
        return st.RoundScore(r, f"m{r}.onnx", None, {"wound_bed": {"dice": mean}} if mean is not None else {}, mean)

    result = st.SelfTrainResult(tmp_path, [row(0, 0.70), row(1, 0.84), row(2, 0.83)], 10.0)
    assert result.best().round == 1
    text = result.summary()
    assert "best on the held-out captures: round 1 (class mean 0.840, the last round 0.830) -> m1.onnx" in text
    assert st.SelfTrainResult(tmp_path, [row(0, 0.7), row(1, 0.7)], 1.0).best().round == 0  # a tie: the earlier
    unscored = st.SelfTrainResult(tmp_path, [row(0, None), row(1, None)], 1.0)
    assert unscored.best() is None and "held-out" not in unscored.summary()


def test_a_loop_recorded_before_an_option_existed_continues_as_that_options_default():
    """selftrain.json written by an older version lacks options added since, at any depth (the
    nested training config too): those ran as their defaults, so the loop continues; a recorded
    value that differs from today's still refuses."""
    cfg = SelfTrainConfig(rounds=2, train=TrainConfig(**TINY_TRAIN))
    settings = {"captures": ["a"], "model": "m0.onnx", "holdout": [], "config": json.loads(json.dumps(asdict(cfg)))}
    older = json.loads(json.dumps(settings))
    del older["config"]["cross_fit"]  # a top-level option added since
    nested = next(iter(older["config"]["train"]))
    del older["config"]["train"][nested]  # and one inside the training config
    assert st._same_settings(older, settings)
    changed = json.loads(json.dumps(older))
    changed["config"]["train"]["steps"] = TINY_TRAIN["steps"] + 1
    assert not st._same_settings(changed, settings)
    assert not st._same_settings({"config": "not a mapping"}, settings)
