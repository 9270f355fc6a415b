"""Outputs that are either complete or absent: folders built in ``X.partial``, renamed at the end.

Why: a run that is interrupted (Ctrl-C, a crash, a full disk) must never leave an ``X`` that
looks finished. Every command that writes a folder (``expand``, ``synth``, ``segment``,
``relabel``, ``export``) builds it under ``X.partial`` beside ``X`` with ``building``; single
files (``labels.h5``, ``transforms.json``) are written to ``partial_path(X)`` and renamed the
same way. A folder that replaces an existing ``X`` (``expand --force``, ``relabel``) is swapped
in by two renames: ``X`` -> ``X.previous``, ``X.partial`` -> ``X``; ``X.previous`` is then
removed (or kept, when asked), so at every moment either the old ``X`` or the new one is whole.

A ``X.partial`` left by a killed run is removed when the next run starts.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import LabelsynthError

PARTIAL_SUFFIX = ".partial"
PREVIOUS_SUFFIX = ".previous"


def partial_path(path: str | Path) -> Path:
    """Where ``path`` is assembled before it is complete: ``path`` + ``.partial``, beside it."""
    path = Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def previous_path(path: str | Path) -> Path:
    """Where a replaced folder ``path`` waits while its successor is renamed in: ``path`` + ``.previous``."""
    path = Path(path)
    return path.with_name(path.name + PREVIOUS_SUFFIX)


def check_out(out: str | Path, force: bool = False) -> None:
    """Refuse an output folder that exists and is not empty (unless ``force``), or that is a
    file; one line naming the folder. Cheap: call it before any long work."""
    out = Path(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise LabelsynthError(f"{out}: exists and is not a folder")
    if not force and any(out.iterdir()):
        raise LabelsynthError(f"{out}: output folder exists and is not empty (use --force to replace it)")


@contextmanager
def building(out: str | Path, *, force: bool = False, merge: bool = False, keep_previous: bool = False) -> Iterator[Path]:
    """Yield ``OUT.partial`` (fresh and empty) to write into; on leaving the block normally it
    becomes ``OUT``, on an exception (KeyboardInterrupt included) it is removed and ``OUT`` is
    left as it was.

    ``merge=False`` (``expand``, ``synth``, ``relabel``): ``OUT`` must be empty or absent unless
    ``force``, and is replaced as a whole: renamed to ``OUT.previous`` (an older one there is
    removed first), ``OUT.partial`` renamed to ``OUT``, then ``OUT.previous`` removed unless
    ``keep_previous``. ``merge=True`` (``segment``, whose ``OUT`` may be a capture's
    ``predictions/``): the finished files are moved into ``OUT`` one by one (each move is
    atomic), replacing files of the same name and keeping the others.
    """
    out = Path(out)
    if not merge:
        check_out(out, force)
    elif out.exists() and not out.is_dir():
        raise LabelsynthError(f"{out}: exists and is not a folder")
    partial = partial_path(out)
    try:
        if partial.exists():
            shutil.rmtree(partial)
        partial.mkdir(parents=True)
    except OSError as exc:
        raise LabelsynthError(f"{partial}: cannot create output folder ({exc.strerror or exc})") from exc
    try:
        yield partial
        if merge and out.exists():
            for item in sorted(partial.iterdir()):
                target = out / item.name
                if target.is_dir() and not item.is_dir():
                    raise LabelsynthError(f"{target}: is a folder, cannot replace it with a file")
                if target.is_dir():
                    shutil.rmtree(target)
                os.replace(item, target)
            partial.rmdir()
        elif out.exists():
            previous = previous_path(out)
            if previous.exists():
                shutil.rmtree(previous)
            os.replace(out, previous)
            try:
                os.replace(partial, out)
            except BaseException:
                os.replace(previous, out)
                raise
            if not keep_previous:
                shutil.rmtree(previous, ignore_errors=True)
        else:
            os.replace(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield ``partial_path(path)`` to write one file into; it becomes ``path`` when the block
    ends normally and is removed on any exception, so readers never see half a file."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a text file through ``partial_path(path)`` and rename it; the parent folder is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
