"""How much an expert frame should weigh against predictions in ``expand --labels both``.

    nice -n 5 python benchmarks/bench_expert_weight.py --work /tmp/ew          # the default cases
    python benchmarks/bench_expert_weight.py --work /tmp/ew --weights 1,4 --cases s5:plain:4:5

Each case is a ``labelsynth synth`` capture (its noisy predictions of every frame and K exact
expert frames): ``expand --labels predictions`` fits the geometry and fuses the predictions alone;
then ``expand --labels both --geometry`` (the same geometry, semantic stage only) once per
``semantic.expert_weight`` in --weights. Scored against the exact truth on the frames that carry
no expert mask: wound bed Dice and the mean Dice of the tissues present. Every expand is a CLI
call (what a user runs) and cached under --work: WORK/NAME (the synth output), WORK/NAME-pred,
WORK/NAME-both<W> (a finished output is not redone).

A case is NAME:plain|phone:K:SEED (K expert frames; phone = ``synth --phone``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

DEFAULT_CASES = "s111:plain:1:111,s112:plain:1:112,s5:plain:4:5,p131:phone:1:131,p132:phone:1:132"


def run(cmd: list[str], log: Path) -> None:
    with log.open("w") as fh:
        res = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
    if res.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed: see {log}")


def finished(out: Path) -> bool:
    return (out / "run.json").is_file()


def case_runs(work: Path, name: str, kind: str, k: int, seed: int, args) -> dict[str, Path]:
    cli = [sys.executable, "-m", "labelsynth.cli"]
    synth = work / name
    if not (synth / "truth").is_dir():
        run([*cli, "synth", str(synth), "--frames", str(args.frames), "--width", str(args.width), "--height",
             str(args.height), "--annotated", str(k), "--seed", str(seed), *(["--phone"] if kind == "phone" else [])],
            work / f"{name}.synth.log")
    capture = synth / "capture"
    common = ["--recipe", args.recipe, "--no-report", "--force", *(w for o in args.overrides for w in ("--set", o))]
    outs = {"pred": work / f"{name}-pred"}
    if not finished(outs["pred"]):
        run([*cli, "expand", str(capture), "--out", str(outs["pred"]), "--labels", "predictions", *common],
            work / f"{name}-pred.log")
    for w in args.weights:
        out = outs[f"both{w:g}"] = work / f"{name}-both{w:g}"
        if not finished(out):
            run([*cli, "expand", str(capture), "--out", str(out), "--labels", "both", "--geometry", str(outs["pred"]),
                 "--set", f"semantic.expert_weight={w:g}", *common], work / f"{name}-both{w:g}.log")
    return outs


def scores(synth: Path, out: Path) -> tuple[float, float]:
    """Wound bed and tissue-mean Dice on the frames without an expert mask (bench_suggest's scoring)."""
    from bench_suggest import scores_of

    from labelsynth.capture import load_capture

    experts = sorted(p.stem for p in (synth / "capture" / "annotations").glob("*.png"))
    result = scores_of(out, synth / "truth", load_capture(synth / "capture").classes, experts)
    return result["wound_bed"], result["tissue_mean"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--cases", default=DEFAULT_CASES, help="NAME:plain|phone:K:SEED, comma separated")
    ap.add_argument("--weights", default="1,2,4", help="semantic.expert_weight values")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--recipe", default="fast")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="recipe override of every expand")
    args = ap.parse_args()
    args.weights = [float(w) for w in args.weights.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")
    arms = ["pred", *(f"both{w:g}" for w in args.weights)]
    lines = ["| case | expert frames | " + " | ".join(f"{a}: wb / tissue mean" for a in arms) + " |",
             "|---|---|" + "---|" * len(arms)]
    means: dict[str, list[tuple[float, float]]] = {a: [] for a in arms}
    for spec in args.cases.split(","):
        name, kind, k, seed = spec.split(":")
        outs = case_runs(args.work, name, kind, int(k), int(seed), args)
        row = {a: scores(args.work / name, outs[a]) for a in arms}
        for a in arms:
            means[a].append(row[a])
        lines.append(f"| {name} ({kind}, seed {seed}) | {k} | " + " | ".join(f"{wb:.3f} / {tm:.3f}" for wb, tm in row.values()) + " |")
        print(lines[-1], flush=True)
    lines.append("| mean | | " + " | ".join(f"{np.mean([s[0] for s in means[a]]):.3f} / {np.mean([s[1] for s in means[a]]):.3f}"
                                           for a in arms) + " |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
