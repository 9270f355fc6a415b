"""Masks out to the tools annotators and ML engineers use: CVAT, Pascal VOC, COCO, Cityscapes.

``export_frames(frames, classes, to, fmt=...)`` writes a stream of ``ExportFrame`` (name,
image, class-id mask, confidence) in one of ``EXPORT_FORMATS``:

- ``cvat``: a zip that CVAT imports into a task as "Segmentation mask 1.1" (``voc``'s files);
- ``voc``: the same layout as a folder (``formats.voc``);
- ``coco``: ``annotations/instances.json`` with pycocotools RLE, one annotation per class
  region per frame, confidence as ``score`` (``formats.coco``);
- ``cityscapes``: ``*_gtFine_labelIds.png`` beside ``*_leftImg8bit.png`` trees (``formats.cityscapes``).

``export_run(OUT, to, fmt=...)`` (``labelsynth export``) does it for a finished expand output:
every frame of OUT/labels.h5, or the report's flagged ones, or those no expert annotated.

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
from ...errors import LabelsynthError
from ...outdir import atomic_file, building, check_writable
from ...progress import track
from ..dataset import ExportError
from .cityscapes import CityscapesWriter
from .coco import CocoWriter
from .common import ExportFrame, Sink, readme_text
from .voc import VocWriter

EXPORT_FORMATS: tuple[str, ...] = ("cvat", "voc", "coco", "cityscapes")
FRAME_CHOICES: tuple[str, ...] = ("all", "flagged", "unannotated")
README = "README.txt"

__all__ = ["EXPORT_FORMATS", "FRAME_CHOICES", "ExportFrame", "ExportResult", "choose_frames", "export_frames",
           "export_run"]


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


def _check_target(to: Path, fmt: str, force: bool, keep_out_of: dict[str, tuple[Path, str]]) -> None:
    """Refuse, before anything is written, a target that cannot or must not be written: the wrong
    kind for the format, one that exists without ``force``, or one inside (or holding) a folder in
    ``keep_out_of`` (the run itself: ``--force`` would delete it; the capture: never written)."""
    if fmt == "cvat" and to.suffix.lower() != ".zip":
        raise ExportError(f"{to}: a cvat export is a .zip file (e.g. --to {to.with_suffix('.zip').name})")
    try:  # a link (looping, dangling), a file in the way, a read-only disk: refused now, not mid-export
        check_writable(to)
    except LabelsynthError as exc:
        raise ExportError(str(exc)) from None
    if to.exists():
        if fmt == "cvat" and to.is_dir():
            raise ExportError(f"{to}: exists and is a folder (a cvat export is a .zip file)")
        if fmt != "cvat" and not to.is_dir():
            raise ExportError(f"{to}: exists and is not a folder (a {fmt} export is a folder)")
        if not force and (fmt == "cvat" or any(to.iterdir())):
            raise ExportError(f"{to}: exists (use --force to replace it)")
    target = to.resolve()
    for what, (folder, why) in keep_out_of.items():
        folder = folder.resolve()
        if folder in target.parents:
            raise ExportError(f"{to}: inside {what} {folder} ({why}); export somewhere else")
        if target == folder or target in folder.parents:
            raise ExportError(f"{to}: would replace {what} {folder}; export somewhere else")


def export_run(
    out: str | Path,
    to: str | Path,
    *,
    fmt: str,
    frames: str = "all",
    min_confidence: float | None = None,
    force: bool = False,
    progress: bool = True,
) -> ExportResult:
    """Export a finished expand output (``labelsynth export``): the frames of OUT/labels.h5 that
    ``frames`` chooses (``choose_frames``), read one at a time with their images and confidence,
    the report's flagged frames listed in the export. Every option and the target are checked
    before anything is written; nothing in OUT or the capture is ever written."""
    from ...rundir import RunFolder
    from ..labels_h5 import LabelsReader

    if fmt not in EXPORT_FORMATS:
        raise ExportError(f"--format {fmt!r}: expected one of {', '.join(EXPORT_FORMATS)}")
    if frames not in FRAME_CHOICES:
        raise ExportError(f"--frames {frames!r}: expected one of {', '.join(FRAME_CHOICES)}")
    if min_confidence is not None and not (isinstance(min_confidence, (int, float)) and 0.0 <= min_confidence <= 1.0):
        raise ExportError(f"--min-confidence {min_confidence}: expected a number in 0..1")
    run = RunFolder(out)
    run.check_finished()
    capture = Path(run.read_run().capture)
    to = Path(to)
    _check_target(to, fmt, force, {
        "the run folder": (run.path, "relabel replaces that folder as a whole"),
        "the capture": (capture, "labelsynth never writes into a capture, and an export in annotations/ "
                                 "would be read as expert masks"),
    })
    summary = run.read_report_summary()
    flagged = summary.get("flagged") if summary else None
    reader = LabelsReader(run.labels_path)
    with reader:
        chosen = choose_frames(reader.frame_names, list(reader.annotated), frames, flagged)
        index = {n: i for i, n in enumerate(reader.frame_names)}

        def stream():
            for name in chosen:
                image, mask, confidence = reader.read_checked(index[name])  # a foreign file's ids and confidences
                yield ExportFrame(name, mask, image, confidence, bool(reader.annotated[index[name]]))

        return export_frames(stream(), reader.classes, to, fmt=fmt, flagged=list(flagged or []),
                             min_confidence=min_confidence, source=str(run.path.resolve()), name=capture.name,
                             total=len(chosen), force=force, progress=progress)
