"""Files that users hand each other (field.pt, checkpoint.pt) are read without running code.

Both are one ``torch.save`` of ``{"<format key>": "<JSON text>", "tensors": {name: Tensor}}``:
a description in JSON and the numbers as tensors. They are read with
``torch.load(weights_only=True)``, which rebuilds tensors, strings, numbers and containers and
refuses anything else, so a file that was altered to call Python code when unpickled (a
``__reduce__`` payload) is refused before any of it runs. Every way such a file can be bad
(truncated, empty, not a torch file, a pickle naming code, no description, unreadable JSON) is
one line naming the file. The formats themselves live beside their readers
(``rundir`` for field.pt, ``train.checkpoint`` for checkpoint.pt).
"""

from __future__ import annotations

import io
import json
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from .errors import LabelsynthError
from .outdir import atomic_file

TENSORS_KEY = "tensors"


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message (or its type's name)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def save_described(path: str | Path, key: str, description: dict[str, Any], tensors: dict[str, torch.Tensor]) -> Path:
    """Write ``{key: json(description), "tensors": tensors}`` atomically (``outdir.atomic_file``)."""
    path = Path(path)
    buffer = io.BytesIO()  # serialised in memory, written by Python: a full disk is an OSError naming
    torch.save({key: json.dumps(description),  # the file, not torch's "PytorchStreamWriter failed"
                TENSORS_KEY: {k: v.detach().cpu() for k, v in tensors.items()}}, buffer)
    with atomic_file(path) as tmp:
        tmp.write_bytes(buffer.getbuffer())
    return path


def load_plain(path: str | Path, *, kind: str, remedy: str, error: type[LabelsynthError] = LabelsynthError,
               map_location: torch.device | str = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` with every failure as one ``error`` line:
    ``kind`` names what the file should be ("labelsynth field file"), ``remedy`` what to do."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: not found" if not path.exists() else f"{path}: not a file (expected a {kind})")
    try:
        with warnings.catch_warnings():  # torch's note on a foreign pickle protocol: the error below says it all
            warnings.simplefilter("ignore")
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        code = re.search(r"GLOBAL (\S+) was not an allowed global", str(exc))
        if code:  # the pickle names a function or class to call: what a tampered file does
            raise error(f"{path}: refused: it would call Python code ({code.group(1)}) when opened, which labelsynth "
                        f"never does (a {path.name} from elsewhere or altered could run code); {remedy}") from None
        raise error(f"{path}: not a {kind} (not tensors and plain values); {remedy}") from None
    except Exception as exc:  # truncated zip, not a torch file at all, I/O: torch raises many kinds
        raise error(f"{path}: truncated or not a {kind} ({first_line(exc)[:200]}); {remedy}") from None


def read_described(state: Any, key: str, path: Path, *, kind: str, error: type[LabelsynthError] = LabelsynthError
                   ) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The JSON description and the tensors of a loaded ``save_described`` file, checked."""
    if not isinstance(state, dict) or key not in state:
        raise error(f"{path}: not a {kind} (no description in it)")
    try:
        description = json.loads(state[key])
    except (TypeError, ValueError):
        description = None
    if not isinstance(description, dict):
        raise error(f"{path}: not a {kind} (its description is not readable)")
    tensors = state.get(TENSORS_KEY)
    if not isinstance(tensors, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                for k, v in tensors.items()):
        raise error(f"{path}: not a {kind} (no tensors)")
    return description, tensors


def tensors_under(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors named ``<prefix>.<name>``, by ``<name>``."""
    return {k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + ".")}
