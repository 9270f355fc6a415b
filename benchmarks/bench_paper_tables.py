"""Reproduce the shape of the paper's Tables 1 and 2 on a synthetic capture.

Synthesises a capture (default: 50 frames at 640x480, 4 annotated, as in the paper's setting),
runs ``labelsynth.evaluation.bench.run_bench`` on it and prints the tables, the wall time and
the peak memory. A small smoke run:

    python benchmarks/bench_paper_tables.py --frames 8 --width 160 --height 120 --recipe fast

The full default run takes a while on a CPU; use ``--device cuda`` where there is one.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

from labelsynth.evaluation.bench import bench_markdown, run_bench
from labelsynth.evaluation.synth import SynthConfig, synthesize


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--annotated", type=int, default=4)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--noise", type=float, default=1.0, help="noise of the synthetic 2D predictions")
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="recipe override key=value")
    ap.add_argument("--perturb", default=None, help="comma list (default: all)")
    ap.add_argument("--methods", default=None, help="comma list (default: all)")
    ap.add_argument("--shared-geometry", action="store_true", help="half-frames: reuse the all-frames geometry")
    ap.add_argument("--out", type=Path, default=None, help="folder for the capture and results (default: a temp dir)")
    args = ap.parse_args(argv)

    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory(prefix="labelsynth-bench-")
        root = Path(tmp.name)
    else:
        root = args.out
        root.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        cfg = SynthConfig(frames=args.frames, annotated=args.annotated, width=args.width, height=args.height,
                          noise=args.noise, seed=args.seed)
        synth = synthesize(root / "synth", cfg, force=True)
        t_synth = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = run_bench(
            synth.capture_dir, synth.truth_dir, root / "bench", perturbations=args.perturb, methods=args.methods,
            recipe=args.recipe, device=args.device, overrides=args.overrides, seed=args.seed,
            half_geometry=not args.shared_geometry,
        )
        t_bench = time.perf_counter() - t0
        print(bench_markdown(result))
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        print(f"synth: {t_synth:.1f} s; bench: {t_bench:.1f} s; peak RSS {peak_mb:.0f} MiB")
        try:
            import torch

            if torch.cuda.is_available() and torch.cuda.max_memory_allocated() > 0:
                print(f"peak CUDA memory {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB")
        except Exception:  # pragma: no cover - torch is a dependency; be quiet if CUDA queries fail
            pass
        if tmp is None:
            print(f"results in {root / 'bench'}")
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
