"""Where do expanded labels train a better 2D segmenter? Scarce experts, self-training, varied frames.

    nice -n 5 python benchmarks/bench_retrain.py --out /tmp/retrain                  # the full scale (hours on 2 cores)
    nice -n 5 python benchmarks/bench_retrain.py --out /tmp/retrain --arms d,a1,b1   # some arms only
    python benchmarks/bench_retrain.py --out /tmp/retrain --table                    # print what is done

Captures are ``labelsynth synth`` captures (320x240, 50 frames): train seeds, one validation
seed (its exact truth validates every arm, so the curves are comparable) and test seeds, never
trained on. Every arm trains the same SegFormer-b0 with ``labelsynth.train.train`` (same steps,
batch, crop, augmentation and seed) and is scored by ``segment`` (its ONNX model, as a user runs
it) on every frame of the test captures against their exact truth (mean Dice over the frames
whose truth holds the class). Arms (``--arms``; K = expert frames per capture):

  scarce experts (plain captures)
    aK  the K expert frames of each train capture (capture folders: what a user has)
    bK  every frame, expanded from those K by ``labelsynth expand --labels annotations``, unweighted
    cK  (b') bK with each pixel weighted by its labels.h5 confidence
    fK  (b'') bK with pixels below a confidence floor (``--floor``) ignored
    eK  bK with the expert frames' pixels weighted ``--expert-weight`` (labels.h5 marks them annotated)
    a1-split  a1 with ``train``'s old default split: the last capture held out (trains on 5 frames)
    d   the exact truth of every frame: the ceiling
  self-training (plain captures; M0 = a1's model; new captures ``--self-seeds`` with 1 expert frame)
    st-raw       ``labelsynth selftrain --labels raw``: M0's masks of every frame as they are (i)
    st-pred      ``--labels predictions``: M0's masks fused by expand (ii); round 2: M1 -> masks -> fuse -> M2
    st-both      ``--labels both``: (ii) with each capture's expert frame (iii); round 2 likewise
    st-pred-warm st-pred with ``--warm-start``: each round's model starts from the previous one's weights
    st-pred-acc  st-pred with ``--accumulate``: round 2 trains on round 1's fused labels and its own
    st-pred-conf st-pred with each pixel weighted by its fused label's confidence (``train``'s default;
                 the other self-training arms train unweighted)
    st-pred-cross st-pred with ``--cross-fit``: from round 2, each capture segmented by a teacher trained on
                 the other captures' labels of the round before, not by M1, which learnt its own
    st-pred-agree st-pred with ``--agree``: from round 2, only the pixels whose fused class the round
                 before's labels give too (the others ignored)
    st-truth     the exact truth of every frame of the self-training captures: the loop's own ceiling
                 (what its rounds would reach were their fused labels perfect)
  varied frames (``synth --phone`` captures: exposure, white balance, blur, noise, JPEG, distance, zoom)
    pa1, pb1, pc1, pd   as a1, b1, c1, d on phone-like captures, tested on phone-like captures
    pst-raw, pst-pred, pst-both, pst-pred-warm, pst-pred-acc, pst-pred-conf, pst-pred-cross, pst-pred-agree, pst-truth   self-training on phone-like captures (``--phone-self-seeds``) from
                 M0 = pa1's model: the weak model whose masks disagree from view to view (it fails
                 where a video's exposure or distance drifts), the paper's main mode

The reduced run measured in docs/training.md (20 frames of 160x120, 3 train / 2 test / 2 self-training
captures, 400 steps of 4 crops of 96) is the command written there.

Expansion and self-training run through the command line (``labelsynth expand ... --no-report``,
``labelsynth selftrain``), whose contract does not change. Everything is cached under --out
(captures, views with K expert frames, expansions, models, masks, each arm's scores in
arms/<arm>.json), so a rerun skips what is done; --retrain redoes the models of the arms asked.
Printed: one table (test Dice per class, the quality of each arm's training labels against the
truth, training time), the targets, the confidence of the expanded labels, the ceiling's
validation curve; OUT/results.json and OUT/curves.png (every arm's validation curve).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TISSUES = ("granulation", "slough", "necrotic", "epithelial", "unknown")
PLAIN, PHONE = "plain", "phone"
VARIANTS = {"warm": ("--warm-start", "the model started from {source}'s weights"),
            "acc": ("--accumulate", "plus every earlier round's fused labels"),
            "conf": ("--confidence-weight", "each pixel weighted by its labels.h5 confidence (train's default)"),
            "cross": ("--cross-fit", "each capture's masks from a teacher trained on the other captures' labels"),
            "agree": ("--agree", "only the pixels whose class the round before's labels agree with")}
"""Self-training arm suffixes (st-pred-warm, ...): the selftrain option, and what the table says of it
(every other self-training arm trains unweighted, ``--no-confidence-weight``, like bK)."""


def _ints(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


class Bench:
    """The cached pieces: captures, views, expansions, models, scores."""

    def __init__(self, args) -> None:
        self.args = args
        self.root: Path = args.out
        self.seeds = {
            PLAIN: {"train": args.train_seeds, "val": [args.val_seed], "test": args.test_seeds, "self": args.self_seeds},
            PHONE: {"train": args.phone_train_seeds, "val": [args.phone_val_seed], "test": args.phone_test_seeds,
                    "self": args.phone_self_seeds},
        }
        self._classes = None

    # --- data ---------------------------------------------------------------------------------
    def synth(self, kind: str, seed: int) -> Path:
        """OUT/captures/<kind>/seed<S>/{capture,truth}, made once (no annotations: views hold them)."""
        from labelsynth.evaluation.synth import SynthConfig, synthesize

        out = self.root / "captures" / kind / f"seed{seed}"
        if not out.exists():
            a = self.args
            base = dict(frames=a.frames, annotated=0, width=a.width, height=a.height, seed=seed)
            cfg = SynthConfig.phone(**base) if kind == PHONE else SynthConfig(**base)
            t0 = time.perf_counter()
            synthesize(out, cfg, progress=False)
            log(f"synth {kind} seed {seed}: {time.perf_counter() - t0:.0f} s")
        return out

    def view(self, kind: str, seed: int, k: int | None) -> Path:
        """OUT/views/<kind>-K<k>/seed<S>: the capture with K expert frames (their exact truth,
        spread as ``synth --annotated K`` spreads them); k=None: every frame's truth."""
        from labelsynth.capture.view import capture_view
        from labelsynth.evaluation.synth import annotated_indices

        base = self.synth(kind, seed)
        out = self.root / "views" / f"{kind}-{'all' if k is None else f'K{k}'}" / f"seed{seed}"
        if not out.exists():
            names = sorted(p.stem for p in (base / "truth").glob("*.png"))
            pick = range(len(names)) if k is None else annotated_indices(len(names), k)
            capture_view(base / "capture", out, annotations={names[i]: base / "truth" / f"{names[i]}.png" for i in pick})
        return out

    def expand(self, kind: str, seed: int, k: int) -> Path:
        """OUT/expanded/<kind>-K<k>/seed<S>: ``labelsynth expand VIEW --labels annotations --no-report``."""
        out = self.root / "expanded" / f"{kind}-K{k}" / f"seed{seed}"
        if not (out / "labels.h5").is_file():
            view = self.view(kind, seed, k)
            cmd = ["expand", str(view), "--out", str(out), "--labels", "annotations", "--recipe", self.args.recipe,
                   "--no-report", "--device", self.args.device, "--force"]
            for o in self.args.overrides:
                cmd += ["--set", o]
            self.cli(cmd, f"expand-{kind}-K{k}-seed{seed}")
        return out

    def cli(self, cmd: list[str], name: str) -> float:
        """Run ``labelsynth CMD`` (this checkout's, via ``python -m labelsynth.cli``); output in OUT/logs."""
        logs = self.root / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        log(f"labelsynth {' '.join(cmd)}")
        with open(logs / f"{name}.log", "w") as fh:
            rc = subprocess.call([sys.executable, "-m", "labelsynth.cli", *cmd], stdout=fh, stderr=subprocess.STDOUT)
        seconds = time.perf_counter() - t0
        if rc != 0:
            tail = (logs / f"{name}.log").read_text().strip().splitlines()[-3:]
            raise SystemExit(f"{name} failed (exit {rc}): {' / '.join(tail)}")
        log(f"{name}: {seconds:.0f} s")
        return seconds

    @property
    def classes(self):
        if self._classes is None:
            from labelsynth.classes import ClassMap

            self._classes = ClassMap.of_capture(self.synth(PLAIN, self.args.test_seeds[0]) / "capture")
        return self._classes

    def val_tissues(self, kind: str) -> list[str]:
        """The tissues the validation capture's truth holds (in any frame)."""
        from labelsynth.capture.masks import read_mask

        truth = self.synth(kind, self.seeds[kind]["val"][0]) / "truth"
        ids = set()
        for p in truth.glob("*.png"):
            ids |= set(np.unique(read_mask(p, None, self.classes)).tolist())
        return [c.name for c in self.classes.classes if c.id in ids and c.name in TISSUES]

    # --- scoring ------------------------------------------------------------------------------
    def score_dir(self, masks: Path, truth: Path, names: list[str] | None = None):
        from labelsynth.capture.masks import read_mask
        from labelsynth.metrics import score_frames

        names = names or sorted(p.stem for p in truth.glob("*.png"))
        preds = [read_mask(masks / f"{n}.png", None, self.classes) for n in names]
        truths = [read_mask(truth / f"{n}.png", None, self.classes) for n in names]
        return score_frames(preds, truths, self.classes, [f"{truth.parent.name}/{n}" for n in names])

    def test_scores(self, arm: str, model: Path, kind: str) -> tuple[dict, float, int]:
        """``segment`` every frame of the test captures with ``model``; Dice against the truth."""
        from labelsynth.train.segment import segment_capture

        scores, seconds, frames = [], 0.0, 0
        for s in self.seeds[kind]["test"]:
            base = self.synth(kind, s)
            out = self.root / "segment" / arm / f"{kind}-seed{s}"
            if not out.is_dir():
                # auto: onnxruntime's CUDA provider where it has one (onnxruntime-gpu), else the CPU; --device
                # cuda is for training and expand, and a CPU-only onnxruntime beside a CUDA torch is common.
                rep = segment_capture(base / "capture", model, out, device="auto", progress=False)
                seconds, frames = seconds + rep.seconds, frames + rep.frames
            scores.append(self.score_dir(out, base / "truth"))
        return summary(pool(scores)), seconds, frames

    def label_quality(self, mask_dirs: list[tuple[Path, Path]]) -> dict:
        """Training labels (mask folders) against the truth of the same frames, pooled."""
        return summary(pool([self.score_dir(m, t) for m, t in mask_dirs]))

    def confidence_stats(self, kind: str, k: int) -> dict:
        """How well the expanded labels' confidence separates right from wrong pixels (train seeds)."""
        from labelsynth.capture.masks import read_mask
        from labelsynth.export.labels_h5 import LabelsReader

        floor = self.args.floor
        right_conf, wrong_conf, n, n_right, kept, kept_right = [], [], 0, 0, 0, 0
        for s in self.seeds[kind]["train"]:
            reader = LabelsReader(self.expand(kind, s, k) / "labels.h5")
            truth_dir = self.synth(kind, s) / "truth"
            for i, name in enumerate(reader.frame_names):
                _, mask, conf = reader.read(i)
                truth = read_mask(truth_dir / f"{Path(name).stem}.png", None, self.classes)
                ok = mask == truth
                conf = conf.astype(np.float32)
                right_conf.append(float(conf[ok].sum()))
                wrong_conf.append(float(conf[~ok].sum()))
                n += ok.size
                n_right += int(ok.sum())
                keep = conf >= floor
                kept += int(keep.sum())
                kept_right += int((ok & keep).sum())
        n_wrong = n - n_right
        return {"pixel_accuracy": n_right / n, "mean_conf_right": sum(right_conf) / max(1, n_right),
                "mean_conf_wrong": sum(wrong_conf) / max(1, n_wrong), "floor": floor, "kept": kept / n,
                "accuracy_kept": kept_right / max(1, kept),
                "wrong_removed": 1 - (kept - kept_right) / max(1, n_wrong)}

    # --- training -----------------------------------------------------------------------------
    def train_cfg(self, **over):
        from labelsynth.train import TrainConfig

        a = self.args
        base = dict(arch=a.arch, encoder=a.encoder, steps=a.steps, batch_size=a.batch_size, crop=a.crop, lr=a.lr,
                    confidence_weight=False, min_confidence=0.0, expert_weight=1.0, val_split="none",
                    eval_every=max(1, a.steps // 10), device=a.device, seed=a.seed, input_size=a.input_size)
        return TrainConfig(**{**base, **over})

    def train(self, arm: str, sources: list[Path], kind: str, **over) -> dict:
        from labelsynth.train import train

        model_dir = self.root / "models" / arm
        report = model_dir / "train.json"
        if report.exists() and (model_dir / "model.onnx").exists() and not self.args.retrain_arm(arm):
            data = json.loads(report.read_text())
            if data["step"] == self.args.steps and not data["interrupted"]:
                return data
        val = self.view(kind, self.seeds[kind]["val"][0], None)
        holdout = over.pop("holdout", False)
        cfg = self.train_cfg(**over) if holdout else self.train_cfg(val_captures=[str(val)], **over)
        t0 = time.perf_counter()
        train([*sources] if holdout else [*sources, val], model_dir, cfg, force=True, progress=False,
              log=lambda m: log(f"{arm}: {m}"))
        log(f"{arm}: trained in {time.perf_counter() - t0:.0f} s")
        seg = self.root / "segment" / arm
        if seg.exists():  # masks of an earlier model
            import shutil

            shutil.rmtree(seg)
        return json.loads(report.read_text())

    def selftrain(self, mode: str, kind: str = PLAIN, variant: str = "") -> Path:
        """``labelsynth selftrain`` from M0 (a1's model; pa1's on phone-like captures) on the self-training
        captures (views with one expert frame), held out: the validation capture's every frame;
        ``variant``: a key of ``VARIANTS`` (its selftrain option) or ""."""
        a = self.args
        prefix = "p" if kind == PHONE else ""
        out = self.root / "selftrain" / _selftrain_folder(kind, mode, variant)
        m0 = self.root / "models" / f"{prefix}a1" / "model.onnx"
        if not m0.is_file():
            self.run_arm(f"{prefix}a1")
        rounds = {"raw": 1, "predictions": a.rounds, "both": a.both_rounds}[mode]
        done = out / "selftrain.json"
        arm = prefix + "st-" + {"predictions": "pred"}.get(mode, mode) + (f"-{variant}" if variant else "")
        if done.is_file() and len(json.loads(done.read_text()).get("rounds", [])) == rounds + 1 \
                and not a.retrain_arm(arm):
            return out
        if not self.seeds[kind]["self"]:
            raise SystemExit(f"{arm}: no self-training captures (--{'phone-' if prefix else ''}self-seeds)")
        caps = [str(self.view(kind, s, 1)) for s in self.seeds[kind]["self"]]
        cmd = ["selftrain", *caps, "--model", str(m0), "--out", str(out), "--labels", mode, "--rounds", str(rounds),
               "--holdout", str(self.view(kind, self.seeds[kind]["val"][0], None)), "--recipe", a.recipe,
               "--device", a.device,
               "--steps", str(a.steps), "--batch-size", str(a.batch_size), "--crop", str(a.crop), "--lr", str(a.lr),
               "--input-size", a.input_size, "--seed", str(a.seed),
               "--eval-every", str(max(1, a.steps // 10))]
        for o in a.overrides:
            cmd += ["--set", o]
        cmd.append("--confidence-weight" if variant == "conf" else "--no-confidence-weight")
        if variant and variant != "conf":
            cmd.append(VARIANTS[variant][0])
        if a.retrain_arm(arm):
            cmd.append("--force")
        self.cli(cmd, f"selftrain-{prefix}{mode}{f'-{variant}' if variant else ''}")
        return out

    def reseed(self, row: dict, seeds: list[int]) -> dict[str, dict]:
        """A self-training round's model trained again on the same labels with other training seeds.

        One loop's round 2 - round 1 mixes what its labels gained with what a training seed moves;
        retraining each round's fused labels (fixed) with several seeds separates the two. Same
        settings as the loop's own training (its holdout validates); warm-start and accumulated
        arms are not reseeded (their sources depend on the previous round's model)."""
        kind, arm, r = row["kind"], row["arm"], row["round"]
        short = arm.lstrip("p")[3:]
        short, _, variant = short.partition("-")
        if variant in ("warm", "acc"):
            return {}
        mode = {"raw": "raw", "pred": "predictions", "both": "both"}[short]
        out = self.root / "selftrain" / _selftrain_folder(kind, mode, variant) / f"round{r}"
        state = json.loads((out.parent / "selftrain.json").read_text())
        names = [Path(c).name for c in state["settings"]["captures"]]
        sources = [out / "labels" / f"{n}.h5" for n in names] if mode == "raw" else \
            [out / "expanded" / n / "labels.h5" for n in names]
        if variant == "agree" and r > 1:  # what the loop's own round trained on
            sources = [out / "agreed" / f"{n}.h5" for n in names]
        results = {}
        for s in seeds:
            if s == self.args.seed:
                continue
            name = f"{arm}-r{r}-s{s}"
            report = self.train(name, sources, kind, seed=s, confidence_weight=variant == "conf")
            test, _, _ = self.test_scores(name, self.root / "models" / name / "model.onnx", kind)
            results[str(s)] = {"test": test, "train_s": report["times"]["train_s"]}
            log(f"{name}: test wound bed Dice {fmt(test['classes']['wound_bed']['dice'])}, "
                f"tissue mean {fmt(test['tissue_mean_dice'])}")
        return results

    # --- arms ---------------------------------------------------------------------------------
    def run_arm(self, arm: str) -> dict:
        """Train (or read) the arm's model(s), score them; OUT/arms/<arm>.json (one entry per row)."""
        cache = self.root / "arms" / f"{arm}.json"
        if cache.is_file() and not self.args.retrain_arm(arm):
            rows = json.loads(cache.read_text())
            if all(r["steps"] == self.args.steps for r in rows):  # else the arm is redone at these steps
                return rows
        rows = self._run_arm(arm)
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps(rows, indent=2))
        return rows

    def _row(self, arm: str, regime: str, what: str, kind: str, model_dir: Path, report: dict, quality: dict | None,
             **extra) -> dict:
        test, seg_s, seg_n = self.test_scores(arm if "round" not in extra else f"{arm}-r{extra['round']}",
                                              model_dir / "model.onnx", kind)
        row = {"arm": arm, "regime": regime, "what": what, "kind": kind, "train_frames": report["split"]["train_frames"],
               "split": report["split"]["description"], "train_s": report["times"]["train_s"], "steps": report["step"],
               "test": test, "labels": quality, "segment_fps": seg_n / seg_s if seg_s else None,
               "model_dir": str(model_dir), **extra}
        log(f"{arm}{' round ' + str(extra['round']) if 'round' in extra else ''}: test wound bed Dice "
            f"{fmt(test['classes']['wound_bed']['dice'])}, tissue mean {fmt(test['tissue_mean_dice'])}")
        return row

    def _run_arm(self, arm: str) -> list[dict]:
        a = self.args
        kind = PHONE if arm.startswith("p") else PLAIN
        name = arm[1:] if kind == PHONE else arm
        train_seeds = self.seeds[kind]["train"]
        regime = "varied frames" if kind == PHONE else "scarce experts"
        if name == "d":
            sources = [self.view(kind, s, None) for s in train_seeds]
            report = self.train(arm, sources, kind)
            return [self._row(arm, regime, "exact truth of every frame (ceiling)", kind, self.root / "models" / arm,
                              report, {"exact": True})]
        if name.startswith("a"):
            k = int(name[1:].split("-")[0])
            sources = [self.view(kind, s, k) for s in train_seeds]
            if name.endswith("-split"):
                report = self.train(arm, sources, kind, holdout=True, val_split="capture")
                what = f"{k} expert frame(s) per capture, the last capture held out for validation"
            else:
                report = self.train(arm, sources, kind)
                what = f"{k} expert frame(s) per capture"
            return [self._row(arm, regime, what, kind, self.root / "models" / arm, report, {"exact": True}, k=k)]
        if name[0] in "bcfe":
            k = int(name[1:])
            sources = [self.expand(kind, s, k) / "labels.h5" for s in train_seeds]
            over, what = {}, f"every frame expanded from {k} expert frame(s)"
            if name[0] == "c":
                over, what = {"confidence_weight": True}, what + ", confidence-weighted"
            elif name[0] == "f":
                over, what = {"min_confidence": a.floor}, what + f", confidence >= {a.floor:g}"
            elif name[0] == "e":
                over, what = {"expert_weight": a.expert_weight}, what + f", its expert frames weighted {a.expert_weight:g}x"
            report = self.train(arm, sources, kind, **over)
            quality = self.label_quality([(self.expand(kind, s, k) / "masks", self.synth(kind, s) / "truth")
                                          for s in train_seeds])
            return [self._row(arm, regime, what, kind, self.root / "models" / arm, report, quality, k=k)]
        if name == "st-truth":
            sources = [self.view(kind, s, None) for s in self.seeds[kind]["self"]]
            if not sources:
                raise SystemExit(f"{arm}: no self-training captures (--{'phone-' if kind == PHONE else ''}self-seeds)")
            report = self.train(arm, sources, kind)
            return [self._row(arm, "self-training" + (" (varied frames)" if kind == PHONE else ""),
                              "exact truth of every frame of the self-training captures (the loop's ceiling)", kind,
                              self.root / "models" / arm, report, {"exact": True})]
        if name.startswith("st-"):
            short, _, variant = name[3:].partition("-")
            mode = {"raw": "raw", "pred": "predictions", "both": "both"}[short]
            if variant and variant not in VARIANTS:
                raise SystemExit(f"unknown arm {arm!r}")
            out = self.selftrain(mode, kind, variant)
            state = json.loads((out / "selftrain.json").read_text())
            names = [Path(c).name for c in state["settings"]["captures"]]
            rows = []
            for r in range(1, len(state["rounds"])):
                here = out / f"round{r}"
                truth = [self.synth(kind, s) / "truth" for s in self.seeds[kind]["self"]]
                label_dirs = [here / "predictions" / n for n in names] if mode == "raw" else \
                    [here / "expanded" / n / "masks" for n in names]
                quality = self.label_quality(list(zip(label_dirs, truth)))
                quality["predictions"] = self.label_quality(list(zip([here / "predictions" / n for n in names], truth)))
                report = json.loads((here / "model" / "train.json").read_text())
                source = "M0" if r == 1 else f"M{r - 1}"
                cross = variant == "cross" and r > 1  # round 1's masks are M0's in every variant
                owner = "the fold teachers'" if cross else f"{source}'s"
                what = {"raw": f"{owner} masks of every frame, raw",
                        "predictions": f"{owner} masks fused by expand --labels predictions",
                        "both": f"{owner} masks + 1 expert frame fused by expand --labels both"}[mode]
                if variant and (variant != "cross" or cross):
                    what += ", " + VARIANTS[variant][1].format(source=source)
                regime = "self-training" + (" (varied frames)" if kind == PHONE else "")
                rows.append(self._row(arm, regime, what, kind, here / "model", report, quality, round=r))
            return rows
        raise SystemExit(f"unknown arm {arm!r}")


def _model_dir(root: Path, row: dict) -> Path:
    if "model_dir" in row:
        return Path(row["model_dir"])
    if row["arm"].lstrip("p").startswith("st-"):
        short = row["arm"].split("-", 1)[1]
        short, _, variant = short.partition("-")
        mode = {"raw": "raw", "pred": "predictions", "both": "both"}[short]
        folder = _selftrain_folder(PHONE if row["arm"].startswith("p") else PLAIN, mode, variant)
        return root / "selftrain" / folder / f"round{row['round']}" / "model"
    return root / "models" / row["arm"]


def _selftrain_folder(kind: str, mode: str, variant: str) -> str:
    """OUT/selftrain/<this>: a self-training arm's loop."""
    return (f"{kind}-{mode}" if kind == PHONE else mode) + (f"-{variant}" if variant else "")


def curve(root: Path, row: dict, present: list[str]) -> list[dict]:
    """The arm's validation curve from its train.json: loss, and the mean Dice of the tissues the
    validation capture's truth holds (a tissue it lacks has no Dice worth averaging, only false alarms)."""
    report = json.loads((_model_dir(root, row) / "train.json").read_text())
    out = []
    for h in report["history"]:
        dice = h.get("val_dice") or {}
        vals = [dice[t] for t in present if dice.get(t) is not None]
        out.append({"step": h["step"], "val_loss": h.get("val_loss"),
                    "val_tissue_mean": float(np.mean(vals)) if vals else None})
    return out


def pool(scores: list):
    """One Scores over several captures' frames."""
    from labelsynth.metrics import Scores

    return Scores(keys=scores[0].keys, frames=[f for s in scores for f in s.frames],
                  per_frame=[fc for s in scores for fc in s.per_frame])


def summary(scores) -> dict:
    """Per-class mean Dice/recall (paper rule) plus the mean Dice of the tissue classes present."""
    rows = {r["class"]: r for r in scores.table()}
    present = [t for t in TISSUES if t in rows and rows[t]["n"]]
    return {"classes": {k: {"dice": r["dice"], "recall": r["recall"], "n": r["n"]} for k, r in rows.items()},
            "tissue_mean_dice": float(np.mean([rows[t]["dice"] for t in present])) if present else None,
            "tissues_present": present}


# --- report ------------------------------------------------------------------------------------
def _label(row: dict) -> str:
    return f"{row['arm']}" + (f" r{row['round']}" if "round" in row else "")


def print_table(rows: list[dict]) -> str:
    lines = ["| regime | arm | training labels | frames | labels vs truth: wound bed / tissue mean | "
             "test wound bed Dice / recall | " + " | ".join(TISSUES) + " | tissue mean | train s |",
             "|---" * (len(TISSUES) + 8) + "|"]
    for r in rows:
        lab = r["labels"] or {}
        if lab.get("exact"):
            quality = "exact"
        else:
            quality = f"{fmt(lab['classes']['wound_bed']['dice'])} / {fmt(lab['tissue_mean_dice'])}"
        c = r["test"]["classes"]
        cells = [fmt(c[t]["dice"]) if c.get(t) and c[t]["n"] else "-" for t in TISSUES]
        lines.append(f"| {r['regime']} | {_label(r)} | {r['what']} | {r['train_frames']} | {quality} | "
                     f"{fmt(c['wound_bed']['dice'])} / {fmt(c['wound_bed']['recall'])} | " + " | ".join(cells)
                     + f" | **{fmt(r['test']['tissue_mean_dice'])}** | {r['train_s']:.0f} |")
    text = "\n".join(lines)
    print(text)
    return text


def _label_quality(row: dict) -> tuple[float | None, float | None]:
    """(wound bed, tissue mean) Dice of an arm's training labels against the truth, where measured."""
    q = row.get("labels") or {}
    wb = ((q.get("classes") or {}).get("wound_bed") or {}).get("dice")
    return wb, q.get("tissue_mean_dice")


def targets(by: dict[str, dict]) -> list[str]:
    """The issue's targets, each with its numbers (only where the arms exist)."""
    out = []

    def wb(a):
        return by[a]["test"]["classes"]["wound_bed"]["dice"]

    def tm(a):
        return by[a]["test"]["tissue_mean_dice"]

    if all(x in by for x in ("a1", "b1", "d")):
        gap = wb("d") - wb("a1")
        if gap > 0:
            closed = (wb("b1") - wb("a1")) / gap
            gap_text = f"(b) closes {closed:.0%} of it (target >= 50%: {'met' if closed >= 0.5 else 'NOT met'})"
        else:
            gap_text = "(d) is not above (a): no gap to close (target NOT met; the ceiling shows no room at this scale)"
        out.append(f"K=1: (b)-(a) tissue mean {tm('b1') - tm('a1'):+.3f} (target >= +0.05: "
                   f"{'met' if tm('b1') - tm('a1') >= 0.05 else 'NOT met'}); wound-bed gap of (a) to (d) "
                   f"{gap:+.3f}, {gap_text}")
        room = tm("d") - tm("a1")
        if room < 0.05:
            out.append(f"K=1: the ceiling (d) is only {room:+.3f} tissue mean above (a): a +0.05 gain would put (b) "
                       f"above training on the exact truth of every frame, so the target cannot be met at this scale")
        label_wb, label_tm = _label_quality(by["b1"])
        if label_tm is not None and label_tm < tm("a1"):
            out.append(f"K=1: (b)'s training labels score {label_tm:.3f} tissue mean against the truth, below what (a) "
                       f"reaches on the test captures ({tm('a1'):.3f}): the model learns the expansion's errors")
    for k in (2, 4):
        if f"a{k}" in by and f"b{k}" in by:
            line = (f"K={k}: (b)-(a) wound bed {wb(f'b{k}') - wb(f'a{k}'):+.3f}, tissue mean "
                    f"{tm(f'b{k}') - tm(f'a{k}'):+.3f}")
            if k == 4:
                worst = min(wb("b4") - wb("a4"), tm("b4") - tm("a4"))
                line += f" (target: no worse than -0.005: {'met' if worst >= -0.005 else 'NOT met'})"
            out.append(line)
    for p, where in (("", "plain captures, M0 = a1"), ("p", "varied frames, M0 = pa1")):
        if f"{p}st-raw r1" in by and f"{p}st-pred r1" in by:
            dw = wb(f"{p}st-pred r1") - wb(f"{p}st-raw r1")
            dt = tm(f"{p}st-pred r1") - tm(f"{p}st-raw r1")
            out.append(f"self-training ({where}): (ii)-(i) wound bed {dw:+.3f} (target >= +0.03: "
                       f"{'met' if dw >= 0.03 else 'NOT met'}), tissue mean {dt:+.3f} (target >= +0.05: "
                       f"{'met' if dt >= 0.05 else 'NOT met'})")
            ceiling = f"{p}d"
            room = wb(ceiling) - wb(f"{p}st-raw r1") if ceiling in by else None
            if room is not None and room < 0.03:
                out.append(f"self-training ({where}): the ceiling ({ceiling}, exact truth of every frame) is only "
                           f"{room:+.3f} wound bed above (i): a +0.03 gain would put (ii) "
                           f"above it, so that part of the target cannot be met with this M0")
        for mode in ("pred", "both", "pred-warm", "pred-acc", "pred-conf", "pred-cross", "pred-agree"):
            if f"{p}st-{mode} r1" in by and f"{p}st-{mode} r2" in by:
                dw = wb(f"{p}st-{mode} r2") - wb(f"{p}st-{mode} r1")
                dt = tm(f"{p}st-{mode} r2") - tm(f"{p}st-{mode} r1")
                label = {"pred": "ii", "both": "iii", "pred-warm": "ii, warm start", "pred-acc": "ii, accumulated labels",
                         "pred-conf": "ii, confidence-weighted", "pred-cross": "ii, cross-fitted teachers",
                         "pred-agree": "ii, labels both rounds agree on"}[mode]
                out.append(f"self-training ({where}, {label}): round 2 - round 1 wound bed "
                           f"{dw:+.3f}, tissue mean {dt:+.3f} (target: not below: "
                           f"{'met' if min(dw, dt) >= 0 else 'NOT met'})")
        if f"{p}st-truth" in by and f"{p}st-pred r1" in by:
            out.append(f"self-training ({where}): the loop's ceiling ({p}st-truth, exact truth of the self-training "
                       f"captures) is {wb(f'{p}st-truth') - wb(f'{p}st-pred r1'):+.3f} wound bed, "
                       f"{tm(f'{p}st-truth') - tm(f'{p}st-pred r1'):+.3f} tissue mean above round 1 of (ii): the room "
                       f"a second round has")
    return out


def reseed_table(rows: list[dict], seed: int) -> list[str]:
    """Each self-training round over its training seeds (the loop's own and ``--reseed``'s), and
    round 2 - round 1 paired by seed: the labels' gain with the training seed's spread beside it."""
    out = []
    by_arm: dict[str, dict[int, dict]] = {}
    for r in rows:
        if r.get("reseeds"):
            by_arm.setdefault(r["arm"], {})[r["round"]] = {seed: r["test"], **{int(k): v["test"] for k, v in
                                                                                 r["reseeds"].items()}}
    for arm, rounds in by_arm.items():
        def pair(test):
            return test["classes"]["wound_bed"]["dice"], test["tissue_mean_dice"]

        for rnd, tests in sorted(rounds.items()):
            vals = np.array([pair(t) for _, t in sorted(tests.items())])
            seeds_text = ", ".join(f"s{s} {fmt(pair(t)[0])} / {fmt(pair(t)[1])}" for s, t in sorted(tests.items()))
            out.append(f"{arm} round {rnd} over training seeds ({seeds_text}): wound bed {vals[:, 0].mean():.3f} "
                       f"± {vals[:, 0].std(ddof=1) if len(vals) > 1 else 0:.3f}, tissue mean {vals[:, 1].mean():.3f} "
                       f"± {vals[:, 1].std(ddof=1) if len(vals) > 1 else 0:.3f}")
        if 1 in rounds and 2 in rounds:
            common = sorted(set(rounds[1]) & set(rounds[2]))
            d = np.array([np.subtract(pair(rounds[2][s]), pair(rounds[1][s])) for s in common])
            if len(d):
                sd = d.std(axis=0, ddof=1) if len(d) > 1 else np.zeros(2)
                mean = d.mean(axis=0)
                out.append(f"{arm}: round 2 - round 1, paired over {len(d)} training seeds: wound bed "
                           f"{mean[0]:+.3f} ± {sd[0]:.3f}, tissue mean {mean[1]:+.3f} ± {sd[1]:.3f} (target: not "
                           f"below: {'met' if min(mean) >= 0 else 'NOT met'} on the mean; per seed "
                           + ", ".join(f"s{s} {x[0]:+.3f} / {x[1]:+.3f}" for s, x in zip(common, d)) + ")")
    return out


def plot_curves(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_loss) = plt.subplots(1, 2, figsize=(14, 5))
    for r in rows:
        pts = [(c["step"], c["val_tissue_mean"], c["val_loss"]) for c in r["curve"] if c["val_tissue_mean"] is not None]
        if pts:
            steps, dice, loss = zip(*pts)
            width = 2.5 if r["arm"] in ("d", "pd") else 1.2
            ax.plot(steps, dice, label=_label(r), lw=width)
            ax_loss.plot(steps, loss, label=_label(r), lw=width)
    ax.set_xlabel("step")
    ax.set_ylabel("validation Dice, mean of the tissues in its truth")
    ax.set_ylim(0.4, 1)
    ax.legend(fontsize=7, ncol=2)
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("validation loss (CE + Dice)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def scale(a) -> str:
    """What this run is: the sizes every arm shares (printed first and with the table)."""
    return (f"scale: {a.frames} frames of {a.width}x{a.height} per capture; plain: {len(a.train_seeds)} train, 1 validation, "
            f"{len(a.test_seeds)} test, {len(a.self_seeds)} self-training captures; phone: {len(a.phone_train_seeds)} train, "
            f"1 validation, {len(a.phone_test_seeds)} test, {len(a.phone_self_seeds)} self-training; every arm: {a.arch} {a.steps} steps, batch {a.batch_size}, "
            f"crop {a.crop}, lr {a.lr:g}, input {a.input_size}, seed {a.seed}; expand --recipe {a.recipe}"
            + (f" --set {' '.join(a.overrides)}" if a.overrides else "") + f"; {a.threads or 'default'} thread(s)")


DEFAULT_ARMS = "d,a1,b1,c1,f1,a1-split,st-raw,st-pred,st-both,a4,b4,c4,a2,b2,c2,pd,pa1,pb1,pc1,pst-raw,pst-pred,pst-both"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--arms", default=DEFAULT_ARMS, help="comma list, run in this order")
    ap.add_argument("--train-seeds", type=_ints, default=_ints("101,102,103,104,105,106"))
    ap.add_argument("--val-seed", type=int, default=201)
    ap.add_argument("--test-seeds", type=_ints, default=_ints("301,302,303"))
    ap.add_argument("--self-seeds", type=_ints, default=_ints("111,112,113,114,115,116"))
    ap.add_argument("--phone-train-seeds", type=_ints, default=_ints("121,122,123,124,125,126"))
    ap.add_argument("--phone-val-seed", type=int, default=221)
    ap.add_argument("--phone-test-seeds", type=_ints, default=_ints("321,322,323"))
    ap.add_argument("--phone-self-seeds", type=_ints, default=_ints("131,132,133,134,135,136"))
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--recipe", default="fast", help="expand recipe (report off)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="expand recipe override")
    ap.add_argument("--floor", type=float, default=0.5, help="confidence floor of the fK arms")
    ap.add_argument("--expert-weight", type=float, default=4.0, help="expert-frame weight of the eK arms")
    ap.add_argument("--rounds", type=int, default=2, help="self-training rounds of st-pred")
    ap.add_argument("--both-rounds", type=int, default=2, help="self-training rounds of st-both (more continue a run)")
    ap.add_argument("--arch", default="segformer")
    ap.add_argument("--encoder", default=None)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--crop", type=int, default=192)
    ap.add_argument("--lr", type=float, default=6e-4)
    ap.add_argument("--input-size", default="320x240")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--retrain", default="", help="comma list of arms whose models are redone ('all' for every arm)")
    ap.add_argument("--table", action="store_true", help="only print the table of the arms already done")
    ap.add_argument("--reseed", type=_ints, default=[],
                    help="training seeds (comma list) with which every self-training round's model is trained again "
                         "on the same labels (besides --seed's): round 2 - round 1 with the training seed's spread")
    ap.add_argument("--threads", type=int, default=0,
                    help="compute threads of this process and of the commands it runs (0: the libraries' default). "
                         "On 2 cores shared with other jobs (load 17), 1 thread ran a training step in 2.7 s, 2 in 14.5 s")
    args = ap.parse_args()
    if args.threads:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            os.environ[var] = str(args.threads)
        import cv2
        import torch

        torch.set_num_threads(args.threads)
        cv2.setNumThreads(args.threads)
    retrain = set(args.retrain.split(",")) if args.retrain else set()
    args.retrain_arm = lambda arm: "all" in retrain or arm in retrain
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")
    every = [*args.train_seeds, args.val_seed, *args.test_seeds, *args.self_seeds]
    phone = [*args.phone_train_seeds, args.phone_val_seed, *args.phone_test_seeds, *args.phone_self_seeds]
    if len(set(every)) != len(every) or len(set(phone)) != len(phone):
        raise SystemExit("train, validation, test and self-training seeds must all differ")

    args.out.mkdir(parents=True, exist_ok=True)
    bench = Bench(args)
    log(scale(args))
    t_all = time.perf_counter()
    arms = [a for a in args.arms.split(",") if a]
    rows: list[dict] = []
    for arm in arms:
        cache = args.out / "arms" / f"{arm}.json"
        if args.table:
            if cache.is_file():
                rows.extend(json.loads(cache.read_text()))
            continue
        rows.extend(bench.run_arm(arm))
    if not rows:
        raise SystemExit("no arm is done yet")
    if args.reseed:
        for r in rows:
            if r["arm"].lstrip("p").startswith("st-") and "round" in r and not args.table:
                r["reseeds"] = bench.reseed(r, args.reseed)
                cache = args.out / "reseeds" / f"{_label(r).replace(' ', '-')}.json"
                cache.parent.mkdir(parents=True, exist_ok=True)
                cache.write_text(json.dumps(r["reseeds"], indent=2))
            elif args.table:
                cache = args.out / "reseeds" / f"{_label(r).replace(' ', '-')}.json"
                if cache.is_file():
                    r["reseeds"] = json.loads(cache.read_text())
    by = {_label(r): r for r in rows}
    present = {kind: bench.val_tissues(kind) for kind in {r["kind"] for r in rows}}
    for r in rows:
        r["curve"] = curve(args.out, r, present[r["kind"]])
    confidence = {}
    for kind, k in sorted({(r["kind"], r["k"]) for r in rows if "k" in r and r["arm"].lstrip("p")[0] in "bcfe"}):
        confidence[f"{kind}-K{k}"] = bench.confidence_stats(kind, k)
    wall = time.perf_counter() - t_all

    print(f"\n{scale(args)}")
    print("\nHeld-out test captures: Dice (recall for the wound bed), mean over the frames whose truth holds the class; "
          "'labels vs truth' = the arm's training labels against the exact truth of the same frames:\n")
    table = print_table(rows)
    print()
    for line in targets(by):
        print(line)
    if confidence:
        print("\nConfidence of the expanded labels (train captures, every pixel):")
        for key, c in confidence.items():
            print(f"  {key}: pixel accuracy {c['pixel_accuracy']:.3f}; mean confidence right {c['mean_conf_right']:.3f}, "
                  f"wrong {c['mean_conf_wrong']:.3f}; >= {c['floor']:g}: keeps {c['kept']:.1%} of pixels at accuracy "
                  f"{c['accuracy_kept']:.3f}, removes {c['wrong_removed']:.1%} of the wrong ones")
    for r in rows:
        if r["arm"] in ("d", "pd"):
            points = ", ".join(f"{c['step']}: {fmt(c['val_tissue_mean'])}" for c in r["curve"])
            print(f"\nceiling ({r['arm']}) validation Dice (mean of {', '.join(present[r['kind']])}) by step: {points}")
    for r in rows:
        if r["arm"].lstrip("p").startswith("st-") and r["labels"].get("predictions"):
            p = r["labels"]["predictions"]
            print(f"{_label(r)}: the masks it was made from vs truth: wound bed {fmt(p['classes']['wound_bed']['dice'])}, "
                  f"tissue mean {fmt(p['tissue_mean_dice'])}")
    spread = reseed_table(rows, args.seed)
    if spread:
        print()
        for line in spread:
            print(line)
    plot_curves(rows, args.out / "curves.png")
    results = {"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "retrain_arm"},
               "rows": rows, "targets": targets(by), "reseed": spread, "confidence": confidence, "table": table, "wall_s": wall,
               "load": os.getloadavg()}
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"\nwall {wall:.0f} s (this run; cached parts skipped), load average {os.getloadavg()[0]:.1f}; "
          f"{args.out / 'results.json'}, {args.out / 'curves.png'}")


if __name__ == "__main__":
    sys.exit(main())
