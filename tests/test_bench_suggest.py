"""benchmarks/bench_suggest.py end to end on a tiny all-around capture (the numbers mean nothing):
suggest fits the geometry with --fit-seed, every choice (the frame objective's too) expands from it
with that seed, spread's one-frame neighbours are spread's frames moved by one, the table has the
case's row, a rerun with another seed redoes the cached fit instead of reusing it, and --combine
tabulates both runs and counts each choice's cells against the threshold and the neighbours."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from .conftest import TINY_EXPAND, run_benchmark


def _bench(work: Path, seed: int) -> subprocess.CompletedProcess:
    return run_benchmark("bench_suggest.py", ["--work", str(work), "--cases", "around", "--ks", "2", "--random", "1",
                                              "--frames", "6", "--width", "48", "--height", "36", "--recipe", "fast",
                                              "--fit-seed", str(seed), *(w for o in TINY_EXPAND for w in ("--set", o))])


def test_fit_seed_reaches_suggest_and_every_expand(tmp_path: Path) -> None:
    res = _bench(tmp_path, 3)
    assert any(line.startswith("| around | 2 |") for line in res.stdout.splitlines())
    assert json.loads((tmp_path / "around" / "suggest" / "suggest.json").read_text())["seed"] == 3
    for choice in ("suggested", "frames", "appearance", "spread-earlier", "spread-later", "spread", "random0"):
        run = json.loads((tmp_path / "around" / "K2" / choice / "run.json").read_text())
        assert run["seed"] == 3 and len(run["annotated_frames"]) == 2
    summary = json.loads((tmp_path / "bench_suggest.json").read_text())
    row = summary["cases"][0]["by_k"]["2"]
    assert row["suggested"]["scored"] == row["frames"]["scored"] == row["spread"]["scored"] == 4  # 6 less the 2 chosen
    assert row["appearance"]["scored"] == 4
    # spread's frames moved one frame earlier and later: the benchmark's resolution
    frames = {c: json.loads((tmp_path / "around" / "K2" / c / "run.json").read_text())["annotated_frames"]
              for c in ("spread", "spread-earlier", "spread-later")}
    number = {c: [int(n.rsplit("_", 1)[1]) for n in f] for c, f in frames.items()}
    assert number["spread-earlier"] == [i - 1 for i in number["spread"]]
    assert number["spread-later"] == [i + 1 for i in number["spread"]]

    first = tmp_path / "seed3.json"
    first.write_text((tmp_path / "bench_suggest.json").read_text())
    res = _bench(tmp_path, 4)  # another seed on the same --work: the fit is redone, not reused
    assert "suggest fitted the geometry" in res.stdout + res.stderr
    assert json.loads((tmp_path / "around" / "suggest" / "suggest.json").read_text())["seed"] == 4
    assert json.loads((tmp_path / "around" / "K2" / "spread" / "run.json").read_text())["seed"] == 4

    # --combine: one row per case, K and choice over both runs, the differences from spread as mean ± sd
    both = [first, tmp_path / "bench_suggest.json"]
    table = run_benchmark("bench_suggest.py", ["--combine", *map(str, both)]).stdout
    runs = [json.loads(p.read_text())["cases"][0]["by_k"]["2"] for p in both]
    diffs = [r["frames"]["wound_bed"] - r["spread"]["wound_bed"] for r in runs]
    row = next(line for line in table.splitlines() if line.startswith("| around | 2 | frames |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3] == " ".join(f"{r['frames']['wound_bed']:.3f}" for r in runs)
    assert cells[4] == f"{np.mean(diffs):+.3f} ± {np.std(diffs, ddof=1):.3f}"
    assert any(line.startswith("| around | 2 | appearance |") for line in table.splitlines())
    # the summary under the table: per choice, the cells below the threshold and those at or above
    # the worse of spread's one-frame neighbours, from the same means
    spread = runs[0]["spread"]
    groups = ["wound_bed"] + (["tissue_mean"] if spread["tissue_mean"] not in (None, spread["wound_bed"]) else [])
    def mean_diff(choice, key):
        return np.mean([r[choice][key] - r["spread"][key] for r in runs])
    below = sum(mean_diff("frames", g) < -0.005 for g in groups)
    above = sum(mean_diff("frames", g) >= min(0.0, mean_diff("spread-earlier", g), mean_diff("spread-later", g))
                for g in groups)
    assert f"of {len(groups)} (case, K, class group) cells, mean over 2 run(s) minus spread:" in table
    assert f"  frames: {below} below -0.005; {above} at or above the worse of spread's one-frame neighbours" in table
    assert any(line.startswith("  spread-later: ") and "neighbours" not in line for line in table.splitlines())
