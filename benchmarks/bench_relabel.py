"""`labelsynth relabel` and `labelsynth export` on the 50-frame 640x480 wound (issue 28's targets).

    python benchmarks/bench_relabel.py --capture /tmp/s50/capture --truth /tmp/s50/truth \
        --root /tmp/bench_relabel [--recipe default] [--reuse]

1. **relabel, nothing changed**: `expand` once (ROOT/clean), then `relabel` copies of it with
   and without the report (targets: <= 90 s and <= 45 s on 2 CPU cores); the masks must be
   identical to the expand's (same geometry, same seed).
2. **a correction**: one of the 4 expert masks is corrupted (shifted by a fifth of the image
   width), `expand` (ROOT/corrupt), the report's flag is read, the mask is replaced by the
   truth and `relabel` runs: Dice on the frames nobody annotated must come back to the clean
   run's within 0.005.
3. **export**: `labelsynth export` of the relabelled OUT (50 real frames) in every format
   (target: < 10 s each).

Prints each step's wall time with its stage times and the load average before and after: a
time measured while other jobs share the cores is not a valid timing. ``--reuse`` keeps
finished expands of an earlier run of this script (the expands take minutes).
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np


def load() -> str:
    return "load average " + " ".join(f"{v:.1f}" for v in os.getloadavg())


def expand_once(capture: Path, out: Path, args) -> float | None:
    from labelsynth.pipeline import expand
    from labelsynth.rundir import RunFolder

    if args.reuse and RunFolder(out).is_finished(report=True):
        print(f"  reusing {out}")
        return None
    t0 = time.time()
    result = expand(capture, out, labels="annotations", recipe=args.recipe, device=args.device, force=True,
                    overrides=list(args.set), progress=False)
    wall = time.time() - t0
    print(f"  expand {out.name}: {wall:.1f} s ({stages(result.seconds)}; {load()})")
    return wall


def stages(seconds: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())


def relabel_copy(source: Path, out: Path, capture: Path, args, *, report: bool):
    from labelsynth.pipeline import relabel
    from labelsynth.rundir import RunFolder

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(source, out)
    before = load()
    t0 = time.time()
    result = relabel(out, capture=capture, report=report, device=args.device, progress=False)
    wall = time.time() - t0
    info = RunFolder(out).read_run()
    extra = f"; report steps: {stages(info.report_seconds)}" if info.report_seconds else ""
    print(f"  relabel {'with' if report else 'without'} the report: {wall:.1f} s "
          f"({stages(result.seconds)}{extra}; {before} -> {load()})")
    if report:
        print(f"    of which before the report (what --no-report runs: check, semantics, render): "
              f"{sum(v for k, v in result.seconds.items() if k != 'report'):.1f} s")
    return result, wall


def same_masks(a: Path, b: Path) -> tuple[int, int]:
    """(frames whose masks differ, pixels that differ) between two OUTs."""
    from labelsynth.rundir import RunFolder

    names = sorted(p.stem for p in RunFolder(a).masks_dir.glob("*.png"))
    ma, mb = RunFolder(a).read_masks(names), RunFolder(b).read_masks(names)
    diff = [int((ma[n] != mb[n]).sum()) for n in names]
    return sum(d > 0 for d in diff), sum(diff)


def dice_line(out: Path, truth: Path, classes, exclude: set[str]):
    from labelsynth.pipeline import score_against_truth

    return score_against_truth(out, truth, classes, exclude=exclude)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True)
    ap.add_argument("--truth", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=Path("/tmp/bench_relabel"))
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reuse", action="store_true", help="keep finished expands from an earlier run")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="recipe override for the expand (e.g. geometry.iterations=300 when the cores are shared: "
                         "relabel never re-fits the geometry, so its time does not depend on it)")
    ap.add_argument("--corrupt-run", choices=("expand", "reuse-geometry"), default="expand",
                    help="how the run on the corrupted capture is made: a full expand, or (to save one geometry fit "
                         "on busy cores) the clean run's geometry with the semantic stage trained on the corrupted "
                         "masks, i.e. a relabel of a copy of the clean run (the geometry is fitted on the images "
                         "alone, which the corruption does not touch)")
    ap.add_argument("--skip", default="", help="comma list of steps to skip: relabel, relabel-report (step 1 without its run with the report), "
                         "correction, export")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))

    import torch

    from labelsynth.capture import load_capture
    from labelsynth.export.formats import EXPORT_FORMATS, export_run
    from labelsynth.rundir import RunFolder

    args.root.mkdir(parents=True, exist_ok=True)
    print(f"capture {args.capture}, recipe {args.recipe}" + (f" with {', '.join(args.set)}" if args.set else "")
          + f", corrupt run by {args.corrupt_run}, skip {sorted(skip) or 'nothing'}, device {args.device}, torch threads "
          f"{torch.get_num_threads()}, {os.cpu_count()} cores; {load()}")
    capture = load_capture(args.capture)
    annotated = [f.name for f in capture.frames if f.annotation_path is not None]
    clean = args.root / "clean"
    print("1. relabel with nothing changed")
    expand_once(args.capture, clean, args)
    if "relabel" not in skip:
        for report in (False, True):
            if report and "relabel-report" in skip:
                print("  relabel with the report: skipped here (the correction's two relabels below run with it)")
                continue
            out = args.root / ("relabel-report" if report else "relabel-noreport")
            relabel_copy(clean, out, args.capture, args, report=report)
            frames, pixels = same_masks(clean, out)
            print(f"    masks identical to the expand's: {frames == 0} ({frames} frames, {pixels} pixels differ)")

    if "correction" not in skip:
        print("2. a corrected expert mask")
        bad = annotated[1]
        corrupt_cap = args.root / "corrupt-capture"
        if not (args.reuse and corrupt_cap.is_dir()):
            shutil.rmtree(corrupt_cap, ignore_errors=True)
            shutil.copytree(args.capture, corrupt_cap)
        path = corrupt_cap / "annotations" / f"{bad}.png"
        mask = cv2.imread(str(args.capture / "annotations" / f"{bad}.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), np.roll(mask, mask.shape[1] // 5, axis=1))
        corrupt = args.root / "corrupt"
        if args.corrupt_run == "expand":
            expand_once(corrupt_cap, corrupt, args)
        elif not (args.reuse and RunFolder(corrupt).is_finished(report=True)):
            print("  the corrupted run: the clean run's geometry, semantic stage and report from the corrupted masks")
            relabel_copy(clean, corrupt, corrupt_cap, args, report=True)
        flagged = RunFolder(corrupt).read_report_summary().get("flagged", [])
        print(f"  corrupted {bad} (shifted by a fifth of the width); the report flags {flagged}: "
              f"{'found' if bad in flagged else 'NOT found'}")
        shutil.copy(args.truth / f"{bad}.png", path)  # the annotator's fix
        fixed = args.root / "fixed"
        result, wall = relabel_copy(corrupt, fixed, corrupt_cap, args, report=True)
        print(f"    input masks changed: {result.masks_changed}; frames whose labels moved: "
              f"{sum(1 for v in result.pixels_changed.values() if v)}")
        scores = {name: dice_line(args.root / name, args.truth, capture.classes, set(annotated))
                  for name in ("clean", "corrupt", "fixed")}
        for name, s in scores.items():
            print(f"    {name:8s} {s.summary_line()}")
        dice = {name: {row["class"]: row["dice"] for row in s.table()} for name, s in scores.items()}
        gaps = {k: abs(dice["fixed"][k] - dice["clean"][k]) for k in dice["clean"]
                if dice["clean"][k] is not None and dice["fixed"][k] is not None}
        worst = max(gaps, key=gaps.get)
        print(f"    largest |Dice fixed - Dice clean| over the classes: {gaps[worst]:.4f} ({worst}); target <= 0.005: "
              f"{'met' if gaps[worst] <= 0.005 else 'NOT met'}")
        frames, pixels = same_masks(clean, fixed)
        print(f"    masks of the fixed run identical to the clean expand's: {frames == 0} ({frames} frames, "
              f"{pixels} pixels differ)")
        flagged = RunFolder(fixed).read_report_summary().get("flagged", [])
        print(f"    the relabelled report flags {flagged}")

    if "export" not in skip:
        print("3. export of 50 real frames")
        source = args.root / "fixed" if (args.root / "fixed").is_dir() else clean
        for fmt in EXPORT_FORMATS:
            to = args.root / "exports" / ("review.zip" if fmt == "cvat" else fmt)
            t0 = time.time()
            result = export_run(source, to, fmt=fmt, min_confidence=0.5, force=True, progress=False)
            size = to.stat().st_size if to.is_file() else sum(p.stat().st_size for p in to.rglob("*") if p.is_file())
            print(f"  {fmt:10s} {time.time() - t0:5.1f} s  {size / 2**20:6.1f} MiB  {len(result.frames)} frames  "
                  f"{result.ignored_pixels} ignore px ({load()})")
    for name in ("relabel-report", "fixed"):
        page = RunFolder(args.root / name).report_html
        if page.is_file():
            print(f"report.html of the {len(capture)} frames ({name}): {page.stat().st_size / 2**20:.2f} MiB")
            break


if __name__ == "__main__":
    main()
