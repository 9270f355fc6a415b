"""benchmarks/bench_retrain.py end to end on tiny captures (a few steps; the numbers mean nothing):
each arm trains on what it claims (which frames, how many, with which weights), is scored, and
lands in the table. The self-training loop itself is tested in tests/train/test_selftrain.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from .conftest import TINY_EXPAND, load_benchmark, run_benchmark

FRAMES, W, H = 4, 48, 36
# One worker runs the module, so the ~6-minute benchmark fixture runs once, not once per worker.
pytestmark = pytest.mark.xdist_group("bench_retrain")


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bench_retrain") / "out"
    args = ["--out", str(out), "--arms", "d,a1,b1,c1,f1,a1-split,st-raw,pa1,pst-raw,pst-pred-warm,pst-pred-acc,pst-pred-conf,pst-pred-cross,pst-truth", "--train-seeds", "1,2", "--val-seed", "3",
            "--test-seeds", "4", "--self-seeds", "5,6", "--phone-train-seeds", "7,8", "--phone-val-seed", "9",
            "--phone-test-seeds", "10", "--phone-self-seeds", "11,12", "--frames", str(FRAMES), "--width", str(W), "--height", str(H), "--steps", "2",
            "--batch-size", "2", "--crop", "32", "--input-size", f"{W}x{H}", "--floor", "0.6",
            *(w for o in TINY_EXPAND for w in ("--set", o))]
    res = run_benchmark("bench_retrain.py", args, timeout=1500)
    (out / "stdout.txt").write_text(res.stdout)
    return out


def _rows(out: Path) -> dict[str, dict]:
    return {r["arm"] + (f" r{r['round']}" if "round" in r else ""): r
            for r in json.loads((out / "results.json").read_text())["rows"]}


def _train(out: Path, arm: str) -> dict:
    return json.loads((out / "models" / arm / "train.json").read_text())


def test_every_arm_is_in_the_table(bench: Path) -> None:
    rows = _rows(bench)
    assert set(rows) == {"d", "a1", "b1", "c1", "f1", "a1-split", "st-raw r1", "pa1", "pst-raw r1", "pst-pred-warm r1",
                         "pst-pred-warm r2", "pst-pred-acc r1", "pst-pred-acc r2", "pst-pred-conf r1", "pst-pred-conf r2", "pst-pred-cross r1",
                         "pst-pred-cross r2", "pst-truth"}
    text = (bench / "stdout.txt").read_text()
    for arm in rows:
        assert f"| {arm} |" in text
    assert "K=1: (b)-(a) tissue mean" in text and "ceiling (d) validation" in text
    assert f"scale: {FRAMES} frames of {W}x{H} per capture; plain: 2 train" in text and "2 steps, batch 2, crop 32" in text
    assert (bench / "curves.png").is_file()
    for r in rows.values():
        assert r["test"]["classes"]["wound_bed"]["n"] == FRAMES  # every test frame scored
        seg = r["arm"] + (f"-r{r['round']}" if "round" in r else "")
        test = "phone-seed10" if r["kind"] == "phone" else "plain-seed4"
        assert len(list((bench / "segment" / seg / test).glob("*.png"))) == FRAMES


def test_expert_arms_train_on_the_chosen_frames(bench: Path) -> None:
    from labelsynth.capture import load_capture, read_mask
    from labelsynth.evaluation.synth import annotated_indices

    a1 = _train(bench, "a1")
    views = [bench / "views" / "plain-K1" / f"seed{s}" for s in (1, 2)]
    assert a1["sources"][:2] == [str(v) for v in views]
    assert a1["split"]["train_frames"] == 2 and a1["split"]["val_sources"] == [str(bench / "views/plain-all/seed3")]
    middle = annotated_indices(FRAMES, 1)
    for seed, v in zip((1, 2), views):
        cap = load_capture(v)
        assert [i for i, f in enumerate(cap.frames) if f.annotation_path is not None] == middle
        truth = bench / "captures" / "plain" / f"seed{seed}" / "truth" / f"{cap.frames[middle[0]].name}.png"
        np.testing.assert_array_equal(cap.load_annotation(middle[0]), read_mask(truth, None, cap.classes))
    split = _train(bench, "a1-split")
    assert split["split"]["train_frames"] == 1 and split["split"]["val_sources"] == [str(views[1])]
    d = _train(bench, "d")
    assert d["split"]["train_frames"] == 2 * FRAMES


def test_expanded_arms_and_their_weights(bench: Path) -> None:
    from labelsynth.classes import ClassMap
    from labelsynth.export.labels_h5 import LabelsReader
    from labelsynth.train.data import FrameDataset, load_sources, split_by_capture

    runs = {arm: _train(bench, arm) for arm in ("b1", "c1", "f1")}
    for arm, run in runs.items():
        assert run["sources"][:2] == [str(bench / "expanded" / "plain-K1" / f"seed{s}" / "labels.h5") for s in (1, 2)]
        assert run["split"]["train_frames"] == 2 * FRAMES
    assert [runs[a]["arguments"]["confidence_weight"] for a in ("b1", "c1", "f1")] == [False, True, False]
    assert [runs[a]["arguments"]["min_confidence"] for a in ("b1", "c1", "f1")] == [0.0, 0.0, 0.6]
    reader = LabelsReader(Path(runs["b1"]["sources"][0]))
    assert reader.annotated.sum() == 1  # expanded from one expert frame
    # what each arm's settings make of the same frame: c weighs by confidence, f drops what is below the floor
    loaded, classes = load_sources(runs["c1"]["sources"][:1])
    frames = split_by_capture(loaded, mode="none").train
    _, _, conf = frames[0].load()
    for arm in ("b1", "c1", "f1"):
        args = runs[arm]["arguments"]
        item = FrameDataset(frames[:1], classes, confidence_weight=args["confidence_weight"],
                            min_confidence=args["min_confidence"])[0]
        weight = item["weight"].numpy()
        labelled = item["target"].numpy() != 255
        if arm == "c1":
            np.testing.assert_allclose(weight[labelled], conf.astype(np.float32)[labelled], rtol=1e-3)
        elif arm == "f1":
            assert np.all(weight[conf < 0.6] == 0) and np.all(weight[labelled] == 1)
        else:
            assert np.all(weight[labelled] == 1)
    assert ClassMap.of_capture(bench / "views" / "plain-K1" / "seed1").to_json() == classes.to_json()


def test_self_training_arm_reads_m0(bench: Path) -> None:
    state = json.loads((bench / "selftrain" / "raw" / "selftrain.json").read_text())
    assert state["settings"]["model"] == str(bench / "models" / "a1" / "model.onnx")
    assert state["settings"]["captures"] == [str(bench / "views" / "plain-K1" / f"seed{s}") for s in (5, 6)]
    row = _rows(bench)["st-raw r1"]
    assert row["train_frames"] == 2 * FRAMES and row["labels"]["predictions"]["classes"]["wound_bed"]["n"] > 0


def test_phone_self_training_arm_reads_pa1(bench: Path) -> None:
    """pst-*: M0 is the weak model of the varied-frames regime (pa1), the captures are phone-like ones,
    the held-out capture is the phone validation capture, and the row is scored on the phone test captures."""
    state = json.loads((bench / "selftrain" / "phone-raw" / "selftrain.json").read_text())
    assert state["settings"]["model"] == str(bench / "models" / "pa1" / "model.onnx")
    assert state["settings"]["captures"] == [str(bench / "views" / "phone-K1" / f"seed{s}") for s in (11, 12)]
    assert state["settings"]["holdout"] == [str(bench / "views" / "phone-all" / "seed9")]
    row = _rows(bench)["pst-raw r1"]
    assert row["kind"] == "phone" and row["regime"] == "self-training (varied frames)"
    assert row["train_frames"] == 2 * FRAMES
    assert "self-training (varied frames, M0 = pa1)" not in (bench / "stdout.txt").read_text()  # needs pst-pred too


def test_warm_self_training_arm_starts_each_round_from_the_last(bench: Path) -> None:
    """pst-pred-warm: selftrain --warm-start from pa1, in its own folder; both rounds in the table
    (pst-pred-acc: --accumulate, likewise)."""
    loop = bench / "selftrain" / "phone-predictions-warm"
    state = json.loads((loop / "selftrain.json").read_text())
    assert state["settings"]["config"]["warm_start"] is True and state["settings"]["config"]["labels"] == "predictions"
    starts = [json.loads((loop / f"round{r}" / "model" / "train.json").read_text())["arguments"]["init"] for r in (1, 2)]
    assert starts == [str(bench / "models" / "pa1" / "checkpoint.pt"), str(loop / "round1" / "model" / "checkpoint.pt")]
    rows = _rows(bench)
    assert "pst-pred-warm r1" in rows and "pst-pred-warm r2" in rows
    assert "from M1's weights" in rows["pst-pred-warm r2"]["what"]
    assert "varied frames, M0 = pa1, ii, warm start): round 2 - round 1" in (bench / "stdout.txt").read_text()
    acc = json.loads((bench / "selftrain" / "phone-predictions-acc" / "selftrain.json").read_text())["settings"]["config"]
    assert acc["accumulate"] is True and acc["warm_start"] is False
    assert "ii, accumulated labels): round 2 - round 1" in (bench / "stdout.txt").read_text()
    # pst-pred-conf: train's default confidence weighting; every other self-training arm trains unweighted
    conf = json.loads((bench / "selftrain" / "phone-predictions-conf" / "selftrain.json").read_text())["settings"]["config"]
    assert conf["train"]["confidence_weight"] is True and acc["train"]["confidence_weight"] is False
    assert conf["warm_start"] is False and conf["accumulate"] is False
    assert "ii, confidence-weighted): round 2 - round 1" in (bench / "stdout.txt").read_text()
    # pst-pred-cross: round 2's masks from the two fold teachers, each taught by the other capture's round-1 labels
    loop = bench / "selftrain" / "phone-predictions-cross"
    assert json.loads((loop / "selftrain.json").read_text())["settings"]["config"]["cross_fit"] is True
    for fold, other in ((1, "seed12"), (2, "seed11")):
        taught = json.loads((loop / "round2" / "teachers" / f"fold{fold}" / "train.json").read_text())["sources"]
        assert taught[0] == str(loop / "round1" / "expanded" / other / "labels.h5")
    assert "fold teachers' masks" in rows["pst-pred-cross r2"]["what"] and "teacher" not in rows["pst-pred-cross r1"]["what"]
    assert "ii, cross-fitted teachers): round 2 - round 1" in (bench / "stdout.txt").read_text()


def test_loop_ceiling_trains_on_the_self_training_captures_truth(bench: Path) -> None:
    """pst-truth: the exact truth of every frame of the phone self-training captures (not the
    train captures), validated on the phone validation capture like every other arm."""
    sources = _train(bench, "pst-truth")["sources"]
    views = bench / "views"
    assert sources[:2] == [str(views / "phone-all" / f"seed{s}") for s in (11, 12)]
    row = _rows(bench)["pst-truth"]
    assert row["train_frames"] == 2 * FRAMES and row["labels"] == {"exact": True}
    assert row["regime"] == "self-training (varied frames)"


def _scored(wound_bed: float, tissue_mean: float) -> dict:
    return {"test": {"classes": {"wound_bed": {"dice": wound_bed}}, "tissue_mean_dice": tissue_mean}}


def test_self_training_targets_read_the_right_arms() -> None:
    """The target lines compare the arms the issue names, say met / NOT met by the thresholds, and
    say when the ceiling leaves (i) no room for the +0.03 wound-bed gain (no run needed: rows by hand)."""
    targets = load_benchmark("bench_retrain.py").targets
    by = {"pst-raw r1": _scored(0.950, 0.700), "pst-pred r1": _scored(0.970, 0.760),
          "pst-pred r2": _scored(0.969, 0.770), "pd": _scored(0.960, 0.900)}
    lines = targets(by)
    gain = next(x for x in lines if "(ii)-(i)" in x)
    assert "varied frames, M0 = pa1" in gain and "wound bed +0.020 (target >= +0.03: NOT met)" in gain
    assert "tissue mean +0.060 (target >= +0.05: met)" in gain
    ceiling = next(x for x in lines if "the ceiling (pd" in x)
    assert "+0.010 wound bed above (i)" in ceiling
    round2 = next(x for x in lines if "round 2 - round 1" in x)
    assert "wound bed -0.001, tissue mean +0.010" in round2 and "NOT met" in round2
    assert not any("plain captures" in x for x in lines)  # no plain arm given: no plain line

    by["pd"] = _scored(0.990, 0.950)  # room enough: no ceiling line
    by["pst-pred r2"] = _scored(0.971, 0.770)
    lines = targets(by)
    assert not any("the ceiling (pd" in x for x in lines)
    assert "(target: not below: met)" in next(x for x in lines if "round 2 - round 1" in x)
    assert not any("the loop's ceiling" in x for x in lines)
    by["pst-truth"] = _scored(0.975, 0.800)
    room = next(x for x in targets(by) if "the loop's ceiling" in x)
    assert "+0.005 wound bed, +0.040 tissue mean above round 1" in room
