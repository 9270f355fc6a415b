"""`labelsynth bench`: the paper's Tables 1 and 2 on a capture whose every frame has a truth mask.

Three methods, as in the paper:

- ``2d``: the capture's automatic predictions themselves (the per-frame segmenter);
- ``3d2d``: those predictions voted onto the fitted mesh and projected back (``fusion``);
- ``field``: the semantic field trained on those predictions (geometry shared between runs,
  only the cheap semantic stage is refitted), and once more on the expert annotations alone.

Each runs under the paper's perturbations of the predictions (``perturb``): none,
erosion-dilation, jitter, half-frames (2D has no half-frames row: it has no views to drop).
For half-frames, only the kept frames' predictions vote / teach, and by default the geometry is
refitted on the kept frames' images too, since the paper halved the training images.

Scores are ``metrics.score_frames`` against ``TRUTH/<stem>.png`` over the frames that were not
annotated (the annotated frames teach the annotation-trained field, so they are never scored),
averaged per frame over each class's population, the paper's rule.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..capture import ExtraMask, check_capture, load_capture
from ..capture.model import Capture
from ..device import pick_device
from ..errors import LabelsynthError
from ..outdir import building, check_apart, check_writable
from ..pipeline import fit_geometry, fit_semantics, labelled_frames
from ..progress import console, track
from ..render.renderer import FieldRenderer
from ..semantics.head import SemanticHead
from ..recipe import load_recipe
from .fusion import DEFAULT_CUTOFF_DEG, DEFAULT_STRIDE, fusion_baseline, load_mesh_unit
from .metrics import WOUND_BED, Scores, score_frames
from .perturb import PERTURBATIONS, apply_perturbation, half_frames

if TYPE_CHECKING:
    import torch
    import trimesh

    from ..recipe import Recipe

METHODS = ("2d", "3d2d", "field")
METHOD_NAMES = {"2d": "2D", "3d2d": "3D/2D", "field": "Field"}
PERTURBATION_NAMES = {"none": "None", "erosion-dilation": "Erosion-Dilation", "jitter": "Jittering",
                      "half-frames": "Half the frames"}
_METHOD_ALIASES = {"2d": "2d", "3d2d": "3d2d", "3d/2d": "3d2d", "3d-2d": "3d2d", "fusion": "3d2d",
                   "field": "field", "nerf": "field", "ours": "field"}
# The paper's Table 1 columns besides the wound bed (the classes common enough to report).
TABLE1_CLASSES = ("granulation", "slough")
ROW_METRICS = ("dice", "recall", "precision", "iou")


def parse_list(value: str | Iterable[str] | None, default: Sequence[str]) -> list[str]:
    """``"a,b"`` or an iterable of names -> list (None -> the default; an empty name is an error)."""
    if value is None:
        return list(default)
    items = value.split(",") if isinstance(value, str) else [str(v) for v in value]
    items = [i.strip() for i in items]
    if not items or not all(items):
        raise LabelsynthError(f"an empty name in {value!r} (leave the option out for all: {', '.join(default)})")
    return items


def normalise_methods(methods: str | Iterable[str] | None) -> list[str]:
    out = []
    try:
        names = parse_list(methods, METHODS)
    except LabelsynthError as exc:
        raise LabelsynthError(f"--methods: {exc}") from None
    for m in names:
        key = _METHOD_ALIASES.get(m.lower())
        if key is None:
            raise LabelsynthError(f"--methods: unknown bench method {m!r}; choose from {', '.join(METHODS)}")
        if key not in out:
            out.append(key)
    return [m for m in METHODS if m in out]


def normalise_perturbations(perturbations: str | Iterable[str] | None) -> list[str]:
    out = []
    try:
        names = parse_list(perturbations, PERTURBATIONS)
    except LabelsynthError as exc:
        raise LabelsynthError(f"--perturb: {exc}") from None
    for p in names:
        key = p.lower().replace("_", "-")
        key = {"erosion": "erosion-dilation", "jittering": "jitter", "half": "half-frames"}.get(key, key)
        if key not in PERTURBATIONS:
            raise LabelsynthError(f"--perturb: unknown perturbation {p!r}; choose from {', '.join(PERTURBATIONS)}")
        if key not in out:
            out.append(key)
    return [p for p in PERTURBATIONS if p in out]


def load_truths(truth_dir: str | Path, capture: Capture, names: Sequence[str]) -> dict[str, np.ndarray]:
    """``TRUTH/<stem>.png`` for each named frame; a missing folder or file is a one-line error."""
    truth_dir = Path(truth_dir)
    if not truth_dir.is_dir():
        raise LabelsynthError(f"{truth_dir}: truth folder not found")
    missing = [truth_dir / f"{n}.png" for n in names if not (truth_dir / f"{n}.png").is_file()]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise LabelsynthError(f"{missing[0]}: truth mask missing{more}")
    out = {}
    for n in names:
        out[n] = capture.read_mask_file(truth_dir / f"{n}.png", capture.frame(n).size)  # cached by the check
    return out


def _score_rows(method: str, labels: str, perturbation: str, scores: Scores) -> list[dict]:
    rows = []
    for r in scores.table():
        rows.append({"method": method, "labels": labels, "perturbation": perturbation, "class": r["class"],
                     **{m: r[m] for m in ROW_METRICS}, "n": r["n"]})
    return rows


def _render_field(view: FieldRenderer, head: SemanticHead, capture: Capture, names: Sequence[str],
                  progress: bool) -> dict[str, np.ndarray]:
    cams = dict(zip(capture.names, capture.unit_cameras()))
    return {n: view.render(cams[n], head).mask for n in track(list(names), "field render", enabled=progress)}


@dataclass
class _BenchInputs:
    """What every row reads, loaded and checked once before any fit."""

    capture: Capture
    annotated: list[str]  # frames whose annotations teach: never scored
    scored: list[str]
    truth_list: list[np.ndarray]  # in ``scored`` order
    preds: dict[str, np.ndarray]  # the capture's automatic predictions, by frame name
    user_mesh: trimesh.Trimesh | None  # a user mesh for 3D/2D, in the unit cube


@dataclass
class _BenchRows:
    """The rows scored so far and each method's time, with the scoring and logging they share."""

    inputs: _BenchInputs
    progress: bool
    seconds: dict[str, float]
    rows: list[dict] = field(default_factory=list)

    def log(self, msg: str) -> None:
        """One progress line, so a long bench shows each row as it lands."""
        if self.progress:
            console.print(f"[bold]bench[/] {msg}")

    def add(self, method: str, labels: str, perturbation: str, masks: dict[str, np.ndarray], title: str) -> None:
        """Score ``masks`` on the scored frames, keep the rows and log the wound-bed line."""
        inp = self.inputs
        s = score_frames([masks[n] for n in inp.scored], inp.truth_list, inp.capture.classes, inp.scored)
        self.rows += _score_rows(method, labels, perturbation, s)
        self.log(f"{title} / {perturbation}: {s.summary_line([WOUND_BED])}")


def run_bench(
    capture_dir: str | Path,
    truth_dir: str | Path,
    out_dir: str | Path,
    *,
    perturbations: str | Iterable[str] | None = PERTURBATIONS,
    methods: str | Iterable[str] | None = METHODS,
    recipe: str | Path = "default",
    device: str = "auto",
    overrides: list[str] | None = None,
    seed: int = 0,
    progress: bool = True,
    mesh: str | Path | None = None,
    half_geometry: bool = True,
    cutoff_deg: float = DEFAULT_CUTOFF_DEG,
    stride: int = DEFAULT_STRIDE,
    annotated_frames: str | list[str] | None = None,
) -> dict:
    """Score 2D, 3D/2D and the field under each perturbation; write OUT/bench.{json,md,png}.

    ``mesh``: a world-coordinate mesh file for 3D/2D instead of the fitted field's surface.
    ``half_geometry``: refit the geometry on the kept frames for half-frames (the paper's
    setting) rather than reuse the all-frames geometry. ``annotated_frames``: which frames'
    annotations teach (``load_capture``); the others are scored. Returns the bench.json content.
    """
    from ..options import DeviceChoice, finite_number, seed_value, whole_number

    t_start = time.perf_counter()
    seed = seed_value(seed)
    cutoff_deg = finite_number(cutoff_deg, "--cutoff", 0.0, 90.0, low_open=True)
    stride = whole_number(stride, "stride", 1, 4096)
    meths = normalise_methods(methods)
    perts = normalise_perturbations(perturbations)
    rec = load_recipe(recipe, overrides)
    dev = pick_device(DeviceChoice.parse(device, "--device").value)
    capture = load_capture(capture_dir, annotated_frames=annotated_frames)
    out_dir = Path(out_dir)
    check_apart(out_dir, {"the capture": capture.root, "the truth folder": Path(truth_dir)})
    if out_dir.exists() and not out_dir.is_dir():
        raise LabelsynthError(f"{out_dir}: exists and is not a folder")
    check_writable(out_dir)
    needs_field = "field" in meths
    needs_geometry = needs_field or ("3d2d" in meths and mesh is None)
    inputs = _load_inputs(capture, truth_dir, meths, mesh, needs_field=needs_field, needs_geometry=needs_geometry)
    bench = _BenchRows(inputs, progress, seconds={m: 0.0 for m in meths})
    timing: dict[str, float] = {}
    bench.log(f"{len(capture)} frames ({len(inputs.annotated)} annotated, {len(inputs.scored)} scored), "
              f"methods={','.join(meths)}, perturbations={','.join(perts)}, recipe={rec.name}, device={dev}")

    kept = half_frames(capture.names)
    sem = sem_half = None
    if needs_geometry:
        sem, sem_half = _fit_geometries(capture, rec, dev, kept, refit_half="half-frames" in perts and half_geometry,
                                        seed=seed, progress=progress, timing=timing)
    for pert in perts:
        _run_perturbation(bench, pert, meths, kept, sem_half if pert == "half-frames" else sem, rec,
                          seed=seed, cutoff_deg=cutoff_deg, stride=stride)
    annotations_note = None
    if needs_field:
        annotations_note = _run_annotation_field(bench, sem, rec, seed=seed)

    timing["total"] = time.perf_counter() - t_start
    result = {
        "rows": bench.rows,
        "seconds": bench.seconds,
        "timing": timing,
        "capture": str(Path(capture_dir).resolve()),
        "truth": str(Path(truth_dir).resolve()),
        "recipe": rec.name,
        "device": str(dev),
        "seed": seed,
        "methods": meths,
        "perturbations": perts,
        "frames": len(capture),
        "annotated_frames": inputs.annotated,
        "scored_frames": len(inputs.scored),
        "half_frames_kept": len(kept),
        "half_frames_geometry": _half_geometry_note(inputs.user_mesh is not None, needs_field, half_geometry),
        "fusion": {"cutoff_deg": cutoff_deg, "stride": stride, "mesh": str(mesh) if mesh else "fitted field"},
        "notes": [annotations_note] if annotations_note else [],
    }
    _write_bench(result, Path(out_dir))
    bench.log(f"wrote {Path(out_dir) / 'bench.json'}, bench.md, bench.png in {timing['total']:.0f} s")
    return result


def _load_inputs(capture: Capture, truth_dir: str | Path, meths: list[str], mesh: str | Path | None, *,
                 needs_field: bool, needs_geometry: bool) -> _BenchInputs:
    """Split the frames into teaching and scored ones and read every file the bench needs,
    so that a missing or bad file stops the run before any fit rather than after an hour."""
    annotated = [f.name for f in capture.frames if f.annotation_path is not None]
    scored = [n for n in capture.names if n not in set(annotated)]
    if not scored:
        raise LabelsynthError(f"{capture.root}: every frame is annotated; no frame is left to score")
    if not capture.has_predictions:
        raise LabelsynthError(f"{capture.root / 'predictions'}: the benchmark needs automatic predictions, none found")
    if "2d" in meths:
        lacking = [capture.frame(n) for n in scored if capture.frame(n).prediction_path is None]
        if lacking:
            raise LabelsynthError(
                f"{capture.root / 'predictions' / (lacking[0].name + '.png')}: missing; the 2D baseline needs a "
                "prediction for every scored frame"
            )
    if not Path(truth_dir).is_dir():
        raise LabelsynthError(f"{truth_dir}: truth folder not found")
    # Every file the bench reads, checked before any fit: images only when a geometry is fitted,
    # annotations only for the annotation-trained field, the truth of every scored frame.
    truth_masks = [ExtraMask(Path(truth_dir) / f"{n}.png", capture.frame(n).size, "truth") for n in scored]
    check_capture(capture, labels="both" if needs_field else "predictions", images=needs_geometry,
                  extra_masks=truth_masks).raise_if_problems()
    truths = load_truths(truth_dir, capture, scored)
    preds = {f.name: capture.load_prediction(i) for i, f in enumerate(capture.frames) if f.prediction_path is not None}
    user_mesh = load_mesh_unit(mesh, capture.normalization) if mesh is not None else None
    return _BenchInputs(capture, annotated, scored, [truths[n] for n in scored], preds, user_mesh)


def _fit_geometries(capture: Capture, rec: Recipe, dev: torch.device, kept: list[str], *, refit_half: bool,
                    seed: int, progress: bool, timing: dict[str, float]) -> tuple[FieldRenderer, FieldRenderer]:
    """The geometry on all frames, and on the kept half when the half-frames row refits it
    (the paper halved the training images); every row then refits only the cheap semantics."""
    t0 = time.perf_counter()
    fitted, _ = fit_geometry(capture, rec, dev, seed=seed, progress=progress)
    sem = FieldRenderer(fitted)
    timing["geometry"] = time.perf_counter() - t0
    sem_half = sem
    if refit_half:
        t0 = time.perf_counter()
        index = {n: i for i, n in enumerate(capture.names)}
        half, _ = fit_geometry(capture, rec, dev, frames=[index[n] for n in kept], seed=seed, progress=progress)
        sem_half = FieldRenderer(half)
        timing["geometry_half_frames"] = time.perf_counter() - t0
    return sem, sem_half


def _run_perturbation(bench: _BenchRows, pert: str, meths: list[str], kept: list[str],
                      geometry: FieldRenderer | None, rec: Recipe, *, seed: int, cutoff_deg: float,
                      stride: int) -> None:
    """One perturbation's rows: perturb the predictions once, then score each method on them
    (2D scores them as they are, 3D/2D votes them onto a mesh, the field learns from them)."""
    inp = bench.inputs
    t0 = time.perf_counter()
    if pert == "half-frames":
        keep = set(kept)
        masks = {n: np.array(m, copy=True) for n, m in inp.preds.items() if n in keep}
    else:
        masks = apply_perturbation(pert, inp.preds, seed=seed)
    t_perturb = time.perf_counter() - t0

    if "2d" in meths and pert != "half-frames":
        bench.seconds["2d"] += t_perturb
        bench.add("2d", "predictions", pert, masks, "2D")
    if "3d2d" in meths:
        t0 = time.perf_counter()
        source = inp.user_mesh if inp.user_mesh is not None else geometry
        out = fusion_baseline(source, inp.capture, masks, frames=inp.scored, cutoff_deg=cutoff_deg, stride=stride,
                              progress=bench.progress)
        bench.seconds["3d2d"] += time.perf_counter() - t0
        bench.add("3d2d", "predictions", pert, out, "3D/2D")
    if "field" in meths:
        t0 = time.perf_counter()
        frames = labelled_frames(inp.capture, "predictions", rec, predictions=masks)
        fit = fit_semantics(geometry.field, frames, seed=seed, progress=bench.progress)
        out = _render_field(geometry, fit.head, inp.capture, inp.scored, bench.progress)
        bench.seconds["field"] += time.perf_counter() - t0
        bench.add("field", "predictions", pert, out, "field")


def _run_annotation_field(bench: _BenchRows, sem: FieldRenderer, rec: Recipe, *, seed: int) -> str | None:
    """The field taught by the expert annotations alone (the paper's upper reference), or the
    note saying why that row is missing."""
    capture = bench.inputs.capture
    if not capture.has_annotations:
        return "the capture has no annotations/, so there is no annotation-trained field row"
    t0 = time.perf_counter()
    fit = fit_semantics(sem.field, labelled_frames(capture, "annotations", rec), seed=seed, progress=bench.progress)
    out = _render_field(sem, fit.head, capture, bench.inputs.scored, bench.progress)
    bench.seconds["field"] += time.perf_counter() - t0
    bench.add("field", "annotations", "none", out, "field (annotations)")
    return None


def _write_bench(result: dict, out_dir: Path) -> None:
    """bench.json (the numbers), bench.md (the paper's tables) and bench.png (the bars), all
    three moved into OUT together when written (other files in OUT stay)."""
    with building(out_dir, merge=True) as partial:
        (partial / "bench.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
        (partial / "bench.md").write_text(bench_markdown(result), encoding="utf-8")
        bench_plot(result, partial / "bench.png")


def _half_geometry_note(user_mesh: bool, field: bool, refit: bool) -> str:
    fitted = "refit on kept frames" if refit else "shared (all frames)"
    if not user_mesh:
        return fitted
    return f"3D/2D: user mesh; field: {fitted}" if field else "user mesh"


# ------------------------------------------------------------------------------------------
# tables and plot
# ------------------------------------------------------------------------------------------
def _find(rows: list[dict], method: str, labels: str, pert: str, cls: str) -> dict | None:
    for r in rows:
        if (r["method"], r["labels"], r["perturbation"], r["class"]) == (method, labels, pert, cls):
            return r
    return None


def _series(result: dict) -> list[tuple[str, str]]:
    """(method, labels) pairs present, in table order."""
    seen = []
    for m in METHODS:
        for lab in ("predictions", "annotations"):
            if any(r["method"] == m and r["labels"] == lab for r in result["rows"]) and (m, lab) not in seen:
                seen.append((m, lab))
    return seen


def _label(method: str, labels: str) -> str:
    name = METHOD_NAMES[method]
    return f"{name} (annotations)" if labels == "annotations" else name


def _bold_table(values: list[list[float | None]]) -> list[list[str]]:
    """Format to 3 decimals; the best value of each column (ties included) in bold."""
    cols = len(values[0]) if values else 0
    best = []
    for j in range(cols):
        col = [round(v[j], 3) for v in values if v[j] is not None]
        best.append(max(col) if col else None)
    out = []
    for v in values:
        row = []
        for j, x in enumerate(v):
            if x is None:
                row.append("-")
            elif best[j] is not None and round(x, 3) == best[j] and len(values) > 1:
                row.append(f"**{x:.3f}**")
            else:
                row.append(f"{x:.3f}")
        out.append(row)
    return out


def _table1_classes(result: dict) -> list[str]:
    """Wound bed plus granulation and slough (the paper's columns) when present in the
    class map; for other class maps, every non-background class with a population."""
    names = {r["class"] for r in result["rows"]}
    cols = [c for c in TABLE1_CLASSES if c in names]
    if not cols:
        cols = sorted({r["class"] for r in result["rows"] if r["n"] and r["class"] not in (WOUND_BED, "background")})
    return [WOUND_BED, *cols]


def bench_markdown(result: dict) -> str:
    """Tables shaped like the paper's Table 1 (accuracy) and Table 2 (robustness)."""
    series = _series(result)
    lines = _intro_lines(result) + _table1_lines(result, series) + _table2_lines(result, series) + _time_lines(result)
    return "\n".join(lines) + "\n"


def _intro_lines(result: dict) -> list[str]:
    """What was scored against what, and what each method is, so the tables read on their own."""
    lines = [
        "# labelsynth benchmark",
        "",
        f"Capture `{result['capture']}`: {result['frames']} frames, {len(result['annotated_frames'])} annotated "
        f"(never scored), {result['scored_frames']} scored against `{result['truth']}`. Recipe `{result['recipe']}`, "
        f"device {result['device']}, seed {result['seed']}.",
        "",
        "Scores: per-frame Dice (DSC) and recall averaged over the frames whose truth contains the class "
        "(the paper's population rule); n = population size.",
        "",
    ]
    methods = result["methods"]
    if "2d" in methods:
        lines.append("- 2D: the capture's predictions themselves.")
    if "3d2d" in methods:
        lines.append(
            "- 3D/2D: the predictions voted onto the mesh (|cos|-weighted per-vertex majority, cut-off "
            f"{result['fusion']['cutoff_deg']:g} deg, mesh: {result['fusion']['mesh']}) and rendered back."
        )
    if "field" in methods:
        lines.append(
            "- Field: the semantic field trained on the predictions (geometry fitted once and shared by all rows, "
            "half-frames aside: see below; only the semantic stage is refitted). Field (annotations): trained on the expert "
            "annotations alone."
        )
    lines.append("")
    if "half-frames" in result["perturbations"]:
        lines += [
            f"Half the frames: {result['half_frames_kept']} of {result['frames']} frames' predictions (every other "
            f"frame) vote / teach; geometry for that row: {result['half_frames_geometry']}. All rows are scored on "
            "the same frames.",
            "",
        ]
    for note in result.get("notes", []):
        lines += [f"Note: {note}.", ""]
    return lines


def _table1_lines(result: dict, series: list[tuple[str, str]]) -> list[str]:
    """The paper's Table 1: every method's unperturbed Dice and recall per reported class."""
    rows = result["rows"]
    classes = _table1_classes(result)
    t1 = [(m, lab) for m, lab in series if _find(rows, m, lab, "none", WOUND_BED)]
    lines = ["## Table 1: accuracy (no perturbation)", ""]
    if not t1:
        return lines + ["(no unperturbed rows were run)", ""]
    header = "| Method | " + " | ".join(f"{c.replace('_', ' ').title()} DSC | Recall" for c in classes) + " |"
    lines += [header, "|---|" + "---:|---:|" * len(classes)]
    values = []
    for m, lab in t1:
        v = []
        for c in classes:
            r = _find(rows, m, lab, "none", c)
            v += [r["dice"] if r else None, r["recall"] if r else None]
        values.append(v)
    for (m, lab), cells in zip(t1, _bold_table(values)):
        lines.append(f"| {_label(m, lab)} | " + " | ".join(cells) + " |")
    pops = []
    for c in classes:
        r = next((r for r in rows if r["class"] == c and r["perturbation"] == "none"), None)
        pops.append(f"{c.replace('_', ' ')} n={r['n'] if r else 0}")
    return lines + ["", "Population sizes: " + ", ".join(pops) + ".", ""]


def _table2_lines(result: dict, series: list[tuple[str, str]]) -> list[str]:
    """The paper's Table 2: wound-bed Dice and recall of every method under each perturbation."""
    rows = result["rows"]
    lines = ["## Table 2: robustness (wound bed)", "",
             "Best per column within each perturbation in bold.", "",
             "| Method | Perturbation | DSC | Recall |", "|---|---|---:|---:|"]
    for pert in result["perturbations"]:
        block = [(m, lab) for m, lab in series if _find(rows, m, lab, pert, WOUND_BED)]
        if not block:
            continue
        values = [[_find(rows, m, lab, pert, WOUND_BED)["dice"], _find(rows, m, lab, pert, WOUND_BED)["recall"]]
                  for m, lab in block]
        for (m, lab), cells in zip(block, _bold_table(values)):
            lines.append(f"| {_label(m, lab)} | {PERTURBATION_NAMES[pert]} | {cells[0]} | {cells[1]} |")
    return lines


def _time_lines(result: dict) -> list[str]:
    """Each method's time and the geometry fits, since cost is part of the comparison."""
    lines = ["", "## Time", "", "| | seconds |", "|---|---:|"]
    for m, s in result["seconds"].items():
        lines.append(f"| {METHOD_NAMES[m]} (all rows, geometry excluded) | {s:.1f} |")
    for k, s in result.get("timing", {}).items():
        lines.append(f"| {k.replace('_', ' ')} | {s:.1f} |")
    return lines


def bench_plot(result: dict, path: str | Path) -> None:
    """Grouped bars: wound-bed Dice and recall per perturbation, one bar per method."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    rows = result["rows"]
    perts = result["perturbations"]
    series = _series(result)
    fig = Figure(figsize=(max(6.0, 2.2 * len(perts) + 2), 4.2), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    width = 0.8 / max(1, len(series))
    x = np.arange(len(perts))
    values = {}
    for metric in ("dice", "recall"):
        for m, lab in series:
            rs = [_find(rows, m, lab, p, WOUND_BED) for p in perts]
            values[metric, m, lab] = np.array(
                [np.nan if r is None or r[metric] is None else r[metric] for r in rs], dtype=float
            )
    # The methods differ by a few hundredths: an axis from 0 would hide that, so it starts
    # 0.05 below the lowest bar (rounded down to 0.05) and every bar carries its value.
    finite = np.concatenate([v[np.isfinite(v)] for v in values.values()] + [np.array([1.0])])
    floor = max(0.0, np.floor((finite.min() - 0.05) * 20) / 20)
    for ax, metric, title in zip(axes, ("dice", "recall"), ("Wound bed Dice", "Wound bed recall")):
        for k, (m, lab) in enumerate(series):
            bars = ax.bar(x + (k - (len(series) - 1) / 2) * width, values[metric, m, lab], width, label=_label(m, lab))
            ax.bar_label(bars, fmt="%.3f", rotation=90, padding=2, fontsize=7)
        ax.set_xticks(x, [PERTURBATION_NAMES[p] for p in perts], rotation=15)
        ax.set_title(title if floor == 0 else f"{title} (axis from {floor:.2f})")
        ax.set_ylim(floor, 1.0 + 0.12 * (1.0 - floor))  # headroom for the value labels
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("score")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=max(1, len(series)),
               fontsize="small")
    fig.savefig(path, dpi=110)
