"""The training run: sources -> split -> model -> optimiser steps -> MODEL_DIR.

MODEL_DIR holds ``model.onnx`` (``export_onnx``), ``checkpoint.pt`` (model, optimiser, step,
arguments, class table, history: ``--resume`` continues from its step), ``train.json``
(arguments, class table, split, per-evaluation losses and validation Dice per class, times)
and ``curves.png``. Every file is written beside itself as ``X.partial`` and renamed, so a
reader never sees half a file; Ctrl-C saves the checkpoint of the last finished step first.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from .. import __version__
from ..classes import IGNORE_ID, ClassMap
from ..device import optimiser_options, pick_device
from ..errors import LabelsynthError
from ..metrics import Counts
from ..outdir import atomic_file, check_writable, interruptible, write_text_atomic
from ..progress import console, make_progress
from .checkpoint import CHECKPOINT_FILE, load_checkpoint, save_checkpoint
from .contract import INPUT_NAME, OUTPUT_NAME, format_input_size, normalize, parse_input_size
from .data import (VAL_SPLITS, FrameDataset, Split, TrainError, load_sources, make_target, parse_class_weights,
                   require_source, split_by_capture)
from .loss import confusion_counts, segmentation_loss, upsample
from .model import ARCHS, build_model, input_multiple, resolve_encoder

OUTPUTS = ("model.onnx", "checkpoint.pt", "train.json", "curves.png")
MAX_STEPS = 10**9
MAX_BATCH = 4096
MAX_SIDE = 8192
MAX_WORKERS = 256


@dataclass
class TrainConfig:
    """Everything that decides a run (stored in checkpoint.pt and train.json)."""

    arch: str | None = None  # None: segformer, or the checkpoint's with --resume
    encoder: str | None = None  # None: the arch's default (segformer b0, unet/fpn resnet18), or the checkpoint's
    input_size: str | None = None  # "WxH" frames are resized to (and segment feeds); None: the frames' own size
    steps: int = 400  # ~8 min at batch 8, crop 256 with SegFormer-b0 on 2 CPU cores (1.2 s a step)
    batch_size: int = 8
    crop: int = 256
    lr: float = 6e-4
    weight_decay: float = 0.01
    warmup: float = 0.05  # fraction of the steps with a linear warm-up, then cosine decay
    dice_weight: float = 1.0
    min_confidence: float = 0.0
    confidence_weight: bool = True
    expert_weight: float = 1.0
    class_weights: str | None = None  # "id:weight,..." (unnamed classes weigh 1)
    only_annotated: bool = False
    val_captures: list[str] = field(default_factory=list)
    # none | capture | frames | auto, when no val_captures (data.split_by_capture). "none": validation never
    # changes the model, and holding out one of 3 single-expert-frame captures cost 0.158 wound-bed and
    # 0.207 tissue-mean test Dice in bench_retrain (a1-split vs a1, docs/training.md)
    val_split: str = "none"
    eval_every: int | None = None  # None: steps // 10
    device: str = "auto"
    seed: int = 0
    workers: int = 0
    # a MODEL_DIR (or its checkpoint.pt) whose weights start this run (its arch, encoder and input size are
    # adopted; the optimiser, the schedule and the step start afresh): a warm start, e.g. selftrain's next round
    init: str | None = None

    def check(self) -> None:
        """Every value of the run, before any source is read: one ``TrainError`` line naming the option."""
        from ..options import DeviceChoice, OptionError, finite_number, given_text, seed_value, whole_number

        try:
            self.steps = whole_number(self.steps, "--steps", 1, MAX_STEPS)
            self.batch_size = whole_number(self.batch_size, "--batch-size", 1, MAX_BATCH)
            self.crop = whole_number(self.crop, "--crop", 16, MAX_SIDE)
            self.lr = finite_number(self.lr, "--lr", 0.0, 10.0, low_open=True)
            self.weight_decay = finite_number(self.weight_decay, "weight_decay", 0.0)
            self.warmup = finite_number(self.warmup, "warmup", 0.0, 1.0)
            self.dice_weight = finite_number(self.dice_weight, "--dice-weight", 0.0)
            self.min_confidence = finite_number(self.min_confidence, "--min-confidence", 0.0, 1.0)
            self.expert_weight = finite_number(self.expert_weight, "--expert-weight", 0.0)
            if self.eval_every is not None:
                self.eval_every = whole_number(self.eval_every, "--eval-every", 1, MAX_STEPS)
            self.seed = seed_value(self.seed)
            self.workers = whole_number(self.workers, "--workers", 0, MAX_WORKERS)
            self.device = DeviceChoice.parse(self.device, "--device").value
            for option, name in (("--arch", "arch"), ("--encoder", "encoder"), ("--input-size", "input_size"),
                                 ("--class-weights", "class_weights"), ("--init", "init")):
                given_text(getattr(self, name), option)
            if self.arch is not None and self.arch not in ARCHS:
                raise OptionError(f"--arch must be one of {', '.join(ARCHS)}, not {self.arch!r}")
            if self.val_split not in VAL_SPLITS:
                raise OptionError(f"--val-split {self.val_split!r}: expected one of {', '.join(VAL_SPLITS)}")
            for key in self.val_captures:
                if not isinstance(key, str) or not key.strip():
                    raise OptionError(f"--val-captures: an empty source name in {','.join(map(str, self.val_captures))!r}")
        except OptionError as exc:
            raise TrainError(str(exc)) from None
        self.resize_to()

    def resize_to(self) -> tuple[int, int] | None:
        """``input_size`` as (W, H) every frame is resized to (None: frames keep their size)."""
        return parse_input_size(self.input_size, error=TrainError, minimum=16, maximum=MAX_SIDE)


@dataclass
class TrainResult:
    out: Path
    step: int
    steps: int
    seconds: float
    device: str
    history: list[dict[str, Any]]
    split: str
    train_frames: int
    val_frames: int
    resumed_from: int | None = None

    def summary(self) -> str:
        last = self.history[-1] if self.history else {}
        dice = last.get("val_dice") or {}
        shown = ", ".join(f"{k} {v:.3f}" for k, v in dice.items() if v is not None)
        resumed = f" (resumed at step {self.resumed_from})" if self.resumed_from is not None else ""
        line = (f"trained {self.step}/{self.steps} steps{resumed} on {self.train_frames} frames in {self.seconds:.1f} s "
                f"({self.device}) -> {self.out}/model.onnx")
        if "train_loss" in last:
            line += f"; loss {last['train_loss']:.3f}"
        if shown:
            line += f"; validation Dice ({self.val_frames} frames): {shown}"
        return line


# --- output folder ----------------------------------------------------------------------------
def check_out(out: Path, sources: list[str | Path], *, force: bool, resume: bool) -> None:
    """Refuse a non-empty MODEL_DIR (unless ``force``/``resume``) and any MODEL_DIR that is a source.
    Writes nothing: MODEL_DIR is made (``make_out``) only once the sources have been read."""
    try:
        check_writable(out)
    except LabelsynthError as exc:
        raise TrainError(str(exc)) from None
    for s in sources:
        sp = require_source(s).resolve()
        if out.resolve() in (sp, sp.parent if sp.is_file() else sp):
            raise TrainError(f"{out}: is a source (or holds one); train never writes into its sources")
    if out.exists() and not out.is_dir():
        raise TrainError(f"{out}: exists and is not a folder")
    if resume:
        if not (out / "checkpoint.pt").is_file():
            raise TrainError(f"{out / 'checkpoint.pt'}: no checkpoint to resume from")
        return
    if out.exists() and any(out.iterdir()) and not force:
        raise TrainError(f"{out}: output folder exists and is not empty (use --force to replace it, --resume to continue)")


def make_out(out: Path, *, resume: bool) -> None:
    """MODEL_DIR, emptied of an earlier run's outputs unless resuming (``check_out`` allowed it)."""
    if not resume:
        for name in OUTPUTS:
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)


def adopt_checkpoint_model(cfg: TrainConfig, saved: dict[str, Any], path: Path, how: str = "--resume cannot continue it") -> None:
    """``--resume`` (and ``--init``) continue the checkpoint's model: its arch, encoder and input
    size fill in what was not given, and an ``--arch``/``--encoder``/``--input-size`` that differs
    is refused (a silently different model would not load its weights, or would train at another size)."""
    for name, option in (("arch", "--arch"), ("encoder", "--encoder"), ("input_size", "--input-size")):
        mine, theirs = getattr(cfg, name), saved.get(name)
        if mine is not None and mine != theirs:
            was = f"{option} {theirs}" if theirs is not None else "the frames' own size"
            raise TrainError(f"{path}: was trained with {was}; {how} with {option} {mine}")
        setattr(cfg, name, theirs)


def init_checkpoint(init: str | Path) -> Path:
    """``--init``'s checkpoint.pt: the path itself or MODEL_DIR/checkpoint.pt (one line if absent)."""
    path = Path(init)
    path = path / CHECKPOINT_FILE if path.is_dir() else path
    if not path.is_file():
        raise TrainError(f"--init {init}: no {CHECKPOINT_FILE} there (a MODEL_DIR written by labelsynth train, "
                         "or its checkpoint.pt)")
    return path


# --- pieces of the loop ------------------------------------------------------------------------
def learning_rate(cfg: TrainConfig, step: int) -> float:
    warm = max(1, int(cfg.warmup * cfg.steps))
    if step < warm:
        return cfg.lr * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1, cfg.steps - warm))
    return cfg.lr * 0.5 * (1.0 + math.cos(math.pi * t))


def _forward_full(model, image: np.ndarray, multiple: int, device: torch.device) -> torch.Tensor:
    """Logits (C,H,W) for one whole frame, padded to ``multiple`` and cropped back."""
    x = torch.from_numpy(normalize(image))[None].to(device)
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph))
    logits = upsample(model(x), (h + ph, w + pw))
    return logits[0, :, :h, :w]


@torch.no_grad()
def evaluate(model, split: Split, classes: ClassMap, cfg: TrainConfig, multiple: int, device: torch.device) -> tuple[float | None, dict[str, float | None]]:
    """Validation loss (same weighting as training) and Dice per class over all validation pixels."""
    if not split.val:
        return None, {}
    model.eval()
    lut = classes.id_to_index_lut()
    counts = torch.zeros(3, classes.num_classes, dtype=torch.long)
    losses = []
    class_weight = parse_class_weights(cfg.class_weights, classes)
    size = cfg.resize_to()
    for fr in split.val:
        image, mask, confidence = fr.load(size)
        target, weight = make_target(mask, confidence, fr.annotated, lut, min_confidence=cfg.min_confidence,
                                     expert_weight=cfg.expert_weight, confidence_weight=cfg.confidence_weight,
                                     class_weight=class_weight)
        logits = _forward_full(model, image, multiple, device)[None]
        t = torch.from_numpy(target).long()[None].to(device)
        loss, _ = segmentation_loss(logits, t, torch.from_numpy(weight)[None].to(device), dice_weight=cfg.dice_weight)
        if (t != IGNORE_ID).any():
            losses.append(float(loss))
        counts += confusion_counts(logits.argmax(1)[0], t[0], classes.num_classes)
    model.train()
    dice = {}
    for name, (tp, npred, ntrue) in zip(classes.names, counts.T.tolist()):
        c = Counts(tp=tp, fp=npred - tp, fn=ntrue - tp)
        dice[name] = c.dice if c.present or c.predicted else None
    return (float(np.mean(losses)) if losses else None), dice


def _frame_size(split: Split, cfg: TrainConfig) -> tuple[int, int]:
    """The (W, H) the model was trained at: ``--input-size``, else the most common frame size.
    ``segment`` resizes every frame to it (the ONNX metadata says so)."""
    size = cfg.resize_to()
    if size is not None:
        return size
    sizes = Counter(fr.size for fr in split.train + split.val)
    return sizes.most_common(1)[0][0]


def write_curves(path: Path, history: list[dict[str, Any]], class_names: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    fig, (ax_loss, ax_dice) = plt.subplots(1, 2, figsize=(10, 4))
    ax_loss.plot(steps, [h.get("train_loss") for h in history], label="train")
    if any(h.get("val_loss") is not None for h in history):
        ax_loss.plot(steps, [np.nan if h.get("val_loss") is None else h["val_loss"] for h in history], label="validation")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss (CE + Dice)")
    ax_loss.legend()
    for name in class_names:
        ys = [np.nan if (h.get("val_dice") or {}).get(name) is None else h["val_dice"][name] for h in history]
        if not all(np.isnan(ys)):
            ax_dice.plot(steps, ys, label=name)
    ax_dice.set_xlabel("step")
    ax_dice.set_ylabel("validation Dice")
    ax_dice.set_ylim(0, 1)
    if ax_dice.lines:
        ax_dice.legend(fontsize=7)
    fig.tight_layout()
    try:
        with atomic_file(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)


MIN_SEGFORMER_SIDE = 32
"""SegFormer's first attention block reduces a stride-4 feature map with an 8x8 convolution:
inputs below 29 px a side fail inside the model (measured: 28 fails, 29 runs); 32 is the rule."""


def check_model_input(cfg: TrainConfig, split: Split) -> None:
    """Every input the model will see (training crops, whole frames at validation and in the
    ONNX export) is large enough for it; else one line before any training."""
    if cfg.arch != "segformer":
        return  # U-Net/FPN frames are padded to a multiple of 32
    if cfg.crop < MIN_SEGFORMER_SIDE:
        raise TrainError(f"--crop {cfg.crop}: SegFormer needs crops of at least {MIN_SEGFORMER_SIDE} px")
    size = cfg.resize_to()
    if size is not None:
        if min(size) < MIN_SEGFORMER_SIDE:
            raise TrainError(f"--input-size {cfg.input_size}: SegFormer needs both sides of at least "
                             f"{MIN_SEGFORMER_SIDE} px")
        return
    for fr in split.train + split.val:
        if min(fr.size) < MIN_SEGFORMER_SIDE:
            raise TrainError(f"{fr.src.path}: frame {fr.name!r} is {fr.size[0]}x{fr.size[1]}; SegFormer needs both sides "
                             f"of at least {MIN_SEGFORMER_SIDE} px (resize with --input-size WxH)")


def check_resumed(model: torch.nn.Module, optimizer: torch.optim.Optimizer, path: Path) -> None:
    """A resumed model and optimiser hold finite numbers of the parameters' shapes (a checkpoint
    edited by hand would otherwise fail, or train to NaN, after MODEL_DIR is written)."""
    for name, value in model.state_dict().items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise TrainError(f"{path}: the model's {name} holds NaN or infinite values")
    for group in optimizer.param_groups:
        for param in group["params"]:
            for key, value in optimizer.state.get(param, {}).items():
                if not isinstance(value, torch.Tensor):
                    continue
                if value.dim() and value.shape != param.shape:
                    raise TrainError(f"{path}: the optimiser's {key} has shape {tuple(value.shape)} for a parameter of "
                                     f"shape {tuple(param.shape)}")
                if value.is_floating_point() and not torch.isfinite(value).all():
                    raise TrainError(f"{path}: the optimiser's {key} holds NaN or infinite values")


def load_weights(model: torch.nn.Module, optimizer: torch.optim.Optimizer, saved: dict[str, Any], where: str,
                 path: Path, cfg: TrainConfig, *, with_optimizer: bool = True) -> None:
    """A checkpoint's tensors into ``model`` (and ``optimizer``: ``--resume``; ``--init`` starts a
    fresh one), then ``check_resumed``: one line naming ``where`` when they do not fit the model."""
    try:
        model.load_state_dict(saved["model"])
        if with_optimizer:
            optimizer.load_state_dict(saved["optimizer"])
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise TrainError(f"{where}: does not fit a {cfg.arch}/{cfg.encoder} model "
                         f"({str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__})") from None
    check_resumed(model, optimizer, path)


def _infinite(loader):
    while True:
        yield from loader


# --- the run -----------------------------------------------------------------------------------
def train(sources: list[str | Path], out: str | Path, cfg: TrainConfig | None = None, *, force: bool = False,
          resume: bool = False, progress: bool = True, log=None) -> TrainResult:
    """Train a 2D segmenter on ``sources`` (labels.h5 files and capture folders) into ``out``.

    Ctrl-C or SIGTERM during training saves the checkpoint of the last finished step and
    train.json (``interrupted``), then re-raises; a second one exits at once."""
    with interruptible():
        return _train(sources, out, cfg, force=force, resume=resume, progress=progress, log=log)


def _train(sources: list[str | Path], out: str | Path, cfg: TrainConfig | None, *, force: bool, resume: bool,
           progress: bool, log) -> TrainResult:
    cfg = cfg or TrainConfig()
    cfg.check()
    out = Path(out)
    say = log or (lambda msg: console.print(msg, markup=False, highlight=False))
    t0 = time.perf_counter()
    check_out(out, sources, force=force, resume=resume)
    state = load_checkpoint(out / "checkpoint.pt") if resume else None
    if state is not None:  # what the model is comes from the checkpoint; asking for another is an error
        if cfg.init is not None:
            raise TrainError(f"--init {cfg.init} with --resume: a resumed run continues {out / 'checkpoint.pt'}; "
                             "give one of them")
        adopt_checkpoint_model(cfg, state["config"], out / "checkpoint.pt")
    start = None
    if cfg.init is not None:
        start_path = init_checkpoint(cfg.init)
        start = load_checkpoint(start_path, remedy="give --init a MODEL_DIR written by labelsynth train")
        adopt_checkpoint_model(cfg, start["config"], start_path, "--init cannot start from it")
    cfg.arch = cfg.arch or "segformer"
    cfg.encoder = resolve_encoder(cfg.arch, cfg.encoder)

    loaded, classes = load_sources(list(sources), cfg.only_annotated)
    if state is not None and state["classes"].to_json() != classes.to_json():
        raise TrainError(f"{out / 'checkpoint.pt'}: its class table differs from the sources' ({loaded[0].path})")
    if start is not None and start["classes"].to_json() != classes.to_json():
        raise TrainError(f"--init {cfg.init}: its class table differs from the sources' ({loaded[0].path})")
    class_weight = parse_class_weights(cfg.class_weights, classes)
    split = split_by_capture(loaded, cfg.val_captures, cfg.val_split)
    if not split.train:
        raise TrainError("no training frames are left after the validation split")
    check_model_input(cfg, split)
    eval_every = cfg.eval_every or max(1, cfg.steps // 10)

    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.arch, cfg.encoder, classes.num_classes).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, **optimiser_options(device))
    step, history, resumed_from = 0, [], None
    if start is not None:
        load_weights(model, optimizer, start, f"--init {cfg.init}", start_path, cfg, with_optimizer=False)
        say(f"starting from the weights of {start_path}")
    if state is not None:
        load_weights(model, optimizer, state, str(out / "checkpoint.pt"), out / "checkpoint.pt", cfg)
        step = resumed_from = int(state["step"])
        history = [h for h in state["history"] if h["step"] <= step]
        say(f"resuming from step {step} of {out / 'checkpoint.pt'}")
    load_seconds = time.perf_counter() - t0
    say(split.description)
    make_out(out, resume=resume)  # every source and option has been checked: now MODEL_DIR is written

    from .augment import build_augment

    dataset = FrameDataset(split.train, classes, build_augment(cfg.crop, seed=cfg.seed + step),
                           min_confidence=cfg.min_confidence, expert_weight=cfg.expert_weight,
                           confidence_weight=cfg.confidence_weight, class_weight=class_weight,
                           size=cfg.resize_to())
    generator = torch.Generator().manual_seed(cfg.seed + step)
    loader = torch.utils.data.DataLoader(dataset, batch_size=min(cfg.batch_size, len(dataset)), shuffle=True,
                                         drop_last=True, num_workers=cfg.workers, generator=generator)
    multiple = input_multiple(cfg.arch)
    ckpt = out / "checkpoint.pt"
    train_start = time.perf_counter()
    window: list[float] = []
    ema = None
    interrupted: KeyboardInterrupt | None = None

    def record(val: bool = True) -> None:
        entry: dict[str, Any] = {"step": step, "seconds": round(time.perf_counter() - train_start, 3),
                                 "train_loss": float(np.mean(window)) if window else None,
                                 "lr": learning_rate(cfg, max(step - 1, 0))}
        if val:
            entry["val_loss"], entry["val_dice"] = evaluate(model, split, classes, cfg, multiple, device)
        history.append(entry)
        window.clear()

    model.train()
    batches = _infinite(loader)
    try:
        with make_progress(progress) as bar:
            task = bar.add_task("train", total=cfg.steps, completed=min(step, cfg.steps), status="")
            while step < cfg.steps:
                batch = next(batches)
                for g in optimizer.param_groups:
                    g["lr"] = learning_rate(cfg, step)
                logits = model(batch["image"].to(device))
                loss, _ = segmentation_loss(logits, batch["target"].to(device), batch["weight"].to(device),
                                            dice_weight=cfg.dice_weight)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step += 1
                value = float(loss.detach())
                window.append(value)
                ema = value if ema is None else 0.9 * ema + 0.1 * value
                bar.update(task, completed=step, status=f"loss {ema:.3f}")
                if step % eval_every == 0 or step == cfg.steps:
                    record()
                    save_checkpoint(ckpt, model, optimizer, step, cfg, classes, history)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (outdir.Interrupted)
        interrupted = exc
        if window:
            record(val=False)
        save_checkpoint(ckpt, model, optimizer, step, cfg, classes, history)
        say(f"interrupted at step {step}: {ckpt} saved; continue with --resume")
    train_seconds = time.perf_counter() - train_start

    export_seconds = 0.0
    if interrupted is None:
        if not history or history[-1]["step"] != step:  # e.g. resumed at or past --steps
            record()
            save_checkpoint(ckpt, model, optimizer, step, cfg, classes, history)
        from .export_onnx import export_onnx

        t_export = time.perf_counter()
        export_onnx(model, out / "model.onnx", classes, _frame_size(split, cfg))
        export_seconds = time.perf_counter() - t_export
        write_curves(out / "curves.png", history, classes.names)

    seconds = time.perf_counter() - t0
    report = {
        "labelsynth_version": __version__,
        "sources": [str(Path(s)) for s in sources],
        "arguments": asdict(cfg),
        "classes": classes.to_json(),
        "split": {"description": split.description, "train_frames": len(split.train),
                  "val_frames": len(split.val), "val_sources": split.val_sources},
        "device": str(device),
        "step": step,
        "resumed_from": resumed_from,
        "interrupted": interrupted is not None,
        "history": history,
        "times": {"load_s": round(load_seconds, 3), "train_s": round(train_seconds, 3),
                  "export_s": round(export_seconds, 3), "total_s": round(seconds, 3)},
        "outputs": {"onnx": "model.onnx", "input": f"{INPUT_NAME} (N,3,H,W) RGB, ImageNet mean/std",
                    "output": f"{OUTPUT_NAME} (N,C,h,w)", "input_size": format_input_size(_frame_size(split, cfg))},
    }
    write_text_atomic(out / "train.json", json.dumps(report, indent=2))
    if interrupted is not None:
        raise interrupted
    return TrainResult(out, step, cfg.steps, seconds, str(device), history, split.description, len(split.train),
                       len(split.val), resumed_from)
