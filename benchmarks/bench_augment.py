"""Novel views (`labelsynth augment`): image quality, label quality, speed and the retraining gain.

    python benchmarks/bench_augment.py --root /tmp/aug                    # everything (README numbers)
    python benchmarks/bench_augment.py --root /tmp/aug --part loo --part dice
    python benchmarks/bench_augment.py --root /tmp/aug --part loo --sweep  # the blending settings compared

Cases (each made once under --root and reused): ``synth``, a 50-frame 640x480 ``labelsynth synth``
capture (seed 0, 4 annotated) expanded with ``--recipe fast --no-report``; ``lego``, the public
NeRF-synthetic lego (``../shared/data/lego``, its 4 annotated frames), expanded the same way.

Parts:
  loo      leave-one-frame-out: every ``--loo-every``-th real frame rendered from the other frames
           at its own pose; PSNR and SSIM (skimage.metrics) against the real frame on the pixels
           the other frames see (and how many those are); the colour head (``--head-frames``
           frames, volume-rendered at full resolution) on the same pixels for comparison.
  dice     novel views sampled as ``augment`` samples them (synth only): wound-bed and per-class
           Dice of their masks against the exact truth rendered at the same poses by the synth
           generator (``evaluation.synth.SynthScene``), on the pixels the views mark valid.
  time     ``augment(OUT, views=200)`` end to end on the synth case (writes OUT/augment), with
           the rejection counts.
  retrain  the same SegFormer, same steps, trained on OUT/labels.h5 (the expanded frames) and on
           OUT/augment/augment.h5 (those frames + the novel views), validated on a separate synth
           capture's annotated frames, scored with ``segment`` on held-out synth captures
           against their exact truth.
  figure   docs/augment_strip.png: novel views with their mask overlaid.
Results: ROOT/results.json (and printed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_LEGO = REPO.parent / "shared" / "data" / "lego"
PARTS = ("loo", "dice", "time", "retrain", "figure")


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- cases --------------------------------------------------------------------------------------
def synth_capture(root: Path, seed: int, frames: int, annotated: int, width: int, height: int) -> Path:
    from labelsynth.evaluation.synth import SynthConfig, synthesize

    out = root / f"synth_s{seed}_{frames}f_{width}x{height}"
    if not out.exists():
        t0 = time.perf_counter()
        synthesize(out, SynthConfig(frames=frames, annotated=annotated, width=width, height=height, seed=seed),
                   progress=False)
        log(f"synth seed {seed}: {time.perf_counter() - t0:.0f} s")
    return out


def expanded(capture: Path, out: Path, recipe: str) -> Path:
    from labelsynth.pipeline import expand

    if not (out / "field.pt").exists():
        t0 = time.perf_counter()
        expand(capture, out, labels="annotations", recipe=recipe, device="cpu", report=False, progress=False,
               force=True)
        log(f"expand {capture} ({recipe}): {time.perf_counter() - t0:.0f} s")
    return out


def load_case(out: Path):
    """(the run: its capture and the field's renderer, RealFrames, images) of an expand output."""
    from types import SimpleNamespace

    from labelsynth.novel.views import RealFrames
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    run = RunFolder(out)
    _, cap = run.open_capture()
    fitted = run.load_field("cpu")
    run.check_fits(fitted, cap)
    ex = SimpleNamespace(capture=cap, view=FieldRenderer(fitted))
    images = [cap.load_image(i) for i in range(len(cap))]
    return ex, RealFrames(ex.view, cap.unit_cameras(), images), images


# --- leave-one-frame-out ------------------------------------------------------------------------
def masked_metrics(pred: np.ndarray, real: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """PSNR over the valid pixels, SSIM (skimage, per-pixel map) averaged over them."""
    from skimage.metrics import structural_similarity

    diff = (pred.astype(np.float64) - real.astype(np.float64))[valid]
    mse = float(np.mean(diff**2)) if diff.size else float("nan")
    psnr = 10 * np.log10(255.0**2 / max(mse, 1e-10))
    _, smap = structural_similarity(real, pred, channel_axis=-1, data_range=255, full=True)
    return psnr, float(smap.mean(-1)[valid].mean())


def loo(out: Path, every: int, head_frames: int, configs: dict[str, dict]) -> dict:
    from labelsynth.novel.views import BlendConfig, colour_head, render_view

    ex, real, images = load_case(out)
    cams = ex.capture.unit_cameras()
    idx = list(range(every // 2, len(cams), every))
    res = {}
    for label, overrides in configs.items():
        real.cfg = BlendConfig(**overrides)
        rows, t0 = [], time.perf_counter()
        for i in idx:
            v = render_view(ex.view, real, cams[i], exclude={i})
            p, s = masked_metrics(v.image, images[i], v.valid)
            rows.append({"frame": ex.capture.frames[i].name, "psnr": p, "ssim": s, "valid": v.valid_fraction})
        res[label] = {"config": overrides, "frames": rows, "psnr": float(np.mean([r["psnr"] for r in rows])),
                      "ssim": float(np.mean([r["ssim"] for r in rows])),
                      "valid": float(np.mean([r["valid"] for r in rows])),
                      "seconds_per_view": (time.perf_counter() - t0) / len(idx)}
        log(f"loo {out.name} [{label}]: PSNR {res[label]['psnr']:.2f} dB, SSIM {res[label]['ssim']:.3f}, "
            f"valid {res[label]['valid']:.3f} ({len(idx)} frames)")
    if head_frames:
        real.cfg = BlendConfig()
        rows = []
        for i in idx[:head_frames]:
            v = render_view(ex.view, real, cams[i], exclude={i})
            t0 = time.perf_counter()
            rgb = colour_head(ex.view.field, cams[i]).numpy().reshape(v.image.shape).round().clip(0, 255).astype(np.uint8)
            sec = time.perf_counter() - t0
            p_head, s_head = masked_metrics(rgb, images[i], v.valid)
            p_blend, s_blend = masked_metrics(v.image, images[i], v.valid)
            rows.append({"frame": ex.capture.frames[i].name, "head_psnr": p_head, "head_ssim": s_head,
                         "blend_psnr": p_blend, "blend_ssim": s_blend, "head_seconds": sec})
        res["colour_head"] = {"frames": rows, **{k: float(np.mean([r[k] for r in rows])) for k in
                                                 ("head_psnr", "head_ssim", "blend_psnr", "blend_ssim", "head_seconds")}}
        h = res["colour_head"]
        log(f"loo {out.name} colour head ({len(rows)} frames): PSNR {h['head_psnr']:.2f} dB, SSIM {h['head_ssim']:.3f} "
            f"vs blend {h['blend_psnr']:.2f} / {h['blend_ssim']:.3f}; {h['head_seconds']:.0f} s per frame")
    return res


SWEEP = {
    "default": {},
    "blend1": {"blend": 1},
    "blend3": {"blend": 3},
    "sharp0.5": {"sharpness_deg": 0.5},
    "sharp8": {"sharpness_deg": 8.0},
    "no-far-penalty": {"far_resolution": 0.0},
}


# --- label quality against exact truth ----------------------------------------------------------
def novel_dice(out: Path, truth_dir: Path, views: int, seed: int) -> dict:
    from labelsynth.evaluation.metrics import score_frames
    from labelsynth.evaluation.synth import SynthScene
    from labelsynth.novel.poses import Spread, path_points, sample_poses
    from labelsynth.novel.views import render_view
    from labelsynth.novel.write import world_camera

    ex, real, _ = load_case(out)
    cams = ex.capture.unit_cameras()
    caster = ex.view.render_caster()
    poses = sample_poses(views, np.random.default_rng(seed), path_points(cams, caster), Spread(), caster, real)
    scene = SynthScene.from_truth(truth_dir)
    preds, truths, lost = [], [], []
    for cam in poses.cameras:
        v = render_view(ex.view, real, cam)
        _, truth, _ = scene.render(world_camera(cam, ex.capture.normalization))
        bed = truth > 0
        lost.append(float((bed & ~v.valid).sum() / max(1, bed.sum())))
        preds.append(v.mask)
        truths.append(np.where(v.valid, truth, 255).astype(np.uint8))
    scores = score_frames(preds, truths, ex.capture.classes, [f"novel_{k}" for k in range(len(preds))])
    rows = {r["class"]: r for r in scores.table()}
    res = {"views": len(preds), "rejected": poses.rejected, "classes": rows,
           "wound_bed_outside_valid": float(np.mean(lost))}
    log(f"novel-view Dice ({len(preds)} views, {poses.rejected_total} rejected {poses.rejected}): "
        + scores.summary_line() + f"; wound bed outside the valid pixels {np.mean(lost):.4f}")
    return res


# --- speed --------------------------------------------------------------------------------------
def timing(out: Path, views: int) -> dict:
    from labelsynth.novel import augment

    t0 = time.perf_counter()
    r = augment(out, views, seed=0, device="cpu", force=True, progress=False)
    wall = time.perf_counter() - t0
    res = {"views": r.views, "wall_s": wall, "phases_s": r.seconds, "rejected": r.rejected,
           "valid_fraction": r.valid_fraction, "loadavg": os.getloadavg()}
    log(f"augment {views} views: {wall:.1f} s ({', '.join(f'{k} {v:.1f} s' for k, v in r.seconds.items())}); "
        f"rejected {r.rejected}; valid {r.valid_fraction:.3f}; loadavg {os.getloadavg()[0]:.2f}")
    return res


# --- retraining gain ----------------------------------------------------------------------------
def retrain(root: Path, out: Path, args) -> dict:
    from labelsynth.capture.masks import read_mask
    from labelsynth.evaluation.metrics import score_frames
    from labelsynth.train.segment import segment_capture
    from labelsynth.classes import ClassMap
    from labelsynth.train import TrainConfig, train

    classes = ClassMap.default()

    aug = out / "augment" / "augment.h5"
    if not aug.exists():
        timing(out, args.views)
    val = synth_capture(root, args.val_seed, 12, 4, args.width, args.height) / "capture"
    tests = [synth_capture(root, s, args.test_frames, 4, args.width, args.height) for s in args.test_seeds]
    res = {}
    for arm, sources in (("expanded", [out / "labels.h5"]), ("expanded+novel", [aug])):
        model = root / "models" / arm.replace("+", "_")
        cfg = TrainConfig(steps=args.steps, val_captures=[str(val)], eval_every=max(1, args.steps // 4), device="cpu",
                          seed=0)
        done = model / "train.json"
        record = json.loads(done.read_text()) if (model / "model.onnx").exists() and done.exists() else None
        if record is not None and record["arguments"].get("steps") == args.steps and not args.retrain:
            # this arm's model from an earlier run, same steps
            train_frames, train_s = record["split"]["train_frames"], record["times"]["train_s"]
            log(f"retrain [{arm}]: reusing {model} (--retrain redoes it)")
        else:
            t0 = time.perf_counter()
            tr = train([*sources, val], model, cfg, force=True, progress=False)
            train_s, train_frames = time.perf_counter() - t0, tr.train_frames
        preds, truths, names = [], [], []
        for t in tests:
            seg = root / "segment" / arm.replace("+", "_") / t.name
            segment_capture(t / "capture", model / "model.onnx", seg, device="cpu", progress=False)
            for p in sorted(seg.glob("*.png")):
                preds.append(read_mask(p, None, classes))
                truths.append(read_mask(t / "truth" / p.name, None, classes))
                names.append(f"{t.name}/{p.stem}")
        scores = score_frames(preds, truths, classes, names)
        rows = {r["class"]: r for r in scores.table()}
        res[arm] = {"train_frames": train_frames, "steps": args.steps, "train_s": train_s,
                    "test_frames": len(preds), "classes": rows}
        log(f"retrain [{arm}]: {train_frames} training frames, {train_s:.0f} s; held-out "
            + scores.summary_line())
    return res


# --- figure -------------------------------------------------------------------------------------
def figure(out: Path, path: Path, n: int = 5) -> str:
    import cv2

    from labelsynth.export import LabelsDataset

    import h5py

    h5 = out / "augment" / "augment.h5"
    with h5py.File(h5, "r") as f:
        novel = int(f["novel"][()].sum())
    ds = LabelsDataset(h5, uint8=True)
    cmap = ds.classes
    tiles = []
    for i in np.linspace(0, novel - 1, n).astype(int):
        item = ds[int(i)]
        img = item["image"].numpy().transpose(1, 2, 0)
        mask = item["mask"].numpy().astype(np.uint8)
        colour = cmap.colorize(mask)
        tissue = (mask != 0) & (mask != 255)
        over = img.copy()
        over[tissue] = (0.5 * img[tissue] + 0.5 * colour[tissue]).astype(np.uint8)
        over[mask == 255] = (0.35 * img[mask == 255] + 0.65 * 128).astype(np.uint8)
        tiles.append(np.concatenate([img, over], 0))
    strip = np.concatenate(tiles, 1)
    scale = 1400 / strip.shape[1]
    strip = cv2.resize(strip, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    log(f"figure: {path}")
    return str(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True, help="work folder (captures, expansions, models)")
    ap.add_argument("--part", action="append", choices=PARTS, help="repeatable; default: all")
    ap.add_argument("--case", action="append", choices=("synth", "lego"), help="for loo; default: both")
    ap.add_argument("--lego", type=Path, default=DEFAULT_LEGO)
    ap.add_argument("--recipe", default="fast")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--loo-every", type=int, default=5)
    ap.add_argument("--head-frames", type=int, default=2)
    ap.add_argument("--sweep", action="store_true", help="loo: compare the blending settings")
    ap.add_argument("--dice-views", type=int, default=20)
    ap.add_argument("--views", type=int, default=200)
    ap.add_argument("--steps", type=int, default=1000, help="retrain: SegFormer steps per arm (300 left both arms unconverged)")
    ap.add_argument("--retrain", action="store_true", help="retrain: redo models that exist with the same steps")
    ap.add_argument("--val-seed", type=int, default=50)
    ap.add_argument("--test-seeds", type=lambda s: [int(x) for x in s.split(",")], default=[51, 52])
    ap.add_argument("--test-frames", type=int, default=12)
    ap.add_argument("--figure-path", type=Path, default=REPO / "docs" / "augment_strip.png")
    args = ap.parse_args()
    parts = args.part or list(PARTS)
    root = args.root
    root.mkdir(parents=True, exist_ok=True)
    results_path = root / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    syn = synth_capture(root, 0, 50, 4, args.width, args.height)
    syn_out = expanded(syn / "capture", root / "synth_out", args.recipe)

    def save() -> None:
        results_path.write_text(json.dumps(results, indent=2, default=float))

    if "loo" in parts:
        configs = SWEEP if args.sweep else {"default": {}}
        for case in args.case or ["synth", "lego"]:
            out = syn_out if case == "synth" else expanded(args.lego / "capture", root / "lego_out", args.recipe)
            results.setdefault("loo", {})[case] = loo(out, args.loo_every, args.head_frames, configs)
            save()
    if "dice" in parts:
        results["dice"] = novel_dice(syn_out, syn / "truth", args.dice_views, seed=1)
        save()
    if "time" in parts:
        results["time"] = timing(syn_out, args.views)
        save()
    if "retrain" in parts:
        results["retrain"] = retrain(root, syn_out, args)
        save()
    if "figure" in parts:
        if not (syn_out / "augment" / "augment.h5").exists():
            timing(syn_out, args.views)
        results["figure"] = figure(syn_out, args.figure_path)
        save()
    log(f"results: {results_path}")


if __name__ == "__main__":
    sys.exit(main())
