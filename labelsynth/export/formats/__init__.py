"""Masks out to the tools annotators and ML engineers use: CVAT, Pascal VOC, COCO, Cityscapes.

``export_frames(frames, classes, to, fmt=...)`` writes a stream of ``ExportFrame`` (name,
image, class-id mask, confidence) in one of ``EXPORT_FORMATS``:

- ``cvat``: a zip that CVAT imports into a task as "Segmentation mask 1.1" (``voc``'s files);
- ``voc``: the same layout as a folder (``formats.voc``);
- ``coco``: ``annotations/instances.json`` with pycocotools RLE, one annotation per class
  region per frame, confidence as ``score`` (``formats.coco``);
- ``cityscapes``: ``*_gtFine_labelIds.png`` beside ``*_leftImg8bit.png`` trees (``formats.cityscapes``).

``min_confidence``: pixels less confident become ignore (255; COCO: left out). ``flagged``
(the report's flagged frames) are listed in README.txt (and COCO's ``info``). The export is
built in ``TO.partial`` and renamed when whole, so an interrupted export leaves nothing that
looks finished. labelsynth's capture loader reads the cvat zip and the COCO file back as a
capture's ``annotations/`` (``capture.archives``), and the voc folder's SegmentationClass/ as
ordinary masks.
"""

from __future__ import annotations

import time
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ...classes import IGNORE_ID, ClassMap
from ...outdir import atomic_file, building
from ...progress import track
from ..dataset import ExportError
from .cityscapes import CityscapesWriter
from .coco import CocoWriter
from .common import ExportFrame, Sink, readme_text
from .voc import VocWriter

EXPORT_FORMATS: tuple[str, ...] = ("cvat", "voc", "coco", "cityscapes")
FRAME_CHOICES: tuple[str, ...] = ("all", "flagged", "unannotated")
README = "README.txt"

__all__ = ["EXPORT_FORMATS", "FRAME_CHOICES", "ExportFrame", "ExportResult", "choose_frames", "export_frames"]


@dataclass
class ExportResult:
    """What ``export_frames`` wrote."""

    path: Path
    format: str
    frames: list[str]
    ignored_pixels: int = 0
    seconds: float = 0.0
    flagged: list[str] = field(default_factory=list)

    def summary(self) -> str:
        return (f"wrote {self.path} ({self.format}): {len(self.frames)} frames, {self.ignored_pixels} pixels ignore, "
                f"{self.seconds:.1f} s" + (f"; flagged: {', '.join(self.flagged)}" if self.flagged else ""))


def choose_frames(names: Sequence[str], annotated: Sequence[bool], which: str,
                  flagged: Sequence[str] | None) -> list[str]:
    """The frames ``--frames`` asks for, in their order: ``all``, ``flagged`` (the report's
    flagged frames; None = no report, an error) or ``unannotated`` (those no expert annotated).
    An empty choice is an ExportError: an export of nothing is a mistake, not a result."""
    if which not in FRAME_CHOICES:
        raise ExportError(f"--frames {which!r}: expected one of {', '.join(FRAME_CHOICES)}")
    if which == "all":
        chosen = list(names)
    elif which == "unannotated":
        chosen = [n for n, a in zip(names, annotated) if not a]
    else:
        if flagged is None:
            raise ExportError("--frames flagged: there is no consistency report (run `labelsynth report OUT` first)")
        chosen = [n for n in names if n in set(flagged)]
    if not chosen:
        raise ExportError(f"--frames {which}: no frame to export" + (" (the report flagged none)" if which == "flagged" else ""))
    return chosen


def export_frames(
    frames: Iterable[ExportFrame],
    classes: ClassMap,
    to: str | Path,
    *,
    fmt: str,
    flagged: Sequence[str] = (),
    min_confidence: float | None = None,
    source: str | None = None,
    name: str | None = None,
    total: int | None = None,
    force: bool = False,
    progress: bool = False,
) -> ExportResult:
    """Write ``frames`` (read one at a time) as ``fmt`` at ``to``: a ``.zip`` file for ``cvat``, a
    folder for the others. ``to`` that exists is refused unless ``force``. ``source`` (the run
    folder) and ``name`` (the capture's name: Cityscapes' city) label the export; ``total``
    sizes the progress bar."""
    if fmt not in EXPORT_FORMATS:
        raise ExportError(f"--format {fmt!r}: expected one of {', '.join(EXPORT_FORMATS)}")
    if min_confidence is not None and not 0.0 <= float(min_confidence) <= 1.0:
        raise ExportError(f"--min-confidence {min_confidence}: expected a number in 0..1")
    to = Path(to)
    t0 = time.perf_counter()
    if fmt == "cvat":
        if to.suffix.lower() != ".zip":
            raise ExportError(f"{to}: a cvat export is a .zip file (e.g. --to {to.with_suffix('.zip').name})")
        if to.exists() and (to.is_dir() or not force):
            raise ExportError(f"{to}: exists" + ("" if to.is_dir() else " (use --force to replace it)"))
        to.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(to) as partial, zipfile.ZipFile(partial, "w") as archive:
            result = _write(Sink(archive=archive), frames, classes, fmt, flagged, min_confidence, source, name,
                            total, progress)
    else:
        with building(to, force=force) as partial:
            result = _write(Sink(root=partial), frames, classes, fmt, flagged, min_confidence, source, name,
                            total, progress)
    result.path, result.seconds = to, time.perf_counter() - t0
    return result


def _write(sink: Sink, frames: Iterable[ExportFrame], classes: ClassMap, fmt: str, flagged: Sequence[str],
           min_confidence: float | None, source: str | None, name: str | None, total: int | None,
           progress: bool) -> ExportResult:
    writer: VocWriter | CocoWriter | CityscapesWriter
    if fmt in ("cvat", "voc"):
        writer = VocWriter(sink, classes)
    elif fmt == "coco":
        writer = CocoWriter(sink, classes)
    else:
        writer = CityscapesWriter(sink, classes, name)
    ignored = 0
    seen: set[str] = set()
    for frame in track(frames, f"export ({fmt})", total=total, enabled=progress):
        if frame.name in seen:
            raise ExportError(f"frame {frame.name!r}: exported twice (frame names must be unique)")
        seen.add(frame.name)
        ignored += int((writer.add(frame, min_confidence) == IGNORE_ID).sum())
    if not writer.names:
        raise ExportError("no frame to export")
    writer.finish(flagged=list(flagged), min_confidence=min_confidence, source=source)
    sink.write(README, readme_text(fmt, writer.layout, classes, writer.names, list(flagged), min_confidence,
                                   writer.ignore_text, source))
    return ExportResult(Path(), fmt, list(writer.names), ignored, 0.0, list(flagged))
