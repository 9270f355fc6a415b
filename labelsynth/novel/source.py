"""A finished ``expand`` output and the capture it was fitted to, checked before any rendering.

Novel views need three things from OUT: the fitted field (``field.pt``: surface and semantic
head), the real frames' labels (``labels.h5``, copied into ``augment.h5`` beside the novel
views) and the capture (``run.json`` names it: the real images are what novel views are blended
from). Each one missing is a one-line error naming it, before anything is written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from ..capture import load_capture
from ..capture.model import Capture
from ..errors import LabelsynthError
from ..outdir import PARTIAL_SUFFIX, partial_path
from ..render.field import SemanticField

FIELD_FILE = "field.pt"
RUN_FILE = "run.json"
LABELS_FILE = "labels.h5"


class AugmentError(LabelsynthError, ValueError):
    """An OUT, option or capture that ``augment`` cannot use (one line, names what is missing)."""


@dataclass
class Expanded:
    """What ``augment`` reads from a finished expand output (never writes there, but OUT/augment)."""

    out: Path
    capture: Capture
    field: SemanticField
    run: dict

    @property
    def labels_path(self) -> Path:
        return self.out / LABELS_FILE


def check_expanded(out: str | Path, capture_dir: str | Path | None = None) -> tuple[Path, dict, Path]:
    """(OUT, run.json contents, capture folder) of a finished expand, or an AugmentError.

    Cheap (no field, no pixels): call it before any long work. ``capture_dir`` replaces the
    capture path recorded in run.json (a capture that was moved).
    """
    out = Path(out)
    if out.name.endswith(PARTIAL_SUFFIX):
        raise AugmentError(f"{out}: an unfinished expand (a {PARTIAL_SUFFIX} folder); run expand again to finish it")
    if not out.is_dir():
        if partial_path(out).is_dir():
            raise AugmentError(f"{out}: not finished (only {partial_path(out)} exists); run expand again to finish it")
        raise AugmentError(f"{out}: not found (expected the output folder of labelsynth expand)")
    for name in (FIELD_FILE, RUN_FILE, LABELS_FILE):
        if not (out / name).is_file():
            raise AugmentError(f"{out / name}: not found ({out} is not a finished labelsynth expand output)")
    try:
        run = json.loads((out / RUN_FILE).read_text())
        recorded = run["capture"]
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise AugmentError(f"{out / RUN_FILE}: not a labelsynth run file ({exc})") from None
    cap = Path(capture_dir) if capture_dir is not None else Path(recorded)
    if not cap.is_dir():
        if capture_dir is None:
            raise AugmentError(f"{cap}: the capture named in {out / RUN_FILE} was not found (moved? give --capture)")
        raise AugmentError(f"{cap}: capture folder not found")
    return out, run, cap


def load_expanded(out: str | Path, device: torch.device, capture_dir: str | Path | None = None) -> Expanded:
    """The checked OUT, its capture (with the run's choice of annotated frames) and its field."""
    out, run, cap = check_expanded(out, capture_dir)
    capture = load_capture(cap, annotated_frames=run.get("annotated_frames"))
    try:
        sem = SemanticField.load(out / FIELD_FILE, device)
    except LabelsynthError:
        raise
    except Exception as exc:  # a truncated or foreign file: torch raises many kinds
        raise AugmentError(f"{out / FIELD_FILE}: not a readable labelsynth field ({type(exc).__name__}: {exc})") from None
    if sem.head is None:
        raise AugmentError(f"{out / FIELD_FILE}: the field has no semantic head (its expand did not finish)")
    if sem.classes.to_json() != capture.classes.to_json():
        raise AugmentError(f"{cap}: its class table differs from the field's ({out / FIELD_FILE}); wrong capture?")
    if sem.normalization.to_json() != capture.normalization.to_json():
        raise AugmentError(f"{cap}: its cameras are not those the field was fitted to ({out / FIELD_FILE})")
    return Expanded(out, capture, sem, run)
