"""benchmarks/bench_expert_weight.py end to end on a tiny capture (the numbers mean nothing): the
predictions-only expand fits the geometry, each weight's `--labels both` expand reuses it with
that expert weight, and every arm lands in the table."""

from __future__ import annotations

import json
from pathlib import Path

from .conftest import TINY_EXPAND, run_benchmark


def test_expert_weight_arms(tmp_path: Path) -> None:
    res = run_benchmark("bench_expert_weight.py", ["--work", str(tmp_path), "--cases", "t:plain:2:7", "--weights", "1,4",
                                                   "--frames", "4", "--width", "48", "--height", "36",
                                                   *(w for o in TINY_EXPAND for w in ("--set", o))])
    assert len(list((tmp_path / "t" / "capture" / "annotations").glob("*.png"))) == 2
    pred = json.loads((tmp_path / "t-pred" / "run.json").read_text())
    assert pred["labels"] == "predictions"
    for w in (1, 4):
        run = json.loads((tmp_path / f"t-both{w}" / "run.json").read_text())
        assert run["labels"] == "both" and run["recipe"]["semantic"]["expert_weight"] == w
    rows = [line for line in res.stdout.splitlines() if line.startswith("| t (plain, seed 7) | 2 |")]
    assert len(rows) == 2 and rows[0] == rows[1]  # printed as it is done, then in the table
    assert rows[0].count(" / ") == 3  # pred, both1, both4
    assert res.stdout.splitlines()[-1].startswith("| mean | |")
