"""Operator-level profile of the geometry stage: milliseconds per step over training, and which
torch operators a window of steps spends its time in.

    python benchmarks/profile_geometry.py CAPTURE [--recipe default] [--set section.key=value ...]
        [--window-start 900] [--window 40]

Runs the library's ``fit_geometry`` once (no semantics), times every step, and records
``--window`` steps from ``--window-start`` with ``torch.profiler`` (late steps are the costly
ones: every hash level is on and the band is tight, so more rays fit the sample budget).
Prints the median step time per hundred steps, the stage's time and final PSNR, and the
operator table sorted by own CPU time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile, schedule


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture")
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--window-start", type=int, default=900)
    ap.add_argument("--window", type=int, default=40)
    ap.add_argument("--rows", type=int, default=25)
    args = ap.parse_args()

    import labelsynth.geometry.training as geometry_training
    from labelsynth import pipeline
    from labelsynth.capture import load_capture
    from labelsynth.device import pick_device
    from labelsynth.recipe import load_recipe

    capture = load_capture(args.capture)
    recipe = load_recipe(args.recipe, args.overrides)
    stamps: list[float] = []
    next_ray_count = geometry_training._next_ray_count  # called once per step: the step clock

    def timed_step(*a):
        stamps.append(time.perf_counter())
        prof.step()
        return next_ray_count(*a)

    geometry_training._next_ray_count = timed_step
    window = schedule(wait=args.window_start, warmup=3, active=args.window, repeat=1)
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU], schedule=window) as prof:
        _, stats = pipeline.fit_geometry(capture, recipe, pick_device("auto"), progress=False)
    wall = time.perf_counter() - t0
    geometry_training._next_ray_count = next_ray_count
    steps = np.diff(stamps) * 1000
    print(f"geometry: {stats['seconds']:.1f} s for {stats['iterations']} steps ({wall:.1f} s with loading), "
          f"final PSNR {stats['final_psnr']:.2f} dB, {stats['mean_samples_per_ray']:.1f} samples per ray, "
          f"{torch.get_num_threads()} threads (steps {args.window_start}-{args.window_start + args.window} profiled)")
    for a in range(0, len(steps), 100):
        print(f"  steps {a:5d}-{a + 99:5d}: median {np.median(steps[a:a + 100]):6.1f} ms")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows))


if __name__ == "__main__":
    main()
