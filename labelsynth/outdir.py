"""Outputs that are either complete or absent: folders built in ``X.partial``, renamed at the end.

Why: a run that is interrupted (Ctrl-C, SIGTERM, a crash, a full disk) must never leave an
``X`` that looks finished. Every command that writes a folder (``expand``, ``synth``,
``segment``, ``relabel``, ``export``) builds it under ``X.partial`` beside ``X`` with
``building``; single files (``labels.h5``, ``transforms.json``) are written to
``partial_path(X)`` and renamed the same way. A folder that replaces an existing ``X``
(``expand --force``, ``relabel``) is swapped in by two renames: ``X`` -> ``X.previous``,
``X.partial`` -> ``X``; ``X.previous`` is then removed (or kept, when asked), so at every moment
either the old ``X`` or the new one is whole. A ``X.partial`` left by a killed run (SIGKILL,
power loss) is removed when the next run starts.

Signals: while a command builds its output (``building``, ``atomic_file``, or ``interruptible``
around other long work), SIGTERM is raised as an ``Interrupted`` exception in the main thread,
as Ctrl-C raises ``KeyboardInterrupt``, so the same cleanup runs and ``X.partial`` is removed.
A second Ctrl-C or SIGTERM while that cleanup runs exits at once (exit code 128 + the signal).
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import LabelsynthError

PARTIAL_SUFFIX = ".partial"
SPACE_MARGIN = 8 << 20
"""Bytes that must stay free beyond what a writer is about to write (``ensure_space``)."""
PREVIOUS_SUFFIX = ".previous"


def partial_path(path: str | Path) -> Path:
    """Where ``path`` is assembled before it is complete: ``path`` + ``.partial``, beside it."""
    path = Path(path)
    return path.with_name(path.name + PARTIAL_SUFFIX)


def previous_path(path: str | Path) -> Path:
    """Where a replaced folder ``path`` waits while its successor is renamed in: ``path`` + ``.previous``."""
    path = Path(path)
    return path.with_name(path.name + PREVIOUS_SUFFIX)


# ------------------------------------------------------------------------------------------
# signals
# ------------------------------------------------------------------------------------------
class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGINT raised as an exception in the main thread (``interruptible``); a
    ``KeyboardInterrupt``, so every cleanup written for Ctrl-C runs for SIGTERM too."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_state: dict = {"depth": 0, "previous": {}, "caught": None}


def _on_signal(signum, frame) -> None:
    if _state["caught"] is not None:  # the second one: no more cleanup, exit now
        os.write(2, f"labelsynth: {signal.Signals(signum).name} again: exiting at once\n".encode())
        os._exit(128 + signum)
    _state["caught"] = signum
    raise Interrupted(signum)


def _ours_to_take(signum: int) -> bool:
    """Only a signal nobody else handles is taken over (a Ray worker keeps its own SIGTERM)."""
    return signal.getsignal(signum) in (signal.SIG_DFL, signal.default_int_handler, _on_signal)


@contextmanager
def signal_handlers_kept() -> Iterator[None]:
    """Put back this process's SIGINT and SIGTERM handlers after the block. Why: ``ray.init`` in a
    driver (and an in-process Ray node) installs Ray's own SIGTERM handler and ``ray.shutdown``
    leaves it; ``interruptible`` does not take over a signal someone else handles, so a later
    expand in the same process (a notebook, a script) would no longer clean up on SIGTERM.
    Outside the main thread (where Python cannot set handlers) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.getsignal(s) for s in _SIGNALS}
    try:
        yield
    finally:
        for signum, handler in saved.items():
            if handler is not None:  # None: set from C, cannot be put back from Python
                signal.signal(signum, handler)


@contextmanager
def interruptible() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise ``Interrupted`` once, so ``except`` and
    ``finally`` cleanups run; a second one during that cleanup exits the process at once.
    Blocks nest; outside the main thread (where Python cannot set handlers) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _state["depth"] == 0:
        _state["caught"] = None
        _state["previous"] = {s: signal.signal(s, _on_signal) for s in _SIGNALS if _ours_to_take(s)}
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0:
            for signum, previous in _state["previous"].items():
                signal.signal(signum, previous)
            _state["previous"] = {}


# ------------------------------------------------------------------------------------------
# space
# ------------------------------------------------------------------------------------------
def _mb(nbytes: float) -> str:
    return f"{nbytes / (1 << 20):.1f} MB"


def ensure_space(path: str | Path, nbytes: int, what: str) -> None:
    """Refuse in one line to write ``nbytes`` more at ``path`` when its file system has less
    than that plus ``SPACE_MARGIN`` free. Why: HDF5 crashes the process (a segmentation fault
    after the error, h5py issue 914) when a write meets a full disk, so the writers of .h5
    files ask first; every other writer learns of a full disk from the OSError its write raises."""
    probe = Path(path)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:
        return
    if free < nbytes + SPACE_MARGIN:
        raise LabelsynthError(f"{path}: not enough free space for {what} (needs about {_mb(nbytes + SPACE_MARGIN)}, "
                              f"{_mb(free)} free on its disk)")


# ------------------------------------------------------------------------------------------
# folders and files
# ------------------------------------------------------------------------------------------
def check_writable(out: str | Path) -> None:
    """``out`` can be made where it is asked for: it is not a symbolic link (dangling, looping,
    or one that the final rename would replace), the nearest folder above it that exists is a
    folder, and a folder can be created in it (tried: a probe folder made and removed at
    once, so a read-only disk or a missing permission fails now, not after the training).
    One line naming the path."""
    out = Path(out)
    if out.is_symlink():
        raise LabelsynthError(f"{out}: is a symbolic link; give the folder itself as the output")
    above = out.parent
    while not os.path.lexists(above) and above != above.parent:
        above = above.parent
    if above.is_symlink() and not above.exists():
        raise LabelsynthError(f"{above}: a symbolic link that leads nowhere (or to itself)")
    if not above.is_dir():
        raise LabelsynthError(f"{above}: is a file, not a folder (the output {out} cannot be made there)")
    try:
        probe = tempfile.mkdtemp(prefix=".labelsynth-probe-", dir=above)
    except OSError as exc:
        raise LabelsynthError(f"{above}: cannot create the output there ({_os_problem(exc)})") from None
    os.rmdir(probe)


def check_apart(out: str | Path, inputs: dict[str, str | Path]) -> None:
    """``out`` is none of ``inputs`` (label -> folder) and inside none of them: a command never
    writes into what it reads (a capture above all). One line naming both."""
    out = Path(out)
    try:
        dst = out.resolve()
    except (OSError, RuntimeError):
        return  # a looping link: check_writable names it
    for label, folder in inputs.items():
        try:
            src = Path(folder).resolve()
        except (OSError, RuntimeError):
            continue
        if dst == src or src in dst.parents:
            raise LabelsynthError(f"{out}: inside {label} {folder}; write the output elsewhere (nothing in it is changed)")


def _os_problem(exc: OSError) -> str:
    return (exc.strerror or str(exc) or type(exc).__name__).lower()


def check_out(out: str | Path, force: bool = False) -> None:
    """Refuse an output folder that exists and is not empty (unless ``force``), that is a file
    or a symbolic link, or that cannot be created (``check_writable``); one line naming the
    folder. Cheap: call it before any long work."""
    out = Path(out)
    check_writable(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise LabelsynthError(f"{out}: exists and is not a folder")
    if not force and any(out.iterdir()):
        raise LabelsynthError(f"{out}: output folder exists and is not empty (use --force to replace it)")


@contextmanager
def building(out: str | Path, *, force: bool = False, merge: bool = False, keep_previous: bool = False) -> Iterator[Path]:
    """Yield ``OUT.partial`` (fresh and empty) to write into; on leaving the block normally it
    becomes ``OUT``, on an exception (KeyboardInterrupt and SIGTERM included) it is removed and
    ``OUT`` is left as it was.

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
    else:
        check_writable(out)
        if out.exists() and not out.is_dir():
            raise LabelsynthError(f"{out}: exists and is not a folder")
    partial = partial_path(out)
    with interruptible():
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
        except BaseException as exc:
            shutil.rmtree(partial, ignore_errors=True)
            _name_the_output(exc, partial)
            raise


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield ``partial_path(path)`` to write one file into; it becomes ``path`` when the block
    ends normally and is removed on any exception (SIGTERM included), so readers never see half
    a file."""
    path = Path(path)
    tmp = partial_path(path)
    with interruptible():
        try:
            yield tmp
            os.replace(tmp, path)
        except BaseException as exc:
            tmp.unlink(missing_ok=True)
            _name_the_output(exc, tmp)
            raise


def _name_the_output(exc: BaseException, where: Path) -> None:
    """A failed write (a full disk, a quota) raises an OSError without a file name: say which
    output it was, in one line, now that its partial copy is gone."""
    if isinstance(exc, OSError) and exc.filename is None:
        raise LabelsynthError(f"{where}: {_os_problem(exc)} while writing it (the partial output was removed)") from None


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a text file through ``partial_path(path)`` and rename it; the parent folder is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
