"""K synthetic captures through `labelsynth batch` (Ray) against the same K through a plain loop
of `pipeline.expand` in one process, on this machine.

    python benchmarks/bench_batch.py [--captures 3 --frames 12 --width 320 --height 240
                                      --recipe fast --report/--no-report --parallel --work DIR]

Prints Ray's own costs first (start, a cold worker's first task with the pipeline's imports, a
warm task's round trip, shutdown), then for each way: wall time, peak memory (the largest sum of RSS over the process and all
its descendants, sampled every 0.2 s from /proc: Ray's GCS, raylet and workers count), and for
batch Ray's overhead per capture = (batch wall - the sum of the expand times measured inside the
tasks) / K, also as a share of the loop's mean expand time. Batch asks for --threads CPUs per
capture, the loop's expand uses --threads torch threads: with --threads equal to the cores (the
default) both run one capture at a time, so the difference is Ray's cost alone; --parallel adds
a run with one CPU per capture (as many at once as the cores allow).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

PAGE = os.sysconf("SC_PAGE_SIZE")


def _tree_rss(root: int) -> int:
    """Bytes resident in ``root`` and every descendant (one pass over /proc)."""
    parent, rss = {}, {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
            fields = stat[stat.rindex(")") + 2:].split()
            parent[int(p.name)] = int(fields[1])
            rss[int(p.name)] = int((p / "statm").read_text().split()[1]) * PAGE
        except (OSError, ValueError, IndexError):
            continue
    total, todo = 0, [root]
    children: dict[int, list[int]] = {}
    for pid, ppid in parent.items():
        children.setdefault(ppid, []).append(pid)
    while todo:
        pid = todo.pop()
        total += rss.get(pid, 0)
        todo.extend(children.get(pid, []))
    return total


class PeakMemory:
    """Samples the process tree's RSS in a thread; ``peak`` in bytes."""

    def __enter__(self) -> "PeakMemory":
        self.peak, self._stop = 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _tree_rss(os.getpid()))
            self._stop.wait(0.2)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _tree_rss(os.getpid()))


def _import_pipeline() -> float:
    """In a worker: what a first task pays to import the pipeline (torch, OpenCV, ...)."""
    t0 = time.time()
    import labelsynth.pipeline  # noqa: F401

    return time.time() - t0


def _noop() -> int:
    return os.getpid()


def ray_costs(cpus: int) -> dict[str, float]:
    """Ray's fixed costs on this machine, apart from any fit: start, a cold worker's first task
    (importing the pipeline), a warm task's round trip, shutdown."""
    import ray

    t0 = time.time()
    ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING)
    start = time.time() - t0
    t0 = time.time()
    imported = ray.get(ray.remote(_import_pipeline).options(num_cpus=cpus).remote())
    first = time.time() - t0
    noop = ray.remote(_noop).options(num_cpus=cpus)
    ray.get(noop.remote())
    t0 = time.time()
    for _ in range(20):
        ray.get(noop.remote())
    warm = (time.time() - t0) / 20
    t0 = time.time()
    ray.shutdown()
    return {"start": start, "first task": first, "of which import": imported, "warm task": warm,
            "shutdown": time.time() - t0}


def _print_costs(cpus: int) -> None:
    costs = ray_costs(cpus)
    print("Ray's own costs: " + ", ".join(f"{k} {v:.2f} s" for k, v in costs.items())
          + f", load {open('/proc/loadavg').read().split()[:3]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--recipe", default="fast")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe override for every expand (as expand's --set)")
    ap.add_argument("--report", action=argparse.BooleanOptionalAction, default=False,
                    help="with each capture's consistency report (its leave-one-out refits)")
    ap.add_argument("--parallel", action="store_true", help="also batch with one core per capture")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                    help="compute threads of each expand: the loop's torch threads and batch's --cpus-per-capture "
                         "(default: every core)")
    ap.add_argument("--costs-only", action="store_true", help="only Ray's own costs (seconds, no fits)")
    ap.add_argument("--work", type=Path, default=None, help="folder for captures and outputs (default: a temp dir)")
    args = ap.parse_args()

    import cv2
    import torch

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    from labelsynth.batch import ExpandOptions, run_batch
    from labelsynth.evaluation.synth import SynthConfig, synthesize
    from labelsynth.pipeline import expand

    if args.costs_only:
        _print_costs(args.threads)
        return
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_batch_"))
    root = work / "captures"
    if root.exists():
        shutil.rmtree(root)
    t0 = time.time()
    for k in range(args.captures):
        made = synthesize(work / f"syn{k}", SynthConfig(frames=args.frames, annotated=min(4, args.frames // 3),
                                                        width=args.width, height=args.height, seed=k),
                          force=True, progress=False)
        shutil.copytree(made.capture_dir, root / f"c{k}")
    cores = os.cpu_count() or 1
    print(f"{args.captures} captures of {args.frames} frames at {args.width}x{args.height}, recipe {args.recipe}, "
          f"report={args.report}, {cores} cores, {args.threads} threads per expand; "
          f"synthesised in {time.time() - t0:.0f} s")

    import ray

    _print_costs(args.threads)
    rows = []
    # (label, CPUs per capture, CPUs of the Ray instance): the first runs one capture at a time
    runs = [(f"batch, {args.threads} CPUs per capture", args.threads, args.threads)]
    if args.parallel:
        runs.append(("batch, 1 CPU per capture", 1, cores))
    for label, cpus, ray_cpus in runs:
        out = work / f"batch_{cpus}"
        with PeakMemory() as mem:
            t0 = time.time()  # Ray's start and shutdown count: the CLI pays them too
            ray.init(address="local", num_cpus=ray_cpus, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
            try:
                result = run_batch(root, out, ExpandOptions(labels="annotations", recipe=args.recipe, device="cpu",
                                                            overrides=args.overrides, report=args.report),
                                   cpus_per_capture=cpus, force=True, progress=False)
            finally:
                ray.shutdown()
            wall = time.time() - t0
        failed = result.failed
        if failed:
            raise SystemExit(f"{label}: {len(failed)} failed: {failed[0].reason}")
        inside = [r.seconds for r in result.rows]
        overhead = (wall - sum(inside)) / args.captures if ray_cpus == cpus else None
        rows.append((label, wall, mem.peak, overhead))
        print(f"{label}: {wall:.1f} s wall, expand inside the tasks {', '.join(f'{t:.1f}' for t in inside)} s, "
              f"peak RSS {mem.peak / 2**30:.2f} GB, load {open('/proc/loadavg').read().split()[:3]}")

    loop_out = work / "loop"
    with PeakMemory() as mem:
        t0 = time.time()
        times = []
        for k in range(args.captures):
            t1 = time.time()
            expand(root / f"c{k}", loop_out / f"c{k}", labels="annotations", recipe=args.recipe, device="cpu",
                   overrides=args.overrides, force=True, progress=False, report=args.report)
            times.append(time.time() - t1)
        loop_wall = time.time() - t0
    mean_expand = sum(times) / len(times)
    rows.append(("loop of expand", loop_wall, mem.peak, None))
    print(f"loop: {loop_wall:.1f} s wall, expand per capture {', '.join(f'{t:.1f}' for t in times)} s, "
          f"peak RSS {mem.peak / 2**30:.2f} GB, load {open('/proc/loadavg').read().split()[:3]}")

    print()
    print("| way | wall | per capture | peak RSS | Ray overhead per capture |")
    print("|---|---|---|---|---|")
    for label, wall, peak, overhead in rows:
        ov = "–" if overhead is None else f"{overhead:.1f} s ({100 * overhead / mean_expand:.1f}% of {mean_expand:.1f} s)"
        print(f"| {label} | {wall:.1f} s | {wall / args.captures:.1f} s | {peak / 2**30:.2f} GB | {ov} |")
    print(f"\nbatch ({rows[0][0]}) vs loop, wall: {100 * (rows[0][1] - loop_wall) / loop_wall:+.1f}%")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
