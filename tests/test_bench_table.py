"""benchmarks/bench_table.py end to end with a few steps (the numbers mean nothing): one row per
seed scored as the table test scores, the overrides reach the expand, a rerun reuses the cached
expands, and a bad --seeds is one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from .conftest import REPO, run_benchmark

FEW_STEPS = ["geometry.iterations=20", "semantic.iterations=10", "render.mesh_resolution=32"]


def test_rows_per_seed_overrides_reach_the_expand_and_expands_are_cached(tmp_path: Path) -> None:
    args = ["--work", str(tmp_path), "--seeds", "0,1", *(w for o in FEW_STEPS for w in ("--set", o))]
    res = run_benchmark("bench_table.py", args)
    rows = [line for line in res.stdout.splitlines() if line.startswith("| 0 |") or line.startswith("| 1 |")]
    assert len(rows) == 2 and all(" of 971 |" in row for row in rows)  # every seed sees the whole white top
    result = json.loads((tmp_path / "bench_table.json").read_text())
    assert [r["seed"] for r in result["rows"]] == [0, 1] and result["overrides"] == FEW_STEPS
    runs = sorted(tmp_path.glob("*/seed*/run.json"))
    assert len(runs) == 2
    for path in runs:
        run = json.loads(path.read_text())
        assert run["geometry"]["iterations"] == 20 and run["recipe"]["semantic"]["iterations"] == 10
    for r in result["rows"]:
        assert 0 <= r["top_hit"] <= r["top"] == 971 and 0.0 <= r["dice"] <= 1.0 and r["backdrop"] > 100
    stamps = [p.stat().st_mtime_ns for p in runs]
    again = run_benchmark("bench_table.py", args)
    assert [p.stat().st_mtime_ns for p in runs] == stamps  # cached, not refitted
    assert again.stdout.splitlines()[-1] == res.stdout.splitlines()[-1]


def test_bad_seeds_is_one_line(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_table.py"), "--work", str(tmp_path),
                          "--seeds", "a,b"], capture_output=True, text=True)
    assert res.returncode != 0 and res.stderr.strip() == "--seeds: expected comma-separated integers, not 'a,b'"
