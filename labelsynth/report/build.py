"""Assemble report.json, report.html and the labelled mesh of an expand output folder."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..capture.model import Capture
from ..classes import WOUND_BED, ClassMap
from ..errors import LabelsynthError
from ..export.mesh import MESH_FORMATS, export_labelled_mesh
from ..outdir import write_text_atomic
from ..progress import phase
from ..render.renderer import FieldRenderer
from ..rundir import MESH_STEM, RunFolder
from ..semantics.head import SemanticHead
from . import plots
from .consistency import (
    Check,
    agreement,
    checked_keys,
    class_presence,
    flag_frames,
    leave_one_out,
    pairwise_consistency,
)
from .html import render_html

# names the leave-one-out candidates -> a head per name trained without it
LeaveOneOutHeads = Callable[[list[str]], dict[str, SemanticHead]]


def _inputs(capture: Capture) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Every annotation and prediction of the capture, by frame name."""
    ann, pred = {}, {}
    for i, f in enumerate(capture.frames):
        a = capture.load_annotation(i)
        if a is not None:
            ann[f.name] = a
        p = capture.load_prediction(i)
        if p is not None:
            pred[f.name] = p
    return ann, pred


def _median_over_present(frames: list[dict], field: str, key: str) -> float | None:
    vals = [f[field][key] for f in frames if f.get(field) and key in f.get("_present", ())]
    return float(np.median(vals)) if vals else None


def _agreement_rows(names: list[str], ann: dict, pred: dict, masks: dict, classes: ClassMap) -> list[dict]:
    """Step 1: how far every input mask is from the field's mask of its frame (one row per frame)."""
    frames: list[dict] = []
    for name in names:
        sources, by_source = [], {}
        for source, store in (("annotation", ann), ("prediction", pred)):
            if name in store:
                sources.append(source)
                by_source[source] = agreement(store[name], masks[name], classes)
        ref = ann.get(name, pred.get(name))
        present = set()
        if ref is not None:
            pa, pb = class_presence(ref, classes), class_presence(masks[name], classes)
            present = {k for k in pa if pa[k] > 0 or pb[k] > 0}
        frames.append({
            "name": name,
            "annotated": name in ann,
            "sources": sources,
            "agreement": by_source.get("annotation", by_source.get("prediction", {})),
            "agreement_by_source": by_source,
            "field_pixels": class_presence(masks[name], classes),
            "flagged": False,
            "reason": "",
            "_present": present,
        })
    return frames


def _leave_one_out(view: FieldRenderer, capture: Capture, ann: dict, taught: dict,
                   loo_heads: LeaveOneOutHeads | None, progress: bool) -> dict[str, np.ndarray]:
    """Step 2: each annotated frame judged by a head that did not learn from it (the honest test:
    a field that learnt a wrong mask agrees with it)."""
    if not ann:
        return {}
    if loo_heads is None:
        raise ValueError("build_report: the leave-one-view-out needs loo_heads")
    # only frames with someone else left to learn from
    candidates = [n for n in capture.names if n in ann and any(t != n for t in taught)]
    if not candidates:
        return {}
    return leave_one_out(view, capture, loo_heads(candidates), progress=progress)


def _flag(frames: list[dict], ann: dict, pred: dict, masks: dict, loo_masks: dict, classes: ClassMap) -> None:
    """Step 4: flag the outliers, annotated frames by their leave-one-out Dice, others by agreement."""
    checks = []
    for f in frames:
        name = f["name"]
        if f["annotated"] and f.get("loo_dice"):
            keys = checked_keys(ann[name], loo_masks[name], classes)
            checks.append(Check(name, "loo", {k: 1.0 - f["loo_dice"][k] for k in keys}))
        elif f["sources"]:
            ref = ann.get(name, pred.get(name))
            keys = checked_keys(ref, masks[name], classes)
            checks.append(Check(name, "agreement", {k: 1.0 - f["agreement"][k] for k in keys}))
    flags = flag_frames(checks)
    for f in frames:
        f["flagged"], f["reason"] = flags.get(f["name"], (False, ""))


def _summary(capture: Capture, mode: str, frames: list[dict], ann: dict, pred: dict, pairwise: list,
             mesh_info: dict | None) -> dict:
    """Step 6: the numbers an annotator reads first."""
    classes = capture.classes
    keys = [WOUND_BED] + [classes.classes[i].name for i in classes.wound_bed_indices]
    shared = [v for i, row in enumerate(pairwise) for j, v in enumerate(row) if i < j and v is not None]
    return {
        "capture": str(capture.root),
        "labels": mode,
        "num_frames": len(frames),
        "num_annotated": len(ann),
        "num_predicted": len(pred),
        "keys": keys,
        "median_agreement": {k: _median_over_present(frames, "agreement", k) for k in keys},
        "median_loo_dice": {k: _median_over_present(frames, "loo_dice", k) for k in keys},
        "mean_pairwise_dice": float(np.mean(shared)) if shared else None,
        "flagged": [f["name"] for f in frames if f["flagged"]],
        "mesh": mesh_info,
        "flag_rule": "1 - Dice > median + max(3 * 1.4826 * MAD, 0.05) and > 0.15, per class, "
                     "annotated frames by leave-one-out Dice, others by agreement",
    }


def _figures(capture: Capture, report: dict, ann: dict, pred: dict, masks: dict,
             loo_masks: dict) -> tuple[dict, dict]:
    """Step 7: the plots and, for every flagged frame, its overlay strip."""
    classes, names, frames = capture.classes, capture.names, report["frames"]
    keys, views = report["summary"]["keys"], report["views"]
    figures = {"agreement": plots.agreement_plot(frames, keys, classes),
               "class_area": plots.class_area_plot(names, [f["field_pixels"] for f in frames], classes)}
    if views:
        figures["pairwise"] = plots.pairwise_heatmap(views, report["pairwise"])
    index = {n: i for i, n in enumerate(names)}
    strips = {}
    for f in frames:
        if not f["flagged"]:
            continue
        name = f["name"]
        if name in loo_masks:
            inp, fm, label = ann[name], loo_masks[name], "field without this frame"
        else:
            inp, fm, label = ann.get(name, pred.get(name)), masks[name], "field"
        strips[name] = plots.overlay_strip(capture.load_image(index[name]), inp, fm, classes,
                                           f"{name}: {f['reason']}", label)
    return figures, strips


def build_report(
    out: RunFolder | str | Path,
    capture: Capture,
    view: FieldRenderer,
    masks: dict[str, np.ndarray],
    mode: str,
    *,
    taught: dict[str, np.ndarray],
    loo_heads: LeaveOneOutHeads | None = None,
    progress: bool = True,
    mesh_format: str | None = "ply",
    mm_per_unit: float | None = None,
    loo: bool = True,
) -> dict:
    """Write OUT/report.json, OUT/report.html and OUT/mesh.ply (+ .glb); return the report.

    ``view`` renders the fitted field; ``masks`` are the field's masks by frame name (what
    expand wrote to OUT/masks); ``taught`` the masks the field learnt from, by frame name (the
    caller's rule decides which: ``pipeline.labelled_frames``). ``loo_heads(names)`` returns,
    for each name, a head trained without that frame (needed for the leave-one-view-out; the
    caller supplies it, so the report knows nothing of how a field is fitted); each left-out
    frame is rendered with its own head. ``mesh_format=None`` skips the mesh (and its areas).
    ``loo=False`` skips the leave-one-view-out refits (then annotated frames are judged by
    agreement only).
    """
    t0 = time.time()
    run = out if isinstance(out, RunFolder) else RunFolder(out)
    classes: ClassMap = capture.classes
    names = capture.names
    missing = [n for n in names if n not in masks]
    if missing:
        raise LabelsynthError(f"report: no field mask for frame(s) {', '.join(missing[:5])}")
    if mesh_format is not None and mesh_format not in MESH_FORMATS:
        raise LabelsynthError(f"--mesh-format must be one of {', '.join(MESH_FORMATS)}, not '{mesh_format}'")
    seconds: dict[str, float] = {}
    with phase(seconds, "agreement", "report: reading every input mask", progress):
        ann, pred = _inputs(capture)
        frames = _agreement_rows(names, ann, pred, masks, classes)
    with phase(seconds, "leave_one_out"):
        loo_masks = _leave_one_out(view, capture, ann, taught, loo_heads, progress) if loo else {}
    for f in frames:
        if f["annotated"]:
            m = loo_masks.get(f["name"])
            f["loo_dice"] = None if m is None else agreement(ann[f["name"]], m, classes)

    # Step 3: cross-view consistency of the inputs the field learnt from
    views = [n for n in names if n in taught]
    cams = capture.unit_cameras()
    index = {n: i for i, n in enumerate(names)}
    with phase(seconds, "pairwise"):
        pairwise = pairwise_consistency(
            view.caster(), [cams[index[n]] for n in views], [taught[n] for n in views], classes, progress=progress,
        ) if views else []

    _flag(frames, ann, pred, masks, loo_masks, classes)
    # Step 5: the labelled surface
    mesh_info = None
    if mesh_format is not None:
        with phase(seconds, "mesh", f"report: labelled mesh ({mesh_format})", progress):
            mesh_info = export_labelled_mesh(view, run.path, mesh_format=mesh_format, mm_per_unit=mm_per_unit,
                                             stem=MESH_STEM).to_dict()
    summary = _summary(capture, mode, frames, ann, pred, pairwise, mesh_info)
    for f in frames:
        f.pop("_present")
    report = {"frames": frames, "views": views, "pairwise": pairwise, "summary": summary}
    with phase(seconds, "figures", "report: figures", progress):
        figures, strips = _figures(capture, report, ann, pred, masks, loo_masks)
    summary["seconds"] = time.time() - t0
    summary["phase_seconds"] = seconds
    write_text_atomic(run.report_json, json.dumps(report, indent=2))
    write_text_atomic(run.report_html, render_html(report, figures, strips))
    return report
