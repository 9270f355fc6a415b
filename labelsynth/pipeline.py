"""`labelsynth expand` as a library call: capture in, consistent masks and a dataset out.

The output folder (``rundir.RunFolder``) is built under ``OUT.partial`` and renamed to OUT only
when everything is written (``outdir.building``), so an interrupted run never leaves an OUT that
looks complete. Every option is checked (``options.ExpandOptions.check``) and every input file
(``capture.check``) before OUT.partial exists and before the first training step.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from .capture import check_capture, load_capture
from .capture.model import Capture
from .device import pick_device
from .errors import LabelsynthError
from .export import LabelsWriter, write_masks_png
from .geometry.fingerprint import GeometryFingerprint, require_unchanged
from .geometry.sdf import SDFField, initial_surface_colour
from .geometry.training import RayBank, train_geometry
from .options import DeviceChoice, ExpandOptions, LabelMode, MeshFormat, positive_number
from .outdir import PARTIAL_SUFFIX, building, check_out, check_writable, ensure_space, partial_path, previous_path
from .progress import console, track
from .recipe import Recipe
from .render.field import FittedField
from .render.renderer import FieldRenderer
from .render.support import SurfaceSupport
from .rundir import RunFolder, RunInfo, changed_label_inputs, label_inputs, load_field
from .semantics.fit import HeadFit, fit_head, leave_one_out_heads, scaled_config
from .semantics.head import SemanticHead
from .semantics.training import BakedRays, LabelledFrame, bake_semantic_rays


@dataclass
class ExpandResult:
    out: Path
    frames: list[str]
    annotated: list[str]
    labels: LabelMode
    seconds: dict[str, float] = field(default_factory=dict)
    geometry: dict = field(default_factory=dict)
    semantic: dict = field(default_factory=dict)

    def summary(self) -> str:
        run = RunFolder(self.out)
        total = sum(self.seconds.values())
        return (
            f"{len(self.frames)} masks in {run.masks_dir}; dataset {run.labels_path}; "
            f"labels={self.labels}; {total:.0f} s "
            f"(geometry {self.seconds.get('geometry', 0):.0f} s, semantics {self.seconds.get('semantics', 0):.0f} s, "
            f"render {self.seconds.get('render', 0):.0f} s"
            + (f", report {self.seconds['report']:.0f} s)" if "report" in self.seconds else ")")
            + self._fit_quality()
        )

    def _fit_quality(self) -> str:
        """How well the geometry stage reproduced the images (its training PSNR), the number that
        shows a failed fit (issue 31's table: 15-17 dB where the object never formed, 28-41 dB in the
        best fits; docs/outputs.md); empty when the geometry was reused rather than fitted."""
        psnr = self.geometry.get("final_psnr")
        return "" if psnr is None else f"; geometry training PSNR {psnr:.1f} dB (run.json)"


@dataclass
class FieldFit:
    """Both stages' result on one capture: the field, the rays its head learnt from (the
    report's leave-one-out heads reuse them) and timing/quality statistics."""

    field: FittedField
    baked: BakedRays
    stats: dict[str, Any]


def resolve_label_mode(capture: Capture, labels: LabelMode | str | None) -> LabelMode:
    """The contract: default ``both`` when both folders exist, else whichever exists."""
    has_a, has_p = capture.has_annotations, capture.has_predictions
    if labels is None:
        if has_a and has_p:
            return LabelMode.BOTH
        if has_a:
            return LabelMode.ANNOTATIONS
        if has_p:
            return LabelMode.PREDICTIONS
        raise LabelsynthError(f"{capture.root}: no annotations/ or predictions/ masks to learn from")
    labels = LabelMode.parse(labels, "--labels")
    if labels in (LabelMode.ANNOTATIONS, LabelMode.BOTH) and not has_a:
        raise LabelsynthError(f"{capture.root / 'annotations'}: --labels {labels} needs expert masks, none found")
    if labels in (LabelMode.PREDICTIONS, LabelMode.BOTH) and not has_p:
        raise LabelsynthError(f"{capture.root / 'predictions'}: --labels {labels} needs automatic masks, none found")
    return labels


def labelled_frames(
    capture: Capture,
    mode: LabelMode | str,
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
    mode = LabelMode.parse(mode, "labels")
    cams = capture.unit_cameras()
    out = []
    for i, frame in enumerate(capture.frames):
        if frame.name in exclude:
            continue
        mask, weight, expert = None, 1.0, False
        if mode in (LabelMode.ANNOTATIONS, LabelMode.BOTH):
            mask = annotations.get(frame.name) if annotations is not None else capture.load_annotation(i)
            weight = recipe.semantic.expert_weight if mode == LabelMode.BOTH else 1.0
            expert = mask is not None
        if mask is None and mode in (LabelMode.PREDICTIONS, LabelMode.BOTH):
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
) -> tuple[FittedField, dict]:
    """Stage 1 on the capture's images (all frames, or the given indices): a field without a
    head, its geometry frozen (the paper's stage 2 starts from it), and its statistics."""
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
    init_shape = sdf.initialise_shape([unit[i].forward for i in indices], [unit[i].c2w[:3, 0] for i in indices])
    sdf.initialise_background(bank.border_rgb)
    sdf.initialise_colour(initial_surface_colour(init_shape, bank.border_rgb, bank.mean_rgb))
    sdf = sdf.to(device)
    grid, gstats = train_geometry(sdf, bank, geo, seed=seed, progress=progress)
    for p in sdf.parameters():
        p.requires_grad_(False)  # the paper's stage 2: geometry frozen
    fitted_on = GeometryFingerprint.of(capture, geo, seed, frames=indices)
    fitted = FittedField(sdf, grid, capture.classes, capture.normalization, recipe, fitted_on=fitted_on)
    return fitted, {**vars(gstats), "init_shape": init_shape}


def geometry_file(path: str | Path) -> Path:
    """The field.pt that ``expand --geometry PATH`` reads: PATH itself, or PATH/field.pt for the
    output folder of ``suggest`` or ``expand``. Cheap (names only); one line if there is none."""
    path = Path(path)
    if path.name.endswith(PARTIAL_SUFFIX):
        raise LabelsynthError(f"--geometry {path}: an unfinished run (a {PARTIAL_SUFFIX} folder); run it again to finish it")
    if path.is_file():
        return path
    field_path = RunFolder(path).field_path
    if field_path.is_file():
        return field_path
    if not path.exists():
        if partial_path(path).exists():
            raise LabelsynthError(f"--geometry {path}: not finished (only {partial_path(path)} exists)")
        raise LabelsynthError(f"--geometry {path}: not found (expected the output folder of labelsynth suggest or "
                              "expand, or its field.pt)")
    raise LabelsynthError(f"--geometry {path}: holds no {field_path.name} (expected the output folder of labelsynth "
                          "suggest or expand)")


def reuse_geometry(path: str | Path, capture: Capture, recipe: Recipe, seed: int,
                   device: torch.device) -> FittedField:
    """The geometry stored at ``path`` (``geometry_file``) for this capture, recipe and seed, in
    place of fitting stage 1: refused with one line saying what changed unless it was fitted on
    this capture's images and cameras with the same ``geometry`` recipe and seed
    (``geometry.fingerprint``). The field takes this capture's classes and ``recipe``; a head
    the file holds is dropped."""
    source = geometry_file(path)
    stored = load_field(source, device)
    require_unchanged(stored.fitted_on, capture, where=source, geometry=recipe.geometry, seed=seed)
    return FittedField(stored.sdf, stored.grid, capture.classes, capture.normalization, recipe,
                       fitted_on=stored.fitted_on, surface=stored.surface)


def fit_semantics(
    fitted: FittedField,
    frames: list[LabelledFrame],
    *,
    exclude: set[str] = frozenset(),
    baked: BakedRays | None = None,
    seed: int = 0,
    progress: bool = True,
    steps_fraction: float = 1.0,
) -> HeadFit:
    """A fresh semantic head trained on the field's frozen geometry from the labelled frames
    (``semantics.fit.fit_head`` with the field's recipe); the field is not changed: use
    ``fitted.with_head(fit.head)``.

    Pass ``baked`` (an earlier fit's ``baked``) with ``exclude`` to leave frames out without
    re-sampling the rays. ``steps_fraction`` scales the head's steps and epochs.
    """
    recipe = fitted.recipe
    return fit_head(fitted.sdf, fitted.grid, fitted.classes, recipe.semantic, recipe.geometry.march_steps, frames,
                    baked=baked, exclude=exclude, seed=seed, progress=progress, steps_fraction=steps_fraction)


def fit_field(
    capture: Capture,
    recipe: Recipe,
    labels: LabelMode | str,
    device: torch.device,
    *,
    seed: int = 0,
    progress: bool = True,
    geometry: FittedField | None = None,
) -> FieldFit:
    """Both stages of the paper on one capture; with ``geometry`` (a fitted geometry of this
    capture, e.g. ``reuse_geometry``'s) only the semantic stage, on it."""
    t0 = time.time()
    if geometry is None:
        geometry, gstats = fit_geometry(capture, recipe, device, seed=seed, progress=progress)
    else:
        gstats = {}
    t1 = time.time()
    fit = fit_semantics(geometry, labelled_frames(capture, labels, recipe), seed=seed, progress=progress)
    t2 = time.time()
    stats = {"seconds": {"geometry": t1 - t0, "semantics": t2 - t1}, "geometry": gstats, "semantic": vars(fit.stats)}
    return FieldFit(geometry.with_head(fit.head), fit.baked, stats)


def leave_one_out_heads_of(
    fitted: FittedField,
    capture: Capture,
    mode: LabelMode | str,
    names: list[str],
    *,
    baked: BakedRays | None = None,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, SemanticHead]:
    """The report's leave-one-view-out heads (``semantics.fit.leave_one_out_heads``): one fresh
    head per named frame, trained without it for ``report.loo_fraction`` of the semantic
    stage's steps, on the rays of the full fit (``baked``; baked here, as the fit baked them,
    for a field loaded from disk)."""
    recipe = fitted.recipe
    if baked is None:
        baked = bake_semantic_rays(fitted.sdf, fitted.grid, labelled_frames(capture, mode, recipe), fitted.classes,
                                   recipe.semantic, recipe.geometry.march_steps, seed=seed, progress=progress)
    cfg = scaled_config(recipe.semantic, recipe.report.loo_fraction)
    return leave_one_out_heads(fitted.sdf, fitted.classes, cfg, baked, names, seed=seed, progress=progress)


def render_outputs(
    view: FieldRenderer,
    capture: Capture,
    run: RunFolder,
    *,
    labels: LabelMode,
    recipe_name: str,
    progress: bool = True,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """masks/*.png and labels.h5 for every frame at its input resolution; returns the masks and
    each frame's share of pixels whose surface no teaching frame saw (their labels.h5
    confidence capped: ``render.support``)."""
    cams = capture.unit_cameras()
    support = teaching_support(view, capture, labels)
    unseen: dict[str, float] = {}
    annotated = [f.annotation_path is not None for f in capture.frames]
    classes = capture.classes
    masks: dict[str, np.ndarray] = {}
    recipe_text = yaml.safe_dump(view.field.recipe.to_dict(), sort_keys=False)
    if not view.config.per_pixel:
        view.vertex_logits()  # every vertex at once: most are seen, and one pass beats 50 lazy ones
    with LabelsWriter(
        run.labels_path,
        n_frames=len(capture),
        classes=classes,
        source=str(capture.root),
        recipe=recipe_text,
        attrs={"labels": labels.value, "recipe_name": recipe_name},
    ) as writer:
        for i in track(range(len(capture)), "rendering masks", enabled=progress):
            frame = capture.frames[i]
            r = view.render(cams[i], support=support)
            write_masks_png(run.masks_dir, frame.name, r.mask, classes)
            writer.add(frame.name, capture.load_image(i), r.mask, r.confidence.astype(np.float16), annotated[i])
            masks[frame.name] = r.mask
            unseen[frame.name] = r.unseen_share
    return masks, unseen


def teaching_support(view: FieldRenderer, capture: Capture, labels: LabelMode | str) -> SurfaceSupport:
    """What the frames whose masks taught the head (``labelled_frames``) saw of the field's surface."""
    taught = labelled_frames(capture, labels, view.field.recipe)
    return view.support([f.camera for f in taught], [f.mask for f in taught])


def unseen_shares(view: FieldRenderer, capture: Capture, labels: LabelMode | str, *,
                  progress: bool = False) -> dict[str, float]:
    """Each frame's share of pixels whose surface no teaching frame saw (as ``render_outputs``
    measures it), for a field loaded from disk."""
    support = teaching_support(view, capture, labels)
    cams = capture.unit_cameras()
    caster = view.render_caster()
    out = {}
    for i in track(range(len(capture)), "unseen surface", enabled=progress):
        hit, points, faces, _ = caster.cast(*cams[i].rays())
        out[capture.frames[i].name] = float(support.unseen(hit, points, faces).mean())
    return out


def output_bytes(capture: Capture, recipe: Recipe) -> int:
    """About what an expand writes, to refuse a disk without the room before the training rather
    than after it: the field's parameters (float32) and, per frame, labels.h5's image, mask and
    confidence at half their raw size (gzip) plus a tenth of a byte per pixel of mask PNG."""
    field_bytes = 4 * sum(p.numel() for p in SDFField(recipe.geometry.sdf).parameters())
    pixels = sum(f.size[0] * f.size[1] for f in capture.frames)
    return int(field_bytes + pixels * (6 * 0.5 + 0.1))


def expand(
    capture_dir: str | Path,
    out: str | Path,
    options: ExpandOptions | None = None,
    *,
    geometry: str | Path | None = None,
    force: bool = False,
    progress: bool = True,
    **values: Any,
) -> ExpandResult:
    """Fit the semantic field to a capture and write OUT (the README's "The output folder").

    ``options``, or its fields as keywords (``labels=``, ``recipe=``, ``device=``, ``seed=``,
    ``overrides=``, ``annotated_frames=``, ``report=``, ``mesh_format=``, ``mm_per_unit=``:
    ``options.ExpandOptions``). Every option and every input is checked first (``capture.check``):
    a bad one fails in seconds, with all the others, before any training and before OUT or
    OUT.partial exist. The report reads annotations and predictions whatever ``labels`` is,
    so only ``report=False`` narrows the check to the masks that teach. ``annotated_frames``:
    which frames' annotations teach (``load_capture``); run.json records the chosen names so
    ``labelsynth report`` keeps them.

    ``geometry``: the output folder of ``suggest`` or of an earlier ``expand`` (or its field.pt)
    whose geometry replaces stage 1 (``reuse_geometry``); refused with one line, before OUT
    exists, unless it was fitted on this capture's images and cameras with the same geometry
    recipe and seed, so the masks are those a full expand fitting that geometry writes.
    run.json's ``geometry_from`` names the file.
    """
    opts = options.replace(**values) if options is not None else ExpandOptions(**values)
    rec = opts.check()
    out = Path(out)
    check_out(out, force)
    source = geometry_file(geometry) if geometry is not None else None
    capture = load_capture(capture_dir, annotated_frames=opts.annotated_frames)
    mode = resolve_label_mode(capture, opts.labels)
    check = check_capture(capture, labels="both" if opts.report else mode.value)
    check.raise_if_problems()
    ensure_space(out, output_bytes(capture, rec), "the outputs of expand (field.pt, labels.h5, masks/)")
    dev = pick_device(opts.device.value)
    reused = None
    if source is not None:
        t0 = time.time()
        reused = reuse_geometry(source, capture, rec, opts.seed, dev)
        reuse_seconds = time.time() - t0
    with building(out, force=force) as partial:
        run = RunFolder(partial)
        if progress:
            console.print(f"[bold]labelsynth[/] {check.summary()}")
            console.print(f"[bold]labelsynth[/] {len(capture)} frames, labels={mode}, recipe={rec.name}, device={dev}")
            if source is not None:
                console.print(f"[bold]labelsynth[/] geometry from {source} (fitted on these images and cameras, "
                              f"with this geometry recipe and seed: stage 1 skipped)")
        t0 = time.time()
        inputs = {"label_inputs": label_inputs(capture)}  # what the images were is field.pt's fitted_on
        fingerprints = time.time() - t0
        fit = fit_field(capture, rec, mode, dev, seed=opts.seed, progress=progress, geometry=reused)
        stats = fit.stats
        if source is not None:
            stats["seconds"]["geometry"] = reuse_seconds  # loading and checking it
        stats["seconds"] = {"check": check.seconds + fingerprints, **stats["seconds"]}
        report_seconds = _write_outputs(run, capture, fit.field, fit.baked, mode, seconds=stats["seconds"],
                                        recipe_name=rec.name, seed=opts.seed, report=opts.report,
                                        mesh_format=opts.mesh_format.value, mm_per_unit=opts.mm_per_unit,
                                        progress=progress)
        chosen = None if opts.annotated_frames is None else [f.name for f in capture.frames if f.annotation_path is not None]
        run.write_run(RunInfo(
            capture=str(Path(capture_dir).resolve()), labels=mode.value, annotated_frames=chosen, recipe=rec.to_dict(),
            device=str(dev), seed=opts.seed, seconds=stats["seconds"], geometry=stats["geometry"],
            semantic=stats["semantic"], report_seconds=report_seconds, **inputs,
            geometry_from=None if source is None else str(source.resolve()),
        ))
    return ExpandResult(
        out=out,
        frames=capture.names,
        annotated=[f.name for f in capture.frames if f.annotation_path is not None],
        labels=mode,
        seconds=stats["seconds"],
        geometry=stats["geometry"],
        semantic=stats["semantic"],
    )


def _write_outputs(run: RunFolder, capture: Capture, fitted: FittedField, baked: BakedRays | None, mode: LabelMode, *,
                   seconds: dict[str, float], recipe_name: str, seed: int, report: bool, mesh_format: str,
                   mm_per_unit: float | None, progress: bool, before: dict[str, np.ndarray] | None = None,
                   relabel: dict | None = None) -> dict[str, float] | None:
    """What expand and relabel write after the semantic stage: field.pt, masks/ and labels.h5,
    then (``report``) the report and the mesh. Adds ``render`` and ``report`` to ``seconds``;
    returns the report's own step seconds (None without a report). ``before``: the masks of the
    OUT being replaced, so ``relabel["pixels_changed"]`` (per frame, pixels whose class moved)
    is filled in here and shown by the report."""
    view = FieldRenderer(fitted)
    t0 = time.time()
    run.save_field(view.field_with_surface())
    masks, unseen = render_outputs(view, capture, run, labels=mode, recipe_name=recipe_name, progress=progress)
    seconds["render"] = time.time() - t0
    if before is not None and relabel is not None:
        relabel["pixels_changed"] = {n: int(np.count_nonzero(masks[n] != before[n])) if n in before
                                     and before[n].shape == masks[n].shape else int(masks[n].size) for n in masks}
    if not report:
        return None
    t0 = time.time()
    rep = _report(run, capture, view, masks, mode, baked=baked, seed=seed, progress=progress, mesh_format=mesh_format,
                  mm_per_unit=mm_per_unit, relabel=relabel, unseen=unseen)
    seconds["report"] = time.time() - t0
    return rep["summary"]["phase_seconds"]


def _report(run: RunFolder, capture: Capture, view: FieldRenderer, masks: dict[str, np.ndarray], mode: LabelMode, *,
            baked: BakedRays | None, seed: int, progress: bool, unseen: dict[str, float] | None = None,
            **kwargs) -> dict:
    """build_report with what it needs from the orchestration: the masks that taught, and how
    to get the leave-one-out heads."""
    from .report.build import build_report

    fitted = view.field
    taught = {f.name: f.mask for f in labelled_frames(capture, mode, fitted.recipe)}

    def loo_heads(names: list[str]) -> dict[str, SemanticHead]:
        return leave_one_out_heads_of(fitted, capture, mode, names, baked=baked, seed=seed, progress=progress)

    if unseen is None:
        unseen = unseen_shares(view, capture, mode, progress=progress)
    return build_report(run, capture, view, masks, mode.value, taught=taught, loo_heads=loo_heads,
                        unseen=unseen, progress=progress, **kwargs)


def _report_choices(run: RunFolder, mesh_format: str | None, mm_per_unit: float | None) -> tuple[str, float | None]:
    """The mesh format and mm-per-unit of a new report: as given (checked), else as the OUT's
    previous report chose them."""
    if mesh_format is not None:
        mesh_format = MeshFormat.parse(mesh_format, "--mesh-format").value
    if mm_per_unit is not None:
        mm_per_unit = positive_number(mm_per_unit, "--mm-per-unit")
    prev_mesh = run.read_report_summary().get("mesh") or {}
    if mesh_format is None:
        had_glb = run.mesh_path("glb").name in (prev_mesh.get("files") or []) or run.mesh_path("glb").exists()
        mesh_format = "glb" if had_glb else "ply"
    if mm_per_unit is None:
        mm_per_unit = (prev_mesh.get("areas") or {}).get("mm_per_unit")
    return mesh_format, mm_per_unit


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

    Without ``mesh_format`` / ``mm_per_unit`` the previous report's choices are kept. The
    leave-one-out heads are trained as expand trains them (the labelled rays baked again with
    the run's seed), so they match the first report's. A relabelled OUT keeps showing what the
    relabel changed (run.json's ``relabel``).
    """
    dev = pick_device(DeviceChoice.parse(device, "--device").value)
    run = RunFolder(out_dir)
    mesh_format, mm_per_unit = _report_choices(run, mesh_format, mm_per_unit)
    info, capture = run.open_capture()  # with the run's choice of annotated frames
    fitted = run.load_field(dev)
    # The report reads every mask and every image: check them all before the leave-one-out
    # refits, and that the capture's classes are still the field's.
    check_capture(capture, labels="both", class_tables={str(run.field_path): fitted.classes}).raise_if_problems()
    run.check_fits(fitted, capture)
    masks = run.read_masks(capture.names, capture)
    # report.json, report.html and the mesh are written beside OUT and moved in together at the
    # end: an interrupted or failed rebuild leaves OUT's earlier report as it was
    with building(run.path, merge=True) as partial:
        return _report(RunFolder(partial), capture, FieldRenderer(fitted), masks, LabelMode.parse(info.labels, "labels"),
                       baked=None, seed=info.seed, progress=progress, mesh_format=mesh_format,
                       mm_per_unit=mm_per_unit, loo=loo, relabel=info.relabel)


@dataclass
class RelabelResult:
    """What ``relabel`` did to OUT."""

    out: Path
    frames: list[str]
    labels: LabelMode
    masks_changed: list[str]
    """``kind/frame`` of the input masks that changed since the previous run."""
    pixels_changed: dict[str, int]
    """Per frame, pixels whose class differs from the previous OUT's mask."""
    seconds: dict[str, float] = field(default_factory=dict)
    previous: Path | None = None
    """Where the replaced OUT was kept (``keep_previous``), else None (removed)."""

    def summary(self) -> str:
        moved = {n: p for n, p in self.pixels_changed.items() if p}
        total = sum(self.seconds.values())
        lines = [
            f"relabelled {self.out} (labels={self.labels}): {len(self.masks_changed)} input mask(s) changed"
            + (f" ({', '.join(self.masks_changed[:6])}{', ...' if len(self.masks_changed) > 6 else ''})"
               if self.masks_changed else ""),
            f"{len(moved)} of {len(self.frames)} frames changed class somewhere, "
            f"{sum(moved.values())} pixels in all" + (f" (most: {max(moved, key=moved.get)}, {max(moved.values())})"
                                                     if moved else ""),
            f"{total:.0f} s (" + ", ".join(f"{k} {v:.0f} s" for k, v in self.seconds.items()) + ")"
            + (f"; the previous OUT is kept in {self.previous}" if self.previous else ""),
        ]
        return "\n".join(lines)


def relabel(
    out: str | Path,
    *,
    capture: str | Path | None = None,
    labels: LabelMode | str | None = None,
    report: bool = True,
    device: str = "auto",
    keep_previous: bool = False,
    mesh_format: str | None = None,
    mm_per_unit: float | None = None,
    progress: bool = True,
) -> RelabelResult:
    """Train the semantic stage again on OUT's frozen geometry from the capture's current masks,
    render, report, and replace OUT with the result (``labelsynth relabel``).

    The geometry in OUT/field.pt is reused as it is, so the capture's images and cameras must be
    those it was fitted on (field.pt's ``fitted_on``, ``geometry.fingerprint``; anything else is
    a one-line ``GeometryChanged``). ``capture``: the capture folder when it moved (default: the one
    run.json names). ``labels``: which masks teach (default: the run's). The head is trained with
    the run's seed and recipe, so a relabel of an unchanged capture writes the masks the expand
    wrote. The new OUT is built in OUT.partial and swapped in when whole (``outdir.building``): the
    old OUT stays whole until then, and ``keep_previous`` keeps it as OUT.previous afterwards.
    run.json records which input masks changed (``masks_changed``) and, per frame, how many pixels
    changed class (``pixels_changed``), and the report shows both.
    """
    choice = None if labels is None else LabelMode.parse(labels, "--labels")
    dev_choice = DeviceChoice.parse(device, "--device")
    run = RunFolder(out)
    if report:
        mesh_format, mm_per_unit = _report_choices(run, mesh_format, mm_per_unit)
    t0 = time.time()
    info, cap = run.open_capture(capture)  # with the run's choice of annotated frames
    mode = resolve_label_mode(cap, choice if choice is not None else info.labels)
    dev = pick_device(dev_choice.value)
    fitted = run.load_field(dev)
    require_unchanged(fitted.fitted_on, cap, where=run.field_path,
                      remedy="relabel reuses that geometry: run expand again")
    check = check_capture(cap, labels="both" if report else mode.value,
                          class_tables={str(run.field_path): fitted.classes})
    check.raise_if_problems()
    run.check_fits(fitted, cap, need_head=False)
    before = run.read_masks(cap.names, cap)
    now = label_inputs(cap)
    changes = {"masks_changed": changed_label_inputs(info.label_inputs, now),
               "relabels": int((info.relabel or {}).get("relabels", 0)) + 1}
    seconds = {"check": time.time() - t0}
    if progress:
        console.print(f"[bold]labelsynth[/] relabel {run.path}: {check.summary()}; "
                      f"{len(changes['masks_changed'])} input mask(s) changed since the last run")
    with building(run.path, force=True, keep_previous=keep_previous) as partial:
        t0 = time.time()
        fit = fit_semantics(fitted, labelled_frames(cap, mode, fitted.recipe), seed=info.seed, progress=progress)
        seconds["semantics"] = time.time() - t0
        new = RunFolder(partial)
        report_seconds = _write_outputs(new, cap, fitted.with_head(fit.head), fit.baked, mode, seconds=seconds,
                                        recipe_name=str(info.recipe.get("name", "")), seed=info.seed, report=report,
                                        mesh_format=mesh_format or "ply", mm_per_unit=mm_per_unit, progress=progress,
                                        before=before, relabel=changes)
        new.write_run(RunInfo(
            capture=str(cap.root.resolve()), labels=mode.value, annotated_frames=info.annotated_frames,
            recipe=info.recipe, device=str(dev), seed=info.seed, seconds=seconds, geometry=info.geometry,
            semantic=vars(fit.stats), report_seconds=report_seconds,
            label_inputs=now, relabel=changes,
        ))
    return RelabelResult(run.path, cap.names, mode, changes["masks_changed"], changes["pixels_changed"], seconds,
                         previous_path(run.path) if keep_previous else None)


def score_against_truth(out: str | Path, truth_dir: str | Path, classes, exclude: set[str] = frozenset()):
    """Dice/recall of OUT/masks against exact truth masks (frames in ``exclude`` not scored).

    Both are read with the capture's mask reader, so palette or greyscale id PNGs alike
    give class ids (OpenCV would turn a palette PNG into colours).
    """
    from .capture.masks import read_mask
    from .evaluation.metrics import score_frames

    run, truth_dir = RunFolder(out), Path(truth_dir)
    names = sorted(p.stem for p in run.masks_dir.glob("*.png") if p.stem not in exclude)
    preds, truths = [], []
    for name in names:
        truth_path = truth_dir / f"{name}.png"
        if not truth_path.exists():
            raise LabelsynthError(f"{truth_path}: no truth mask for frame '{name}'")
        preds.append(read_mask(run.mask_path(name), None, classes))
        truths.append(read_mask(truth_path, None, classes))
    return score_frames(preds, truths, classes, names)


DEMO_PARTS = ("synthetic", "expanded")


def check_demo_out(out: Path) -> None:
    """The demo's OUT is new, empty or an earlier demo's (only synthetic/ and expanded/, which it
    replaces): never a folder of the user's own, a capture above all."""
    check_writable(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise LabelsynthError(f"{out}: exists and is not a folder")
    own = {*DEMO_PARTS, *(f"{p}{PARTIAL_SUFFIX}" for p in DEMO_PARTS)}
    other = sorted(p.name for p in out.iterdir() if p.name not in own)
    if other:
        raise LabelsynthError(f"{out}: not an earlier demo's folder (it holds {', '.join(other[:3])}"
                              f"{', ...' if len(other) > 3 else ''}); give a new or empty folder")


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

    options = ExpandOptions(labels="annotations", recipe=recipe, device=device, overrides=overrides or [])
    options.check()  # before anything is made
    config = SynthConfig(frames=frames, annotated=min(4, frames // 3) if isinstance(frames, int) else 0, width=width,
                         height=height)
    out = Path(out)
    check_demo_out(out)
    synth_dir = out / "synthetic"
    if synth_dir.exists():
        shutil.rmtree(synth_dir)
    made = synthesize(synth_dir, config, progress=progress)
    result = expand(made.capture_dir, out / "expanded", options, force=True, progress=progress)
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
