"""A view of a capture with other masks: the same frames and cameras, other annotations/ or
predictions/, built in a folder of its own and never touching the capture.

Why: the self-training loop gives a capture new ``predictions/`` (a model's masks of every frame)
and a benchmark gives it fewer expert frames; writing them into the user's capture is not
allowed (nothing in a capture is ever changed). A view links every entry of the capture
(images/, transforms.json, classes.json, ...) except the mask folders, which it holds itself.
Links are symbolic; where the file system cannot make them, entries are copied.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable, Mapping
from pathlib import Path

from ..errors import CaptureError
from ..outdir import building
from .load import MASK_FOLDERS, find_pose_source

VIEW_MARKER = "capture_view.txt"  # what the view was made from (load_capture ignores it)


def _link(src: Path, dst: Path) -> None:
    try:
        os.symlink(src.resolve(), dst, target_is_directory=src.is_dir())
    except OSError:  # no symlinks here (some Windows setups): copy
        if src.is_dir():
            shutil.copytree(src, dst)
        else:
            shutil.copy2(src, dst)


def _fill(folder: Path, masks: Path | Mapping[str, Path] | Iterable[Path]) -> None:
    """``folder`` linked to a mask folder, or holding links to the given mask files (by stem, or
    under their own names)."""
    if isinstance(masks, (str, Path)):
        _link(Path(masks), folder)
        return
    folder.mkdir()
    items = masks.items() if isinstance(masks, Mapping) else ((Path(p).stem, p) for p in masks)
    for stem, path in items:
        path = Path(path)
        _link(path, folder / f"{stem}{path.suffix}")


def capture_view(capture: str | Path, out: str | Path, *,
                 annotations: Path | Mapping[str, Path] | Iterable[Path] | None = None,
                 predictions: Path | Mapping[str, Path] | Iterable[Path] | None = None,
                 keep_annotations: bool = False, force: bool = False) -> Path:
    """Make OUT, a capture with CAPTURE's frames and cameras and the given masks.

    ``annotations`` / ``predictions``: a mask folder, or mask files (a ``{frame stem: path}``
    mapping, or paths named by their frame's stem); None leaves that folder out, except that
    ``keep_annotations`` links CAPTURE's own annotations/. OUT is built in ``OUT.partial``
    (``outdir.building``); CAPTURE is only read.
    """
    capture, out = Path(capture), Path(out)
    if find_pose_source(capture) is None:
        raise CaptureError(f"{capture}: not a capture folder (no transforms.json, cameras_sphere.npz or sparse/)")
    if out.resolve() == capture.resolve() or capture.resolve() in out.resolve().parents:
        raise CaptureError(f"{out}: a view of {capture} cannot be made inside it")
    if annotations is None and keep_annotations and (capture / "annotations").is_dir():
        annotations = capture / "annotations"
    with building(out, force=force) as tmp:
        for entry in sorted(capture.iterdir()):
            if entry.name not in MASK_FOLDERS and entry.name != VIEW_MARKER and not entry.name.startswith("."):
                _link(entry, tmp / entry.name)
        for name, masks in (("annotations", annotations), ("predictions", predictions)):
            if masks is not None:
                _fill(tmp / name, masks)
        (tmp / VIEW_MARKER).write_text(f"a view of {capture.resolve()} with its own mask folders (labelsynth)\n")
    return out
