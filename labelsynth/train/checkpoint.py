"""MODEL_DIR/checkpoint.pt: what ``train --resume`` continues from, read without running code.

Format version 2 (``safeload``): one ``torch.save`` of a plain dict::

    {"labelsynth_checkpoint": "<JSON text>", "tensors": {"model.<name>": Tensor,
                                                         "optimizer.<param index>.<name>": Tensor}}

The JSON holds the format name and version, the labelsynth version, the step reached, the run's
arguments (``TrainConfig``), the class table, the history of evaluations and the optimiser's
non-tensor state (its parameter groups). It is read with ``torch.load(weights_only=True)``, so
a checkpoint someone sent, or one altered to run code when unpickled, runs nothing: it is
refused in one line, as is a truncated or foreign file. A checkpoint from before version 2
(a dict of state dicts, also only tensors and plain values) is read the same safe way and
converted in memory.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from .. import __version__
from ..classes import ClassMap
from ..safeload import load_plain, read_described, save_described, tensors_under
from .data import TrainError

CHECKPOINT_FILE = "checkpoint.pt"
CHECKPOINT_FORMAT = "labelsynth-checkpoint"
CHECKPOINT_VERSION = 2
_KEY = "labelsynth_checkpoint"
_KIND = "labelsynth train checkpoint"
_REMEDY = "train again without --resume (use --force to replace it)"
_V1_KEYS = {"model", "optimizer", "step", "config", "classes", "history"}


def save_checkpoint(path: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer, step: int, config: Any,
                    classes: ClassMap, history: list[dict[str, Any]]) -> Path:
    """Write checkpoint.pt (format 2) atomically: the model's and the optimiser's tensors, the rest as JSON."""
    tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
    optim = optimizer.state_dict()
    plain_state: dict[str, dict[str, Any]] = {}
    for index, entry in optim["state"].items():
        for name, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"optimizer.{index}.{name}"] = value
            else:
                plain_state.setdefault(str(index), {})[name] = value
    description = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "labelsynth": __version__,
        "step": int(step),
        "config": asdict(config),
        "classes": classes.to_json(),
        "history": history,
        "optimizer": {"param_groups": optim["param_groups"], "state": plain_state},
    }
    return save_described(path, _KEY, description, tensors)


def load_checkpoint(path: Path, remedy: str = _REMEDY) -> dict[str, Any]:
    """checkpoint.pt as ``{"model", "optimizer" (state dicts), "step", "config", "classes"
    (ClassMap), "history"}``; anything else (tampered, truncated, foreign, newer) is one
    ``TrainError`` line naming the file (and ``remedy``), and nothing in it runs."""
    path = Path(path)
    state = load_plain(path, kind=_KIND, remedy=remedy, error=TrainError)
    if isinstance(state, dict) and _KEY in state:
        meta, tensors = read_described(state, _KEY, path, kind=_KIND, error=TrainError)
        version = meta.get("version")
        if meta.get("format") != CHECKPOINT_FORMAT or isinstance(version, bool) or not isinstance(version, int):
            raise TrainError(f"{path}: not a {_KIND} (its description is not readable)")
        if version > CHECKPOINT_VERSION:
            raise TrainError(f"{path}: written by a newer labelsynth (checkpoint format {version}; this one reads up to "
                             f"{CHECKPOINT_VERSION}): update labelsynth")
        try:
            optim = meta["optimizer"]
            opt_state: dict[int, dict[str, Any]] = {}
            for key, value in tensors.items():
                if key.startswith("optimizer."):
                    index, _, name = key[len("optimizer."):].partition(".")
                    opt_state.setdefault(int(index), {})[name] = value
            for index, plain in (optim.get("state") or {}).items():
                opt_state.setdefault(int(index), {}).update(plain)
            out = {"model": tensors_under(tensors, "model"),
                   "optimizer": {"state": opt_state, "param_groups": list(optim["param_groups"])},
                   "step": meta["step"], "config": meta["config"], "classes": meta["classes"], "history": meta["history"]}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise TrainError(f"{path}: not a {_KIND} (bad description: {exc!s:.200})") from None
    elif isinstance(state, dict) and _V1_KEYS <= set(state):  # before format 2: classes and history as JSON text
        try:
            out = {**{k: state[k] for k in _V1_KEYS}, "classes": json.loads(state["classes"]),
                   "history": json.loads(state["history"])}
        except (TypeError, ValueError) as exc:
            raise TrainError(f"{path}: not a usable checkpoint (bad class table or history: {exc!s:.200})") from None
    else:
        missing = sorted(_V1_KEYS - set(state)) if isinstance(state, dict) else sorted(_V1_KEYS)
        raise TrainError(f"{path}: not a {_KIND} (missing {missing})")
    return _checked(out, path)


def _checked(state: dict[str, Any], path: Path) -> dict[str, Any]:
    step, config, history = state["step"], state["config"], state["history"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise TrainError(f"{path}: not a usable checkpoint (step {step!r})")
    if not isinstance(config, dict):
        raise TrainError(f"{path}: not a usable checkpoint (its arguments are not a mapping)")
    if not isinstance(history, list) or not all(isinstance(h, dict) and isinstance(h.get("step"), int) for h in history):
        raise TrainError(f"{path}: not a usable checkpoint (its history is not a list of evaluations)")
    if not isinstance(state["model"], dict) or not isinstance(state["optimizer"], dict):
        raise TrainError(f"{path}: not a usable checkpoint (no model or optimiser state)")
    try:
        state["classes"] = ClassMap.from_dict(state["classes"], str(path))
    except Exception as exc:  # noqa: BLE001 - any malformed table is the same one line
        raise TrainError(f"{path}: not a usable checkpoint (bad class table: {exc!s:.200})") from None
    return state
