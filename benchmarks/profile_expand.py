"""Where the time of one `labelsynth expand` goes: stage by stage, and inside each stage.

    python benchmarks/profile_expand.py CAPTURE --out OUT [--recipe default] [--labels annotations]
        [--set section.key=value ...] [--no-report] [--json PROFILE.json]

Runs the library's ``expand`` once (report on unless --no-report), with Python's cProfile
switched on around each stage (geometry, semantics, render, report; the report's
leave-one-out refits count as report time). Prints each stage's wall time and what share of
it went to the parts the speed work cares about: the hash-grid encoding (forward gathers,
hand-written backward), the MLPs, the rest of autograd's backward (eikonal second derivatives,
MLP backward), ray marching and the occupancy grid, the outer background, the optimiser,
dropout, ray casting and marching cubes, writing, and the own time of Python functions
(which includes tensor arithmetic written as operators: cProfile does not see it apart). cProfile adds a little
overhead of its own, so read shares, and take wall times from run.json of a plain run.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import resource
import sys
import time
from pathlib import Path

# (label, how to match a pstats entry, which time): "cum" = time inside the function and what it
# calls; "tot" = its own time only (for builtins, the C kernel itself).
PARTS: list[tuple[str, tuple[str, ...], str]] = [
    ("hash grid: index math (_lookup, corner weights)", ("encoding.py:_lookup", "encoding.py:_corner_weights"), "cum"),
    ("hash grid: backward (hand-written)", ("encoding.py:backward",), "cum"),
    ("gathers (index_select: hash tables)", ("~:<method 'index_select'",), "tot"),
    ("MLP layers (linear, relu, softplus)", ("~:<built-in method torch._C._nn.linear>", "~:<built-in method torch.relu_>",
                                             "~:<built-in method torch._C._nn.softplus>"), "tot"),
    ("autograd engine, other ops (eikonal 2nd order, MLP backward)", ("~:<method 'run_backward'",), "tot"),
    ("eikonal term, forward", ("training.py:_eikonal_loss",), "cum"),
    ("ray marching (march)", ("sampling.py:march",), "cum"),
    ("occupancy grid updates", ("sampling.py:update",), "cum"),
    ("outer background, forward", ("background.py:forward",), "cum"),
    ("optimiser (Adam)", ("adam.py:step",), "cum"),
    ("dropout", ("~:<built-in method torch.dropout>",), "tot"),
    ("semantic bake (sample_frozen)", ("training.py:sample_frozen",), "cum"),
    ("ray casting (Embree)", ("ray_pyembree.py:intersects_location",), "cum"),
    ("marching cubes + mesh", ("surface.py:extract_mesh",), "cum"),
    ("leave-one-out refits", ("pipeline.py:refit",), "cum"),
    ("pairwise check", ("consistency.py:pairwise_consistency",), "cum"),
    ("labelled mesh export", ("mesh.py:export_labelled_mesh",), "cum"),
    ("writing masks and labels.h5", ("dataset.py:add", "dataset.py:write_masks_png"), "cum"),
]


def _match(key: tuple[str, int, str], pattern: str) -> bool:
    filename, _, func = key
    where, _, name = pattern.partition(":")
    if where == "~":
        return filename == "~" and func.startswith(name)
    return filename.endswith(where) and func == name


def _parts(stats: pstats.Stats) -> dict[str, float]:
    out: dict[str, float] = {}
    python_own = 0.0
    for key, (_, _, tottime, cumtime, _) in stats.stats.items():  # type: ignore[attr-defined]
        if key[0] != "~" and not key[0].startswith("<"):
            python_own += tottime
    for label, patterns, which in PARTS:
        total = 0.0
        for key, (_, _, tottime, cumtime, _) in stats.stats.items():  # type: ignore[attr-defined]
            if any(_match(key, p) for p in patterns):
                total += cumtime if which == "cum" else tottime
        if total > 0:
            out[label] = total
    out["own time of Python functions (incl. tensor arithmetic written as operators)"] = python_own
    return out


class _StageProfiler:
    """Wraps the pipeline's stage functions: a profile per outermost stage call."""

    def __init__(self) -> None:
        self.profiles: dict[str, cProfile.Profile] = {}
        self.wall: dict[str, float] = {}
        self._active: str | None = None

    def wrap(self, name: str, fn):
        def run(*args, **kwargs):
            if self._active is not None:  # nested (the report's refits): counted in the outer stage
                return fn(*args, **kwargs)
            self._active = name
            prof = self.profiles.setdefault(name, cProfile.Profile())
            t0 = time.perf_counter()
            prof.enable()
            try:
                return fn(*args, **kwargs)
            finally:
                prof.disable()
                self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - t0
                self._active = None

        return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--labels", default="annotations", choices=["annotations", "predictions", "both"])
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--no-report", action="store_true")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    args = ap.parse_args()

    from labelsynth import pipeline

    prof = _StageProfiler()
    pipeline.fit_geometry = prof.wrap("geometry", pipeline.fit_geometry)
    pipeline.fit_semantics = prof.wrap("semantics", pipeline.fit_semantics)
    pipeline.render_outputs = prof.wrap("render", pipeline.render_outputs)
    pipeline._report = prof.wrap("report", pipeline._report)
    t0 = time.perf_counter()
    cpu0 = os.times()
    result = pipeline.expand(args.capture, args.out, labels=args.labels, recipe=args.recipe, device=args.device,
                             overrides=args.overrides, force=True, progress=False, report=not args.no_report)
    wall = time.perf_counter() - t0
    cpu = sum(os.times()[:2]) - sum(cpu0[:2])
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    run = json.loads((result.out / "run.json").read_text())

    print(f"expand {args.capture} --recipe {args.recipe} --labels {args.labels}"
          f"{' --no-report' if args.no_report else ''}: {wall:.1f} s wall, {cpu:.1f} s CPU, peak RSS {peak_gb:.2f} GB, "
          f"load average {open('/proc/loadavg').read().split()[0] if Path('/proc/loadavg').exists() else '?'}")
    report: dict = {"wall": wall, "cpu": cpu, "peak_rss_gb": peak_gb, "run_seconds": run["seconds"],
                    "report_seconds": run.get("report_seconds"), "stages": {}}
    for stage, p in prof.profiles.items():
        st_wall = prof.wall[stage]
        parts = _parts(pstats.Stats(p))
        print(f"\n{stage}: {st_wall:.1f} s (profiled)")
        for label, sec in sorted(parts.items(), key=lambda kv: -kv[1]):
            print(f"  {100 * sec / st_wall:5.1f} %  {sec:7.1f} s  {label}")
        report["stages"][stage] = {"seconds": st_wall, "parts": parts}
    if run.get("report_seconds"):
        print("\nreport phases (run.json):", ", ".join(f"{k} {v:.1f} s" for k, v in run["report_seconds"].items()))
    print("(parts overlap: 'cum' parts include what they call, e.g. the gathers inside the hash-grid forward)")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    sys.exit(main())
