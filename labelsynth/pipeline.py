"""`labelsynth expand` as a library call: capture in, consistent masks and a dataset out.

The output folder is built under ``OUT.partial`` and renamed to OUT only when everything is
written (``outdir.building``), so an interrupted run never leaves an OUT that looks complete.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import yaml

from . import __version__
from .capture import check_capture, load_capture
from .capture.model import Capture
from .device import pick_device
from .errors import LabelsynthError
from .export import LabelsWriter, write_masks_png
from .geometry.sdf import SDFField
from .geometry.training import RayBank, train_geometry
from .outdir import building, check_out
from .progress import console, track
from .recipe import Recipe, load_recipe
from .render.field import SemanticField
from .semantics.training import (
    BakedRays,
    LabelledFrame,
    bake_semantic_rays,
    make_semantic_head,
    train_leave_one_out,
    train_semantic,
)

LABEL_MODES = ("annotations", "predictions", "both")
FIELD_FILE = "field.pt"


@dataclass
class ExpandResult:
    out: Path
    frames: list[str]
    annotated: list[str]
    labels: str
    seconds: dict[str, float] = field(default_factory=dict)
    geometry: dict = field(default_factory=dict)
    semantic: dict = field(default_factory=dict)

    def summary(self) -> str:
        total = sum(self.seconds.values())
        return (
            f"{len(self.frames)} masks in {self.out / 'masks'}; dataset {self.out / 'labels.h5'}; "
            f"labels={self.labels}; {total:.0f} s "
            f"(geometry {self.seconds.get('geometry', 0):.0f} s, semantics {self.seconds.get('semantics', 0):.0f} s, "
            f"render {self.seconds.get('render', 0):.0f} s"
            + (f", report {self.seconds['report']:.0f} s)" if "report" in self.seconds else ")")
        )


def resolve_label_mode(capture: Capture, labels: str | None) -> str:
    """The contract: default ``both`` when both folders exist, else whichever exists."""
    if labels is not None and labels not in LABEL_MODES:
        raise LabelsynthError(f"--labels must be one of {', '.join(LABEL_MODES)}, not '{labels}'")
    has_a, has_p = capture.has_annotations, capture.has_predictions
    if labels is None:
        if has_a and has_p:
            return "both"
        if has_a:
            return "annotations"
        if has_p:
            return "predictions"
        raise LabelsynthError(f"{capture.root}: no annotations/ or predictions/ masks to learn from")
    if labels in ("annotations", "both") and not has_a:
        raise LabelsynthError(f"{capture.root / 'annotations'}: --labels {labels} needs expert masks, none found")
    if labels in ("predictions", "both") and not has_p:
        raise LabelsynthError(f"{capture.root / 'predictions'}: --labels {labels} needs automatic masks, none found")
    return labels


def labelled_frames(
    capture: Capture,
    mode: str,
    recipe: Recipe,
    *,
    exclude: set[str] = frozenset(),
    predictions: dict[str, np.ndarray] | None = None,
    annotations: dict[str, np.ndarray] | None = None,
) -> list[LabelledFrame]:
    """The masks that teach the semantic stage. An expert mask replaces a prediction of the same frame.

    ``predictions`` / ``annotations`` replace the capture's own masks (e.g. perturbed ones in
    the benchmark); a frame missing from a given dict has no mask of that kind.
    """
    cams = capture.unit_cameras()
    out = []
    for i, frame in enumerate(capture.frames):
        if frame.name in exclude:
            continue
        mask, weight, expert = None, 1.0, False
        if mode in ("annotations", "both"):
            mask = annotations.get(frame.name) if annotations is not None else capture.load_annotation(i)
            weight = recipe.semantic.expert_weight if mode == "both" else 1.0
            expert = mask is not None
        if mask is None and mode in ("predictions", "both"):
            mask = predictions.get(frame.name) if predictions is not None else capture.load_prediction(i)
            weight = 1.0
        if mask is not None:
            out.append(LabelledFrame(cams[i], mask, weight, frame.name, expert))
    return out


def fit_geometry(
    capture: Capture,
    recipe: Recipe,
    device: torch.device,
    *,
    frames: list[int] | None = None,
    seed: int = 0,
    progress: bool = True,
) -> tuple[SemanticField, dict]:
    """Stage 1 on the capture's images (all frames, or the given indices); no semantics yet."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    geo = recipe.geometry
    indices = list(range(len(capture))) if frames is None else list(frames)
    unit = capture.unit_cameras()
    cams = [unit[i].scaled(geo.train_scale) for i in indices]
    images = [capture.load_image(i) for i in track(indices, "loading images", enabled=progress)]
    bank = RayBank(cams, images, device)
    del images
    sdf = SDFField(geo.sdf)
    init_shape = sdf.initialise_shape([unit[i].forward for i in indices])
    sdf.initialise_background(bank.border_rgb)
    sdf.initialise_colour(bank.mean_rgb)
    sdf = sdf.to(device)
    grid, gstats = train_geometry(sdf, bank, geo, seed=seed, progress=progress)
    for p in sdf.parameters():
        p.requires_grad_(False)  # the paper's stage 2: geometry frozen
    sem = SemanticField(sdf, None, grid, capture.classes, capture.normalization, recipe, device)
    return sem, {**vars(gstats), "init_shape": init_shape}


def fit_field(
    capture: Capture,
    recipe: Recipe,
    labels: str,
    device: torch.device,
    *,
    seed: int = 0,
    progress: bool = True,
) -> tuple[SemanticField, dict]:
    """Both stages of the paper on one capture; returns the field and timing/quality stats."""
    t0 = time.time()
    sem, gstats = fit_geometry(capture, recipe, device, seed=seed, progress=progress)
    t1 = time.time()
    sstats = fit_semantics(sem, labelled_frames(capture, labels, recipe), seed=seed, progress=progress)
    t2 = time.time()
    return sem, {"seconds": {"geometry": t1 - t0, "semantics": t2 - t1}, "geometry": gstats, "semantic": sstats}


def _scaled_semantic(cfg, fraction: float):
    """The semantic stage's config with its steps and epochs scaled (the report's refits)."""
    if fraction == 1.0:
        return cfg
    return replace(cfg, iterations=max(1, math.ceil(cfg.iterations * fraction)), min_epochs=cfg.min_epochs * fraction)


def fit_semantics(
    sem: SemanticField,
    frames: list[LabelledFrame],
    *,
    exclude: set[str] = frozenset(),
    baked: BakedRays | None = None,
    seed: int = 0,
    progress: bool = True,
    steps_fraction: float = 1.0,
) -> dict:
    """(Re)train the semantic head on frozen geometry from the given labelled frames.

    Pass ``baked`` (from an earlier call's ``sem.baked``) with ``exclude`` to leave frames out
    without re-sampling the rays: leave-one-out then costs only the head's training.
    ``steps_fraction`` scales the head's steps and epochs (the report's refits: ``report.loo_fraction``).
    """
    recipe = sem.recipe
    cfg = _scaled_semantic(recipe.semantic, steps_fraction)
    if baked is None:
        baked = bake_semantic_rays(
            sem.sdf, sem.grid, frames, sem.classes, recipe.semantic, recipe.geometry.march_steps, seed=seed, progress=progress
        )
        sem.baked = baked
    if exclude:
        baked = baked.without(set(exclude))
        if len(baked) == 0:
            raise LabelsynthError("no labelled pixels left after leaving out " + ", ".join(sorted(exclude)))
    head = make_semantic_head(sem.sdf, sem.classes, cfg)
    stats = train_semantic(head, baked, sem.classes, cfg, seed=seed, progress=progress)
    sem.head = head
    return vars(stats)


def render_outputs(
    sem: SemanticField,
    capture: Capture,
    out: Path,
    *,
    labels: str,
    recipe_name: str,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """masks/*.png and labels.h5 for every frame at its input resolution; returns the masks."""
    cams = capture.unit_cameras()
    annotated = [f.annotation_path is not None for f in capture.frames]
    masks: dict[str, np.ndarray] = {}
    recipe_text = yaml.safe_dump(sem.recipe.to_dict(), sort_keys=False)
    with LabelsWriter(
        out / "labels.h5",
        n_frames=len(capture),
        classes=capture.classes,
        source=str(capture.root),
        recipe=recipe_text,
        attrs={"labels": labels, "recipe_name": recipe_name},
    ) as writer:
        for i in track(range(len(capture)), "rendering masks", enabled=progress):
            frame = capture.frames[i]
            r = sem.render(cams[i])
            write_masks_png(out / "masks", frame.name, r.mask, capture.classes)
            writer.add(frame.name, capture.load_image(i), r.mask, r.confidence.astype(np.float16), annotated[i])
            masks[frame.name] = r.mask
    return masks


def _write_run_json(out: Path, capture_dir: str | Path, mode: str, annotated_frames: list[str] | None,
                    recipe: Recipe, device: torch.device, seed: int, stats: dict) -> None:
    """OUT/run.json: what ran and how long each phase took (``labelsynth report`` reads it back)."""
    run = {
        "version": __version__,
        "capture": str(Path(capture_dir).resolve()),
        "labels": mode,
        "annotated_frames": annotated_frames,
        "recipe": recipe.to_dict(),
        "device": str(device),
        "seed": seed,
        **stats,
    }
    (out / "run.json").write_text(json.dumps(run, indent=2, default=float))


def expand(
    capture_dir: str | Path,
    out: str | Path,
    *,
    labels: str | None = None,
    recipe: str | Path = "default",
    device: str = "auto",
    seed: int = 0,
    overrides: list[str] | None = None,
    force: bool = False,
    progress: bool = True,
    report: bool = True,
    mesh_format: str = "ply",
    mm_per_unit: float | None = None,
    annotated_frames: str | list[str] | None = None,
) -> ExpandResult:
    """Fit the semantic field to a capture and write OUT (the README's "The output folder").

    Every input is checked first (``capture.check``): a bad file fails in seconds, with all
    the others, before any training and before OUT or OUT.partial exist. The report reads
    annotations and predictions whatever ``labels`` is, so only ``report=False`` narrows the
    check to the masks that teach. ``annotated_frames``: which frames' annotations teach
    (``load_capture``); run.json records the chosen names so ``labelsynth report`` keeps them.
    """
    capture = load_capture(capture_dir, annotated_frames=annotated_frames)
    mode = resolve_label_mode(capture, labels)
    rec = load_recipe(recipe, overrides)
    out = Path(out)
    check_out(out, force)
    check = check_capture(capture, labels="both" if report else mode)
    check.raise_if_problems()
    dev = pick_device(device)
    with building(out, force=force) as partial:
        if progress:
            console.print(f"[bold]labelsynth[/] {check.summary()}")
            console.print(f"[bold]labelsynth[/] {len(capture)} frames, labels={mode}, recipe={rec.name}, device={dev}")
        sem, stats = fit_field(capture, rec, mode, dev, seed=seed, progress=progress)
        stats["seconds"] = {"check": check.seconds, **stats["seconds"]}
        sem.save(partial / FIELD_FILE)
        t0 = time.time()
        masks = render_outputs(sem, capture, partial, labels=mode, recipe_name=rec.name, progress=progress)
        stats["seconds"]["render"] = time.time() - t0
        if report:
            t0 = time.time()
            rep = _report(partial, capture, sem, masks, mode, seed=seed, progress=progress, mesh_format=mesh_format,
                          mm_per_unit=mm_per_unit)
            stats["seconds"]["report"] = time.time() - t0
            stats["report_seconds"] = rep["summary"]["phase_seconds"]
        chosen = None if annotated_frames is None else [f.name for f in capture.frames if f.annotation_path is not None]
        _write_run_json(partial, capture_dir, mode, chosen, rec, dev, seed, stats)
    return ExpandResult(
        out=out,
        frames=capture.names,
        annotated=[f.name for f in capture.frames if f.annotation_path is not None],
        labels=mode,
        seconds=stats["seconds"],
        geometry=stats["geometry"],
        semantic=stats["semantic"],
    )


class LeaveOneOutRefit:
    """The report's leave-one-view-out: ``refit(name)`` puts in ``sem.head`` a fresh head trained
    without that frame, geometry frozen, for ``report.loo_fraction`` of the semantic stage's steps.

    ``prepare(names)`` trains the heads of all the named frames at once on the full fit's baked
    rays (``semantics.training.train_leave_one_out``: one batch and one position lookup per step
    for all of them); a name not prepared is refitted alone, re-baking the other frames' labels
    when the full fit's rays are not there (a field loaded from disk).
    """

    def __init__(self, sem: SemanticField, capture: Capture, mode: str, seed: int = 0) -> None:
        self.sem, self.capture, self.mode, self.seed = sem, capture, mode, seed
        self.fraction = sem.recipe.report.loo_fraction
        self.heads: dict = {}

    def prepare(self, names: list[str], progress: bool = False) -> None:
        sem, baked = self.sem, self.sem.baked
        if baked is None:
            return
        # frames with baked rays whose absence leaves some; the others are refitted alone
        # (which trains on every ray, or says which frame left nothing)
        per_frame = torch.bincount(baked.frame_of_ray, minlength=len(baked.frame_names))
        index = {n: i for i, n in enumerate(baked.frame_names)}
        todo = [n for n in names if n not in self.heads and n in index]
        if not todo or any(int(per_frame[index[n]]) == len(baked) for n in todo):
            return
        cfg = _scaled_semantic(sem.recipe.semantic, self.fraction)
        self.heads.update(train_leave_one_out(lambda: make_semantic_head(sem.sdf, sem.classes, cfg), sem.baked,
                                              sem.classes, cfg, todo, seed=self.seed, progress=progress))

    def __call__(self, name: str) -> None:
        sem = self.sem
        if name in self.heads:
            sem.head = self.heads.pop(name)
        elif sem.baked is not None:
            fit_semantics(sem, [], exclude={name}, baked=sem.baked, seed=self.seed, progress=False,
                          steps_fraction=self.fraction)
        else:
            fit_semantics(sem, labelled_frames(self.capture, self.mode, sem.recipe, exclude={name}), seed=self.seed,
                          progress=False, steps_fraction=self.fraction)


def refit_without(sem: SemanticField, capture: Capture, mode: str, seed: int = 0) -> LeaveOneOutRefit:
    """The report's refit callable (``LeaveOneOutRefit``)."""
    return LeaveOneOutRefit(sem, capture, mode, seed)


def _report(out: Path, capture: Capture, sem: SemanticField, masks: dict[str, np.ndarray], mode: str, *,
            seed: int, progress: bool, **kwargs) -> dict:
    """build_report with what it needs from the orchestration: the masks that taught, a refit."""
    from .report import build_report

    taught = {f.name: f.mask for f in labelled_frames(capture, mode, sem.recipe)}
    return build_report(out, capture, sem, masks, mode, taught=taught, refit=refit_without(sem, capture, mode, seed),
                        progress=progress, **kwargs)


def rebuild_report(
    out_dir: str | Path,
    *,
    device: str = "auto",
    progress: bool = True,
    mesh_format: str | None = None,
    mm_per_unit: float | None = None,
    loo: bool = True,
) -> dict:
    """Write report.json/html (and the mesh) of a finished OUT again, from OUT/field.pt and OUT/masks.

    Without ``mesh_format`` / ``mm_per_unit`` the previous report's choices are kept.
    """
    from .report import REPORT_JSON, read_field_masks

    out_dir = Path(out_dir)
    run_path, field_path = out_dir / "run.json", out_dir / "field.pt"
    for p in (run_path, field_path):
        if not p.is_file():
            raise LabelsynthError(f"{p}: not found (is {out_dir} the output of labelsynth expand?)")
    try:
        run = json.loads(run_path.read_text())
        capture_dir, mode = run["capture"], run["labels"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise LabelsynthError(f"{run_path}: not a labelsynth run file ({exc})") from exc
    previous = {}
    if (out_dir / REPORT_JSON).is_file():
        try:
            previous = json.loads((out_dir / REPORT_JSON).read_text()).get("summary", {}) or {}
        except json.JSONDecodeError:
            previous = {}
    prev_mesh = previous.get("mesh") or {}
    if mesh_format is None:
        had_glb = "mesh.glb" in prev_mesh.get("files", []) or (out_dir / "mesh.glb").exists()
        mesh_format = "glb" if had_glb else "ply"
    if mm_per_unit is None:
        mm_per_unit = (prev_mesh.get("areas") or {}).get("mm_per_unit")
    capture = load_capture(capture_dir, annotated_frames=run.get("annotated_frames"))  # as the run chose
    sem = SemanticField.load(field_path, pick_device(device))
    # The report reads every mask and, for flagged frames, images: check them all before the
    # leave-one-out refits, and that the capture's classes are still the field's.
    check_capture(capture, labels="both", class_tables={str(field_path): sem.classes}).raise_if_problems()
    masks = read_field_masks(out_dir, capture.names)
    return _report(out_dir, capture, sem, masks, mode, seed=int(run.get("seed", 0)), progress=progress,
                   mesh_format=mesh_format, mm_per_unit=mm_per_unit, loo=loo)


def score_against_truth(out: str | Path, truth_dir: str | Path, classes, exclude: set[str] = frozenset()):
    """Dice/recall of OUT/masks against exact truth masks (frames in ``exclude`` not scored).

    Both are read with the capture's mask reader, so palette or greyscale id PNGs alike
    give class ids (OpenCV would turn a palette PNG into colours).
    """
    from .capture.masks import read_mask
    from .evaluation.metrics import score_frames

    out, truth_dir = Path(out), Path(truth_dir)
    names = sorted(p.stem for p in (out / "masks").glob("*.png") if p.stem not in exclude)
    preds, truths = [], []
    for name in names:
        truth_path = truth_dir / f"{name}.png"
        if not truth_path.exists():
            raise LabelsynthError(f"{truth_path}: no truth mask for frame '{name}'")
        preds.append(read_mask(out / "masks" / f"{name}.png", None, classes))
        truths.append(read_mask(truth_path, None, classes))
    return score_frames(preds, truths, classes, names)


def demo(
    out: str | Path = "labelsynth-demo",
    *,
    frames: int = 12,
    width: int = 320,
    height: int = 240,
    recipe: str = "fast",
    device: str = "auto",
    overrides: list[str] | None = None,
    progress: bool = True,
) -> str:
    """Synthesise a capture, expand it from its annotations, and score it against the truth."""
    from .evaluation.synth import SynthConfig, synthesize

    out = Path(out)
    synth_dir = out / "synthetic"
    if synth_dir.exists():
        shutil.rmtree(synth_dir)
    made = synthesize(synth_dir, SynthConfig(frames=frames, annotated=min(4, frames // 3), width=width, height=height), progress=progress)
    result = expand(
        made.capture_dir, out / "expanded", labels="annotations", recipe=recipe, device=device,
        overrides=overrides, force=True, progress=progress,
    )
    capture = load_capture(made.capture_dir)
    scores = score_against_truth(result.out, made.truth_dir, capture.classes, exclude=set(result.annotated))
    lines = [
        f"capture:  {made.capture_dir} ({frames} frames, {len(result.annotated)} annotated)",
        f"results:  {result.out} (masks/, labels.h5, report.html)",
        result.summary(),
        "Dice against the exact truth on the frames that were not annotated:",
        "  " + scores.summary_line(),
    ]
    return "\n".join(lines)
