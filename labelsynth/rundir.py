"""A finished ``expand`` output folder (OUT): its file names, run.json's schema and field.pt's format.

Every command that reads or writes an OUT (``expand``, ``report``, ``augment``, ``batch``'s
resume and table) goes through ``RunFolder``; no other module spells these file names.

``field.pt`` (format version 2) is one ``torch.save`` of a plain dict::

    {"labelsynth_field": "<JSON text>", "tensors": {"sdf.<name>": Tensor, "head.<name>": Tensor,
                                                    "grid.<name>": Tensor}}

The JSON holds the format name and version, the labelsynth version, the class table, the scene
normalisation, the recipe the field was fitted with, what its geometry was fitted on
(``fitted_on``: ``geometry.fingerprint``; absent in files from before it) and the non-tensor
parts of the state (the occupancy grid's resolution). It is read with ``torch.load(weights_only=True)``, which
rebuilds tensors, strings and containers and refuses anything else, so a field.pt someone sent
can never run code when opened. A file from before version 2 (a pickled dict of state dicts)
holds only tensors and plain values too: it is read the same safe way and converted in memory.
A file that cannot be read that way (altered, truncated, not a field) is a one-line error.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from . import __version__
from .capture.load import load_capture
from .capture.model import Capture, SceneNormalization
from .classes import ClassMap
from .errors import LabelsynthError
from .geometry.fingerprint import GeometryChanged, GeometryFingerprint
from .geometry.sampling import OccupancyGrid
from .geometry.sdf import SDFField
from .outdir import PARTIAL_SUFFIX, partial_path, previous_path, write_text_atomic
from .recipe import Recipe
from .render.field import FittedField, SurfaceMesh
from .safeload import first_line as _first_line
from .safeload import load_plain, read_described, save_described
from .safeload import tensors_under as _part

MASKS_DIR = "masks"
LABELS_FILE = "labels.h5"
REPORT_JSON = "report.json"
REPORT_HTML = "report.html"
MESH_STEM = "mesh"  # mesh.ply, and mesh.glb with --mesh-format glb
FIELD_FILE = "field.pt"
RUN_FILE = "run.json"

FIELD_FORMAT = "labelsynth-field"
FIELD_VERSION = 2
_META_KEY = "labelsynth_field"
_RECREATE = "re-create it with `labelsynth expand`"


class RunFolderError(LabelsynthError, ValueError):
    """An OUT, run.json or field.pt that cannot be used (one line, names the file)."""


# ------------------------------------------------------------------------------------------
# run.json
# ------------------------------------------------------------------------------------------
@dataclass
class RunInfo:
    """OUT/run.json: what ran (capture, labels, recipe, device, seed) and how long each phase took."""

    capture: str
    """The capture folder, absolute."""
    labels: str
    """annotations | predictions | both: what taught the semantic stage."""
    recipe: dict = field(default_factory=dict)
    """The recipe as resolved (every value; ``Recipe.to_dict``)."""
    annotated_frames: list[str] | None = None
    """The frames whose annotations taught, when ``--annotated-frames`` chose them (else None: all)."""
    device: str = "cpu"
    seed: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    """Seconds of every phase (check, geometry, semantics, render, report)."""
    geometry: dict[str, Any] = field(default_factory=dict)
    """The geometry stage's statistics (``geometry.training.GeometryStats`` and the initial shape)."""
    semantic: dict[str, Any] = field(default_factory=dict)
    """The semantic stage's statistics (``semantics.training.SemanticStats``)."""
    report_seconds: dict[str, float] | None = None
    """Seconds of the report's own steps (agreement, leave_one_out, pairwise, mesh, figures)."""
    geometry_from: str | None = None
    """The geometry file (field.pt, absolute) whose geometry this run reused instead of fitting
    stage 1 (``expand --geometry``); None: fitted in this run."""
    label_inputs: dict[str, dict[str, str]] | None = None
    """The masks the run read (``label_inputs``): per kind (annotations, predictions) and frame,
    the SHA-256 of the decoded class ids. The next ``relabel`` lists what changed since."""
    relabel: dict[str, Any] | None = None
    """Set by ``relabel``: ``masks_changed`` (``kind/frame`` whose mask changed, was added or
    removed since the previous run), ``pixels_changed`` (per frame, pixels whose class differs
    from the previous OUT's mask) and ``relabels`` (how many relabels since the geometry was fitted)."""
    version: str = __version__
    """The labelsynth version that wrote it."""

    @property
    def total_seconds(self) -> float:
        return float(sum(self.seconds.values()))

    def to_json(self) -> dict[str, Any]:
        data = {"version": self.version, "capture": self.capture, "labels": self.labels,
                "annotated_frames": self.annotated_frames, "recipe": self.recipe, "device": self.device,
                "seed": self.seed, "seconds": self.seconds, "geometry": self.geometry, "semantic": self.semantic}
        for key in ("report_seconds", "geometry_from", "label_inputs", "relabel"):
            if getattr(self, key) is not None:
                data[key] = getattr(self, key)
        return data

    @classmethod
    def from_json(cls, data: Any, where: str) -> "RunInfo":
        """A run.json's contents, checked; anything else is a one-line ``RunFolderError``."""
        bad = f"{where}: not a labelsynth run file"
        if not isinstance(data, dict):
            raise RunFolderError(f"{bad} (expected a JSON object)")
        for key in ("capture", "labels"):
            if not isinstance(data.get(key), str):
                raise RunFolderError(f"{bad} (no '{key}')")
        if data["labels"] not in ("annotations", "predictions", "both"):
            raise RunFolderError(f"{bad} (labels '{data['labels']}')")
        frames = data.get("annotated_frames")
        if frames is not None and not (isinstance(frames, list) and all(isinstance(f, str) for f in frames)):
            raise RunFolderError(f"{bad} ('annotated_frames' is not a list of frame names)")
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise RunFolderError(f"{bad} ('seed' is not a whole number)")
        seconds = data.get("seconds") or {}
        if not isinstance(seconds, dict) or not all(isinstance(v, (int, float)) for v in seconds.values()):
            raise RunFolderError(f"{bad} ('seconds' is not a mapping of numbers)")
        if not isinstance(data.get("geometry_from", ""), str):
            raise RunFolderError(f"{bad} ('geometry_from' is not a path)")
        # (a run.json of an earlier version may also hold "geometry_inputs": what the images and
        # cameras were is field.pt's fitted_on now, so it is not read)
        kept = {k: data[k] for k in ("recipe", "device", "geometry", "semantic", "report_seconds", "geometry_from",
                                     "label_inputs", "relabel", "version") if k in data}
        for key in ("recipe", "geometry", "semantic", "label_inputs", "relabel"):
            if not isinstance(kept.get(key) or {}, dict):
                raise RunFolderError(f"{bad} ('{key}' is not a mapping)")
        if not all(isinstance(v, dict) and all(isinstance(h, str) for h in v.values())
                   for v in (kept.get("label_inputs") or {}).values()):
            raise RunFolderError(f"{bad} ('label_inputs' is not a mapping of frame names to digests)")
        return cls(capture=data["capture"], labels=data["labels"], annotated_frames=frames, seed=seed,
                   seconds={k: float(v) for k, v in seconds.items()}, **kept)


# ------------------------------------------------------------------------------------------
# field.pt
# ------------------------------------------------------------------------------------------
def save_field(fitted: FittedField, path: str | Path) -> Path:
    """Write ``fitted`` as field.pt (format version 2), atomically."""
    path = Path(path)
    tensors: dict[str, torch.Tensor] = {}
    plain: dict[str, dict] = {}
    parts = {"sdf": fitted.sdf.state_dict(), "grid": fitted.grid.state_dict()}
    if fitted.head is not None:
        parts["head"] = fitted.head.state_dict()
    for prefix, state in parts.items():
        plain[prefix] = {}
        for key, value in state.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{prefix}.{key}"] = value.detach()
            else:
                plain[prefix][key] = value
    meta = {
        "format": FIELD_FORMAT,
        "version": FIELD_VERSION,
        "labelsynth": __version__,
        "classes": fitted.classes.to_json(),
        "normalization": fitted.normalization.to_json(),
        "recipe": fitted.recipe.to_dict(),
        "state": plain,
        "has_head": fitted.head is not None,
    }
    if fitted.fitted_on is not None:
        meta["fitted_on"] = fitted.fitted_on.to_json()
    if fitted.surface is not None:
        meta["surface_resolution"] = fitted.surface.resolution
        for name in ("vertices", "faces", "normals"):
            tensors[f"surface.{name}"] = torch.from_numpy(np.array(getattr(fitted.surface, name), copy=True))
    return save_described(path, _META_KEY, meta, tensors)


def load_field(path: str | Path, device: torch.device | str = "cpu") -> FittedField:
    """A field.pt as a ``FittedField`` on ``device``, read without unpickling any code; a file
    from before format version 2 is converted. Anything unreadable is one ``RunFolderError`` line."""
    path = Path(path)
    device = torch.device(device)
    state = load_plain(path, kind="labelsynth field file", remedy=_RECREATE, error=RunFolderError, map_location=device)
    if isinstance(state, dict) and _META_KEY in state:
        meta, tensors = _read_v2(state, path)
    elif isinstance(state, dict) and {"sdf", "head", "grid", "classes", "normalization", "recipe"} <= set(state):
        meta, tensors = _convert_v1(state, path)
    else:
        raise RunFolderError(f"{path}: not a labelsynth field file (no field description in it)")
    return _build_field(meta, tensors, path, device)


def _read_v2(state: dict, path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    meta, tensors = read_described(state, _META_KEY, path, kind="labelsynth field file", error=RunFolderError)
    if meta.get("format") != FIELD_FORMAT:
        raise RunFolderError(f"{path}: not a labelsynth field file (its description is not readable)")
    version = meta.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise RunFolderError(f"{path}: not a labelsynth field file (format version {version!r})")
    if version > FIELD_VERSION:
        raise RunFolderError(f"{path}: written by a newer labelsynth (field format {version}; this one reads up to "
                             f"{FIELD_VERSION}): update labelsynth")
    return meta, tensors


def _convert_v1(state: dict, path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    """A field.pt from before format 2 (``{"sdf": state_dict, "head": ..., "grid": {...},
    "classes", "normalization", "recipe"}``, already read safely) as version-2 parts."""
    sdf, grid, head = state["sdf"], state["grid"], state["head"]
    if not isinstance(sdf, dict) or not isinstance(grid, dict) or not (head is None or isinstance(head, dict)):
        raise RunFolderError(f"{path}: not a labelsynth field file (an old field whose state is not readable)")
    recipe = copy.deepcopy(state["recipe"])
    if not any(str(k).startswith("outer.") for k in sdf) and isinstance(recipe, dict):
        # files from before the outer background
        geometry = recipe.setdefault("geometry", {})
        if isinstance(geometry, dict) and isinstance(geometry.setdefault("sdf", {}), dict):
            geometry["sdf"]["background"] = "env"
    sdf = dict(sdf)
    sdf.setdefault("inv_s_floor", torch.tensor(1.0))  # files from before the sharpness floor existed
    tensors, plain = {}, {}
    for prefix, part in (("sdf", sdf), ("grid", grid), ("head", head or {})):
        plain[prefix] = {k: v for k, v in part.items() if not isinstance(v, torch.Tensor)}
        tensors.update({f"{prefix}.{k}": v for k, v in part.items() if isinstance(v, torch.Tensor)})
    meta = {"format": FIELD_FORMAT, "version": 1, "classes": state["classes"], "normalization": state["normalization"],
            "recipe": recipe, "state": plain, "has_head": head is not None}
    return meta, tensors


def _surface(meta: dict, tensors: dict[str, torch.Tensor], path: Path) -> SurfaceMesh | None:
    """The stored surface (``FittedField.surface``), checked; None in files without one."""
    if "surface_resolution" not in meta:
        return None
    part = _part(tensors, "surface")
    resolution = meta["surface_resolution"]
    try:
        verts, faces, normals = (part[k].cpu().numpy() for k in ("vertices", "faces", "normals"))
        ok = (not isinstance(resolution, bool) and isinstance(resolution, int) and resolution > 0
              and verts.ndim == 2 and verts.shape[1] == 3 and normals.shape == verts.shape
              and faces.ndim == 2 and faces.shape[1] == 3 and faces.dtype.kind in "iu"
              and (faces.size == 0 or (faces.min() >= 0 and faces.max() < len(verts))))
    except (KeyError, AttributeError, TypeError):
        ok = False
    if not ok:
        raise RunFolderError(f"{path}: its stored surface is not a mesh of its field; {_RECREATE}")
    return SurfaceMesh(resolution, verts, faces, normals)


def _build_field(meta: dict, tensors: dict[str, torch.Tensor], path: Path, device: torch.device) -> FittedField:
    recipe = Recipe.from_dict(meta.get("recipe"), f"{path}: recipe")
    classes = ClassMap.from_dict(meta.get("classes"), str(path), "class table of the field")
    try:
        normalization = SceneNormalization.from_json(meta["normalization"])
        if not (np.all(np.isfinite(normalization.center)) and math.isfinite(normalization.scale)
                and normalization.scale > 0 and normalization.center.shape == (3,)):
            raise ValueError("not finite")
        plain = meta.get("state") or {}
        grid_state = {**plain.get("grid", {}), **_part(tensors, "grid")}
        resolution = grid_state.get("resolution")
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
            raise ValueError(f"occupancy grid resolution {resolution!r}")
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RunFolderError(f"{path}: not a labelsynth field file (bad description: {_first_line(exc)})") from None
    try:
        fitted_on = GeometryFingerprint.from_json(meta["fitted_on"], str(path)) if "fitted_on" in meta else None
    except GeometryChanged as exc:
        raise RunFolderError(f"{exc}; {_RECREATE}") from None
    surface = _surface(meta, tensors, path)
    sdf = SDFField(recipe.geometry.sdf).to(device)
    fitted = FittedField(sdf, OccupancyGrid(resolution, device), classes, normalization, recipe, fitted_on=fitted_on,
                         surface=surface)
    head = fitted.new_head() if meta.get("has_head") else None
    try:
        sdf.load_state_dict(_part(tensors, "sdf"))
        if head is not None:
            head.load_state_dict(_part(tensors, "head"))
        if grid_state.get("occupied") is None or tuple(grid_state["occupied"].shape) != (resolution,) * 3:
            raise RuntimeError("the occupancy grid does not match its resolution")
        fitted.grid.load_state_dict(grid_state)
    except (RuntimeError, KeyError, ValueError) as exc:
        raise RunFolderError(f"{path}: its tensors do not fit the recipe it records ({_first_line(exc)}); "
                             f"{_RECREATE}") from None
    for name, value in tensors.items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise RunFolderError(f"{path}: its {name} holds NaN or infinite values; {_RECREATE}")
    sdf.eval()
    for p in sdf.parameters():
        p.requires_grad_(False)  # the geometry of a fitted field is frozen
    if head is not None:
        head.eval()
    return fitted.with_head(head)


# ------------------------------------------------------------------------------------------
# what a run read: run.json's label_inputs (the images and cameras: field.pt's fitted_on)
# ------------------------------------------------------------------------------------------
def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def mask_digest(mask: np.ndarray) -> str:
    """SHA-256 of a decoded mask (its class ids and shape): a mask re-saved in another PNG
    flavour or moved into a CVAT zip is the same mask."""
    mask = np.ascontiguousarray(mask, dtype=np.uint8)
    return _sha256(np.array(mask.shape, dtype=np.int64).tobytes() + mask.tobytes())


def label_inputs(capture: Capture) -> dict[str, dict[str, str]]:
    """The capture's masks, per kind (``annotations``, ``predictions``) and frame: the SHA-256
    of the decoded class ids (``mask_digest``; masks the input check decoded come from its cache)."""
    out: dict[str, dict[str, str]] = {"annotations": {}, "predictions": {}}
    for i, f in enumerate(capture.frames):
        for kind, load in (("annotations", capture.load_annotation), ("predictions", capture.load_prediction)):
            mask = load(i)
            if mask is not None:
                out[kind][f.name] = mask_digest(mask)
    return out


def changed_label_inputs(before: dict[str, dict[str, str]] | None, after: dict[str, dict[str, str]]) -> list[str]:
    """``kind/frame`` of every mask that changed, appeared or went away between two
    ``label_inputs`` (sorted); None before (a run that did not record them): every mask."""
    before = before or {}
    changed = []
    for kind in sorted(set(before) | set(after)):
        old, new = before.get(kind, {}), after.get(kind, {})
        changed += [f"{kind}/{name}" for name in sorted(set(old) | set(new)) if old.get(name) != new.get(name)]
    return changed


# ------------------------------------------------------------------------------------------
# the folder
# ------------------------------------------------------------------------------------------
class RunFolder:
    """An expand output folder: where each file lives, whether it is finished, and its readers.

    ``RunFolder(OUT)`` names the files of a finished OUT; ``expand`` writes them into
    ``RunFolder(OUT.partial)`` (``outdir.building``), which is renamed to OUT when complete.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    # --- file names -----------------------------------------------------------------------
    @property
    def masks_dir(self) -> Path:
        return self.path / MASKS_DIR

    def mask_path(self, frame: str) -> Path:
        return self.masks_dir / f"{frame}.png"

    @property
    def labels_path(self) -> Path:
        return self.path / LABELS_FILE

    @property
    def report_json(self) -> Path:
        return self.path / REPORT_JSON

    @property
    def report_html(self) -> Path:
        return self.path / REPORT_HTML

    def mesh_path(self, mesh_format: str = "ply") -> Path:
        return self.path / f"{MESH_STEM}.{mesh_format}"

    @property
    def field_path(self) -> Path:
        return self.path / FIELD_FILE

    @property
    def run_path(self) -> Path:
        return self.path / RUN_FILE

    # --- finished or not --------------------------------------------------------------------
    def required(self, report: bool = False) -> list[Path]:
        """What a finished expand leaves (``report``: and its report)."""
        files = [self.masks_dir, self.labels_path, self.field_path, self.run_path]
        return files + ([self.report_json] if report else [])

    def missing(self, report: bool = False) -> list[Path]:
        return [p for p in self.required(report) if not (p.is_dir() if p == self.masks_dir else p.is_file())]

    def is_finished(self, report: bool = False) -> bool:
        """A finished expand output (the folder exists only once it is renamed from OUT.partial)."""
        return self.path.is_dir() and not self.missing(report)

    def check_finished(self, report: bool = False) -> None:
        """Raise a one-line ``RunFolderError`` unless this is a finished expand output."""
        out = self.path
        if out.name.endswith(PARTIAL_SUFFIX):
            raise RunFolderError(f"{out}: an unfinished expand (a {PARTIAL_SUFFIX} folder); run expand again to finish it")
        if not out.is_dir():
            if previous_path(out).is_dir() and not out.exists():
                raise RunFolderError(f"{out}: not found, but {previous_path(out)} holds the run it was replacing (a "
                                     f"relabel or expand --force stopped while swapping them): rename it back to {out.name}")
            if partial_path(out).is_dir():
                raise RunFolderError(f"{out}: not finished (only {partial_path(out)} exists); run expand again to finish it")
            if out.exists():
                raise RunFolderError(f"{out}: not a folder (expected the output folder of labelsynth expand)")
            raise RunFolderError(f"{out}: not found (expected the output folder of labelsynth expand)")
        missing = self.missing(report)
        if missing:
            raise RunFolderError(f"{missing[0]}: not found ({out} is not a finished labelsynth expand output)")

    # --- readers and writers ----------------------------------------------------------------
    def read_run(self) -> RunInfo:
        try:
            data = json.loads(self.run_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise RunFolderError(f"{self.run_path}: not found") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RunFolderError(f"{self.run_path}: not a labelsynth run file ({_first_line(exc)})") from None
        return RunInfo.from_json(data, str(self.run_path))

    def write_run(self, info: RunInfo) -> Path:
        return write_text_atomic(self.run_path, json.dumps(info.to_json(), indent=2, default=float))

    def load_field(self, device: torch.device | str = "cpu") -> FittedField:
        return load_field(self.field_path, device)

    def save_field(self, fitted: FittedField) -> Path:
        return save_field(fitted, self.field_path)

    def open_capture(self, capture_dir: str | Path | None = None) -> tuple[RunInfo, Capture]:
        """This finished OUT's run.json and the capture it was fitted to (the one run.json names,
        or ``capture_dir`` for a capture that moved), with the run's choice of annotated frames.
        Cheap (no pixels): call it before any long work."""
        self.check_finished()
        info = self.read_run()
        cap = Path(capture_dir) if capture_dir is not None else Path(info.capture)
        if not cap.is_dir():
            if capture_dir is None:
                raise RunFolderError(f"{cap}: the capture named in {self.run_path} was not found (moved? give --capture)")
            raise RunFolderError(f"{cap}: capture folder not found")
        return info, load_capture(cap, annotated_frames=info.annotated_frames)

    def check_fits(self, fitted: FittedField, capture: Capture, *, need_head: bool = True) -> None:
        """The field (this OUT's field.pt) was fitted to ``capture`` (the same class table and
        cameras) and, with ``need_head``, has a semantic head; otherwise one line naming both."""
        if need_head and fitted.head is None:
            raise RunFolderError(f"{self.field_path}: the field has no semantic head (its expand did not finish)")
        if fitted.classes.to_json() != capture.classes.to_json():
            raise RunFolderError(f"{capture.root}: its class table differs from the field's ({self.field_path}); "
                                 "wrong capture?")
        if fitted.normalization.to_json() != capture.normalization.to_json():
            raise RunFolderError(f"{capture.root}: its cameras are not those the field was fitted to ({self.field_path})")

    def read_masks(self, names: list[str], capture: Capture | None = None) -> dict[str, np.ndarray]:
        """masks/<name>.png of every named frame, as expand wrote them; with ``capture``, each is
        checked to have its frame's size and only the capture's class ids (one line naming it)."""
        from .capture.masks import read_mask
        from .errors import CaptureError

        frames = {f.name: f for f in capture.frames} if capture is not None else {}
        masks = {}
        for name in names:
            path = self.mask_path(name)
            if not path.is_file():
                raise RunFolderError(f"{path}: missing (masks/ of a finished expand has every frame's mask)")
            if capture is not None:
                try:
                    masks[name] = read_mask(path, frames[name].size, capture.classes)
                except CaptureError as exc:
                    raise RunFolderError(str(exc).splitlines()[0]) from None
                continue
            m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if m is None or m.ndim != 2:
                raise RunFolderError(f"{path}: missing or not a single-channel class-id mask")
            masks[name] = m
        return masks

    def read_report_summary(self) -> dict[str, Any]:
        """The summary of report.json, or {} when there is none or it is unreadable."""
        try:
            summary = json.loads(self.report_json.read_text(encoding="utf-8")).get("summary")
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            return {}
        return summary if isinstance(summary, dict) else {}


__all__ = [
    "FIELD_FILE", "FIELD_FORMAT", "FIELD_VERSION", "LABELS_FILE", "MASKS_DIR", "MESH_STEM", "REPORT_HTML",
    "REPORT_JSON", "RUN_FILE", "RunFolder", "RunFolderError", "RunInfo",
    "changed_label_inputs", "label_inputs", "load_field", "mask_digest", "save_field",
]
