"""Masks inside an annotation tool's export, read where they lie: nothing is extracted or written.

A capture's ``annotations/`` (or ``predictions/``) may hold, beside or instead of PNG masks:

- a **CVAT "Segmentation mask 1.1" zip** (what CVAT exports, and ``labelsynth export --format
  cvat`` writes): ``SegmentationClass/<frame>.png`` colour masks, decoded with the zip's own
  ``labelmap.txt`` (its label names matched to the class table by name) or, without one, the
  capture's colours. Every mask in ``SegmentationClass/`` is one annotated frame; frames that
  the zip lists without a mask are not annotated.
- a **COCO instances JSON** (any ``*.json``), decoded with pycocotools: categories matched to
  the class table by name, each image with at least one annotation is an annotated frame, its
  annotations (polygons or RLE) painted in file order (a later one wins where two overlap).
  Pixels that no annotation covers are background, unless the file annotates the background
  class itself (as ``labelsynth export --format coco`` does): then they are ignore (255).

A label name the class table does not know is a one-line ``ClassMapError`` listing them all
(``background`` is id 0; ``ignored``/``ignore``/``void`` mean 255: ``capture.masks.label_ids_by_name``).

Each mask inside such a file is addressed by a path below the file, e.g.
``annotations/task.zip/SegmentationClass/frame_000.png`` or ``annotations/coco.json/frame_000.jpg``
(the image's ``file_name``), so the capture's masks stay paths: ``read_mask``, ``mask_size``,
``mask_exists`` and ``file_stamp`` recognise such paths and come here, and every command
(expand, report, bench, train) reads them the same way. A file's index (its member list,
colours, categories) is parsed once per version of the file (size and modification time).
"""

from __future__ import annotations

import contextlib
import io
import json
import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from ..classes import BACKGROUND_ID, IGNORE_ID, ClassMap
from ..errors import CaptureError, ClassMapError
from .masks import ColorTable, decode_mask_image, label_ids_by_name, labelmap_table, parse_labelmap

ARCHIVE_SUFFIXES: tuple[str, ...] = (".zip", ".json")
CVAT_CLASS_DIR = "SegmentationClass"
CVAT_LABELMAP = "labelmap.txt"


def container_of(path: str | Path) -> tuple[Path, str] | None:
    """(export file, member name) when ``path`` lies inside a zip or JSON export, else None.

    Cheap for ordinary files: only parents whose name ends in .zip or .json are looked at."""
    path = Path(path)
    for parent in path.parents:
        if parent.suffix.lower() in ARCHIVE_SUFFIXES and parent.is_file():
            return parent, path.relative_to(parent).as_posix()
    return None


def archive_masks(path: str | Path, classes: ClassMap) -> dict[str, Path]:
    """Frame name (stem) -> the path of its mask inside the export ``path`` (a .zip or .json).

    The file's labels are matched to ``classes`` here, so an unknown name fails when the
    capture is loaded, before anything trains. Two masks for one frame are an error."""
    index = _index(Path(path))
    index.class_ids(classes)  # unknown label names: one line listing them
    found: dict[str, Path] = {}
    for member in index.members:
        stem = PurePosixPath(member).stem
        if stem in found:
            raise CaptureError(f"{path}: two masks for frame '{stem}' ({found[stem].name} and {member})")
        found[stem] = Path(path) / member
    return found


def member_exists(path: str | Path) -> bool:
    where = container_of(path)
    if where is None:
        return False
    try:
        return where[1] in _index(where[0]).members
    except CaptureError:
        return False


def member_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of a mask inside an export, without decoding its pixels."""
    container, member = _located(path)
    index = _index(container)
    if isinstance(index, _CocoExport):
        image = index.coco.imgs[index.members[member]]
        return int(image["width"]), int(image["height"])
    from PIL import Image

    with _open_zip(container) as zf, Image.open(io.BytesIO(zf.read(index.prefix + member))) as im:
        return int(im.size[0]), int(im.size[1])


def read_member_mask(
    path: str | Path, size: tuple[int, int] | None, classes: ClassMap, color_table: ColorTable | None, kind: str
) -> np.ndarray:
    """A mask inside an export as (H,W) uint8 class ids (``read_mask``'s contract)."""
    from PIL import Image

    path = Path(path)
    if kind != "classes":
        raise CaptureError(f"{path}: masks inside an annotation export are class masks, not {kind!r}")
    container, member = _located(path)
    index = _index(container)
    if isinstance(index, _CocoExport):
        return index.decode(member, path, size, classes)
    own = index.class_ids(classes)
    with _open_zip(container) as zf:
        data = zf.read(index.prefix + member)
    try:
        with Image.open(io.BytesIO(data)) as im:
            return decode_mask_image(im, path, size, classes, own or color_table, kind)
    except CaptureError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise CaptureError(f"{path}: cannot read mask ({exc})") from exc


# --- the two kinds of export ----------------------------------------------------------------
@dataclass
class _CvatExport:
    """A CVAT "Segmentation mask 1.1" zip: its class masks and its own colours."""

    path: Path
    prefix: str  # the folder inside the zip that holds SegmentationClass/ ("" at the top)
    members: dict[str, None]  # "SegmentationClass/<id>.png" (relative to prefix), in zip order
    labelmap: list[tuple[str, tuple[int, int, int]]] | None  # the zip's labelmap.txt, if any

    def class_ids(self, classes: ClassMap) -> ColorTable | None:
        """Colour -> class id from the zip's labelmap (None without one: the capture's colours)."""
        if self.labelmap is None:
            return None
        return labelmap_table(self.labelmap, classes, f"{self.path}/{self.prefix}{CVAT_LABELMAP}", strict=True)


@dataclass
class _CocoExport:
    """A COCO instances file: pycocotools' index of it."""

    path: Path
    coco: Any  # pycocotools.coco.COCO
    members: dict[str, int]  # image file_name -> image id (images with annotations only)

    def class_ids(self, classes: ClassMap) -> dict[int, int]:
        """Category id -> class id, matched by name; unknown names are one ``ClassMapError``."""
        by_name = label_ids_by_name(classes)
        cats = self.coco.cats
        unknown = [str(c["name"]) for c in cats.values() if str(c["name"]).lower() not in by_name]
        if unknown:
            raise ClassMapError(f"{self.path}: categories not in the class table: {', '.join(unknown)} "
                                f"(classes: {', '.join(classes.names)})")
        return {int(i): by_name[str(c["name"]).lower()] for i, c in cats.items()}

    def decode(self, member: str, path: Path, size: tuple[int, int] | None, classes: ClassMap) -> np.ndarray:
        class_of = self.class_ids(classes)
        # Pixels no annotation covers: background, unless the file annotates background itself.
        annotated_background = any(class_of[int(a["category_id"])] == BACKGROUND_ID for a in self.coco.anns.values())
        image_id = self.members[member]
        image = self.coco.imgs[image_id]
        w, h = int(image["width"]), int(image["height"])
        if size is not None and (w, h) != (int(size[0]), int(size[1])):
            raise CaptureError(f"{path}: mask is {w}x{h} but its image is {int(size[0])}x{int(size[1])}")
        mask = np.full((h, w), IGNORE_ID if annotated_background else BACKGROUND_ID, dtype=np.uint8)
        for ann in self.coco.imgToAnns[image_id]:
            try:
                region = self.coco.annToMask(ann).astype(bool)
            except Exception as exc:  # noqa: BLE001 - pycocotools raises many kinds on a bad segmentation
                raise CaptureError(f"{path}: annotation {ann.get('id')} has no readable segmentation "
                                   f"({type(exc).__name__}: {exc})") from exc
            if region.shape != mask.shape:
                raise CaptureError(f"{path}: annotation {ann.get('id')} is {region.shape[1]}x{region.shape[0]} "
                                   f"but its image is {w}x{h}")
            mask[region] = class_of[int(ann["category_id"])]
        return mask


def _located(path: str | Path) -> tuple[Path, str]:
    where = container_of(path)
    if where is None:
        raise CaptureError(f"{path}: not inside a .zip or .json annotation export")
    if where[1] not in _index(where[0]).members:
        raise CaptureError(f"{path}: no such mask in {where[0].name}")
    return where


def _index(path: Path) -> _CvatExport | _CocoExport:
    """The parsed export, cached per version of the file (its modification time and size)."""
    try:
        stat = path.stat()
    except OSError as exc:
        raise CaptureError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    return _parse(path, (stat.st_mtime_ns, stat.st_size))


@lru_cache(maxsize=16)
def _parse(path: Path, stamp: tuple[int, int]) -> _CvatExport | _CocoExport:
    if path.suffix.lower() == ".zip":
        return _parse_cvat(path)
    return _parse_coco(path)


def _open_zip(path: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as exc:
        raise CaptureError(f"{path}: not a readable zip ({exc})") from exc


def _parse_cvat(path: Path) -> _CvatExport:
    with _open_zip(path) as zf:
        names = [n for n in zf.namelist() if not n.endswith("/")]
        prefixes = set()
        for name in names:
            parts = PurePosixPath(name).parts
            if CVAT_CLASS_DIR in parts[:-1] and name.lower().endswith(".png"):
                prefixes.add("/".join(parts[: parts.index(CVAT_CLASS_DIR)]))
        if not prefixes:
            raise CaptureError(f"{path}: not a CVAT 'Segmentation mask 1.1' export (no {CVAT_CLASS_DIR}/*.png inside)")
        if len(prefixes) > 1:
            raise CaptureError(f"{path}: holds more than one {CVAT_CLASS_DIR}/ folder ({', '.join(sorted(prefixes))})")
        prefix = prefixes.pop()
        prefix = f"{prefix}/" if prefix else ""
        members = {n[len(prefix):]: None for n in names
                   if n.startswith(prefix + CVAT_CLASS_DIR + "/") and n.lower().endswith(".png")}
        labelmap = None
        if prefix + CVAT_LABELMAP in names:
            where = f"{path}/{prefix}{CVAT_LABELMAP}"
            try:
                text = zf.read(prefix + CVAT_LABELMAP).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise ClassMapError(f"{where}: not UTF-8 text ({exc})") from exc
            labelmap = parse_labelmap(text, where)
    return _CvatExport(path, prefix, members, labelmap)


def _parse_coco(path: Path) -> _CocoExport:
    from pycocotools.coco import COCO

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(data, dict) or not all(isinstance(data.get(k), list) for k in ("images", "annotations", "categories")):
        raise CaptureError(f"{path}: not a COCO instances file (needs 'images', 'annotations' and 'categories' lists)")
    try:
        category_ids = {int(c["id"]) for c in data["categories"] if str(c["name"])}
        image_ids = {int(im["id"]) for im in data["images"] if (int(im["width"]), int(im["height"]), str(im["file_name"]))}
        ann_ids: set[int] = set()
        for ann in data["annotations"]:
            if int(ann["id"]) in ann_ids:
                raise ValueError(f"two annotations have id {ann['id']}")
            ann_ids.add(int(ann["id"]))
            if int(ann["image_id"]) not in image_ids:
                raise ValueError(f"annotation {ann.get('id')} refers to image {ann['image_id']}, which is not listed")
            if int(ann["category_id"]) not in category_ids:
                raise ValueError(f"annotation {ann.get('id')} has category {ann['category_id']}, which is not listed")
            if not ann.get("segmentation"):
                raise ValueError(f"annotation {ann.get('id')} has no segmentation")
    except (KeyError, TypeError, ValueError) as exc:
        raise CaptureError(f"{path}: not a valid COCO instances file ({exc})") from exc
    coco = COCO()
    coco.dataset = data
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints its progress
        coco.createIndex()
    members = {str(coco.imgs[i]["file_name"]): i for i in sorted(coco.imgs) if coco.imgToAnns.get(i)}
    return _CocoExport(path, coco, members)
