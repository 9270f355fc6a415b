"""Running one malformed case and checking what every bad input must give:

- exit code 2;
- exactly one line ``labelsynth: error: ...`` on stderr, containing what the case names (the
  option or the file, and the problem), and nothing else there but one-line warnings
  (``labelsynth: warning: ...``, e.g. a posed frame skipped because its image is missing); the
  one exception is the input check that lists every bad file of a capture at once
  (``capture.check``): one error line per bad file, then one summary line (``N problems in
  CAPTURE ...; nothing was trained``);
- no Python traceback anywhere in the output;
- no file or folder of the case's inputs changed, created or removed (a snapshot of the whole
  case folder before and after: CAPTURE, a finished OUT, the model, and the output path, which
  must be absent afterwards, or exactly as it was before; so no OUT and no OUT.partial).

The rule for click's own usage errors (``--seed abc``, a missing ``--out``, an unknown option)
is the same one line: ``labelsynth: error: labelsynth CMD: <click's message> (see 'labelsynth
CMD --help')``, never the usage text or a framed panel.

Training, structure-from-motion, decoding of frames, inference and Ray are replaced by a
``Reached`` exception (``heavy``): a case that gets that far failed to be refused in time.
"""

from __future__ import annotations

import errno
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
from typer.testing import CliRunner

from labelsynth.cli import app

from .world import World, snapshot

# Where the long work of every command starts: reaching one of these is a failed case.
HEAVY = {
    "synth": ("labelsynth.evaluation.synth.writer", "build_layout"),
    "import-video": ("labelsynth.capture.video", "_import_video"),
    "import-photos": ("labelsynth.capture.video", "_import_photos"),
    "poses": ("labelsynth.capture.poses", "_run_sfm"),
    "expand": ("labelsynth.pipeline", "fit_field"),
    "geometry": ("labelsynth.pipeline", "fit_geometry"),
    "bench": ("labelsynth.evaluation.bench", "_fit_geometries"),
    "bench-2d": ("labelsynth.evaluation.bench", "_run_perturbation"),
    "train": ("labelsynth.train.loop", "make_out"),
    "segment": ("labelsynth.train.segment", "_segment_frames"),
    "augment": ("labelsynth.novel.views", "RealFrames"),
    "report": ("labelsynth.pipeline", "_report"),
    "batch": ("labelsynth.batch.run", "_connect"),
    "export": ("labelsynth.export.formats", "export_frames"),
}


CHECK_SUMMARY = re.compile(r"^labelsynth: error: \d+ problems in .*; nothing was (trained|written)")


class Reached(Exception):
    """The long work of a command started: the case was not refused before it."""


def patch_heavy(monkeypatch, keep: tuple[str, ...] = ()) -> None:
    import importlib

    for name, (module, attr) in HEAVY.items():
        if name in keep:
            continue

        def reached(*args, _name=name, **kwargs):
            raise Reached(_name)

        monkeypatch.setattr(importlib.import_module(module), attr, reached)


@dataclass
class Case:
    """One malformed invocation. ``argv`` may name the world's paths as ``{cap}``, ``{run}``,
    ``{out}``, ... (``World.names``); ``expect`` are texts the one error line must contain
    (formatted the same way); ``setup`` breaks the world's copy first; ``patch`` fakes an OS
    failure (a full disk, no permission) with pytest's monkeypatch; ``keep`` lets some long
    work run (a case that must fail inside it: a full disk while writing)."""

    id: str
    argv: list[str]
    expect: tuple[str, ...]
    setup: Callable[[World], None] | None = None
    patch: Callable[[pytest.MonkeyPatch, World], None] | None = None
    keep: tuple[str, ...] = ()
    checkpoint: bool = False
    """The case needs the world's train checkpoint ({ckpt_dir}/checkpoint.pt)."""

    @property
    def command(self) -> str:
        return self.argv[0]


def _fmt(text: str, names: dict[str, str]) -> str:
    for key, value in names.items():
        text = text.replace("{" + key + "}", value)
    return text


def run_case(case: Case, world: World, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run ``case`` in ``world`` (a fresh copy) and check every property; returns the error line."""
    names = world.names()
    if case.setup is not None:
        case.setup(world)
    argv = [_fmt(a, names) for a in case.argv]
    patch_heavy(monkeypatch, case.keep)
    if case.patch is not None:
        case.patch(monkeypatch, world)
    before = snapshot(world.root)
    result = CliRunner().invoke(app, argv)
    monkeypatch.undo()
    after = snapshot(world.root)
    output = result.output + (result.stderr if result.stderr not in result.output else "")
    where = f"{case.id}: labelsynth {' '.join(argv)}\n--- output:\n{output}"
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(f"{where}\n--- raised {type(result.exception).__name__}: {result.exception}") \
            from result.exception
    assert result.exit_code == 2, where
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("labelsynth: error: ")]
    # nothing but the error (and one-line warnings, e.g. a frame skipped for want of its image)
    assert errors and all(ln in errors or ln.startswith("labelsynth: warning: ") for ln in lines), where
    # one line; or, for the input check that lists every bad file at once, one line per file and a summary
    assert len(errors) == 1 or CHECK_SUMMARY.search(errors[-1]), where
    line = "\n".join(lines)
    for text in case.expect:  # the problem's words in any case ("No space left" / "no space left")
        assert _fmt(text, names).lower() in line.lower(), f"{where}\n--- expected {_fmt(text, names)!r} in the error line"
    assert "Traceback" not in output, where
    changed = sorted(set(before) ^ set(after)) + sorted(k for k in before.keys() & after.keys() if before[k] != after[k])
    assert not changed, f"{where}\n--- changed on disk: {[os.fsdecode(c) for c in changed[:10]]}"
    return line


# --- faked OS failures ----------------------------------------------------------------------
def deny_writes_under(folder_of: Callable[[World], Path], code: int = errno.EACCES):
    """Every folder or file created under a folder fails as on a read-only or locked disk
    (the tests run as root, whom chmod does not stop)."""

    def patch(monkeypatch: pytest.MonkeyPatch, world: World) -> None:
        locked = os.fsencode(folder_of(world))
        real_mkdir, real_open = os.mkdir, os.open

        def under(path) -> bool:
            p = os.fsencode(os.path.abspath(path))
            return p == locked or p.startswith(locked + b"/")

        def mkdir(path, mode=0o777, *, dir_fd=None):
            if under(path):
                raise OSError(code, os.strerror(code), os.fsdecode(path))
            return real_mkdir(path, mode, dir_fd=dir_fd)

        def open_(path, flags, mode=0o777, *, dir_fd=None):
            if under(path) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
                raise OSError(code, os.strerror(code), os.fsdecode(path))
            return real_open(path, flags, mode, dir_fd=dir_fd)

        import builtins
        import io

        real_io_open = io.open

        def io_open(file, mode="r", *args, **kwargs):
            if isinstance(file, (str, bytes, os.PathLike)) and any(c in mode for c in "wax+") and under(file):
                raise OSError(code, os.strerror(code), os.fsdecode(file))
            return real_io_open(file, mode, *args, **kwargs)

        monkeypatch.setattr(os, "mkdir", mkdir)
        monkeypatch.setattr(os, "open", open_)
        monkeypatch.setattr(builtins, "open", io_open)
        monkeypatch.setattr(io, "open", io_open)

    return patch


def disk_full_after(nbytes: int):
    """Python-level file writes (``open(..., 'wb')``, ``Path.write_bytes``/``write_text``) fail
    with ENOSPC once ``nbytes`` have been written: a disk that fills up mid-run."""

    def patch(monkeypatch: pytest.MonkeyPatch, world: World) -> None:
        import builtins
        import io

        budget = {"left": nbytes}
        real_open = builtins.open

        class Full(io.FileIO):
            def write(self, data):
                n = len(memoryview(data).cast("B"))
                if n > budget["left"]:
                    budget["left"] = 0
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self.name)
                budget["left"] -= n
                return super().write(data)

        def open_(file, mode="r", *args, **kwargs):
            if isinstance(file, (str, bytes, os.PathLike)) and any(c in mode for c in "wax+") and \
                    os.fsencode(os.path.abspath(file)).startswith(os.fsencode(world.root)):
                raw = Full(file, mode.replace("t", "").replace("b", "") + "b" if "b" not in mode else mode.replace("t", ""))
                if "b" in mode:
                    return io.BufferedWriter(raw) if kwargs.get("buffering", -1) != 0 else raw
                return io.TextIOWrapper(io.BufferedWriter(raw), encoding=kwargs.get("encoding") or "utf-8",
                                        newline=kwargs.get("newline"))
            return real_open(file, mode, *args, **kwargs)

        monkeypatch.setattr(builtins, "open", open_)
        monkeypatch.setattr(io, "open", open_)

    return patch
