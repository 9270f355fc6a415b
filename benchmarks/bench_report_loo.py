"""Does a shorter leave-one-view-out refit judge the annotations as the full one does?

    python benchmarks/bench_report_loo.py CAPTURE [--recipe default] [--fractions 1,0.25,0.125]
        [--shift NAME] [--set section.key=value ...]

Fits the field once (geometry, then the head on the capture's annotations), then runs the
report's leave-one-out for every annotated frame at each ``report.loo_fraction`` given: a fresh
head trained on the other annotated frames for that fraction of the semantic stage's steps.
Prints, per fraction, the time of all refits and each frame's leave-one-out wound-bed Dice
against its own annotation, and the frames the report's rule flags. With ``--shift NAME``
that annotation is first moved sideways by a fifth of the image (in a copy of the capture),
so the flags have a known answer. Nothing in CAPTURE is changed.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--fractions", default="1,0.25,0.125")
    ap.add_argument("--shift", help="shift this frame's annotation first (a known bad annotation)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--device", default="auto")
    args = ap.parse_args()

    from labelsynth.capture import load_capture
    from labelsynth.classes import WOUND_BED
    from labelsynth.device import pick_device
    from labelsynth.pipeline import fit_geometry, fit_semantics, labelled_frames, leave_one_out_heads_of
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.recipe import load_recipe
    from labelsynth.report.consistency import Check, agreement, checked_keys, flag_frames, leave_one_out

    capture_dir = args.capture
    tmp = None
    if args.shift:
        tmp = Path(tempfile.mkdtemp(prefix="loo-bench-"))
        shutil.copytree(args.capture, tmp / "capture")
        capture_dir = tmp / "capture"
        path = next((capture_dir / "annotations").glob(f"{args.shift}.*"))
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), np.roll(mask, mask.shape[1] // 5, axis=1))
    try:
        capture = load_capture(capture_dir)
        recipe = load_recipe(args.recipe, args.overrides)
        device = pick_device(args.device)
        t0 = time.time()
        geometry, _ = fit_geometry(capture, recipe, device, progress=True)
        frames = labelled_frames(capture, "annotations", recipe)
        fit = fit_semantics(geometry, frames, progress=True)
        fitted = geometry.with_head(fit.head)
        view = FieldRenderer(fitted)
        print(f"field: {time.time() - t0:.0f} s (semantic stage {fit.stats.seconds:.1f} s, {fit.stats.iterations} steps)")
        ann = {f.name: f.mask for f in frames}
        names = [n for n in capture.names if n in ann]
        for fraction in [float(x) for x in args.fractions.split(",")]:
            fitted.recipe.report.loo_fraction = fraction
            t1 = time.time()
            heads = leave_one_out_heads_of(fitted, capture, "annotations", names, baked=fit.baked)
            loo = leave_one_out(view, capture, heads, progress=False)
            seconds = time.time() - t1
            dice = {n: agreement(ann[n], loo[n], capture.classes) for n in names}
            checks = [Check(n, "loo", {k: 1.0 - dice[n][k] for k in checked_keys(ann[n], loo[n], capture.classes)})
                      for n in names]
            flagged = sorted(n for n, (hit, _) in flag_frames(checks).items() if hit)
            row = ", ".join(f"{n} {dice[n][WOUND_BED]:.3f}" for n in names)
            print(f"loo_fraction {fraction:g}: {seconds:.1f} s for {len(names)} refits; wound-bed LOO Dice {row}; "
                  f"flagged: {', '.join(flagged) or 'none'}")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
