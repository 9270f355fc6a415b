"""Metrics against hand-computed small cases."""

import numpy as np
import pytest

from labelsynth.classes import ClassInfo, ClassMap
from labelsynth.metrics import Counts, confusion_matrix, frame_counts, score_frames

CM = ClassMap.default()


def test_counts_formulas():
    c = Counts(tp=3, fp=1, fn=2, tn=10)
    assert c.dice == pytest.approx(6 / 9)
    assert c.recall == pytest.approx(3 / 5)
    assert c.precision == pytest.approx(3 / 4)
    assert c.iou == pytest.approx(3 / 6)
    assert c.present and c.predicted


def test_counts_empty_cases():
    both_empty = Counts(tn=5)
    assert both_empty.metrics() == {"dice": 1.0, "recall": 1.0, "precision": 1.0, "iou": 1.0}
    assert not both_empty.present
    missed = Counts(fn=4)  # truth has it, prediction has none
    assert missed.metrics() == {"dice": 0.0, "recall": 0.0, "precision": 0.0, "iou": 0.0}
    hallucinated = Counts(fp=4)  # prediction has it, truth none
    assert hallucinated.dice == 0.0 and hallucinated.recall == 0.0 and not hallucinated.present


def test_frame_counts_hand_case():
    truth = np.array([[0, 1, 1],
                      [0, 2, 2],
                      [0, 0, 255]], dtype=np.uint8)
    pred = np.array([[1, 1, 2],
                     [0, 2, 2],
                     [0, 0, 1]], dtype=np.uint8)  # the 1 under ignore must not count
    fc = frame_counts(pred, truth, CM)
    assert fc["granulation"] == Counts(tp=1, fp=1, fn=1, tn=5)
    assert fc["slough"] == Counts(tp=2, fp=1, fn=0, tn=5)
    assert fc["background"] == Counts(tp=3, fp=0, fn=1, tn=4)
    # wound bed: truth {1,2} at 4 px; pred wound bed at (0,0),(0,1),(0,2),(1,1),(1,2)
    assert fc["wound_bed"] == Counts(tp=4, fp=1, fn=0, tn=3)
    assert fc["wound_bed"].dice == pytest.approx(8 / 9)
    assert fc["necrotic"] == Counts(tn=8)
    assert sum(confusion_matrix(pred, truth).ravel()) == 8


def test_ignore_everywhere_gives_no_population():
    truth = np.full((2, 2), 255, np.uint8)
    pred = np.ones((2, 2), np.uint8)
    fc = frame_counts(pred, truth, CM)
    assert all(c == Counts() for c in fc.values())


def test_population_rule_and_pooled():
    # frame A: granulation in truth, predicted half -> dice 2*2/(4+2)=2/3, recall 1/2
    ta = np.array([[1, 1, 1, 1], [0, 0, 0, 0]], np.uint8)
    pa = np.array([[1, 1, 0, 0], [0, 0, 0, 0]], np.uint8)
    # frame B: granulation absent in truth but predicted -> not in granulation population
    tb = np.array([[2, 2, 0, 0], [0, 0, 0, 0]], np.uint8)
    pb = np.array([[2, 2, 1, 1], [0, 0, 0, 0]], np.uint8)
    # frame C: granulation absent in both -> not in population either
    tc = np.zeros((2, 4), np.uint8)
    pc = np.zeros((2, 4), np.uint8)
    s = score_frames([pa, pb, pc], [ta, tb, tc], CM, names=["a", "b", "c"])
    rows = {r["class"]: r for r in s.table()}
    g = rows["granulation"]
    assert g["n"] == 1
    assert g["dice"] == pytest.approx(2 / 3)
    assert g["recall"] == pytest.approx(0.5)
    assert g["precision"] == pytest.approx(1.0)
    assert g["iou"] == pytest.approx(0.5)
    # slough only in frame B, predicted exactly
    assert rows["slough"]["n"] == 1 and rows["slough"]["dice"] == pytest.approx(1.0)
    # wound bed: frames A and B have it; C does not
    wb = rows["wound_bed"]
    assert wb["n"] == 2
    # A: tp 2 fn 2 -> dice 2/3 ; B: tp 2 fp 2 -> dice 4/6
    assert wb["dice"] == pytest.approx(2 / 3)
    assert wb["recall"] == pytest.approx((0.5 + 1.0) / 2)
    # necrotic: nobody has it -> metrics None, n 0
    assert rows["necrotic"]["n"] == 0 and rows["necrotic"]["dice"] is None
    # pooled granulation counts include B's false positives
    assert s.pooled("granulation") == Counts(tp=2, fp=2, fn=2, tn=18)
    pooled = {r["class"]: r for r in s.table(pooled=True)}
    assert pooled["granulation"]["dice"] == pytest.approx(4 / 8)
    assert pooled["granulation"]["n"] == 1
    assert pooled["necrotic"]["dice"] is None
    assert s.population("granulation") == [0]
    assert [r["class"] for r in s.table()][0] == "wound_bed"


def test_summary_line_and_frame_table():
    t = np.array([[1, 0]], np.uint8)
    s = score_frames([t], [t], CM)
    line = s.summary_line()
    assert "wound bed: Dice 1.000 recall 1.000 (n=1)" in line
    assert "slough: -" in line and "background" not in line
    ft = s.frame_table()
    assert len(ft) == len(CM.names) + 1
    assert {r["class"] for r in ft if r["in_population"]} == {"wound_bed", "granulation", "background"}
    d = s.to_dict()
    assert set(d) == {"mean", "pooled", "frames"}


def test_two_class_map_wound_bed_is_foreground():
    cm = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(7, "object", (255, 255, 255))))
    t = np.array([[7, 7, 0, 0]], np.uint8)
    p = np.array([[7, 0, 0, 0]], np.uint8)
    fc = frame_counts(p, t, cm)
    assert fc["wound_bed"] == fc["object"] == Counts(tp=1, fp=0, fn=1, tn=2)


def test_shape_mismatch_and_bad_lists():
    with pytest.raises(ValueError):
        frame_counts(np.zeros((2, 2), np.uint8), np.zeros((2, 3), np.uint8), CM)
    with pytest.raises(ValueError):
        score_frames([np.zeros((2, 2), np.uint8)], [], CM)


def test_one_metrics_module_for_report_train_and_evaluation():
    """``labelsynth.evaluation.metrics`` is the same module's names; the report and training
    score with ``labelsynth.metrics`` and do not load ``evaluation`` (not the product path)."""
    import subprocess
    import sys

    import labelsynth.evaluation.metrics as old
    import labelsynth.metrics as new

    assert old.Counts is new.Counts and old.score_frames is new.score_frames and old.frame_counts is new.frame_counts
    code = ("import sys, labelsynth.report, labelsynth.train.loop; "
            "print(sorted(m for m in sys.modules if m.startswith('labelsynth.evaluation')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_errors_far_from_edge_tells_a_wrong_region_from_a_wide_boundary():
    from labelsynth.metrics import errors_far_from_edge

    truth = np.zeros((60, 60), bool)
    truth[10:30, 10:30] = True
    wide = truth.copy()
    wide[9, 10:30] = True  # one row too many: at the edge
    assert errors_far_from_edge(wide, truth) == (20, 0)
    blob = truth.copy()
    blob[45:50, 45:50] = True  # a region labelled wrong, 15+ px from the truth
    assert errors_far_from_edge(blob, truth) == (25, 25)
    hole = truth.copy()
    hole[18:22, 18:22] = False  # a hole in the middle: 8+ px inside the edge
    assert errors_far_from_edge(hole, truth) == (16, 16)
    valid = np.ones_like(truth)
    valid[45:50, 45:50] = False  # errors where nothing counts are not errors
    assert errors_far_from_edge(blob, truth, valid) == (0, 0)
    assert errors_far_from_edge(blob, np.zeros_like(truth)) == (int(blob.sum()), int(blob.sum()))  # no edge
