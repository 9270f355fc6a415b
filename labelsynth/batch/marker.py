"""The resume marker: what a finished capture was made from, so an unchanged one is skipped.

``OUT/markers/<name>.json`` is written (atomically) only after that capture's
``OUT/captures/<name>/`` is complete. It holds a hash of

- the inputs: every file of the capture folder by relative path, size and modification time
  (as ``make`` and ``rsync`` judge a file changed; reading every image again would cost as much
  as a large capture's input check on every resume),
- the recipe as resolved (the named or given YAML plus the ``--set`` overrides, every default
  filled in), so an edited recipe file or a changed default reruns,
- the options that change the output (labels mode, seed, annotated frames, report, mesh),
- the labelsynth version.

A capture is skipped when its marker's key equals the key computed now and its output folder
is a finished ``expand`` output (``rundir.RunFolder.is_finished``). Anything else (no marker, a different key, a
folder removed by hand, a run killed between the rename and the marker) redoes it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..outdir import write_text_atomic
from ..rundir import RunFolder

MARKERS_DIR = "markers"


def _sha(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def input_listing(capture: Path) -> list[tuple[str, int, int]]:
    """(relative path, size, mtime in ns) of every non-hidden file of the capture, sorted."""
    capture = Path(capture)
    rows = []
    for dirpath, dirnames, filenames in os.walk(capture):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in filenames:
            if name.startswith("."):
                continue
            p = Path(dirpath) / name
            st = p.stat()
            rows.append((p.relative_to(capture).as_posix(), st.st_size, st.st_mtime_ns))
    return sorted(rows)


@dataclass
class Marker:
    """The identity of one capture's output; ``key`` decides skip or redo."""

    inputs: str
    recipe: str
    options: dict[str, Any] = field(default_factory=dict)
    version: str = __version__

    @property
    def key(self) -> str:
        return _sha({"inputs": self.inputs, "recipe": self.recipe, "options": self.options, "version": self.version})

    def to_json(self) -> dict[str, Any]:
        return {"key": self.key, "inputs": self.inputs, "recipe": self.recipe, "options": self.options,
                "version": self.version}


def make_marker(capture: Path, recipe: dict[str, Any], options: dict[str, Any]) -> Marker:
    """The marker a run of ``capture`` with this resolved recipe and these options would leave."""
    return Marker(inputs=_sha(input_listing(capture)), recipe=_sha(recipe), options=dict(options))


def marker_path(out: Path, name: str) -> Path:
    return Path(out) / MARKERS_DIR / f"{name}.json"


def is_done(out: Path, name: str, marker: Marker, output: Path, report: bool) -> bool:
    """Complete output and a stored marker with the same key: nothing to redo."""
    path = marker_path(out, name)
    try:
        stored = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return isinstance(stored, dict) and stored.get("key") == marker.key and RunFolder(output).is_finished(report)


def write_marker(out: Path, name: str, marker: Marker) -> Path:
    """Record a finished capture (atomic: a reader sees the old marker or the new one)."""
    return write_text_atomic(marker_path(out, name), json.dumps(marker.to_json(), indent=2))


def clear_marker(out: Path, name: str) -> None:
    """Forget a capture before redoing it, so a half-replaced output is never taken as done."""
    marker_path(out, name).unlink(missing_ok=True)
