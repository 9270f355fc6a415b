"""Which captures a batch runs: every capture folder under a root, or the paths listed in a text file.

A capture is a folder that ``load_capture`` can read poses from (``capture.load.is_capture``:
``transforms.json``, ``transforms_train.json``, ``cameras_sphere.npz`` or a COLMAP model in
``sparse/0`` or ``sparse/``). Each gets a name that is unique in the batch and safe as a
folder name: its output goes to ``OUT/captures/<name>/`` and its frames carry that name in
``OUT/dataset.h5``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..capture.load import POSE_SOURCES, is_capture
from ..errors import LabelsynthError

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


class BatchError(LabelsynthError, ValueError):
    """A batch that cannot start as asked (no captures, a bad list file, an impossible resource request)."""


@dataclass(frozen=True)
class CaptureJob:
    """One capture of the batch: where it is and the name of its output folder."""

    name: str
    path: Path


def find_captures(root: Path, exclude: Path | None = None) -> list[Path]:
    """Capture folders under ``root`` (``root`` itself if it is one), sorted; a capture's own
    subfolders are not searched, nor hidden folders, nor ``exclude`` (the batch's OUT)."""
    root = Path(root)
    if is_capture(root):
        return [root]
    skip = exclude.resolve() if exclude is not None else None
    found: list[Path] = []
    for dirpath, dirnames, _ in os.walk(root):
        here = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and not d.endswith(".partial"))
        keep = []
        for d in dirnames:
            sub = here / d
            if skip is not None and sub.resolve() == skip:
                continue
            if is_capture(sub):
                found.append(sub)
            else:
                keep.append(d)
        dirnames[:] = keep
    return sorted(found)


def read_capture_list(list_file: Path) -> list[Path]:
    """A text file with one capture folder per line (relative to the file's folder); blank lines
    and ``#`` comments are skipped. A line that is not a capture is an error naming the line."""
    paths = []
    try:
        lines = Path(list_file).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise BatchError(f"{list_file}: cannot read the capture list ({exc})") from None
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        path = Path(text).expanduser()
        if not path.is_absolute():
            path = Path(list_file).parent / path
        if not path.is_dir():
            raise BatchError(f"{list_file}:{number}: {text}: no such capture folder")
        if not is_capture(path):
            raise BatchError(f"{list_file}:{number}: {text}: not a capture (no {POSE_SOURCES})")
        paths.append(path)
    return paths


def _safe(text: str) -> str:
    return _UNSAFE.sub("_", text).strip("._") or "capture"


def name_jobs(paths: list[Path], root: Path | None = None) -> list[CaptureJob]:
    """Unique folder-safe names: the folder's name, or its path below ``root`` (parts joined by
    ``__``) when two captures share a folder name; a duplicate folder is an error."""
    seen: dict[Path, Path] = {}
    for p in paths:
        key = p.resolve()
        if key in seen:
            raise BatchError(f"{p}: the same capture is listed twice (also as {seen[key]})")
        seen[key] = p
    base = [_safe(p.resolve().name) for p in paths]
    names = list(base)
    clashes = {n for n in base if base.count(n) > 1}
    for i, p in enumerate(paths):
        if names[i] in clashes:
            rp = p.resolve()
            try:
                rel = rp.relative_to(root.resolve()) if root is not None else None
            except ValueError:
                rel = None
            parts = rel.parts if rel is not None and rel.parts else rp.parts[-3:]
            names[i] = "__".join(_safe(part) for part in parts)
    for i, n in enumerate(names):  # still equal (e.g. a/b_c vs a_b/c): number them
        if names.count(n) > 1:
            names[i] = f"{n}__{i}"
    return [CaptureJob(n, p) for n, p in zip(names, paths)]


def discover(source: str | Path, out: Path | None = None) -> list[CaptureJob]:
    """The batch's captures from a root folder (searched) or a text file (a list of paths)."""
    source = Path(source)
    if source.is_file():
        paths, root = read_capture_list(source), None
        what = f"{source}: lists no captures"
    elif source.is_dir():
        paths, root = find_captures(source, exclude=out), source
        what = f"{source}: no capture folders found (a capture has {POSE_SOURCES})"
    else:
        raise BatchError(f"{source}: no such folder or capture list")
    if not paths:
        raise BatchError(what)
    return name_jobs(paths, root)
