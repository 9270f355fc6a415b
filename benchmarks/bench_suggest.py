"""Which frames to annotate: `suggest`'s coverage choice against spread:K and against the worst of
a few random K-subsets, by the Dice of the masks expanded from each choice.

Cases (every frame carries its exact truth as an annotation, so any choice can teach):

    wound-a, wound-b  one-sided synthetic wounds (`labelsynth synth`, seeds 11 and 12)
    around            a wound wrapped around a limb, filmed in one even turn (seed 13)
    uneven            the same scene and wobbles as `around` (seed 13), the turn dwelling on one side
                      of the limb for 3/4 of the frames (layout all-around-uneven)
    lego              the NeRF-synthetic lego (/work/shared/data/lego), every --lego-step-th view,
                      resized to --lego-size

Per case, `suggest --annotate max(K)` fits the geometry once (greedy: its first K frames are its
choice for every smaller K). Then for each K and each choice (suggested, the frame objective's choice
on the same geometry (`suggest --objective frames`, ``SurfaceViews.frame_choice``), the surface
objective with each sample weighted by the rarity of its colour (appearance, ``appearance_weights``), the frame
objective on the same weighted samples (frames-appearance), spread:K moved one frame earlier or later
(spread-earlier, spread-later: the benchmark's resolution), spread:K, --random subsets drawn with a fixed
seed) `expand --geometry SUGGEST_OUT --annotated-frames CHOICE --labels annotations --no-report`
(``pipeline.expand``, what the CLI calls), scored against the truth on the frames not chosen: wound
bed Dice and the mean Dice of the tissue classes present (the lego: foreground Dice, its one class).
"worst random" is the random subset of lowest wound-bed Dice. `--combine` ends with, per choice, the
(case, K, class group) cells below the threshold and those at or above the worse of spread's neighbours.
Targets (issue 27): suggested no worse than spread by more than 0.005 on any case and class group,
and better by at least 0.02 on the uneven capture.

`--timing`: the 50-frame 640x480 one-sided wound (seed 0), a full `expand --no-report` with the
default recipe, then `expand --geometry` of that output: wall time of each, their stage seconds
from run.json, and whether every mask is byte-identical (`--timing-only` writes
bench_suggest_timing.json). `--timing-suggest`: also `suggest --annotate 4` on that wound.

Everything is cached under --work (a finished suggest, expand or score is not redone):

    nice -n 5 python benchmarks/bench_suggest.py --work /tmp/bench_suggest --recipe fast \\
        --frames 30 --width 320 --height 240 --random 6
    nice -n 5 python benchmarks/bench_suggest.py --work /tmp/bench_suggest --timing-only --timing-suggest

Over several fits (one --work per --fit-seed), then one table of mean ± sd against spread:

    for s in 0 1 2; do python benchmarks/bench_suggest.py --work W/s$s --fit-seed $s ...; done
    python benchmarks/bench_suggest.py --combine W/s0/bench_suggest.json W/s1/bench_suggest.json W/s2/bench_suggest.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEFAULT_LEGO = next((p for p in (REPO.parent / "shared" / "data" / "lego", REPO.parent.parent / "shared" / "data" / "lego")
                     if p.is_dir()), REPO.parent / "shared" / "data" / "lego")  # /work/main or a worktree
SYNTH_CASES = {"wound-a": ("one-sided", 11), "wound-b": ("one-sided", 12), "around": ("all-around", 13),
               "uneven": ("all-around-uneven", 13)}
CHOICES = ("suggested", "frames", "appearance", "frames-appearance", "spread-earlier", "spread-later", "spread")
"""Each K's choices besides the random ones: suggest's (surface objective), the frame objective's,
the surface objective on samples weighted by the rarity of their colour (``appearance_weights``), the
frame objective on the same weighted samples, spread:K with each of its frames one frame earlier or
later (how far a choice one frame from spread's moves the scores: the benchmark's resolution),
spread:K (``--choices`` runs a subset)."""


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- cases ------------------------------------------------------------------------------------
def synth_case(folder: Path, layout: str, seed: int, frames: int, width: int, height: int) -> Path:
    if not (folder / "capture" / "transforms.json").is_file():
        from labelsynth.evaluation.synth import SynthConfig, synthesize

        synthesize(folder, SynthConfig(frames=frames, annotated=frames, width=width, height=height, seed=seed,
                                       layout=layout), force=True, progress=False)
    return folder


def lego_case(folder: Path, lego: Path, step: int, size: int) -> Path:
    """Every ``step``-th lego view at ``size`` pixels, its truth as the annotation of every frame."""
    if (folder / "capture" / "transforms.json").is_file():
        return folder
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    cap, truth = tmp / "capture", tmp / "truth"
    for sub in (cap / "images", cap / "annotations", truth):
        sub.mkdir(parents=True)
    data = json.loads((lego / "capture" / "transforms.json").read_text())
    scale = size / data["w"]
    frames = sorted(data["frames"], key=lambda f: f["file_path"])[::step]
    for f in frames:
        name = Path(f["file_path"]).stem
        img = cv2.imread(str(lego / "capture" / f["file_path"]), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(cap / "images" / f"{name}.png"), cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA))
        mask = cv2.imread(str(lego / "truth" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        small = cv2.resize(mask, (size, size), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(truth / f"{name}.png"), small)
        cv2.imwrite(str(cap / "annotations" / f"{name}.png"), small)
    out = {**data, "frames": frames, "w": size, "h": size}
    for key in ("fl_x", "fl_y", "cx", "cy"):
        out[key] = data[key] * scale
    (cap / "transforms.json").write_text(json.dumps(out))
    shutil.copy(lego / "capture" / "classes.json", cap / "classes.json")
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    return folder


# --- one case ---------------------------------------------------------------------------------
def scores_of(out: Path, truth: Path, classes, chosen: list[str]) -> dict:
    """Dice on the frames not chosen: wound bed and the mean of the tissue classes present."""
    from labelsynth.pipeline import score_against_truth

    rows = {r["class"]: r for r in score_against_truth(out, truth, classes, exclude=set(chosen)).table()}
    tissues = [c.name for c in classes.classes if c.id != 0 and rows.get(c.name, {}).get("n")]
    return {"wound_bed": rows["wound_bed"]["dice"],
            "tissue_mean": float(np.mean([rows[t]["dice"] for t in tissues])) if tissues else None,
            "classes": {t: rows[t]["dice"] for t in tissues}, "scored": len(list((out / "masks").glob("*.png"))) - len(chosen)}


def run_choice(case: Path, suggest_out: Path, out: Path, chosen: list[str], args) -> dict:
    """expand --geometry from ``chosen`` (cached), then its scores (cached in OUT/../NAME.score.json)."""
    from labelsynth.capture import load_capture
    from labelsynth.pipeline import expand
    from labelsynth.rundir import RunFolder

    score_file = out.with_name(out.name + ".score.json")
    if score_file.is_file():
        cached = json.loads(score_file.read_text())
        if cached.get("chosen") == chosen and cached.get("seed", 0) == args.fit_seed:
            return cached
    run = RunFolder(out).read_run() if RunFolder(out).is_finished() else None
    if run is None or run.annotated_frames != chosen or run.seed != args.fit_seed:
        t0 = time.time()
        expand(case / "capture", out, labels="annotations", recipe=args.recipe, overrides=args.set, device=args.device,
               annotated_frames=list(chosen), report=False, geometry=suggest_out, force=True, progress=False,
               seed=args.fit_seed)
        log(f"  expanded {out.relative_to(args.work)} from {', '.join(chosen)} in {time.time() - t0:.0f} s")
    cap = load_capture(case / "capture")
    result = {"chosen": chosen, "seed": args.fit_seed, **scores_of(out, case / "truth", cap.classes, chosen),
              "seconds": RunFolder(out).read_run().seconds}
    score_file.write_text(json.dumps(result, indent=1))
    return result


def run_case(name: str, case: Path, args) -> dict:
    from labelsynth.capture import load_capture
    from labelsynth.capture.select import select_frames
    from labelsynth.options import SuggestOptions
    from labelsynth.suggest import read_suggestion, suggest

    work = args.work / name
    suggest_out = work / "suggest"
    kmax = max(args.ks)
    done = read_suggestion(suggest_out) if (suggest_out / "suggest.json").is_file() else None
    if done is None or done["annotate"] < kmax or done.get("seed", 0) != args.fit_seed:
        t0 = time.time()
        suggest(case / "capture", SuggestOptions(annotate=kmax, recipe=args.recipe, overrides=args.set,
                                                 device=args.device, seed=args.fit_seed), suggest_out, force=True,
                progress=False)
        log(f"{name}: suggest fitted the geometry and ranked the frames in {time.time() - t0:.0f} s")
    sug = read_suggestion(suggest_out)
    names = load_capture(case / "capture").names
    ranked = [f["name"] for f in sug["frames"]]  # greedy: its first K are its choice for K (a run per --ks shares it)
    rows = {}
    for k in args.ks:
        rng = np.random.default_rng([args.seed, k])
        views = _views(suggest_out)
        make = {"suggested": lambda: sorted(ranked[:k]),
                "frames": lambda: sorted(names[i] for i in views.frame_choice(k)),
                "appearance": lambda: sorted(p.name for p in _appearance_views(suggest_out).greedy(k)),
                "frames-appearance": lambda: sorted(names[i] for i in _appearance_views(suggest_out).frame_choice(k)),
                "spread-earlier": lambda: shifted_spread(names, k, -1),
                "spread-later": lambda: shifted_spread(names, k, +1),
                "spread": lambda: select_frames(f"spread:{k}", names)}
        choices = {c: make[c]() for c in dict.fromkeys([*args.choices, *(c for c in args.only if c in make)])}
        for r in range(args.random):
            choices[f"random{r}"] = sorted(names[i] for i in rng.choice(len(names), k, replace=False))
        if args.only:  # one process per choice: expand and score those only (a later run without --only tabulates)
            for c in args.only:
                run_choice(case, suggest_out, work / f"K{k}" / c, choices[c], args)
            continue
        res = {c: run_choice(case, suggest_out, work / f"K{k}" / c, chosen, args) for c, chosen in choices.items()}
        randoms = [res[c] for c in res if c.startswith("random")]
        worst = min(randoms, key=lambda r: r["wound_bed"]) if randoms else None
        cov = {c: _coverage(suggest_out, chosen) for c, chosen in choices.items()}
        rows[k] = {**{c: res[c] for c in args.choices}, "worst_random": worst,
                   "random_mean_wound_bed": float(np.mean([r["wound_bed"] for r in randoms])) if randoms else None,
                   "coverage": {**{c: cov[c] for c in args.choices},
                                "worst_random": cov[next(c for c in res if res[c] is worst)] if worst else None}}
        log(f"{name} K={k}: wound bed " + " ".join(f"{c} {res[c]['wound_bed']:.3f}" for c in args.choices)
            + (f" worst random {worst['wound_bed']:.3f}" if worst else "")
            + "; tissue mean " + " ".join(f"{c} {_f(res[c]['tissue_mean'])}" for c in args.choices))
    return {"case": name, "frames": len(names), "ranked": ranked, "coverage": sug["coverage_by_k"],
            "geometry_seconds": sug["seconds"].get("geometry"), "suggest_seconds": sug["seconds"], "by_k": rows}


def shifted_spread(names: list[str], k: int, step: int) -> list[str]:
    """spread:K with each frame moved ``step`` frames along the video (kept inside it): a choice as
    close to spread's as a choice can be, so its Dice minus spread's is the smallest difference a
    different choice makes."""
    from labelsynth.capture.select import select_frames

    index = {n: i for i, n in enumerate(names)}
    moved = [min(max(index[n] + step, 0), len(names) - 1) for n in select_frames(f"spread:{k}", names)]
    if len(set(moved)) < k:
        raise ValueError(f"spread:{k} of {len(names)} frames moved by {step}: two frames coincide")
    return [names[i] for i in moved]


def _coverage(suggest_out: Path, chosen: list[str]) -> float:
    """Coverage of a choice by the suggest run's own measure (recomputed from field.pt)."""
    cache = suggest_out.parent / "coverage.json"
    known = json.loads(cache.read_text()) if cache.is_file() else {}
    key = ",".join(chosen)
    if key not in known:
        views = _views(suggest_out)
        known[key] = views.coverage([views.names.index(n) for n in chosen])
        if cache.is_file():  # another run (other --ks) may have added to it meanwhile
            known = {**json.loads(cache.read_text()), key: known[key]}
        tmp = cache.with_name(f"{cache.name}.{os.getpid()}")
        tmp.write_text(json.dumps(known, indent=1))
        os.replace(tmp, cache)
    return known[key]


def _views(suggest_out: Path):
    """The suggest run's ``SurfaceViews``, recomputed from its field.pt (once per process)."""
    if _VIEWS.get(suggest_out) is None:
        import torch

        from labelsynth.capture import load_capture
        from labelsynth.render.renderer import FieldRenderer
        from labelsynth.rundir import load_field
        from labelsynth.suggest import CoverageConfig, read_suggestion, surface_views

        capture = load_capture(read_suggestion(suggest_out)["capture"])
        view = FieldRenderer(load_field(suggest_out / "field.pt", torch.device("cpu")))
        _VIEWS[suggest_out] = surface_views(view.mesh(), capture.unit_cameras(), capture.names, CoverageConfig(),
                                            caster=view.caster(), progress=False)
    return _VIEWS[suggest_out]


_VIEWS: dict = {}
_APPEARANCE: dict = {}


def _appearance_views(suggest_out: Path):
    """The suggest run's ``SurfaceViews`` with its samples weighted by ``appearance_weights``."""
    if _APPEARANCE.get(suggest_out) is None:
        from labelsynth.capture import load_capture
        from labelsynth.suggest.coverage import appearance_weights, surface_colours

        views = _views(suggest_out)
        capture = load_capture(json.loads((suggest_out / "suggest.json").read_text())["capture"])
        colours = surface_colours(views, capture.unit_cameras(), capture.load_image, progress=False)
        _APPEARANCE[suggest_out] = views.weighted(appearance_weights(colours))
    return _APPEARANCE[suggest_out]


def _f(x) -> str:
    return "-" if x is None else f"{x:.3f}"


# --- timing -----------------------------------------------------------------------------------
def timing(args) -> dict:
    """Full expand --no-report vs expand --geometry of it, on the 50-frame 640x480 wound."""
    from labelsynth.pipeline import expand
    from labelsynth.rundir import RunFolder

    folder = synth_case(args.work / "timing" / "wound50", "one-sided", 0, 50, 640, 480)
    full, reused = args.work / "timing" / "full", args.work / "timing" / "reused"
    walls = {}
    for out, geometry in ((full, None), (reused, full)):
        wall_file = out.with_name(out.name + ".wall.json")
        if not (RunFolder(out).is_finished() and wall_file.is_file()):
            load0 = os.getloadavg()[0]
            t0 = time.time()
            expand(folder / "capture", out, labels="annotations", recipe="default", device=args.device, report=False,
                   geometry=geometry, force=True, progress=False)
            wall_file.write_text(json.dumps({"wall_s": time.time() - t0, "load_before": load0,
                                             "load_after": os.getloadavg()[0]}))
        walls[out.name] = json.loads(wall_file.read_text())
        log(f"timing: {out.name} {walls[out.name]['wall_s']:.0f} s (load average {walls[out.name]['load_before']:.1f}"
            f" -> {walls[out.name]['load_after']:.1f}); stages {_stages(RunFolder(out).read_run().seconds)}")
    a, b = RunFolder(full), RunFolder(reused)
    names = sorted(p.stem for p in a.masks_dir.glob("*.png"))
    same = all(a.mask_path(n).read_bytes() == b.mask_path(n).read_bytes() for n in names)
    ratio = walls["reused"]["wall_s"] / walls["full"]["wall_s"]
    log(f"timing: expand --geometry / full expand = {ratio:.2f} (target <= 0.5); masks identical: {same} ({len(names)})")
    return {"walls": walls, "ratio": ratio, "masks_identical": same, "frames": len(names),
            "stages": {"full": a.read_run().seconds, "reused": b.read_run().seconds},
            "suggest": suggest_timing(folder, args) if args.timing_suggest else None}


def suggest_timing(folder: Path, args) -> dict:
    """``suggest --annotate 4`` on the 50-frame wound with the default recipe (the workflow's step 2)."""
    from labelsynth.options import SuggestOptions
    from labelsynth.suggest import read_suggestion, suggest

    out = args.work / "timing" / "suggest"
    wall_file = out.with_name(out.name + ".wall.json")
    if not ((out / "suggest.json").is_file() and wall_file.is_file()):
        load0 = os.getloadavg()[0]
        t0 = time.time()
        suggest(folder / "capture", SuggestOptions(annotate=4, recipe="default", device=args.device), out, force=True,
                progress=False)
        wall_file.write_text(json.dumps({"wall_s": time.time() - t0, "load_before": load0,
                                         "load_after": os.getloadavg()[0]}))
    wall = json.loads(wall_file.read_text())
    sug = read_suggestion(out)
    log(f"timing: suggest --annotate 4 {wall['wall_s']:.0f} s (load average {wall['load_before']:.1f} -> "
        f"{wall['load_after']:.1f}); stages {_stages(sug['seconds'])}; frames {', '.join(f['name'] for f in sug['frames'])}"
        f" cover {sug['coverage']:.3f}, spread:4 {sug['spread']['coverage']:.3f}")
    return {"wall": wall, "seconds": sug["seconds"], "frames": [f["name"] for f in sug["frames"]],
            "coverage": sug["coverage"], "spread_coverage": sug["spread"]["coverage"]}


def _stages(seconds: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())


# --- report -----------------------------------------------------------------------------------
def table(results: list[dict], run: tuple[str, ...] = CHOICES) -> str:
    """One row per case and K of the choices in ``run`` (spread among them)."""
    choices = [c for c in run if c != "spread"]
    short = {"suggested": "sugg", "frames": "frames", "appearance": "appear", "frames-appearance": "fr-app",
             "spread-earlier": "spr-1", "spread-later": "spr+1", "spread": "spread"}
    head = " / ".join(short[c] for c in run)
    lines = [f"| case | K | coverage {head} / worst rnd | wound bed {head} / worst rnd | tissue mean {head} / worst rnd | "
             + " | ".join(f"{short[c]} - spread (wb / tissue)" for c in choices) + " |",
             "|---" * (5 + len(choices)) + "|"]
    for res in results:
        for k, row in res["by_k"].items():
            w, cov = row["worst_random"] or {}, row["coverage"]
            cells = [" / ".join([*(f"{cov[c]:.3f}" for c in run), _f(cov["worst_random"])]),
                     " / ".join([*(f"{row[c]['wound_bed']:.3f}" for c in run), _f(w.get("wound_bed"))]),
                     " / ".join([*(_f(row[c]["tissue_mean"]) for c in run), _f(w.get("tissue_mean"))]),
                     *(_diff(row[c], row["spread"]) for c in choices)]
            lines.append(f"| {res['case']} | {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _diff(a: dict, b: dict) -> str:
    """a - b as 'wound bed / tissue mean'."""
    dt = a["tissue_mean"] - b["tissue_mean"] if a["tissue_mean"] is not None and b["tissue_mean"] is not None else None
    return f"{a['wound_bed'] - b['wound_bed']:+.3f} / {'-' if dt is None else f'{dt:+.3f}'}"


def combine(summaries: list[Path]) -> str:
    """One table over several runs' bench_suggest.json (e.g. one --work per --fit-seed): per case and
    K, each choice's wound bed and tissue mean in every run and its difference from spread as
    mean ± sd over the runs."""
    runs = [json.loads(Path(p).read_text()) for p in summaries]
    cases = [c["case"] for c in runs[0]["cases"]]
    lines = [f"over {len(runs)} runs ({', '.join(str(p) for p in summaries)})",
             "| case | K | choice | wound bed (each run) | − spread, mean ± sd | tissue mean (each run) | − spread, mean ± sd |",
             "|---|---|---|---|---|---|---|"]
    for name in cases:
        rows = [next(c for c in r["cases"] if c["case"] == name)["by_k"] for r in runs]
        for k in rows[0]:
            for choice in [c for c in CHOICES if all(c in r[k] for r in rows)]:  # older runs lack a newer choice
                cells = []
                for key in ("wound_bed", "tissue_mean"):
                    vals = [r[k][choice][key] for r in rows]
                    diffs = [r[k][choice][key] - r[k]["spread"][key] for r in rows if r[k][choice][key] is not None]
                    cells.append(" ".join(_f(v) for v in vals))
                    cells.append("" if choice == "spread" or not diffs else
                                 f"{np.mean(diffs):+.3f} ± {np.std(diffs, ddof=1) if len(diffs) > 1 else 0.0:.3f}")
                lines.append(f"| {name} | {k} | {choice} | " + " | ".join(cells) + " |")
    return "\n".join([*lines, "", *resolution(runs)])


NEIGHBOURS = ("spread-earlier", "spread-later")


def resolution(runs: list[dict], threshold: float = 0.005) -> list[str]:
    """Per choice, over the runs' (case, K, class group) cells: how many miss the issue's threshold
    (mean minus spread below -``threshold``) and, where the runs have spread's one-frame neighbours,
    how many are at or above the worse of them (mean minus spread): what the benchmark can resolve.
    A case whose tissue mean is its wound bed (the lego's one class) counts once."""
    cells: dict[str, list[tuple[float, float | None]]] = {}  # choice: [(mean - spread, worse neighbour's)]
    n_cells = 0
    for name in [c["case"] for c in runs[0]["cases"]]:
        rows = [next(c for c in r["cases"] if c["case"] == name)["by_k"] for r in runs]
        for k in rows[0]:
            for key in ("wound_bed", "tissue_mean"):
                if key == "tissue_mean" and all(r[k]["spread"]["tissue_mean"] in (None, r[k]["spread"]["wound_bed"])
                                                for r in rows):
                    continue
                mean = {}
                for choice in [c for c in CHOICES if c != "spread" and all(c in r[k] for r in rows)]:
                    diffs = [r[k][choice][key] - r[k]["spread"][key] for r in rows if r[k][choice][key] is not None]
                    if diffs:
                        mean[choice] = float(np.mean(diffs))
                n_cells += 1
                worse = min([0.0, *(mean[c] for c in NEIGHBOURS)]) if all(c in mean for c in NEIGHBOURS) else None
                for choice, m in mean.items():
                    cells.setdefault(choice, []).append((m, worse))
    if not cells:
        return []
    lines = [f"of {n_cells} (case, K, class group) cells, mean over {len(runs)} run(s) minus spread:"]
    for choice, vals in cells.items():
        line = f"  {choice}: {sum(m < -threshold for m, _ in vals)} below -{threshold}"
        if all(lo is not None for _, lo in vals) and choice not in NEIGHBOURS:
            line += f"; {sum(m >= lo for m, lo in vals)} at or above the worse of spread's one-frame neighbours"
        lines.append(line)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=None, help="where cases, fits, expands and bench_suggest.json go")
    ap.add_argument("--cases", default="wound-a,wound-b,around,uneven,lego")
    ap.add_argument("--ks", default="2,3,4")
    ap.add_argument("--random", type=int, default=10, help="random K-subsets per K (the worst is reported)")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--lego", type=Path, default=DEFAULT_LEGO)
    ap.add_argument("--lego-step", type=int, default=2, help="every Nth lego view")
    ap.add_argument("--lego-size", type=int, default=400)
    ap.add_argument("--recipe", default="default")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random subsets")
    ap.add_argument("--fit-seed", type=int, default=0,
                    help="seed of suggest's geometry and of every expand (one --work per seed keeps each seed's cache: how "
                         "much of a difference between choices is the fit's own variation); a cached fit of another "
                         "seed is redone")
    ap.add_argument("--choices", default=",".join(CHOICES),
                    help=f"comma list of the choices to expand and tabulate, spread always among them ({', '.join(CHOICES)})")
    ap.add_argument("--only", default="", help="comma list of choices (suggested, spread, random0, ...) to expand and "
                    "score, without the table: runs in parallel fill the cache, a run without --only tabulates")
    ap.add_argument("--timing", action="store_true", help="also the --geometry timing on the 50-frame wound")
    ap.add_argument("--timing-only", action="store_true")
    ap.add_argument("--json", default=None, help="the summary's file name under --work (default bench_suggest.json, "
                    "bench_suggest_timing.json with --timing-only): several runs of disjoint --cases can share --work")
    ap.add_argument("--timing-suggest", action="store_true", help="with the timing: also suggest --annotate 4 on that wound")
    ap.add_argument("--combine", type=Path, nargs="+", default=None, metavar="SUMMARY",
                    help="only print one table over these runs' bench_suggest.json (mean ± sd of each choice minus spread)")
    args = ap.parse_args()
    if args.combine:
        print(combine(args.combine))
        return
    args.ks = [int(k) for k in args.ks.split(",")]
    if args.work is None:
        ap.error("--work is required (unless --combine)")
    args.only = [c for c in args.only.split(",") if c]
    wanted = {c for c in args.choices.split(",") if c} | {"spread"}
    if wanted - set(CHOICES):
        ap.error(f"--choices: unknown {', '.join(sorted(wanted - set(CHOICES)))} (known: {', '.join(CHOICES)})")
    args.choices = tuple(c for c in CHOICES if c in wanted)
    args.work.mkdir(parents=True, exist_ok=True)
    summary: dict = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    report = args.work / (args.json or ("bench_suggest_timing.json" if args.timing_only else "bench_suggest.json"))
    if not args.timing_only:
        results = []
        for name in [c for c in args.cases.split(",") if c]:
            folder = args.work / "cases" / name
            if name == "lego":
                case = lego_case(folder, args.lego, args.lego_step, args.lego_size)
            else:
                layout, seed = SYNTH_CASES[name]
                case = synth_case(folder, layout, seed, args.frames, args.width, args.height)
            results.append(run_case(name, case, args))
            if args.only:
                continue
            report.write_text(json.dumps({**summary, "cases": results}, indent=1, default=str))
        summary["cases"] = results
        if args.only:
            print(f"expanded and scored {', '.join(args.only)} (no table: run again without --only)")
            return
        print(table(results, args.choices))
    if args.timing or args.timing_only:
        summary["timing"] = timing(args)
    report.write_text(json.dumps(summary, indent=1, default=str))
    print(f"wrote {report}")


if __name__ == "__main__":
    main()
