"""Does training on labelsynth's expanded labels give a better 2D segmenter than the 4 expert frames?

    python benchmarks/bench_retrain.py --out /tmp/retrain            # the README's run
    python benchmarks/bench_retrain.py --out /tmp/retrain --prepare-only

Train captures (``--train-seeds``) and test captures (``--test-seeds``, never trained on) are
``labelsynth synth`` captures; one more seed (``--val-seed``) is the validation capture of every
arm (its exact truth, so the validation curves of the arms are comparable). Each train capture is
expanded once with ``expand --labels annotations`` (``--recipe``, report off). Arms, all with the
same architecture, optimiser steps, batch, crop and augmentation (``labelsynth.train.train``):

  a  the expert-annotated frames of each train capture (the capture folders: what a user has)
  b  every frame of each train capture as expanded (labels.h5), no confidence weighting
  c  (b) with each pixel weighted by its labels.h5 confidence
  d  the exact truth of every frame (a labels.h5 written from the synth truth): the ceiling

Score: ``segment`` (the ONNX model, as a user runs it) every frame of every test capture, then
Dice/recall per class and for the wound bed against the exact truth (``evaluation.metrics``,
the paper's per-frame population rule, all test frames pooled). Also printed, to explain the
result: the quality of the labels each arm trains on (expanded vs truth on the train captures)
and each model's score on one train capture (fit vs generalisation).

Everything is cached under --out (captures, expansions, truth labels.h5, models, masks), so a
rerun skips what is there; --retrain redoes the arms' models. Results: OUT/results-<arms>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

TISSUES = ("granulation", "slough", "necrotic", "epithelial", "unknown")


def _seeds(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- data --------------------------------------------------------------------------------------
def make_capture(root: Path, seed: int, args) -> Path:
    """OUT/captures/seed<S>/{capture,truth}, made once."""
    from labelsynth.evaluation.synth import SynthConfig, synthesize

    out = root / "captures" / f"seed{seed}"
    if not out.exists():
        t0 = time.perf_counter()
        synthesize(out, SynthConfig(frames=args.frames, annotated=args.annotated, width=args.width,
                                    height=args.height, seed=seed), progress=False)
        log(f"synth seed {seed}: {time.perf_counter() - t0:.0f} s")
    return out


def expand_capture(root: Path, seed: int, args) -> Path:
    """OUT/expanded/seed<S>/labels.h5 from ``expand --labels annotations``, made once."""
    from labelsynth.pipeline import expand

    out = root / "expanded" / f"seed{seed}"
    if not out.exists():
        t0 = time.perf_counter()
        expand(root / "captures" / f"seed{seed}" / "capture", out, labels="annotations", recipe=args.recipe,
               device=args.device, overrides=args.overrides, progress=False, report=False)
        log(f"expand seed {seed} (--recipe {args.recipe} --no-report): {time.perf_counter() - t0:.0f} s")
    return out / "labels.h5"


def truth_labels(root: Path, seed: int) -> Path:
    """OUT/truth/seed<S>/labels.h5: the capture's frames with their exact truth masks (confidence 1)."""
    from labelsynth.capture import load_capture
    from labelsynth.capture.masks import read_mask
    from labelsynth.export import write_labels_h5

    path = root / "truth" / f"seed{seed}" / "labels.h5"
    if not path.exists():
        cap_dir = root / "captures" / f"seed{seed}"
        cap = load_capture(cap_dir / "capture")
        path.parent.mkdir(parents=True, exist_ok=True)
        write_labels_h5(path, images=lambda i: cap.load_image(i),
                        masks=lambda i: read_mask(cap_dir / "truth" / f"{cap.frames[i].name}.png", None, cap.classes),
                        frame_names=cap.names, classes=cap.classes, annotated=np.ones(len(cap), dtype=bool),
                        source=cap_dir / "capture")
    return path


def score_masks(mask_dir: Path, truth_dir: Path, classes, names: list[str] | None = None):
    """Scores of mask_dir/<stem>.png against truth_dir/<stem>.png (every mask, or ``names``)."""
    from labelsynth.capture.masks import read_mask
    from labelsynth.evaluation.metrics import score_frames

    names = names or sorted(p.stem for p in mask_dir.glob("*.png"))
    preds = [read_mask(mask_dir / f"{n}.png", None, classes) for n in names]
    truths = [read_mask(truth_dir / f"{n}.png", None, classes) for n in names]
    return score_frames(preds, truths, classes, [f"{truth_dir.parent.name}/{n}" for n in names])


def pool(scores: list):
    """One Scores over several captures' frames."""
    from labelsynth.evaluation.metrics import Scores

    return Scores(keys=scores[0].keys, frames=[f for s in scores for f in s.frames],
                  per_frame=[fc for s in scores for fc in s.per_frame])


def summary(scores) -> dict:
    """Per-class mean Dice/recall (paper rule) plus the mean Dice of the tissue classes present."""
    rows = {r["class"]: r for r in scores.table()}
    present = [t for t in TISSUES if t in rows and rows[t]["n"]]
    out = {"classes": {k: {"dice": r["dice"], "recall": r["recall"], "n": r["n"]} for k, r in rows.items()},
           "tissue_mean_dice": float(np.mean([rows[t]["dice"] for t in present])) if present else None,
           "tissues_present": present}
    return out


# --- arms --------------------------------------------------------------------------------------
ARMS = {
    "a": "4 expert frames per train capture",
    "b": "every frame, expanded (annotations)",
    "c": "(b) + confidence weighting",
    "d": "exact truth of every frame (ceiling)",
}


def arm_sources(arm: str, root: Path, train_seeds: list[int]) -> tuple[list[Path], bool]:
    """The arm's training sources and whether pixels are weighted by confidence."""
    if arm == "a":
        return [root / "captures" / f"seed{s}" / "capture" for s in train_seeds], False
    if arm in ("b", "c"):
        return [root / "expanded" / f"seed{s}" / "labels.h5" for s in train_seeds], arm == "c"
    if arm == "d":
        return [root / "truth" / f"seed{s}" / "labels.h5" for s in train_seeds], False
    raise SystemExit(f"unknown arm {arm!r} (expected a, b, c, d)")


def run_arm(arm: str, root: Path, args) -> dict:
    from labelsynth.train import TrainConfig, train

    sources, conf_weight = arm_sources(arm, root, args.train_seeds)
    val = root / "truth" / f"seed{args.val_seed}" / "labels.h5"
    model_dir = root / "models" / arm
    result_file = model_dir / "train.json"
    if result_file.exists() and (model_dir / "model.onnx").exists() and not args.retrain:
        report = json.loads(result_file.read_text())
        log(f"arm {arm}: cached model ({report['times']['train_s']:.0f} s of training)")
        return report
    cfg = TrainConfig(arch=args.arch, encoder=args.encoder, steps=args.steps, batch_size=args.batch_size,
                      crop=args.crop, lr=args.lr, confidence_weight=conf_weight, val_captures=[str(val)],
                      eval_every=max(1, args.steps // 2), device=args.device, seed=args.seed,
                      input_size=args.input_size)
    t0 = time.perf_counter()
    train([*sources, val], model_dir, cfg, force=True, progress=False, log=lambda m: log(f"arm {arm}: {m}"))
    log(f"arm {arm}: trained in {time.perf_counter() - t0:.0f} s")
    return json.loads(result_file.read_text())


def segment_and_score(arm: str, root: Path, seeds: list[int], classes, args, tag: str) -> tuple[dict, float, int]:
    from labelsynth.train.segment import segment_capture

    scores, seconds, frames = [], 0.0, 0
    for s in seeds:
        cap_dir = root / "captures" / f"seed{s}"
        out = root / "segment" / arm / f"seed{s}"
        if not out.exists() or args.retrain:
            rep = segment_capture(cap_dir / "capture", root / "models" / arm / "model.onnx", out, device=args.device,
                                  progress=False)
            seconds += rep.seconds
            frames += rep.frames
        scores.append(score_masks(out, cap_dir / "truth", classes))
    return summary(pool(scores)), seconds, frames


# --- table -------------------------------------------------------------------------------------
def fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def print_table(results: dict, label_quality: dict | None) -> None:
    arms = [a for a in ARMS if a in results]
    keys = ["wound_bed", *TISSUES]
    print()
    print("Held-out test captures (Dice / recall, mean over frames whose truth has the class):")
    print("| arm | training labels | wound bed | " + " | ".join(TISSUES) + " | tissue mean Dice | train s |")
    print("|---" * (len(keys) + 4) + "|")
    for a in arms:
        r = results[a]
        cells = []
        for k in keys:
            c = r["test"]["classes"].get(k)
            cells.append("-" if not c or not c["n"] else f"{fmt(c['dice'])} / {fmt(c['recall'])}")
        print(f"| {a} | {ARMS[a]} | " + " | ".join(cells) + f" | {fmt(r['test']['tissue_mean_dice'])} | "
              f"{r['train_s']:.0f} |")
    ns = {k: results[arms[0]]["test"]["classes"][k]["n"] for k in keys if k in results[arms[0]]["test"]["classes"]}
    print("population n (frames): " + ", ".join(f"{k} {n}" for k, n in ns.items()))
    if all(a in results for a in "abd"):
        wb = {a: results[a]["test"]["classes"]["wound_bed"]["dice"] for a in "abd"}
        tm = {a: results[a]["test"]["tissue_mean_dice"] for a in "abd"}
        print(f"(b) - (a): wound bed {wb['b'] - wb['a']:+.3f} (target >= +0.05), tissue mean {tm['b'] - tm['a']:+.3f} "
              f"(target >= +0.05); (d) - (b): wound bed {wb['d'] - wb['b']:+.3f}, tissue mean {tm['d'] - tm['b']:+.3f} "
              "(target <= 0.03)")
    print()
    print("Each model on its first train capture (fit) vs the test captures (generalisation), Dice:")
    print("| arm | wound bed fit | wound bed test | tissue mean fit | tissue mean test | validation tissue mean Dice (last step) |")
    print("|---|---|---|---|---|---|")
    for a in arms:
        r = results[a]
        print(f"| {a} | {fmt(r['fit']['classes']['wound_bed']['dice'])} | {fmt(r['test']['classes']['wound_bed']['dice'])} | "
              f"{fmt(r['fit']['tissue_mean_dice'])} | {fmt(r['test']['tissue_mean_dice'])} | {fmt(r.get('val_tissue_mean'))} |")
    if label_quality:
        print()
        print("Label quality: the expanded labels of the train captures vs truth (every frame; Dice / recall):")
        for k in ["wound_bed", *TISSUES]:
            c = label_quality["classes"].get(k)
            if c and c["n"]:
                print(f"  {k}: {fmt(c['dice'])} / {fmt(c['recall'])} (n={c['n']})")
        print(f"  tissue mean Dice {fmt(label_quality['tissue_mean_dice'])}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--train-seeds", type=_seeds, default=_seeds("101,102,103"))
    ap.add_argument("--val-seed", type=int, default=201)
    ap.add_argument("--test-seeds", type=_seeds, default=_seeds("301,302"))
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--annotated", type=int, default=4)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--recipe", default="fast", help="expand recipe (report off)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="expand recipe override")
    ap.add_argument("--arms", default="abcd")
    ap.add_argument("--arch", default="segformer")
    ap.add_argument("--encoder", default=None)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--crop", type=int, default=192)
    ap.add_argument("--lr", type=float, default=6e-4)
    ap.add_argument("--input-size", default="320x240", help="frames are resized to this for training and segment")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--prepare-only", action="store_true", help="make the captures and expansions, then stop")
    ap.add_argument("--retrain", action="store_true", help="redo the models and their masks")
    args = ap.parse_args()
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")

    root = args.out
    root.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    every = [*args.train_seeds, args.val_seed, *args.test_seeds]
    if len(set(every)) != len(every):
        raise SystemExit("train, validation and test seeds must all differ")
    for s in every:
        make_capture(root, s, args)
    expanded = any(a in args.arms for a in "bc")  # only arms b and c train on expansions
    for s in args.train_seeds if expanded else []:
        expand_capture(root, s, args)
    for s in [*args.train_seeds, args.val_seed]:
        truth_labels(root, s)
    log(f"data ready under {root} ({time.perf_counter() - t_all:.0f} s)")
    if args.prepare_only:
        return

    from labelsynth.classes import ClassMap

    classes = ClassMap.of_capture(root / "captures" / f"seed{args.test_seeds[0]}" / "capture")
    label_quality = summary(pool([score_masks(root / "expanded" / f"seed{s}" / "masks",
                                              root / "captures" / f"seed{s}" / "truth", classes)
                                  for s in args.train_seeds])) if expanded else None
    results: dict[str, dict] = {}
    for arm in args.arms:
        report = run_arm(arm, root, args)
        test, seg_s, seg_frames = segment_and_score(arm, root, args.test_seeds, classes, args, "test")
        fit, _, _ = segment_and_score(arm, root, args.train_seeds[:1], classes, args, "fit")
        last = report["history"][-1].get("val_dice") or {}
        val_t = [last[t] for t in TISSUES if last.get(t) is not None]
        results[arm] = {"sources": report["sources"], "train_frames": report["split"]["train_frames"],
                        "train_s": report["times"]["train_s"], "steps": report["step"],
                        "segment_s": seg_s, "segment_frames": seg_frames, "test": test, "fit": fit,
                        "val_tissue_mean": float(np.mean(val_t)) if val_t else None,
                        "history": report["history"]}
        log(f"arm {arm}: test wound bed Dice {fmt(test['classes']['wound_bed']['dice'])}, tissue mean "
            f"{fmt(test['tissue_mean_dice'])}" + (f"; segment {seg_frames / seg_s:.1f} frames/s" if seg_s else ""))
    wall = time.perf_counter() - t_all
    (root / f"results-{''.join(args.arms)}.json").write_text(json.dumps({"args": {k: (str(v) if isinstance(v, Path) else v)
                                                            for k, v in vars(args).items()},
                                                   "label_quality": label_quality, "arms": results,
                                                   "wall_s": wall}, indent=2))
    print_table(results, label_quality)
    print(f"\nwall {wall:.0f} s (this run; cached steps skipped), load {os.getloadavg()[0]:.2f}; "
          f"results in {root / ('results-' + ''.join(args.arms) + '.json')}")


if __name__ == "__main__":
    sys.exit(main())
