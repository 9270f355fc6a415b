"""``load_capture``: a capture folder -> ``Capture`` (read-only; nothing is ever written there).

Pose sources, first found wins (``find_pose_source``, the one rule of what a capture folder
is, which ``batch`` discovery uses too): ``transforms.json``; ``transforms_train.json`` (the
NeRF-synthetic layout, which has no plain ``transforms.json``); ``cameras_sphere.npz`` (the
NeuS / IDR layout of DTU and BlendedMVS, ``capture.neus``); a COLMAP model in ``sparse/0`` or
directly in ``sparse/``. Without any, the error tells the user to run ``labelsynth poses CAPTURE``.

Expert masks come from ``annotations/`` (by image stem; PNG masks, or a CVAT "Segmentation
mask 1.1" zip or a COCO instances JSON read in place: ``capture.archives``) or, in a NeuS capture, from its
``mask/`` (exact object masks, paired by sorted order). A NeuS capture with an
``annotations/`` folder of masks learns from that folder alone: mask/ is ignored with a
warning, since the user made annotations/ on purpose. ``annotated_frames``
(``capture.select``) then keeps the annotations of the chosen frames only; the other frames
count as unannotated everywhere (what teaches, ``labels.h5``'s ``annotated``, which frames a
benchmark scores).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..classes import CLASSES_FILE, ClassMap
from ..errors import CaptureError
from .archives import ARCHIVE_SUFFIXES, archive_masks
from .colmap import find_sparse_model, read_colmap
from .images import image_size, not_a_file
from .masks import BINARY_OBJECT_ID, MASK_EXTENSIONS, color_table_for, mask_size
from .model import Capture, Frame
from .neus import find_neus, read_neus
from .normalize import region_of_interest
from .select import FrameSpec, select_frames
from .transforms import PosedFrames, read_transforms, white_background_of

TRANSFORMS_NAMES = ("transforms.json", "transforms_train.json")
POSE_SOURCES = "transforms.json, transforms_train.json, cameras_sphere.npz or a COLMAP model in sparse/0 or sparse/"
MASK_FOLDERS = ("annotations", "predictions")
LOSSY_EXTENSIONS = (".jpg", ".jpeg")


def load_capture(
    path: str | Path, *, classes: ClassMap | None = None, annotated_frames: FrameSpec | None = None
) -> Capture:
    """Read a capture folder: poses, frames, mask paths, classes, colour table, ROI.

    Pixels are not read here (only image headers where the pose source lacks sizes); mask
    sizes are checked when a mask is read, or all at once by ``validate_capture``.
    Frames whose image is missing are skipped with one warning (with their masks).
    ``annotated_frames``: which frames' annotations teach (``capture.select``: names,
    indices, ``every:K``, ``spread:N``); the others' annotation paths are dropped. None: all.
    """
    root = Path(path)
    if not root.is_dir():
        raise CaptureError(f"{root}: capture folder not found")

    posed = _posed_frames(root)
    classes_json = root / CLASSES_FILE
    if classes is None:
        classes = ClassMap.of_capture(root, posed.classes)
    labelmap = root / "labelmap.txt"
    color_table = color_table_for(classes, labelmap if labelmap.is_file() else None)
    _attach_masks(root, posed, classes, classes_json)

    if annotated_frames is not None:
        _keep_annotations(posed.frames, annotated_frames, root)

    cameras = [f.camera for f in posed.frames]
    normalization = posed.normalization or region_of_interest(cameras, posed.points)
    return Capture(
        root=root,
        frames=posed.frames,
        classes=classes,
        normalization=normalization,
        points=posed.points,
        color_table=color_table,
        white_background=posed.white_background,
        source=posed.source,
        mask_kinds=dict(posed.mask_kinds),
    )


def _posed_frames(root: Path) -> PosedFrames:
    """The pose source's frames that have an image, sorted by name (deterministic, whatever
    order the file lists); frames without an image are skipped with one warning."""
    posed = _read_poses(root)
    if posed.skipped:
        shown = ", ".join(posed.skipped[:5]) + (" ..." if len(posed.skipped) > 5 else "")
        warnings.warn(
            f"{root}: {len(posed.skipped)} frame(s) skipped because their image file is missing ({shown})",
            stacklevel=3,  # load_capture's caller
        )
    if not posed.frames:
        raise CaptureError(f"{root}: none of the {len(posed.skipped)} posed frames has an image file")
    _check_unique_names(posed.frames, root)
    posed.frames.sort(key=lambda f: f.name)  # deterministic, whatever order the file lists
    return posed


def _attach_masks(root: Path, posed: PosedFrames, classes: ClassMap, classes_json: Path) -> None:
    """Point each frame at its annotation and prediction masks (in place). An annotations/
    folder overrides the layout's own masks, since two teaching sources would disagree; a mask
    without a frame is an error, as its name is likely a typo."""
    found = {folder: _mask_files(root / folder, classes) for folder in MASK_FOLDERS}
    if posed.mask_kinds and found["annotations"]:
        layout_masks = ", ".join(f"{p.name}/" for p in posed.mask_kinds)
        warnings.warn(f"{root / 'annotations'}: these annotations teach; the {layout_masks} masks are ignored",
                      stacklevel=3)  # load_capture's caller
        for f in posed.frames:
            f.annotation_path = None
        posed.mask_kinds = {}
    if "binary" in posed.mask_kinds.values() and BINARY_OBJECT_ID not in classes.ids:
        raise CaptureError(
            f"{classes_json if classes_json.is_file() else root}: the object masks in "
            f"{', '.join(str(p) for p in posed.mask_kinds)} are class id {BINARY_OBJECT_ID}, which the class table lacks"
        )

    frames_by_name = {f.name: f for f in posed.frames}
    for folder in MASK_FOLDERS:
        for name, mask_path in found[folder].items():
            frame = frames_by_name.get(name)
            if frame is None:
                if name in posed.skipped:
                    continue  # its frame was skipped (missing image); already warned
                raise CaptureError(f"{mask_path}: no frame named '{name}' (masks are named <image stem>.png)")
            setattr(frame, "annotation_path" if folder == "annotations" else "prediction_path", mask_path)


def capture_white_background(path: str | Path) -> bool:
    """Whether a capture's RGBA frames are composited on white (else black), decided as
    ``load_capture`` decides it, but without poses: tools that read a capture's frames
    before it has any (``segment``) see the same pixels as the field. Only the transforms
    file is read; other pose sources (NeuS, COLMAP), a capture without poses and a transforms
    file that cannot be read mean black."""
    source = find_pose_source(path)
    if source is None or source.kind != "transforms":
        return False
    try:
        data = json.loads(source.path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False  # load_capture reports a broken file; it is not this caller's to judge
    return white_background_of(data) if isinstance(data, dict) else False


def _keep_annotations(frames: list[Frame], spec: FrameSpec, root: Path) -> None:
    """Drop the annotation of every frame ``spec`` does not choose (frames sorted by name)."""
    keep = set(select_frames(spec, [f.name for f in frames]))
    bare = [f.name for f in frames if f.name in keep and f.annotation_path is None]
    for f in frames:
        if f.name not in keep:
            f.annotation_path = None
    if bare:
        shown = ", ".join(bare[:5]) + (" ..." if len(bare) > 5 else "")
        warnings.warn(f"{root}: {len(bare)} of the {len(keep)} frames chosen to teach have no annotation ({shown})",
                      stacklevel=3)


def validate_capture(capture: Capture) -> None:
    """Check every image's and mask's size against its camera from the file headers (fast,
    no decoding), so that a bad file fails before training rather than after; raise a
    ``CaptureError`` naming the first file that does not fit."""
    for frame in capture.frames:
        size = image_size(frame.image_path)
        if size != frame.size:
            raise CaptureError(
                f"{frame.image_path}: image is {size[0]}x{size[1]} but its camera expects {frame.size[0]}x{frame.size[1]}"
            )
        for mask_path in (frame.annotation_path, frame.prediction_path):
            if mask_path is None:
                continue
            size = mask_size(mask_path)
            if size != frame.size:
                raise CaptureError(
                    f"{mask_path}: mask is {size[0]}x{size[1]} but its image is {frame.size[0]}x{frame.size[1]}"
                )


@dataclass(frozen=True)
class PoseSource:
    """Where a capture folder's camera poses are: the file (transforms, NeuS) or the COLMAP model folder."""

    kind: Literal["transforms", "neus", "colmap"]
    path: Path


def find_pose_source(folder: str | Path) -> PoseSource | None:
    """The pose source ``load_capture`` reads in ``folder`` (first found wins, see the module
    docstring), or None: the one rule of what a capture folder is. Only names are looked at."""
    root = Path(folder)
    for name in TRANSFORMS_NAMES:
        if (root / name).is_file():
            return PoseSource("transforms", root / name)
    npz = find_neus(root)
    if npz is not None:
        return PoseSource("neus", npz)
    model = find_sparse_model(root)
    if model is not None:
        return PoseSource("colmap", model)
    return None


def is_capture(folder: str | Path) -> bool:
    """Whether ``folder`` holds a pose source ``load_capture`` reads."""
    return find_pose_source(folder) is not None


def _read_poses(root: Path) -> PosedFrames:
    source = find_pose_source(root)
    if source is None:
        raise CaptureError(f"{root}: no camera poses (no {POSE_SOURCES}); run `labelsynth poses {root}` to estimate them")
    if source.kind == "transforms":
        return read_transforms(source.path)
    if source.kind == "neus":
        return read_neus(source.path)
    return read_colmap(source.path, root / "images")


def _check_unique_names(frames: list[Frame], root: Path) -> None:
    seen: dict[str, Path] = {}
    for f in frames:
        if f.name in seen:
            raise CaptureError(
                f"{f.image_path}: frame name '{f.name}' is also used by {seen[f.name]}; "
                "image stems must be unique (masks are matched by stem)"
            )
        seen[f.name] = f.image_path


def _mask_files(folder: Path, classes: ClassMap) -> dict[str, Path]:
    """stem -> mask path for the PNGs in ``folder`` (hidden files and other files ignored) and
    for the masks inside a CVAT "Segmentation mask 1.1" zip or a COCO instances JSON there
    (``capture.archives``: paths below that file)."""
    if not folder.is_dir():
        return {}
    found: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue
        if not p.is_file():
            problem = not_a_file(p) if p.suffix.lower() in (*MASK_EXTENSIONS, *ARCHIVE_SUFFIXES) else None
            if problem:
                raise CaptureError(f"{p}: {problem} (expected a mask)")
            continue
        if p.suffix.lower() in LOSSY_EXTENSIONS:
            raise CaptureError(f"{p}: masks must be PNG (JPEG compression changes class ids at edges)")
        if p.suffix.lower() in ARCHIVE_SUFFIXES:
            masks = archive_masks(p, classes)
        elif p.suffix in MASK_EXTENSIONS:
            masks = {p.stem: p}
        else:
            continue
        for stem, path in masks.items():
            if stem in found:
                raise CaptureError(f"{path}: two masks for frame '{stem}' ({found[stem]} and {path})")
            found[stem] = path
    return found
