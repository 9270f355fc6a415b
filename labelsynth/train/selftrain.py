"""``labelsynth selftrain``: the self-training loop, one command.

A model (round 0: e.g. one trained on a few expert frames) segments every frame of new captures;
``expand`` fuses its masks into one view-consistent labelling per capture (``--labels
predictions``, or ``both`` with the captures' own expert frames); a new model is trained on
the fused labels; it makes the next round's masks. Each round's model is scored on held-out
captures' expert annotations (``holdout``), so the table says whether the loop keeps improving.

OUT/
  selftrain.json            the settings and every round's held-out scores (rewritten atomically)
  round<R>/predictions/<C>/ the previous model's masks of capture C (``segment``)
  round<R>/captures/<C>/    C with those masks as predictions/ (``capture.view``: C itself is never written)
  round<R>/expanded/<C>/    ``expand`` of that view (labels.h5); ``raw``: round<R>/labels/<C>.h5 instead
  round<R>/agreed/<C>.h5    ``agree``, R >= 2: round R's labels of C where round R-1's gave the same class (else ignore)
  round<R>/model/           ``train``: model.onnx, train.json, curves.png (``warm_start``: from round R-1's weights;
                            ``accumulate``: on rounds 1..R's labels; ``agree``: on round<R>/agreed/)
  round<R>/teachers/fold<F>/ ``cross_fit``, R >= 2: the model that segments fold F's captures (train's files)
  round<R>/holdout/<H>/     the round's model's masks of held-out capture H, scored against its annotations/

Every step's output is complete or absent (``outdir.building``, ``train``'s atomic files), so a
rerun with the same settings continues where the last one stopped; other settings need ``force``.
The one call into ``pipeline.expand`` is ``_expand``.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..capture.view import capture_view
from ..classes import BACKGROUND_ID, IGNORE_ID, WOUND_BED, ClassMap
from ..config import with_defaults
from ..errors import LabelsynthError
from ..outdir import check_apart, check_writable, write_text_atomic
from ..progress import console
from ..rundir import LABELS_FILE
from .data import TrainError, load_sources
from .checkpoint import CHECKPOINT_FILE
from .loop import TrainConfig

MODES = ("predictions", "both", "raw")
MAX_ROUNDS = 1000


class SelfTrainError(TrainError):
    """A capture, model or option ``selftrain`` cannot use (one line, names it)."""


@dataclass
class SelfTrainConfig:
    """What the loop does each round (stored in selftrain.json; a rerun must match it)."""

    rounds: int = 1
    """Rounds of segment -> expand -> train; round R's masks come from round R-1's model. One by default:
    on the phone-like benchmark a second round's tissue mean fell below the first's in every training
    seed (by 0.015-0.017 on average, docs/training.md), while more unannotated captures raised round 1."""
    labels: str = "predictions"
    """What teaches a round: ``predictions`` (the model's masks, fused by ``expand --labels
    predictions``), ``both`` (fused with each capture's own expert frames, ``--labels both``) or
    ``raw`` (the masks themselves, not fused: the baseline the field is measured against)."""
    recipe: str = "default"
    """``expand``'s recipe (name or YAML path)."""
    overrides: list[str] = field(default_factory=list)
    """``expand``'s ``--set`` overrides."""
    seed: int = 0
    """``expand``'s seed (training has its own, in ``train``)."""
    device: str = "auto"
    """auto | cpu | cuda, for segment, expand and train."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Every round trains a new model with these settings."""
    warm_start: bool = False
    """Round R's model starts from round R-1's weights (round 1 from the checkpoint.pt beside the
    round-0 model), with a fresh optimiser and schedule; else from scratch."""
    accumulate: bool = False
    """Round R trains on the labels of rounds 1..R (each capture once a round); else on round R's."""
    cross_fit: bool = False
    """From round 2 on, each capture is segmented by a teacher trained (from scratch, same settings) on
    round R-1's labels of the *other* captures (two folds: captures 1, 3, ... and 2, 4, ...), not
    by round R-1's model, which learnt that capture's own labels and mostly repeats them."""
    agree: bool = False
    """From round 2 on, round R trains only on the pixels whose fused class round R-1's labels gave
    too; the others are ignored (255). Why: a label that changes from round to round is one the
    loop is unsure of (on the phone-like benchmark, 0.3-2.4% of the pixels, right 15-63% of the
    time against 98-99% for the rest). Off by default: over three training seeds it moved round 2 -
    round 1 from -0.002 / -0.001 to +0.000 / +0.003 (wound bed / tissue mean), a gain in every
    seed but within one seed's spread (docs/training.md), and ``rounds`` defaults to 1."""

    def check(self) -> None:
        """Every value, and the recipe expand will use (file, keys, types, ranges) and the device,
        before any work: one ``SelfTrainError`` line naming the option."""
        from ..options import OptionError, whole_number

        try:
            self.rounds = whole_number(self.rounds, "--rounds", 1, MAX_ROUNDS)
            if self.labels not in MODES:
                raise OptionError(f"--labels {self.labels!r}: expected one of {', '.join(MODES)}")
            if self.cross_fit and self.warm_start:
                raise OptionError("--cross-fit with --warm-start: a fold's teacher has no earlier weights of its "
                                  "own to start from; choose one")
            self.expand_options().check()
        except LabelsynthError as exc:
            raise SelfTrainError(str(exc)) from None
        self.train.check()

    def expand_options(self, labels: str | None = None):
        """``expand``'s options in every round (``labels``: the round's label mode)."""
        from ..options import ExpandOptions

        return ExpandOptions(labels=labels, recipe=self.recipe, device=self.device, seed=self.seed,
                             overrides=list(self.overrides), report=False)


@dataclass
class RoundScore:
    """One row of the table: a round's model on the held-out captures."""

    round: int
    model: str
    train_frames: int | None
    scores: dict[str, dict[str, float | int | None]]  # class (and wound_bed) -> dice, recall, n
    mean_dice: float | None  # over the classes other than background (and the wound bed) present
    seconds: float = 0.0

    def dice(self, key: str) -> float | None:
        return (self.scores.get(key) or {}).get("dice")


@dataclass
class SelfTrainResult:
    out: Path
    rounds: list[RoundScore]
    seconds: float

    def table(self) -> str:
        """Markdown: each round's held-out Dice (wound bed, per class, mean of the classes)."""
        if not self.rounds or not self.rounds[0].scores:
            return "(no held-out captures: nothing scored)"
        keys = [k for k in self.rounds[0].scores if k != "background"]
        head = "| round | model | trained on (frames) | " + " | ".join(k.replace("_", " ") for k in keys) + " | class mean |"
        lines = [head, "|---" * (len(keys) + 4) + "|"]
        for r in self.rounds:
            cells = [_fmt(r.dice(k)) for k in keys]
            lines.append(f"| {r.round} | {r.model} | {'-' if r.train_frames is None else r.train_frames} | "
                         + " | ".join(cells) + f" | {_fmt(r.mean_dice)} |")
        return "\n".join(lines)

    def best(self) -> RoundScore | None:
        """The round whose model scores the highest class mean on the held-out captures (round 0,
        the starting model, included; the earlier round on a tie); None without held-out captures.

        A further round is not always better (docs/training.md measures round 2 against round 1),
        so the loop names the model to use rather than leaving the last one as the answer."""
        scored = [r for r in self.rounds if r.mean_dice is not None]
        return max(scored, key=lambda r: r.mean_dice) if scored else None

    def summary(self) -> str:
        last = self.rounds[-1]
        text = f"self-training: {len(self.rounds) - 1} round(s) in {self.seconds:.0f} s -> {last.model}"
        best = self.best()
        if best is not None:
            text += (f"; best on the held-out captures: round {best.round} (class mean {_fmt(best.mean_dice)}"
                     + (f", the last round {_fmt(last.mean_dice)}" if best is not last else "") + f") -> {best.model}")
        return text + f"; results in {self.out / 'selftrain.json'}"


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


# --- steps ----------------------------------------------------------------------------------------
def _expand(capture: Path, out: Path, labels: str, cfg: SelfTrainConfig) -> Path:
    """``expand CAPTURE --out OUT --labels L --recipe R --no-report``: the loop's one call into the
    pipeline; returns OUT/labels.h5."""
    from ..pipeline import expand

    expand(capture, out, cfg.expand_options(labels), force=True, progress=False)
    return out / LABELS_FILE


def raw_labels_h5(capture: Path, path: Path) -> Path:
    """labels.h5 of a capture's predictions/ as they are (confidence 1, no frame annotated): what
    ``train`` learns from when the masks are not fused (``labels="raw"``)."""
    from ..capture import load_capture
    from ..export import write_labels_h5

    cap = load_capture(capture)
    missing = [f.name for f in cap.frames if f.prediction_path is None]
    if missing:
        raise SelfTrainError(f"{capture / 'predictions'}: no mask for {len(missing)} frame(s) ({', '.join(missing[:3])})")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_labels_h5(path, images=cap.load_image, masks=cap.load_prediction, frame_names=cap.names,
                    classes=cap.classes, annotated=np.zeros(len(cap), dtype=bool), source=capture)
    return path


def agreed_labels_h5(now: Path, before: Path, path: Path) -> Path:
    """``now`` (a labels.h5) with every pixel whose class differs in ``before`` (the same capture's
    labels.h5 of the round before) set to ignore (255, confidence 0): what ``agree`` trains on.
    Written as ``path``.partial and renamed when complete."""
    from ..export import LabelsReader, LabelsWriter

    a, b = LabelsReader(now), LabelsReader(before)
    if a.frame_names != b.frame_names or (a.height, a.width) != (b.height, b.width):
        raise SelfTrainError(f"{before}: not the same frames as {now} (cannot compare the rounds' labels)")
    with LabelsWriter(path, len(a), a.classes, source=a.attrs.get("source"), attrs={"agreed_with": str(before)}) as w:
        for i, name in enumerate(a.frame_names):
            image, mask, conf = (np.asarray(x) for x in a.read(i))
            differ = np.asarray(b.read(i)[1]) != mask
            w.add(name, image, np.where(differ, IGNORE_ID, mask).astype(np.uint8), np.where(differ, 0.0, conf),
                  bool(a.annotated[i]))
    return path


def score_on_annotations(model: Path, captures: list[Path], out: Path, classes: ClassMap, device: str) -> dict:
    """The model's masks of every frame of ``captures`` (in OUT/<name>/), scored against their
    annotations/ (the frames that have one): per class (and wound bed) mean Dice/recall over the
    frames whose annotation holds the class, and the mean Dice of the classes other than background."""
    from ..capture import load_capture
    from ..capture.masks import read_mask
    from ..metrics import score_frames
    from .segment import segment_capture

    preds, truths, names = [], [], []
    for cap_dir, name in zip(captures, unique_names(captures)):
        masks = out / name
        if not masks.is_dir():
            segment_capture(cap_dir, model, masks, device=device, progress=False)
        cap = load_capture(cap_dir)
        for i, frame in enumerate(cap.frames):
            if frame.annotation_path is not None:
                preds.append(read_mask(masks / f"{frame.name}.png", None, classes))
                truths.append(cap.load_annotation(i))
                names.append(f"{name}/{frame.name}")
    scores = score_frames(preds, truths, classes, names)
    table = {r["class"]: {"dice": r["dice"], "recall": r["recall"], "n": r["n"]} for r in scores.table()}
    background = next(c.name for c in classes.classes if c.id == BACKGROUND_ID)
    tissues = [k for k in table if k not in (WOUND_BED, background) and table[k]["n"]]
    mean = float(np.mean([table[k]["dice"] for k in tissues])) if tissues else None
    return {"classes": table, "mean_dice": mean, "frames": len(names)}


def unique_names(paths: list[Path]) -> list[str]:
    """Folder names for ``paths``, made unique with a numeric suffix where two share a name."""
    seen: dict[str, int] = {}
    out = []
    for p in paths:
        base = Path(p).name or "capture"
        seen[base] = seen.get(base, 0) + 1
        out.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    return out


def _model_done(model_dir: Path, steps: int) -> bool:
    report = model_dir / "train.json"
    if not (report.is_file() and (model_dir / "model.onnx").is_file()):
        return False
    data = json.loads(report.read_text())
    return not data.get("interrupted") and data.get("step") == steps


def _same_settings(previous: dict | None, settings: dict) -> bool:
    """Whether OUT's rounds can be continued: the same settings, except the number of rounds
    (asking for more rounds continues a finished loop; fewer stops at the last one asked)."""
    if previous is None:
        return False
    a, b = json.loads(json.dumps(previous)), json.loads(json.dumps(settings))
    if not isinstance(a.get("config"), dict):
        return False  # not what this version writes: other settings
    a["config"] = with_defaults(a["config"], asdict(SelfTrainConfig()))  # options added since: their defaults then
    a["config"].pop("rounds", None)
    b["config"].pop("rounds", None)
    return a == b


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a looping link: refused where it is read
        return path


def _check_out(out: Path, inputs: list[tuple[str, Path]]) -> None:
    """OUT can be made (``outdir.check_writable``), is a folder if it exists, and is inside none
    of the ``inputs`` (label, path): a capture is never written into."""
    check_writable(out)
    if out.exists() and not out.is_dir():
        raise SelfTrainError(f"{out}: exists and is not a folder")
    for label, path in inputs:
        check_apart(out, {label: path})


def _previous_settings(state_file: Path) -> dict | None:
    """The settings an earlier run in OUT recorded (None: no selftrain.json); one line if unreadable."""
    if not state_file.exists():
        return None
    try:
        state = json.loads(state_file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SelfTrainError(f"{state_file}: unreadable ({exc}); use --force to start over") from None
    if not isinstance(state, dict) or not isinstance(state.get("settings", {}), dict):
        raise SelfTrainError(f"{state_file}: not a selftrain.json (use --force to start over)")
    return state.get("settings")


# --- the loop -----------------------------------------------------------------------------------
def _fold_teacher(fold: int, labels_before: list[Path], here: Path, tcfg: TrainConfig, also: list[Path],
                  holdout: list[Path], step: str, say: Callable[[str], None], progress: bool) -> Path:
    """``cross_fit``: the model that segments the captures of ``fold`` (0: captures 1, 3, ...; 1:
    2, 4, ...) this round, trained once (here/teachers/fold<F>) on the round before's labels of the
    other fold's captures, so that no capture is labelled by a model that learnt its own labels."""
    from .loop import train

    fold_dir = here / "teachers" / f"fold{fold + 1}"
    if not _model_done(fold_dir, tcfg.steps):
        others = [*also, *(h5 for j, h5 in enumerate(labels_before) if j % 2 != fold)]
        say(f"{step}: fold {fold + 1}/2's teacher, trained on the other fold's labels of the round before "
            f"({len(others)} sources)")
        train([*others, *holdout], fold_dir, tcfg, force=True, progress=progress, log=say)
    return fold_dir / "model.onnx"


def selftrain(captures: list[str | Path], model: str | Path, out: str | Path, cfg: SelfTrainConfig | None = None, *,
              holdout: list[str | Path] = (), also: list[str | Path] = (), force: bool = False,
              progress: bool = True, log: Callable[[str], None] | None = None) -> SelfTrainResult:
    """Run ``cfg.rounds`` rounds of segment -> expand -> train on ``captures``, starting from
    ``model`` (an ONNX segmenter, e.g. ``train``'s model.onnx), into OUT.

    ``also``: training sources added to every round (labels.h5 files or capture folders, e.g.
    the expert frames the first model learned from). ``holdout``: captures whose annotations/
    score every round's model (round 0 included) and are each round's validation; they are
    never trained on. Returns the rounds' scores; OUT/selftrain.json holds them too.
    """
    from ..capture import check_capture, load_capture
    from .loop import train
    from .segment import OnnxSegmenter

    cfg = cfg or SelfTrainConfig()
    cfg.check()
    say = log or (lambda msg: console.print(f"[bold]selftrain[/] {msg}", highlight=False, soft_wrap=True))
    out, model = Path(out), Path(model)
    captures = [Path(c) for c in captures]
    holdout = [Path(h) for h in holdout]
    also = [Path(a) for a in also]
    if not captures:
        raise SelfTrainError("give at least one CAPTURE to label")
    if cfg.cross_fit and len(captures) < 2:
        raise SelfTrainError(f"--cross-fit needs at least 2 captures (a fold's teacher learns from the others); "
                             f"got {len(captures)}")
    for group, paths in (("CAPTURE", captures), ("--holdout", holdout)):
        for p in paths:
            if not p.is_dir():
                raise SelfTrainError(f"{p}: {group} is not a capture folder")
    seen: dict[Path, Path] = {}
    for p in [*captures, *also]:
        if _resolved(p) in seen:
            raise SelfTrainError(f"{p}: given twice (also as {seen[_resolved(p)]})")
        seen[_resolved(p)] = p
    trained = set(seen)
    for h in holdout:
        if _resolved(h) in trained:
            raise SelfTrainError(f"{h}: a --holdout capture cannot also be trained on")
    loaded = [load_capture(c) for c in captures]  # a bad capture fails now, before any work
    held = [load_capture(h) for h in holdout]
    for cap in [*loaded, *held]:  # every frame segment will read decodes, at its camera's size
        check_capture(cap, labels=None).raise_if_problems()
    classes = loaded[0].classes
    for c, cap in zip(captures, loaded):
        if cap.classes.to_json() != classes.to_json():
            raise SelfTrainError(f"{c}: its class table differs from {captures[0]}'s")
        if cfg.labels == "both" and not cap.has_annotations:
            raise SelfTrainError(f"{c / 'annotations'}: --labels both needs expert frames in every capture")
    for h, cap in zip(holdout, held):
        if not cap.has_annotations:
            raise SelfTrainError(f"{h / 'annotations'}: a --holdout capture needs annotations to score against")
    _check_out(out, [*(("the capture", c) for c in captures), *(("the --holdout capture", h) for h in holdout),
                     *(("the --also source", a) for a in also)])
    OnnxSegmenter(model, cfg.device)  # opened now: a file that is not a segmenter fails before OUT exists
    if cfg.warm_start and not (model.parent / CHECKPOINT_FILE).is_file():
        raise SelfTrainError(f"--model {model}: --warm-start needs the {CHECKPOINT_FILE} train wrote beside it "
                             f"(none in {model.parent})")
    if also:  # every --also source read and checked now (train reads them again each round)
        try:
            _, also_classes = load_sources(also)
        except LabelsynthError as exc:
            raise SelfTrainError(f"--also {exc}") from None
        if also_classes.to_json() != classes.to_json():
            raise SelfTrainError(f"--also {also[0]}: its class table differs from {captures[0]}'s")

    settings = {"captures": [str(c) for c in captures], "model": str(model), "holdout": [str(h) for h in holdout],
                "also": [str(a) for a in also], "config": asdict(cfg)}
    state_file = out / "selftrain.json"
    if out.exists() and not force:
        previous = _previous_settings(state_file)
        if not _same_settings(previous, settings):
            what = "was made with other settings" if previous is not None else "exists and is not a selftrain folder"
            raise SelfTrainError(f"{out}: {what} (use --force to start over)")
        say(f"continuing in {out}")
    elif out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    names = unique_names(captures)
    rows: list[RoundScore] = []
    state: dict[str, Any] = {"settings": settings, "rounds": []}

    def save() -> None:
        state["rounds"] = [asdict(r) for r in rows]
        write_text_atomic(state_file, json.dumps(state, indent=2))

    def score(r: int, model_path: Path, label: str, frames: int | None, started: float) -> None:
        if holdout:
            s = score_on_annotations(model_path, holdout, out / f"round{r}" / "holdout", classes, cfg.device)
            row = RoundScore(r, label, frames, s["classes"], s["mean_dice"], time.perf_counter() - started)
            bed = row.dice(WOUND_BED)
            say(f"round {r}: held-out ({s['frames']} annotated frames) wound bed Dice {_fmt(bed)}, "
                f"class mean {_fmt(row.mean_dice)}")
        else:
            row = RoundScore(r, label, frames, {}, None, time.perf_counter() - started)
        rows.append(row)
        save()

    score(0, model, str(model), None, t0)
    current = model
    earlier: list[Path] = []  # the labels of the rounds before (``accumulate``)
    labels_before: list[Path] = []  # the round before's labels, one per capture (``cross_fit``, ``agree``)
    for r in range(1, cfg.rounds + 1):
        started = time.perf_counter()
        here = out / f"round{r}"
        tcfg = TrainConfig(**{**asdict(cfg.train), "device": cfg.device})
        if cfg.warm_start:
            tcfg.init = str(Path(current).parent / CHECKPOINT_FILE)
        if holdout:
            tcfg.val_captures = [str(h) for h in holdout]

        sources: list[Path] = []  # what this round trains on
        fused: list[Path] = []  # this round's labels of each capture (``agree`` compares the next round's with them)
        for i, (cap_dir, name) in enumerate(zip(captures, names)):
            step = f"round {r}/{cfg.rounds}, capture {i + 1}/{len(captures)} ({name})"
            masks = here / "predictions" / name
            if not masks.is_dir():
                by = current
                if cfg.cross_fit and r > 1:
                    by = _fold_teacher(i % 2, labels_before, here, tcfg, also, holdout,
                                       f"round {r}/{cfg.rounds}", say, progress)
                say(f"{step}: segment with {by}")
                from .segment import segment_capture

                segment_capture(cap_dir, by, masks, device=cfg.device, progress=progress)
            view = here / "captures" / name
            if not view.is_dir():
                capture_view(cap_dir, view, predictions=masks, keep_annotations=cfg.labels == "both")
            if cfg.labels == "raw":
                h5 = here / "labels" / f"{name}.h5"
                if not h5.is_file():
                    say(f"{step}: labels.h5 of the raw masks")
                    raw_labels_h5(view, h5)  # written as h5.partial, renamed when complete
            else:
                expanded = here / "expanded" / name
                h5 = expanded / LABELS_FILE
                if not h5.is_file():
                    say(f"{step}: expand --labels {cfg.labels} --recipe {cfg.recipe}")
                    t = time.perf_counter()
                    _expand(view, expanded, cfg.labels, cfg)
                    say(f"{step}: expanded in {time.perf_counter() - t:.0f} s")
            fused.append(h5)
            if cfg.agree and labels_before:
                agreed = here / "agreed" / f"{name}.h5"
                if not agreed.is_file():
                    say(f"{step}: keep the labels round {r - 1} agrees with")
                    agreed_labels_h5(h5, labels_before[i], agreed)
                sources.append(agreed)
            else:
                sources.append(h5)
        model_dir = here / "model"
        if not _model_done(model_dir, tcfg.steps):
            taught = [*also, *(earlier if cfg.accumulate else []), *sources]
            say(f"round {r}/{cfg.rounds}: train on {len(taught)} sources")
            result = train([*taught, *holdout], model_dir, tcfg, force=True, progress=progress, log=say)
            frames = result.train_frames
        else:
            frames = json.loads((model_dir / "train.json").read_text())["split"]["train_frames"]
        current = model_dir / "model.onnx"
        earlier += sources
        labels_before = fused
        score(r, current, str(current), frames, started)
    result = SelfTrainResult(out, rows, time.perf_counter() - t0)
    state["table"] = result.table()
    best = result.best()
    state["best"] = None if best is None else {"round": best.round, "model": best.model, "mean_dice": best.mean_dice}
    save()
    return result
