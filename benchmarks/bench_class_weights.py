"""Class weighting x decision rule: one geometry fit, the semantic head refitted per scheme.

Scores the field's masks of the unannotated frames against exact truth, per class, for each
``semantic.class_weighting`` (``scheme`` or ``scheme:background_weight``) and each
``render.decision``, learning from the predictions and/or the annotations. Used to choose the
recipes' ``class_weighting: auto`` (README, Benchmarks).

    python benchmarks/bench_class_weights.py --capture /tmp/bench50/capture --truth /tmp/bench50/truth \\
        --schemes paper,uniform,equal-tissue:0.1,equal-tissue:0.3 --labels predictions,annotations
"""

from __future__ import annotations

import argparse
import time

from labelsynth.capture import load_capture
from labelsynth.device import pick_device
from labelsynth.evaluation.bench import load_truths
from labelsynth.evaluation.metrics import score_frames
from labelsynth.pipeline import fit_geometry, fit_semantics, labelled_frames
from labelsynth.recipe import load_recipe
from labelsynth.render.renderer import FieldRenderer
from labelsynth.semantics.config import DECISION_RULES


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--recipe", default="fast")
    ap.add_argument("--schemes", default="paper,uniform,equal-tissue")
    ap.add_argument("--decisions", default=",".join(DECISION_RULES))
    ap.add_argument("--labels", default="predictions,annotations")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--device", default="auto")
    args = ap.parse_args()

    capture = load_capture(args.capture)
    device = pick_device(args.device)
    annotated = {f.name for f in capture.frames if f.annotation_path is not None}
    scored = [n for n in capture.names if n not in annotated]
    truths = load_truths(args.truth, capture, scored)
    t0 = time.perf_counter()
    geometry, _ = fit_geometry(capture, load_recipe(args.recipe, args.overrides), device, progress=False)
    view = FieldRenderer(geometry)  # one surface for every scheme and rule
    print(f"geometry {time.perf_counter() - t0:.0f} s; scoring {len(scored)} unannotated frames", flush=True)
    cams = dict(zip(capture.names, capture.unit_cameras()))
    for mode in args.labels.split(","):
        baked = None  # the rays depend on the labels only: baked once per label source
        for spec in args.schemes.split(","):
            scheme, _, background = spec.partition(":")
            sets = [f"semantic.class_weighting={scheme}"] + ([f"semantic.background_weight={background}"] if background else [])
            geometry.recipe = load_recipe(args.recipe, args.overrides + sets)  # this benchmark's own field
            t0 = time.perf_counter()
            fit = fit_semantics(geometry, labelled_frames(capture, mode, geometry.recipe), baked=baked, progress=False)
            baked = fit.baked if baked is None else baked
            stats = vars(fit.stats)
            for rule in args.decisions.split(","):
                geometry.recipe.render.decision = rule
                masks = [view.render(cams[n], fit.head).mask for n in scored]
                scores = score_frames(masks, [truths[n] for n in scored], capture.classes, scored)
                cells = " ".join(f"{r['class']} {r['dice']:.3f}/{r['recall']:.3f}" for r in scores.table() if r["n"])
                print(f"{mode:11s} {spec:18s} ({stats['class_weighting']}) {rule:15s} "
                      f"{time.perf_counter() - t0:4.0f} s | {cells}", flush=True)


if __name__ == "__main__":
    main()
