"""The field on captures of any shape: foreground Dice/recall, time and training PSNR.

One recipe for every capture (issue 12). Each CASE is a folder holding ``capture/`` (a
labelsynth capture with a few annotated frames) and ``truth/`` (a class-id mask for every
frame); the field learns from the annotations and is scored on the frames that were not
annotated. Cases:

    lego     the public NeRF-synthetic lego (../shared/data/lego): 100 views all around an
             object on white, 4 annotated
    wound    a one-sided synthetic wound capture (`labelsynth synth`, made here if missing)
    around   a wound wrapped around a limb, filmed all around (`labelsynth synth --layout
             all-around`, made here if missing)
    NAME=DIR any other case folder, e.g. a DTU scan converted by make_dtu_capture.py
             (real photographs of an object on a table; its licence keeps it out of the
             repository, so give its path)
    --real DIR   every case folder in DIR (real photographs converted by make_dtu_capture.py
             from the NeuS layout: DTU scans, H3DS heads; README, Captures of any shape)

    python benchmarks/bench_general.py --out /tmp/general                       # lego, wound, around
    python benchmarks/bench_general.py --out /tmp/general --case lego --case dtu65=/tmp/dtu65
    python benchmarks/bench_general.py --out /tmp/general --real /data/cases    # real photos only

Scored per case: foreground Dice and recall per view (mean and worst view), the share of the
wrong pixels farther than 5 px from the true edge (region errors rather than boundary ones),
the share of the pixels whose surface no annotated frame saw (``render.support``) and of the
wrong pixels that lie there, and the geometry stage's training PSNR, steps and samples per ray.

Every case runs in its own process, so each peak memory is that run's own. Prints one table
(foreground = every class but background; wound bed where the class table has one) and
writes OUT/bench_general.json.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
FAR_FROM_EDGE_PX = 5.0  # wrong pixels farther than this from the true edge are region errors, not boundary ones
DEFAULT_LEGO = REPO.parent / "shared" / "data" / "lego"


def synth_case(kind: str, root: Path, frames: int, width: int, height: int) -> Path:
    """The synthetic case folder, made once (``labelsynth synth`` writes capture/ and truth/)."""
    folder = root / f"synth-{kind}"
    if not (folder / "capture" / "transforms.json").is_file():
        from labelsynth.evaluation.synth import SynthConfig, synthesize

        cfg = SynthConfig(frames=frames, width=width, height=height, **({"layout": "all-around"} if kind == "around" else {}))
        synthesize(folder, cfg, force=True, progress=False)
    return folder


def run_case(name: str, folder: Path, out: Path, recipe: str, overrides: list[str], device: str,
             rescore: bool = False) -> dict:
    """expand from the annotations (or, with ``rescore``, reuse OUT), then score every frame
    that was not annotated."""
    import numpy as np

    from labelsynth.capture import load_capture
    from labelsynth.capture.masks import read_mask
    from labelsynth.metrics import Counts, errors_far_from_edge
    from labelsynth.pipeline import expand, score_against_truth, teaching_support
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    capture, truth = folder / "capture", folder / "truth"
    if rescore and (out / "run.json").is_file():
        run = json.loads((out / "run.json").read_text())
        seconds, geometry = run["seconds"], run["geometry"]
        wall = sum(seconds.values())
    else:
        t0 = time.time()
        result = expand(capture, out, labels="annotations", recipe=recipe, device=device, overrides=overrides,
                        force=True, progress=False, report=False)
        wall = time.time() - t0
        seconds, geometry = result.seconds, result.geometry
    cap = load_capture(capture)
    annotated = {f.name for f in cap.frames if f.annotation_path is not None}
    scores = score_against_truth(out, truth, cap.classes, exclude=annotated)
    bg = 0  # class id 0 is background in every class table (classes.py)
    # surface no annotated frame saw (render.support): where the head guessed a label
    view = FieldRenderer(RunFolder(out).load_field())
    support = teaching_support(view, cap, "annotations")
    caster, cams, index = view.render_caster(), cap.unit_cameras(), {n: i for i, n in enumerate(cap.names)}
    per_frame, pooled, frames, wrong, far, on_unseen = [], Counts(), {}, 0, 0, 0
    for name_ in sorted(set(cap.names) - annotated):
        pred = read_mask(out / "masks" / f"{name_}.png", None, cap.classes) != bg
        t = read_mask(truth / f"{name_}.png", None, cap.classes)
        valid = t != 255
        tf = (t != bg) & valid
        pf = pred & valid
        c = Counts(int((pf & tf).sum()), int((pf & ~tf).sum()), int((~pf & tf).sum()), int((~pf & ~tf & valid).sum()))
        pooled = pooled + c
        n_wrong, n_far = errors_far_from_edge(pf, tf, valid, FAR_FROM_EDGE_PX)
        wrong, far = wrong + n_wrong, far + n_far
        hit, points, faces, _ = caster.cast(*cams[index[name_]].rays())
        unseen = support.unseen(hit, points, faces).reshape(tf.shape)
        n_unseen_wrong = int(((pf != tf) & valid & unseen).sum())
        on_unseen += n_unseen_wrong
        frames[name_] = {"dice": c.dice, "recall": c.recall, "fp": c.fp, "fn": c.fn, "far_from_edge": n_far,
                         "unseen_share": float(unseen.mean()), "wrong_on_unseen": n_unseen_wrong,
                         "present": c.present}
        if c.present:
            per_frame.append((c.dice, c.recall))
    fg = np.array(per_frame) if per_frame else np.zeros((0, 2))
    worst = min((n for n in frames if frames[n]["present"]), key=lambda n: frames[n]["dice"], default=None)
    return {
        "case": name,
        "frames": len(cap),
        "annotated": sorted(annotated),
        "scored": len(cap) - len(annotated),
        "foreground_dice": float(fg[:, 0].mean()) if len(fg) else None,
        "foreground_recall": float(fg[:, 1].mean()) if len(fg) else None,
        "foreground_dice_min": float(fg[:, 0].min()) if len(fg) else None,
        "foreground_dice_pooled": pooled.dice,
        "worst_view": worst,
        # of the wrong foreground pixels, the share farther than FAR_FROM_EDGE_PX from the true edge
        "far_from_edge_share": far / wrong if wrong else 0.0,
        # of the wrong foreground pixels, the share on surface no annotated frame saw
        "wrong_on_unseen_share": on_unseen / wrong if wrong else 0.0,
        "unseen_share": float(np.mean([f["unseen_share"] for f in frames.values()])) if frames else 0.0,
        "per_frame": frames,
        "classes": [r for r in scores.table() if r["class"] != "background" and r["n"] > 0],
        "wall_s": wall,
        "seconds": seconds,
        "train_psnr": geometry.get("final_psnr"),
        "geometry_iterations": geometry.get("iterations"),
        "samples_per_ray": geometry.get("mean_samples_per_ray"),
        "init_shape": geometry.get("init_shape"),
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2,
        "recipe": recipe,
        "overrides": overrides,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="work folder (synthetic cases and outputs)")
    ap.add_argument("--case", action="append", default=[], help="lego | wound | around | NAME=DIR (repeatable)")
    ap.add_argument("--lego", type=Path, default=DEFAULT_LEGO)
    ap.add_argument("--real", type=Path, action="append", default=[],
                    help="a folder of case folders (capture/ + truth/), each one case named after its folder")
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--frames", type=int, default=50, help="frames of the synthetic cases")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--rescore", action="store_true", help="score an existing OUT/out-NAME instead of fitting again")
    ap.add_argument("--one", nargs=2, metavar=("NAME", "DIR"), help=argparse.SUPPRESS)  # internal: one case
    args = ap.parse_args()

    if args.one:
        name, folder = args.one
        res = run_case(name, Path(folder), args.out / f"out-{name}", args.recipe, args.overrides, args.device,
                       args.rescore)
        (args.out / f"case-{name}.json").write_text(json.dumps(res, indent=2, default=float))
        return

    args.out.mkdir(parents=True, exist_ok=True)
    cases: list[tuple[str, Path]] = []
    for root in args.real:
        found = sorted(d for d in root.iterdir() if (d / "capture").is_dir()) if root.is_dir() else []
        if not found:
            sys.exit(f"--real {root}: no case folders (capture/ and truth/) in it")
        cases += [(d.name, d) for d in found]
    for spec in args.case or ([] if args.real else ["lego", "wound", "around"]):
        if spec == "lego":
            cases.append(("lego", args.lego))
        elif spec in ("wound", "around"):
            cases.append((spec, synth_case(spec, args.out, args.frames, args.width, args.height)))
        elif "=" in spec:
            name, folder = spec.split("=", 1)
            cases.append((name, Path(folder)))
        else:
            sys.exit(f"--case {spec}: expected lego, wound, around or NAME=DIR")
    for name, folder in cases:
        if not (folder / "capture").is_dir() or not (folder / "truth").is_dir():
            sys.exit(f"{folder}: a case folder needs capture/ and truth/")

    rows = []
    for name, folder in cases:
        cmd = [sys.executable, __file__, "--out", str(args.out), "--recipe", args.recipe, "--device", args.device,
               "--one", name, str(folder)] + (["--rescore"] if args.rescore else [])
        for o in args.overrides:
            cmd += ["--set", o]
        print(f"[{name}] {folder}", flush=True)
        subprocess.run(cmd, check=True)
        rows.append(json.loads((args.out / f"case-{name}.json").read_text()))
        r = rows[-1]
        print(f"[{name}] foreground Dice {r['foreground_dice']:.3f} (worst view {r['foreground_dice_min']:.3f}) "
              f"recall {r['foreground_recall']:.3f}, {r['far_from_edge_share']:.0%} of the errors far from the edge, "
              f"{r['wrong_on_unseen_share']:.0%} on unseen surface ({r['unseen_share']:.1%} of the pixels), "
              f"psnr {r['train_psnr']:.2f} dB, {r['wall_s']:.0f} s", flush=True)

    print(f"\nrecipe {args.recipe} {' '.join(args.overrides)}")
    print(f"{'case':12s} {'frames':>6s} {'scored':>6s} {'fg dice':>7s} {'recall':>6s} {'worst':>5s} {'far>5px':>7s} "
          f"{'unseen':>6s} {'err-u':>5s} {'psnr':>6s} {'init':>6s} {'steps':>5s} {'spr':>5s} {'wall':>6s} "
          f"{'geometry':>8s} {'RSS GB':>6s}")
    for r in rows:
        print(f"{r['case']:12s} {r['frames']:6d} {r['scored']:6d} {r['foreground_dice']:7.3f} {r['foreground_recall']:6.3f} "
              f"{r['foreground_dice_min']:5.3f} {r['far_from_edge_share']:7.2f} {r['unseen_share']:6.3f} "
              f"{r['wrong_on_unseen_share']:5.2f} {r['train_psnr']:6.2f} "
              f"{r['init_shape']:>6s} {r['geometry_iterations']:5d} {r['samples_per_ray']:5.1f} {r['wall_s']:6.0f} "
              f"{r['seconds'].get('geometry', 0):8.0f} {r['peak_rss_gb']:6.2f}")
    print(f"\nfar>5px: share of the wrong pixels more than {FAR_FROM_EDGE_PX:g} px from the true edge; unseen: share "
          "of the pixels whose surface no annotated frame saw; err-u: share of the wrong pixels there")
    print("worst view per case (foreground Dice):")
    for r in rows:
        if r["worst_view"] is not None:
            print(f"  {r['case']}: {r['worst_view']} {r['per_frame'][r['worst_view']]['dice']:.3f}")
    print("\nper class (Dice / recall, frames not annotated):")
    for r in rows:
        print(f"  {r['case']}: " + ", ".join(f"{c['class']} {c['dice']:.3f}/{c['recall']:.3f}" for c in r["classes"]))
    (args.out / "bench_general.json").write_text(json.dumps(rows, indent=2, default=float))


if __name__ == "__main__":
    main()
