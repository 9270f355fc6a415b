"""One progress-bar style for the whole package (rich), silent when asked or not on a TTY-less CI."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, nullcontext
from typing import TypeVar

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

T = TypeVar("T")

console = Console(stderr=True)


def make_progress(enabled: bool = True) -> Progress:
    """A rich Progress printing to stderr when it is a terminal; ``enabled=False``, or stderr
    redirected to a file or a pipe, gives a no-op display (a log gets the summary lines, not
    the final frame of every bar, and an error stays the one line on stderr)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not enabled or not console.is_terminal,
        transient=False,
    )


def track(items: Iterable[T], description: str, total: int | None = None, enabled: bool = True) -> Iterator[T]:
    """Iterate with a progress bar (a thin wrapper so call sites stay one line)."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with make_progress(enabled) as progress:
        task = progress.add_task(description, total=total, status="")
        for item in items:
            yield item
            progress.advance(task)


@contextmanager
def phase(seconds: dict[str, float], name: str, spinner: str | None = None, enabled: bool = True) -> Iterator[None]:
    """Time a step into ``seconds[name]`` (run.json and the report record them).

    ``spinner`` names a step that has no count to show a bar for (a mesh, the figures): a
    spinner with that text runs while it works. Steps that draw their own bar pass none, since
    rich shows one live display at a time.
    """
    t0 = time.perf_counter()
    with console.status(spinner) if enabled and spinner else nullcontext():
        yield
    seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
