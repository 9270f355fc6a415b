"""Check every input a run will read before it trains, and report every problem at once.

Masks and images are otherwise read lazily, some only after the geometry stage (minutes), so a
broken mask used to cost a geometry fit per mistake. ``check_capture`` decodes each file once
with the readers the run uses (``read_image``, ``read_mask``: same checks, same messages),
in threads (OpenCV, PIL and zlib release the GIL), and keeps the decoded masks on the capture
(``Capture.mask_cache``) so the semantic stage does not decode them again. Nothing is written.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from ..classes import CLASSES_FILE, ClassMap
from ..errors import CaptureError, CheckError
from . import images as _images
from . import masks as _masks  # module lookups at call time: a patched reader is the one used
from .model import Capture, file_stamp

if TYPE_CHECKING:
    import numpy as np

LABEL_CHOICES = ("annotations", "predictions", "both")


class ExtraMask(NamedTuple):
    """A mask the run reads besides the capture's own (e.g. a benchmark's truth)."""

    path: Path
    size: tuple[int, int] | None  # (width, height) it must have
    role: str = "extra"  # named in the "missing" message: "truth mask missing"


@dataclass
class CheckReport:
    """What ``check_capture`` found: ``problems`` has one line per bad file, naming it."""

    root: Path
    problems: list[str] = field(default_factory=list)
    files: int = 0
    seconds: float = 0.0
    cached_masks: int = 0
    stopped: str = "nothing was trained"
    """What the summary says did not happen because of the problems."""

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        if self.ok:
            return f"checked {self.files} files in {self.seconds:.1f} s"
        n = len(self.problems)
        return (
            f"{n} problem{'s' if n != 1 else ''} in {self.root} "
            f"(checked {self.files} files in {self.seconds:.1f} s); {self.stopped}"
        )

    def raise_if_problems(self) -> None:
        """Raise one ``CheckError`` listing every problem (its ``problems``, one per line)."""
        if self.problems:
            raise CheckError(self.problems, self.summary())


def check_capture(
    capture: Capture,
    *,
    labels: str | None = "both",
    images: bool = True,
    extra_masks: Sequence[ExtraMask] = (),
    class_tables: Mapping[str, ClassMap] | None = None,
    workers: int | None = None,
    cache: bool = True,
) -> CheckReport:
    """Decode every input a run will read and list what is wrong; never raises for bad files.

    What is checked is what the run reads, nothing more: ``labels`` names the mask folders
    (``annotations``, ``predictions``, ``both``, or None for none), so ``--labels annotations``
    without a report leaves predictions undecoded; ``images=False`` skips the frames (a run
    that fits no geometry). Each image must decode, be complete and have its camera's size;
    each mask must decode, have its frame's size and hold only known ids or colours;
    ``class_tables`` (where from -> table, e.g. a saved field's) must match the capture's ids,
    names and wound-bed flags (colours may differ: they only draw). Call
    ``.raise_if_problems()`` on the result to stop a run. Decoded masks are cached on the
    capture (``cache=True``) within ``capture.mask_cache_limit``.
    """
    if labels is not None and labels not in LABEL_CHOICES:
        raise ValueError(f"labels must be one of {', '.join(LABEL_CHOICES)} or None, not {labels!r}")
    t0 = time.perf_counter()
    folders = () if labels is None else ("annotations", "predictions") if labels == "both" else (labels,)
    report = CheckReport(root=capture.root)
    for where, table in (class_tables or {}).items():
        problem = compare_class_tables(capture.classes, _classes_source(capture), table, where)
        if problem:
            report.problems.append(problem)

    tasks = _read_tasks(capture, folders, images, extra_masks)
    n_workers = max(1, min(workers or _cpu_count(), len(tasks) or 1))
    with ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="labelsynth-check") as pool:
        for (_, path, _, _), (problem, mask, stamp) in zip(tasks, pool.map(lambda t: _check_file(capture, t), tasks)):
            if problem:
                report.problems.append(problem)
            elif mask is not None and cache and capture.cache_mask(path, mask, stamp):
                report.cached_masks += 1
    report.files = len(tasks)
    report.seconds = time.perf_counter() - t0
    return report


def check_image_files(paths: Sequence[Path], root: Path, *, white_background: bool = False,
                      workers: int | None = None) -> CheckReport:
    """Decode every image a command will read (``segment``, ``poses``, ``import`` of photos)
    with the reader it uses, before it writes anything; every bad file is one line (a
    truncated or foreign file, a broken link). Sizes are free: these commands take any."""
    t0 = time.perf_counter()
    report = CheckReport(root=Path(root), stopped="nothing was written")

    def check(path: Path) -> str | None:
        try:
            _images.read_image(path, None, white_background)
            return None
        except CaptureError as exc:
            return str(exc).splitlines()[0]
        except Exception as exc:  # noqa: BLE001 - one odd file must not hide the others' problems
            return f"{path}: cannot read image ({type(exc).__name__}: {exc})"

    n_workers = max(1, min(workers or _cpu_count(), len(paths) or 1))
    with ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="labelsynth-check") as pool:
        report.problems = [p for p in pool.map(check, paths) if p]
    report.files = len(paths)
    report.seconds = time.perf_counter() - t0
    return report


_Task = tuple[str, Path, tuple[int, int] | None, str]  # kind ("image" or "mask"), path, size, role


def _read_tasks(capture: Capture, folders: Sequence[str], images: bool, extra_masks: Sequence[ExtraMask]) -> list[_Task]:
    """Every file the run will read, frame by frame, then the extra masks: exactly what the run
    reads, so a check never fails a run on a file it would not have opened."""
    tasks: list[_Task] = []
    for frame in capture.frames:
        if images:
            tasks.append(("image", frame.image_path, frame.size, "image"))
        if "annotations" in folders and frame.annotation_path is not None:
            tasks.append(("mask", frame.annotation_path, frame.size, "annotation"))
        if "predictions" in folders and frame.prediction_path is not None:
            tasks.append(("mask", frame.prediction_path, frame.size, "prediction"))
    tasks += [("mask", Path(m.path), m.size, m.role) for m in extra_masks]
    return tasks


def _check_file(capture: Capture, task: _Task) -> tuple[str | None, np.ndarray | None, tuple[int, int] | None]:
    """(problem line or None, decoded mask or None, its file stamp or None) for one file, decoded
    by the run's own reader so the check finds what the run would; never raises for a bad file."""
    kind, path, size, role = task
    if not (path.is_file() if kind == "image" else _masks.mask_exists(path)):
        return f"{path}: {role} {'file' if kind == 'image' else 'mask'} missing", None, None
    stamp = file_stamp(path)
    try:
        if kind == "image":
            _images.read_image(path, size, capture.white_background)
            return None, None, None
        mask = _masks.read_mask(path, size, capture.classes, capture.color_table, kind=capture.mask_kind(path))
        return None, mask, stamp
    except CaptureError as exc:
        return str(exc).splitlines()[0], None, None
    except Exception as exc:  # noqa: BLE001 - one odd file must not hide the others' problems
        return f"{path}: cannot read {kind} ({type(exc).__name__}: {exc})", None, None


def compare_class_tables(a: ClassMap, a_name: str, b: ClassMap, b_name: str) -> str | None:
    """One line saying how two class tables differ in ids, names or wound-bed flags (None if
    they agree): masks from one read with the other would mean different tissues."""
    def key(m: ClassMap) -> dict[int, tuple[str, bool]]:
        return {c.id: (c.name, c.id in m.wound_bed_ids) for c in m.classes}

    ka, kb = key(a), key(b)
    if ka == kb:
        return None
    diffs = []
    for i in sorted(set(ka) | set(kb)):
        if i not in kb:
            diffs.append(f"id {i} ({ka[i][0]}) only here")
        elif i not in ka:
            diffs.append(f"id {i} ({kb[i][0]}) only there")
        elif ka[i][0] != kb[i][0]:
            diffs.append(f"id {i} is '{ka[i][0]}' here, '{kb[i][0]}' there")
        elif ka[i][1] != kb[i][1]:
            diffs.append(f"id {i} ({ka[i][0]}) is {'' if ka[i][1] else 'not '}wound bed here, "
                         f"{'' if kb[i][1] else 'not '}there")
    shown = "; ".join(diffs[:4]) + (f"; and {len(diffs) - 4} more" if len(diffs) > 4 else "")
    return f"{a_name}: class table differs from the one in {b_name} ({shown})"


def _classes_source(capture: Capture) -> str:
    path = capture.root / CLASSES_FILE
    return str(path) if path.is_file() else f"{capture.root} (default class table, no classes.json)"


def _cpu_count() -> int:
    """CPUs this process may use (the affinity mask, not the machine's count), at most 8:
    beyond that the disk, not decoding, is the limit."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(8, n))


__all__ = ["CheckReport", "ExtraMask", "check_capture", "check_image_files", "compare_class_tables"]
