"""Quality, wall time and peak memory of `labelsynth expand` on a synthetic capture.

    python benchmarks/bench_expand.py --synth /tmp/bench50            # makes the capture once
    python benchmarks/bench_expand.py --capture /tmp/bench50/capture --truth /tmp/bench50/truth \
        --labels annotations --recipe default --out /tmp/bench50/out-default

The report is built as `expand` builds it (``--no-report`` for masks only); its steps' times and
the frames it flags are printed. Prints Dice/recall per class and for the wound bed on the frames that were not annotated and,
with --labels predictions, the same for the automatic predictions themselves (the "2D" row).
Each configuration is one process, so the peak memory printed is that run's own.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synth", type=Path, help="make a synthetic capture here first (then exit)")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--capture", type=Path)
    ap.add_argument("--truth", type=Path)
    ap.add_argument("--labels", default="annotations", choices=["annotations", "predictions", "both"])
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--report", action=argparse.BooleanOptionalAction, default=True,
                    help="build the consistency report as `expand` does by default (--no-report: masks only)")
    args = ap.parse_args()

    if args.synth:
        subprocess.run(
            [sys.executable, "-m", "labelsynth.cli", "synth", str(args.synth), "--frames", str(args.frames),
             "--width", str(args.width), "--height", str(args.height), "--seed", str(args.seed), "--force"],
            check=True,
        )
        return

    from labelsynth.capture import load_capture
    from labelsynth.evaluation.metrics import score_frames
    from labelsynth.pipeline import expand, score_against_truth

    out = args.out or args.capture.parent / f"out-{args.recipe}-{args.labels}"
    t0 = time.time()
    result = expand(args.capture, out, labels=args.labels, recipe=args.recipe, device=args.device,
                    overrides=args.overrides, force=True, progress=False, report=args.report)
    wall = time.time() - t0
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    cap = load_capture(args.capture)
    annotated = set(result.annotated)
    field_scores = score_against_truth(out, args.truth, cap.classes, exclude=annotated)
    rows = {"field": field_scores.table()}
    if args.labels == "predictions":
        names = [f.name for f in cap.frames if f.name not in annotated and f.prediction_path is not None]
        preds = [cv2.imread(str(cap.frame(n).prediction_path), cv2.IMREAD_UNCHANGED) for n in names]
        truths = [cv2.imread(str(args.truth / f"{n}.png"), cv2.IMREAD_UNCHANGED) for n in names]
        rows["2d (predictions)"] = score_frames(preds, truths, cap.classes, names).table()

    print(f"recipe={args.recipe} labels={args.labels} frames={len(result.frames)} scored={len(result.frames) - len(annotated)}")
    print(f"wall {wall:.0f} s (" + ", ".join(f"{k} {v:.0f} s" for k, v in result.seconds.items()) + f"), peak RSS {peak_gb:.2f} GB")
    if args.report:
        run = json.loads((out / "run.json").read_text())
        report = json.loads((out / "report.json").read_text())
        phases = run.get("report_seconds", {})
        print("report: " + ", ".join(f"{k} {v:.1f} s" for k, v in phases.items()))
        flagged = report["summary"]["flagged"]
        loo = report["summary"]["median_loo_dice"].get("wound_bed")
        print(f"report flags: {', '.join(flagged) if flagged else 'none'}; median leave-one-out wound-bed Dice {loo}")
    print(f"{'method':18s} {'class':12s} {'dice':>6s} {'recall':>6s} {'n':>3s}")
    for method, table in rows.items():
        for row in table:
            if row["class"] == "background" or row["n"] == 0:
                continue
            print(f"{method:18s} {row['class']:12s} {row['dice']:6.3f} {row['recall']:6.3f} {row['n']:3d}")
    (out / "bench_expand.json").write_text(json.dumps(
        {"wall_s": wall, "peak_rss_gb": peak_gb, "seconds": result.seconds, "rows": rows,
         "recipe": args.recipe, "labels": args.labels, "report": args.report}, indent=2, default=float))


if __name__ == "__main__":
    main()
