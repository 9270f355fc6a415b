"""What a geometry was fitted on, so that a later run can reuse it only on the same inputs.

Stage 1 reads the capture's images and cameras (with the scene box they give) and the recipe's
``geometry`` section, and draws from the seed; nothing else (no mask, no class table). A
``GeometryFingerprint`` records exactly those: a SHA-256 of every image file, of every camera
(size, intrinsics, distortion, pose), the scene normalisation, the ``geometry`` section as
resolved, the seed, and the labelsynth version that fitted it. ``field.pt`` carries it
(``FittedField.fitted_on``, written by ``rundir.save_field``), so a geometry file says what it
belongs to wherever it is copied.

Who checks: ``expand --geometry`` (``pipeline.expand``: images, cameras, geometry recipe and
seed must all match, else stage 1 is not skipped but refused) and anything that reuses a fitted
field on a capture later (``require_unchanged(stored, capture, where=...)`` without a recipe or
seed compares images and cameras only). The version is recorded, never compared.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import __version__
from ..config import with_defaults
from ..errors import LabelsynthError
from .config import GeometryConfig

DEFAULT_REMEDY = "fit it again (without --geometry) or use the capture, recipe and seed it was fitted with"
"""What ``require_unchanged``'s refusal tells the user to do, unless the caller says otherwise."""

PARTS = ("images", "cameras", "geometry recipe", "seed")
"""What a fingerprint compares, in the order a mismatch names them."""


class GeometryChanged(LabelsynthError, ValueError):
    """The capture (or recipe, or seed) is not what the geometry was fitted on (one line)."""


@dataclass(frozen=True)
class GeometryFingerprint:
    """The inputs of one geometry fit (see the module docstring)."""

    images: dict[str, str]
    """Frame name -> SHA-256 of its image file's bytes (the frames stage 1 read)."""
    white_background: bool
    """Whether RGBA frames were composited on white (else black): part of the pixels it saw."""
    cameras: dict[str, str]
    """Frame name -> SHA-256 of its camera: size, intrinsics, distortion and camera-to-world."""
    normalization: dict[str, Any]
    """The scene box (``SceneNormalization.to_json``): world <-> the unit cube the SDF lives in."""
    geometry: dict[str, Any]
    """The recipe's ``geometry`` section as resolved (every value)."""
    seed: int
    version: str = __version__
    """The labelsynth version that fitted it (recorded, not compared)."""

    @classmethod
    def of(cls, capture, geometry: GeometryConfig, seed: int, frames: Sequence[int] | None = None) -> "GeometryFingerprint":
        """The fingerprint of fitting ``geometry`` with ``seed`` on ``capture`` (a ``Capture``;
        all frames, or the given indices). Reads every image file once (no decoding)."""
        indices = range(len(capture.frames)) if frames is None else frames
        chosen = [capture.frames[i] for i in indices]
        return cls(
            images={f.name: file_sha256(f.image_path) for f in chosen},
            white_background=bool(capture.white_background),
            cameras={f.name: camera_sha256(f.camera) for f in chosen},
            normalization=capture.normalization.to_json(),
            geometry=dataclasses.asdict(geometry),
            seed=int(seed),
        )

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: Any, where: str) -> "GeometryFingerprint":
        """A stored fingerprint, checked; anything else is one ``GeometryChanged`` line naming ``where``."""
        bad = f"{where}: its record of what the geometry was fitted on is not readable"
        if not isinstance(data, dict):
            raise GeometryChanged(bad)
        try:
            fp = cls(images=dict(data["images"]), white_background=bool(data["white_background"]),
                     cameras=dict(data["cameras"]), normalization=dict(data["normalization"]),
                     geometry=dict(data["geometry"]), seed=data["seed"], version=str(data.get("version", "")))
        except (KeyError, TypeError, ValueError):
            raise GeometryChanged(bad) from None
        texts = [*fp.images.items(), *fp.cameras.items()]
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in texts) or isinstance(fp.seed, bool) \
                or not isinstance(fp.seed, int):
            raise GeometryChanged(bad)
        return fp

    def changes(self, current: "GeometryFingerprint", parts: Sequence[str] = PARTS) -> dict[str, str]:
        """Part -> what differs in ``current`` from this (stored) fingerprint, for the ``parts``
        asked (of ``PARTS``); empty when they all match."""
        out: dict[str, str] = {}
        if "images" in parts:
            detail = _frame_changes(self.images, current.images)
            if self.white_background != current.white_background:
                detail = ", ".join(filter(None, [detail, "RGBA compositing background changed"]))
            if detail:
                out["images"] = detail
        if "cameras" in parts:
            detail = _frame_changes(self.cameras, current.cameras, membership=False)
            if self.normalization != current.normalization:
                detail = ", ".join(filter(None, [detail, "scene box changed"]))
            if detail:
                out["cameras"] = detail
        if "geometry recipe" in parts:
            stored = with_defaults(self.geometry, dataclasses.asdict(GeometryConfig()))
            diff = _dict_changes(stored, current.geometry, "geometry")
            if diff:
                out["geometry recipe"] = ", ".join(diff[:3]) + (f" and {len(diff) - 3} more" if len(diff) > 3 else "")
        if "seed" in parts and self.seed != current.seed:
            out["seed"] = f"{self.seed} -> {current.seed}"
        return out


def require_unchanged(
    stored: GeometryFingerprint | None,
    capture,
    *,
    where: str | Path,
    geometry: GeometryConfig | None = None,
    seed: int | None = None,
    remedy: str | None = None,
) -> GeometryFingerprint:
    """Refuse to reuse a geometry on ``capture`` unless it was fitted on these inputs.

    Always compares the images and cameras; the geometry recipe too when ``geometry`` is given,
    and the seed when ``seed`` is given. ``stored``: the geometry's fingerprint
    (``FittedField.fitted_on``; None for a field.pt written before fingerprints, which cannot be
    vouched for). ``where`` names the geometry file in the message. Raises one
    ``GeometryChanged`` line saying what changed; returns the current fingerprint.
    """
    if stored is None:
        raise GeometryChanged(f"{where}: holds no record of what its geometry was fitted on (written by an older "
                              f"labelsynth); {remedy or 'fit it again (labelsynth suggest or expand)'}")
    parts = ["images", "cameras"] + (["geometry recipe"] if geometry is not None else []) \
        + (["seed"] if seed is not None else [])
    current = GeometryFingerprint.of(capture, geometry if geometry is not None else GeometryConfig(),
                                     seed if seed is not None else stored.seed, frames=None)
    changed = stored.changes(current, parts)
    if changed:
        what = " and ".join(changed)
        detail = "; ".join(f"{part}: {text}" for part, text in changed.items())
        raise GeometryChanged(f"{capture.root}: {what} changed since the geometry in {where} was fitted ({detail}); "
                              f"{remedy or DEFAULT_REMEDY}")
    return current


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def camera_sha256(camera) -> str:
    """SHA-256 of a camera's size, intrinsics, distortion and pose (exact float values)."""
    values = [camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
              camera.k1, camera.k2, camera.p1, camera.p2, *camera.c2w.ravel().tolist()]
    return hashlib.sha256(json.dumps([float(v) for v in values]).encode()).hexdigest()


def _frame_changes(before: dict[str, str], after: dict[str, str], membership: bool = True) -> str:
    """'frame_0003 differs, 2 frames added (...)' (what a user can act on), or '' when equal;
    ``membership=False``: frames only in one of them are not mentioned (the images part does)."""
    differ = sorted(n for n in before.keys() & after.keys() if before[n] != after[n])
    parts = [f"{_names(differ)} {'differs' if len(differ) == 1 else 'differ'}"] if differ else []
    if membership:
        added, removed = sorted(after.keys() - before.keys()), sorted(before.keys() - after.keys())
        if added:
            parts.append(f"{_count(added, 'frame')} added ({_names(added)})")
        if removed:
            parts.append(f"{_count(removed, 'frame')} removed ({_names(removed)})")
    return ", ".join(parts)


def _dict_changes(before: Any, after: Any, prefix: str) -> list[str]:
    if isinstance(before, dict) and isinstance(after, dict):
        out = []
        for key in sorted(before.keys() | after.keys()):
            out += _dict_changes(before.get(key), after.get(key), f"{prefix}.{key}")
        return out
    return [] if before == after else [f"{prefix} {before!r} -> {after!r}"]


def _names(names: list[str]) -> str:
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def _count(names: list[str], noun: str) -> str:
    return f"{len(names)} {noun}{'s' if len(names) != 1 else ''}"
