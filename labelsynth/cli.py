"""The `labelsynth` command line: parses, calls the library, prints. Nothing else lives here."""

from __future__ import annotations

import errno
import functools
import os
import sys
import warnings
from pathlib import Path
from typing import Optional

import typer
from typer.core import TyperGroup

try:  # typer 0.2x vendors click as typer._click; older typers use click itself
    from typer._click import exceptions as _usage
except ImportError:  # pragma: no cover - depends on the installed typer
    from click import exceptions as _usage

from .errors import CheckError, LabelsynthError
from .outdir import Interrupted

PROG = "labelsynth"


def _one_line(text: str) -> str:
    return " ".join(text.split())


class _OneLineUsageErrors(TyperGroup):
    """click's usage errors (``--seed abc``, a missing ``--out``, an unknown command or option)
    as ONE line on stderr, ``labelsynth: error: <command>: <what is wrong> (see <command>
    --help)``, exit code 2: the same shape as every other error, never the usage text or a
    framed panel. ``labelsynth`` alone still prints the help."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _usage.NoArgsIsHelpError as exc:  # the help is printed (rich prints it as it is made)
            if exc.format_message().strip():
                typer.echo(exc.format_message(), err=True)
            sys.exit(exc.exit_code)
        except _usage.ClickException as exc:
            ctx = getattr(exc, "ctx", None)
            where = ctx.command_path if ctx is not None else (prog_name or PROG)
            message = _one_line(exc.format_message())
            if isinstance(exc, _usage.UsageError):
                message += f" (see '{where} --help')"
            typer.echo(f"{PROG}: error: {where}: {message}", err=True)
            sys.exit(exc.exit_code)
        except typer.Abort:  # Ctrl-C at a prompt, or EOF
            typer.echo(f"{PROG}: interrupted", err=True)
            sys.exit(130)
        sys.exit(code if isinstance(code, int) else 0)


app = typer.Typer(
    cls=_OneLineUsageErrors,
    add_completion=False,
    no_args_is_help=True,
    help="View-consistent segmentation masks for every frame of a capture, from a 3D semantic field.",
    pretty_exceptions_enable=False,
)


def _fail(message: str) -> None:
    typer.echo(f"{PROG}: error: {_one_line(message)}", err=True)
    raise typer.Exit(code=2)


_OS_PROBLEMS = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "read-only file system",
    errno.EFBIG: "file too large for this file system (or the process's file size limit)",
    errno.EIO: "input/output error",
    errno.ENAMETOOLONG: "file name too long",
    errno.ELOOP: "too many levels of symbolic links",
    errno.EISDIR: "is a folder",
    errno.ENOTDIR: "a part of the path is not a folder",
    errno.EEXIST: "exists",
}


def os_error_line(exc: OSError) -> str:
    """One line for an OSError the library did not turn into a LabelsynthError: the path(s)
    and the problem (``no space left on the device``, ``permission denied``, ...)."""
    problem = _OS_PROBLEMS.get(exc.errno) or (exc.strerror or "").lower() or _one_line(str(exc)) or type(exc).__name__
    paths = [os.fsdecode(p) for p in (exc.filename, exc.filename2) if p is not None]
    where = " -> ".join(paths) if paths else "writing the output"
    return f"{where}: {problem}"


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one line on stderr, ``labelsynth: warning: ...`` (not Python's two-line
    form with the source line that raised it)."""
    typer.echo(f"{PROG}: warning: {_one_line(str(message))}", err=True)


def friendly_errors(func):
    """Turn the library's user-facing errors into one line on stderr and exit code 2
    (a failed input check: one line per bad file, then one summary line); an OSError
    (full disk, no permission, read-only file system) is one line naming the path; Ctrl-C
    and SIGTERM (``outdir.Interrupted``) exit 130 / 143 after the partial output is removed."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _warning_line
                return func(*args, **kwargs)
        except CheckError as exc:
            lines = exc.problems if len(exc.problems) == 1 else [*exc.problems, exc.summary]
            for line in lines[:-1]:
                typer.echo(f"{PROG}: error: {_one_line(line)}", err=True)
            _fail(lines[-1])
        except LabelsynthError as exc:  # a text the user typed may hold a line break: one line all the same
            _fail(str(exc) or type(exc).__name__)
        except FileNotFoundError as exc:
            _fail(f"{exc.filename or ''}: file not found".lstrip(": "))
        except OSError as exc:
            _fail(os_error_line(exc))
        except KeyboardInterrupt as exc:  # Ctrl-C, or outdir.Interrupted for SIGTERM
            signame = exc.signal_name if isinstance(exc, Interrupted) else "SIGINT"
            code = exc.exit_code if isinstance(exc, Interrupted) else 130
            try:
                typer.echo(f"{PROG}: interrupted ({signame})", err=True)
            except KeyboardInterrupt:  # another Ctrl-C: the cleanup is done, leave now
                os._exit(code)
            raise typer.Exit(code=code)

    return wrapper


@app.command()
@friendly_errors
def synth(
    out: Path = typer.Argument(..., help="Folder to create: OUT/capture (the capture) and OUT/truth (exact masks)."),
    frames: int = typer.Option(50, min=2, help="Number of frames."),
    annotated: int = typer.Option(4, min=0, help="Frames with expert annotations (well spread)."),
    width: int = typer.Option(640, min=16, help="Image width in pixels."),
    height: int = typer.Option(480, min=16, help="Image height in pixels."),
    noise: float = typer.Option(1.0, min=0.0, help="Noise level of the automatic predictions (0 = exact)."),
    seed: int = typer.Option(0, help="Random seed; the same seed gives the same capture."),
    layout: str = typer.Option(
        "one-sided", help="one-sided (a hand-held arc above a wound on a limb or torso) | all-around "
        "(a wound wrapped around a limb, filmed in one turn around it) | all-around-uneven (the same turn, dwelling on one "
        "side of the limb for 3/4 of the frames and passing the other side quickly).",
    ),
    phone: bool = typer.Option(False, "--phone", help="Phone-video frames: every option below on at a realistic value "
                               "(exposure 0.5, white balance 0.05, defocus 2, motion blur 8, noise 2, JPEG 80, "
                               "distance 0.3, zoom 0.25); any of them given explicitly wins."),
    exposure_drift: Optional[float] = typer.Option(None, "--exposure-drift", help="Auto exposure drifting along the path within +-this many stops (EV)."),
    white_balance_drift: Optional[float] = typer.Option(None, "--white-balance-drift", help="Red/blue gains drifting within 1 +- this."),
    defocus_blur: Optional[float] = typer.Option(None, "--defocus-blur", help="Largest defocus radius, pixels at 640 wide (each frame: 0..this)."),
    motion_blur: Optional[float] = typer.Option(None, "--motion-blur", help="Longest motion-blur streak, pixels at 640 wide (each frame: 0..this)."),
    sensor_noise: Optional[float] = typer.Option(None, "--sensor-noise", help="Sensor noise sigma in grey levels (grows with exposure gain)."),
    jpeg_quality: Optional[int] = typer.Option(None, "--jpeg-quality", help="Write images/ as JPEG at this quality (1..100; 0 = PNG)."),
    distance_change: Optional[float] = typer.Option(None, "--distance-change", help="Camera distance factor along the path: 1/(1+x)..1+x."),
    zoom: Optional[float] = typer.Option(None, "--zoom", help="Focal length factor along the path: 1/(1+x)..1+x (per-frame intrinsics)."),
    force: bool = typer.Option(False, help="Replace OUT if it exists."),
) -> None:
    """Make a synthetic wound capture with exact truth for every frame (optionally phone-like frames)."""
    from .evaluation.synth import PHONE, SynthConfig, synthesize

    given = {"exposure_drift": exposure_drift, "white_balance_drift": white_balance_drift, "defocus_blur": defocus_blur,
             "motion_blur": motion_blur, "sensor_noise": sensor_noise, "jpeg_quality": jpeg_quality,
             "distance_change": distance_change, "zoom": zoom}
    varied = {**(PHONE if phone else {}), **{k: v for k, v in given.items() if v is not None}}
    cfg = SynthConfig(frames=frames, annotated=annotated, width=width, height=height, noise=noise, seed=seed,
                      layout=layout, **varied)
    result = synthesize(out, cfg, force=force)
    typer.echo(f"capture: {result.capture_dir}")
    typer.echo(f"truth:   {result.truth_dir}")
    typer.echo(f"{result.num_frames} frames, {len(result.annotated)} annotated, {result.seconds:.1f} s"
               + (f"; phone-like: {', '.join(f'{k}={v:g}' for k, v in cfg.varied.items())}" if cfg.varied else ""))


@app.command()
@friendly_errors
def poses(
    capture: Path = typer.Argument(..., help="Capture folder with images/."),
    out: Optional[Path] = typer.Option(None, help="Write transforms.json here instead of CAPTURE/transforms.json."),
    force: bool = typer.Option(False, help="Overwrite an existing transforms.json."),
    matching: str = typer.Option("auto", help="auto | sequential | exhaustive"),
) -> None:
    """Estimate camera poses with pycolmap structure-from-motion and write transforms.json."""
    from .capture.poses import estimate_poses

    report = estimate_poses(capture, out=out, force=force, matching=matching)
    typer.echo(report.summary())


@app.command("import")
@friendly_errors
def import_(
    source: Path = typer.Argument(..., metavar="VIDEO_OR_FOLDER", help="A video (MP4, MOV, MKV, AVI, WebM) or a folder of photos."),
    out: Path = typer.Option(..., "--out", help="Capture folder to create (images/, transforms.json, import.json)."),
    frames: int = typer.Option(50, min=1, help="Frames to keep: a video must give this many usable ones; a folder keeps at most this many."),
    max_side: int = typer.Option(1280, "--max-side", min=16, help="Long side of the written frames in pixels (never enlarged)."),
    poses: bool = typer.Option(True, "--poses/--no-poses", help="Estimate camera poses with pycolmap (as `labelsynth poses`)."),
    force: bool = typer.Option(False, help="Replace OUT if it exists."),
) -> None:
    """Make a capture from a phone video or a folder of photos: sharp, distinct frames, resized and posed."""
    from .capture.video import ImportConfig, import_capture

    report = import_capture(source, out, ImportConfig(frames=frames, max_side=max_side, poses=poses), force=force)
    typer.echo(report.summary())


@app.command()
@friendly_errors
def expand(
    capture: Path = typer.Argument(..., help="Capture folder (transforms.json, cameras_sphere.npz or sparse/0; images/, annotations/, predictions/)."),
    out: Path = typer.Option(..., "--out", help="Output folder (masks/, labels.h5, report.*)."),
    labels: Optional[str] = typer.Option(None, help="annotations | predictions | both (default: both when both exist)."),
    recipe: str = typer.Option("default", help="Recipe name (default, fast, quality, paper) or a YAML path."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    seed: int = typer.Option(0, help="Random seed."),
    set_: list[str] = typer.Option([], "--set", help="Override a recipe value, e.g. --set geometry.iterations=500"),
    force: bool = typer.Option(False, help="Replace a finished OUT."),
    mesh_format: str = typer.Option("ply", "--mesh-format", help="ply | glb: OUT/mesh.ply is always written; glb adds OUT/mesh.glb."),
    mm_per_unit: Optional[float] = typer.Option(None, "--mm-per-unit", help="Millimetres per scene unit (> 0): class areas in mm² too."),
    annotated_frames: Optional[str] = typer.Option(
        None, "--annotated-frames",
        help="Only these frames' annotations teach: names or 0-based indices (a,b,3), every:K or spread:N (default: all).",
    ),
    report: bool = typer.Option(
        True, "--report/--no-report",
        help="Write the consistency report and the labelled mesh (its leave-one-out refits take minutes); "
             "--no-report writes masks, labels.h5, field.pt and run.json only (`labelsynth report OUT` adds it later).",
    ),
    geometry: Optional[Path] = typer.Option(
        None, "--geometry",
        help="Reuse the geometry of `labelsynth suggest`'s OUT or an earlier expand's OUT (skips stage 1); refused "
             "unless it was fitted on these images and cameras with the same geometry recipe and seed.",
    ),
) -> None:
    """Fit a 3D semantic field to the capture and render consistent masks for every frame."""
    from .options import ExpandOptions
    from .pipeline import expand as run_expand

    options = ExpandOptions(labels=labels, recipe=recipe, device=device, seed=seed, overrides=set_,
                            annotated_frames=annotated_frames, report=report, mesh_format=mesh_format,
                            mm_per_unit=mm_per_unit)
    result = run_expand(capture, out, options, geometry=geometry, force=force)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def suggest(
    capture: Path = typer.Argument(..., help="Capture folder (images and poses; no annotations needed)."),
    annotate: int = typer.Option(..., "--annotate", help="How many frames to name for annotation (1..6)."),
    objective: str = typer.Option("surface", help="surface: the most surface seen, each point at its best chosen view; frames: every frame's view seen by one chosen frame (greedy, then swaps)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for field.pt (the geometry), suggest.json and suggest.png (default: CAPTURE-suggest beside the capture)."),
    recipe: str = typer.Option("default", help="Recipe name (default, fast, quality, paper) or a YAML path; expand --geometry must use the same geometry section."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    seed: int = typer.Option(0, help="Random seed (expand --geometry must use the same)."),
    set_: list[str] = typer.Option([], "--set", help="Override a recipe value, e.g. --set geometry.iterations=500"),
    force: bool = typer.Option(False, help="Replace OUT if it exists."),
) -> None:
    """Fit the geometry (no labels needed) and name the frames that together show the most surface."""
    from .options import SuggestOptions
    from .suggest import suggest as run_suggest

    options = SuggestOptions(annotate=annotate, objective=objective, recipe=recipe, device=device, seed=seed,
                             overrides=set_)
    result = run_suggest(capture, options, out, force=force)
    typer.echo(result.summary())



@app.command()
@friendly_errors
def batch(
    source: Path = typer.Argument(..., metavar="CAPTURE_ROOT_OR_LIST", help="A folder searched for captures, or a text file of capture paths (one a line)."),
    out: Path = typer.Option(..., "--out", help="Batch folder: captures/<name>/, dataset.h5, batch.json, batch.html."),
    labels: Optional[str] = typer.Option(None, help="annotations | predictions | both (default: per capture, both when both exist)."),
    recipe: str = typer.Option("default", help="Recipe name (default, fast, quality, paper) or a YAML path."),
    device: str = typer.Option("auto", help="auto | cpu | cuda (auto: cuda only with --gpus-per-capture)."),
    seed: int = typer.Option(0, help="Random seed."),
    set_: list[str] = typer.Option([], "--set", help="Override a recipe value, e.g. --set geometry.iterations=500"),
    annotated_frames: Optional[str] = typer.Option(None, "--annotated-frames", help="As for expand, applied to every capture."),
    report: bool = typer.Option(True, "--report/--no-report", help="Write each capture's consistency report and mesh."),
    mesh_format: str = typer.Option("ply", "--mesh-format", help="ply | glb"),
    mm_per_unit: Optional[float] = typer.Option(None, "--mm-per-unit", help="Millimetres per scene unit (> 0)."),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster to attach to (default: RAY_ADDRESS, else a local instance)."),
    cpus_per_capture: Optional[int] = typer.Option(None, "--cpus-per-capture", min=1, help="CPUs (and threads) per capture (default: 4, at most a node's)."),
    gpus_per_capture: float = typer.Option(0.0, "--gpus-per-capture", min=0.0, help="GPUs per capture; only on a cluster with GPUs."),
    retries: int = typer.Option(2, "--retries", min=0, help="Retries of a capture whose worker died (user errors are not retried)."),
    force: bool = typer.Option(False, help="Redo captures that are finished and unchanged."),
) -> None:
    """Expand many captures as Ray tasks: resumable, one table of outcomes, one merged dataset.h5."""
    from rich.console import Console

    from .batch import rich_table, run_batch
    from .options import ExpandOptions

    opts = ExpandOptions(labels=labels, recipe=recipe, device=device, seed=seed, overrides=set_,
                         annotated_frames=annotated_frames, report=report, mesh_format=mesh_format,
                         mm_per_unit=mm_per_unit)
    result = run_batch(source, out, opts, address=address, cpus_per_capture=cpus_per_capture,
                       gpus_per_capture=gpus_per_capture, retries=retries, force=force)
    Console(width=None if sys.stdout.isatty() else 200).print(rich_table(result.rows))  # no folded reasons in logs
    typer.echo(result.summary())
    if not result.ok:
        raise typer.Exit(code=1)

@app.command()
@friendly_errors
def report(
    out: Path = typer.Argument(..., help="Output folder of labelsynth expand (field.pt, run.json, masks/)."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    mesh_format: Optional[str] = typer.Option(None, "--mesh-format", help="ply | glb (default: as before)."),
    mm_per_unit: Optional[float] = typer.Option(None, "--mm-per-unit", help="Millimetres per scene unit, > 0 (default: as before)."),
    loo: bool = typer.Option(True, "--loo/--no-loo", help="Refit the semantic stage without each annotated frame (the honest test)."),
) -> None:
    """Rebuild OUT/report.json, OUT/report.html and the labelled mesh from a finished expand."""
    from .pipeline import rebuild_report
    from .rundir import RunFolder

    rep = rebuild_report(out, device=device, mesh_format=mesh_format, mm_per_unit=mm_per_unit, loo=loo)
    flagged = rep["summary"]["flagged"]
    run = RunFolder(out)
    typer.echo(f"wrote {run.report_json} and {run.report_html}")
    typer.echo(f"{len(rep['frames'])} frames, {len(flagged)} flagged" + (f": {', '.join(flagged)}" if flagged else ""))


@app.command("export")
@friendly_errors
def export_(
    out: Path = typer.Argument(..., help="Output folder of labelsynth expand (labels.h5, report.json)."),
    fmt: str = typer.Option(..., "--format", help="cvat (a zip CVAT imports as 'Segmentation mask 1.1') | voc | coco | cityscapes."),
    to: Path = typer.Option(..., "--to", help="Where to write: a .zip for cvat, a folder for the others."),
    frames: str = typer.Option("all", "--frames", help="all | flagged (the report's flagged frames) | unannotated."),
    min_confidence: Optional[float] = typer.Option(None, "--min-confidence", help="Pixels less confident than this (0..1) become ignore (VOC's void, COCO: left out)."),
    force: bool = typer.Option(False, help="Replace PATH if it exists."),
) -> None:
    """Write OUT's masks for CVAT, Pascal VOC, COCO or Cityscapes-style trainers."""
    from .export.formats import export_run

    result = export_run(out, to, fmt=fmt, frames=frames, min_confidence=min_confidence, force=force)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def relabel(
    out: Path = typer.Argument(..., help="Output folder of labelsynth expand (field.pt, run.json, masks/)."),
    capture: Optional[Path] = typer.Option(None, help="The capture folder, if it moved since expand (default: the one in run.json)."),
    labels: Optional[str] = typer.Option(None, help="annotations | predictions | both (default: as the run)."),
    report: bool = typer.Option(True, "--report/--no-report", help="Rewrite the consistency report and the labelled mesh (--no-report: masks, labels.h5, field.pt, run.json only)."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    keep_previous: bool = typer.Option(False, "--keep-previous", help="Keep the replaced OUT as OUT.previous (default: removed once the new OUT is whole)."),
) -> None:
    """Re-train only the labels on OUT's frozen geometry after masks changed; replace OUT atomically."""
    from .pipeline import relabel as run_relabel

    result = run_relabel(out, capture=capture, labels=labels, report=report, device=device, keep_previous=keep_previous)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def demo(
    out: Path = typer.Option(Path("labelsynth-demo"), help="Folder for the synthetic capture and the results."),
    frames: int = typer.Option(12, min=4, help="Frames of the synthetic capture."),
    recipe: str = typer.Option("fast", help="Recipe for the expansion."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
) -> None:
    """The one-command tour: synthesise a capture, expand it, print Dice against the truth."""
    from .pipeline import demo as run_demo

    summary = run_demo(out, frames=frames, recipe=recipe, device=device)
    typer.echo(summary)


@app.command()
@friendly_errors
def segment(
    capture: Path = typer.Argument(..., help="Capture folder with images/."),
    model: Path = typer.Option(..., "--model", help="ONNX segmenter: input NCHW RGB (pixel_values), output logits (N,C,h,w)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for <image stem>.png class-id masks."),
    into_capture: bool = typer.Option(False, "--into-capture", help="Write CAPTURE/predictions/ instead of --out."),
    input_size: Optional[str] = typer.Option(None, "--input-size", help="WxH for models without a fixed input size (default 512x512)."),
    id_map: Optional[str] = typer.Option(None, "--id-map", help="Model index -> class id, e.g. 0:0,1:1,2:3; unmapped indices keep their number; 255 = ignore."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    batch_size: int = typer.Option(1, "--batch-size", min=1, help="Frames per model call."),
    force: bool = typer.Option(False, help="With --into-capture: replace existing predictions."),
) -> None:
    """Run a 2D ONNX segmenter over every frame (the "2D" baseline) and write class-id masks."""
    from .train.segment import resolve_out_dir, segment_capture

    out_dir = resolve_out_dir(capture, out, into_capture)
    report = segment_capture(
        capture, model, out_dir, input_size=input_size, id_map=id_map, device=device,
        batch_size=batch_size, overwrite=force or not into_capture,
    )
    typer.echo(report.summary())


@app.command()
@friendly_errors
def train(
    sources: list[Path] = typer.Argument(..., metavar="SOURCE", help="labels.h5 files written by expand and/or capture folders (their annotations/)."),
    out: Path = typer.Option(..., "--out", help="Model folder: model.onnx, checkpoint.pt, train.json, curves.png."),
    arch: Optional[str] = typer.Option(None, help="segformer (transformers, from a config; the default) | unet | fpn (segmentation-models-pytorch); --resume keeps the checkpoint's."),
    encoder: Optional[str] = typer.Option(None, help="segformer: b0 | b1; unet/fpn: resnet18, mobilenet_v2, ... (default: b0 / resnet18)."),
    input_size: Optional[str] = typer.Option(None, "--input-size", help="WxH every frame is resized to for training, and segment's input (default: the frames' size)."),
    steps: int = typer.Option(400, min=1, help="Optimiser steps (in all, counting those before --resume)."),
    batch_size: int = typer.Option(8, "--batch-size", min=1, help="Crops per step."),
    crop: int = typer.Option(256, min=16, help="Square training crop in pixels (smaller frames are padded with ignore)."),
    lr: float = typer.Option(6e-4, help="Peak learning rate (AdamW, linear warm-up, cosine decay)."),
    min_confidence: float = typer.Option(0.0, "--min-confidence", min=0.0, max=1.0, help="labels.h5 pixels less confident than this are ignored."),
    confidence_weight: bool = typer.Option(True, "--confidence-weight/--no-confidence-weight", help="Weigh each pixel by its labels.h5 confidence."),
    expert_weight: float = typer.Option(1.0, "--expert-weight", min=0.0, help="Weight of the pixels of expert-annotated frames."),
    class_weights: Optional[str] = typer.Option(None, "--class-weights", help="Per-class weights id:weight, e.g. 0:0.1,5:2 (others 1)."),
    dice_weight: float = typer.Option(1.0, "--dice-weight", min=0.0, help="Weight of the soft Dice term beside cross-entropy."),
    only_annotated: bool = typer.Option(False, "--only-annotated", help="From labels.h5, train on the expert-annotated frames only."),
    val_captures: Optional[str] = typer.Option(
        None, "--val-captures",
        help="Comma list of sources (name or path) held out for validation: they draw the curves and are not trained on.",
    ),
    val_split: str = typer.Option(
        "none", "--val-split",
        help="Without --val-captures: none (train on every frame given, no validation curve) | capture (hold out the "
             "last source) | frames (the last block of each source's frames) | auto (capture with 3+ sources, else "
             "frames). Held-out frames are not trained on; the log says how many.",
    ),
    eval_every: Optional[int] = typer.Option(None, "--eval-every", min=1, help="Validate and checkpoint every N steps (default: steps/10)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoint.pt up to --steps."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from the weights of another run (its MODEL_DIR or checkpoint.pt; its arch, encoder and input size), with a fresh optimiser and schedule."),
    force: bool = typer.Option(False, help="Replace the outputs of an earlier run in OUT."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    seed: int = typer.Option(0, help="Random seed."),
    workers: int = typer.Option(0, min=0, help="DataLoader worker processes for augmentation."),
) -> None:
    """Train a 2D segmenter (ONNX for `segment`) from labels.h5 files and capture annotations."""
    from .train import TrainConfig, train as run_train

    cfg = TrainConfig(
        arch=arch, encoder=encoder, input_size=input_size, steps=steps, batch_size=batch_size, crop=crop, lr=lr,
        min_confidence=min_confidence, confidence_weight=confidence_weight, expert_weight=expert_weight,
        class_weights=class_weights, dice_weight=dice_weight, only_annotated=only_annotated,
        val_captures=[] if val_captures is None else val_captures.split(","), val_split=val_split, eval_every=eval_every,
        device=device, seed=seed, workers=workers, init=None if init is None else str(init),
    )
    result = run_train(sources, out, cfg, force=force, resume=resume)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def selftrain(
    captures: list[Path] = typer.Argument(..., metavar="CAPTURE", help="Captures to label: every frame is segmented each round."),
    model: Path = typer.Option(..., "--model", help="The round-0 segmenter (ONNX, e.g. train's MODEL_DIR/model.onnx)."),
    out: Path = typer.Option(..., "--out", help="Folder for every round's masks, expansions and models, and selftrain.json."),
    rounds: int = typer.Option(1, min=1, help="Rounds of segment -> expand -> train (a larger --rounds continues a "
                        "finished loop; measured, a second round has not beaten the first: docs/training.md)."),
    labels: str = typer.Option("predictions", help="predictions (the masks fused by expand) | both (with each capture's "
                               "expert frames) | raw (the masks as they are, not fused: the baseline)."),
    holdout: list[Path] = typer.Option([], "--holdout", help="A capture whose annotations/ score every round (and validate "
                                       "training); never trained on. Repeatable."),
    also: list[Path] = typer.Option([], "--also", help="A source added to every round's training (labels.h5 or a capture "
                                    "folder, e.g. the expert frames of round 0). Repeatable."),
    recipe: str = typer.Option("default", help="expand's recipe (name or YAML path)."),
    set_: list[str] = typer.Option([], "--set", help="expand's recipe overrides, e.g. --set geometry.iterations=500"),
    input_size: Optional[str] = typer.Option(None, "--input-size", help="As for train."),
    steps: int = typer.Option(400, min=1, help="Optimiser steps of every round's training."),
    batch_size: int = typer.Option(8, "--batch-size", min=1, help="As for train."),
    crop: int = typer.Option(256, min=16, help="As for train."),
    lr: float = typer.Option(6e-4, help="As for train."),
    min_confidence: float = typer.Option(0.0, "--min-confidence", min=0.0, max=1.0, help="As for train."),
    confidence_weight: bool = typer.Option(True, "--confidence-weight/--no-confidence-weight", help="As for train."),
    expert_weight: float = typer.Option(1.0, "--expert-weight", min=0.0, help="As for train."),
    eval_every: Optional[int] = typer.Option(None, "--eval-every", min=1, help="As for train."),
    device: str = typer.Option("auto", help="auto | cpu | cuda (segment, expand and train)."),
    seed: int = typer.Option(0, help="Random seed of expand and train."),
    warm_start: bool = typer.Option(False, "--warm-start", help="Each round's model starts from the previous round's weights (round 1 from --model's checkpoint.pt beside it) instead of from scratch."),
    accumulate: bool = typer.Option(False, "--accumulate", help="Each round trains on the fused labels of every round so far, not only its own."),
    cross_fit: bool = typer.Option(False, "--cross-fit", help="From round 2, segment each capture with a model trained on the "
                                   "other captures' labels of the round before (two folds; 2+ captures), not with one "
                                   "that learnt its own labels."),
    agree: bool = typer.Option(False, "--agree", help="From round 2, train only on the pixels whose fused class the round "
                               "before gave too (the others are ignored)."),
    force: bool = typer.Option(False, help="Start over in OUT (else a rerun with the same settings continues)."),
) -> None:
    """The self-training loop: a model's masks of new captures -> expand -> a new model, round after round."""
    from rich.console import Console

    from .train import TrainConfig
    from .train.selftrain import SelfTrainConfig, selftrain as run_selftrain

    tcfg = TrainConfig(input_size=input_size, steps=steps, batch_size=batch_size, crop=crop, lr=lr,
                       min_confidence=min_confidence, confidence_weight=confidence_weight, expert_weight=expert_weight,
                       eval_every=eval_every, seed=seed)
    cfg = SelfTrainConfig(rounds=rounds, labels=labels, recipe=recipe, overrides=set_, seed=seed, device=device,
                          train=tcfg, warm_start=warm_start, accumulate=accumulate, cross_fit=cross_fit,
                          agree=agree)
    result = run_selftrain(captures, model, out, cfg, holdout=holdout, also=also, force=force)
    Console(width=None if sys.stdout.isatty() else 200).print(result.table(), markup=False, highlight=False)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def augment(
    out: Path = typer.Argument(..., help="A finished expand output (field.pt, run.json, labels.h5)."),
    views: int = typer.Option(..., "--views", help="Number of novel views to add."),
    seed: int = typer.Option(0, help="Random seed of the poses; the same seed gives the same views."),
    spread: str = typer.Option("1", help="How far poses stray from the captured path: a factor on the default bounds "
                               "(0 = the path itself), or key=value pairs: along, tilt (deg), distance, roll (deg), focal."),
    method: str = typer.Option("blend", help="blend (colours of the real frames that see each point) | head (the field's colour head)."),
    capture: Optional[Path] = typer.Option(None, help="The capture folder, if it moved since expand (default: the one in run.json)."),
    device: str = typer.Option("auto", help="auto | cpu | cuda."),
    force: bool = typer.Option(False, help="Replace OUT/augment if it exists."),
) -> None:
    """Add novel views (image, mask, validity) to an expand output: OUT/augment with augment.h5."""
    from .novel import augment as run_augment

    result = run_augment(out, views, seed=seed, spread=spread, method=method, device=device, capture=capture,
                         force=force)
    typer.echo(result.summary())


@app.command()
@friendly_errors
def bench(
    capture: Path = typer.Argument(..., help="Capture folder with predictions/ (and annotations/)."),
    truth: Path = typer.Option(..., "--truth", help="Folder of truth masks <image stem>.png for the frames to score."),
    out: Path = typer.Option(..., "--out", help="Folder for bench.json, bench.md, bench.png."),
    perturb: Optional[str] = typer.Option(None, "--perturb", help="Comma list of none,erosion-dilation,jitter,half-frames (default: all)."),
    methods: Optional[str] = typer.Option(None, "--methods", help="Comma list of 2d,3d2d,field (default: all)."),
    recipe: str = typer.Option("default", help="Recipe name (default, fast, quality, paper) or a YAML path."),
    device: str = typer.Option("auto", help="auto | cpu | cuda"),
    seed: int = typer.Option(0, help="Random seed (training and perturbations)."),
    set_: list[str] = typer.Option([], "--set", help="Override a recipe value, e.g. --set geometry.iterations=500"),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="World-coordinate mesh for 3D/2D instead of the fitted surface."),
    half_geometry: bool = typer.Option(True, "--half-geometry/--shared-geometry", help="Half-frames: refit geometry on the kept frames, or reuse the all-frames geometry."),
    cutoff: float = typer.Option(75.0, "--cutoff", help="3D/2D: views more grazing than this angle (degrees) do not vote."),
    annotated_frames: Optional[str] = typer.Option(
        None, "--annotated-frames",
        help="Only these frames' annotations teach: names or 0-based indices (a,b,3), every:K or spread:N (default: all).",
    ),
) -> None:
    """Paper Tables 1 and 2: 2D, 3D/2D and the field under each perturbation, scored against --truth."""
    from .evaluation.bench import bench_markdown, run_bench

    result = run_bench(
        capture, truth, out, perturbations=perturb, methods=methods, recipe=recipe, device=device,
        overrides=set_, seed=seed, mesh=mesh, half_geometry=half_geometry, cutoff_deg=cutoff,
        annotated_frames=annotated_frames,
    )
    typer.echo(bench_markdown(result))
    typer.echo(f"wrote {out / 'bench.json'}, {out / 'bench.md'}, {out / 'bench.png'}")


def main() -> None:  # pragma: no cover - console entry point alias
    app(prog_name=PROG)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
