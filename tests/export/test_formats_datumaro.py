"""Datumaro (CVAT's own dataset library) imports every export and finds exactly labelsynth's masks.

CVAT imports a "Segmentation mask 1.1" zip by unpacking it and reading it with Datumaro's VOC
reader (cvat/apps/dataset_manager/formats/mask.py), so Datumaro reading the unpacked cvat zip
is what CVAT sees. Datumaro is a dev dependency (pyproject), so these tests run wherever the
suite runs.
"""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from labelsynth.classes import IGNORE_ID

from .test_formats import CM, expected, export

import datumaro as dm  # noqa: E402  (a dev dependency: these tests run wherever the suite runs)
from datumaro.components.annotation import AnnotationType  # noqa: E402
from datumaro.components.dataset import Dataset  # noqa: E402
from datumaro.components.environment import Environment  # noqa: E402
from datumaro.util.mask_tools import load_mask  # noqa: E402


def _ids_from_masks(item, label_names: list[str], h: int, w: int) -> np.ndarray:
    """Class ids from an item's mask annotations (label names matched to the class table);
    pixels that no annotation covers stay 254 (not a class id)."""
    ids = np.full((h, w), 254, np.uint8)
    for ann in item.annotations:
        if ann.type != AnnotationType.mask:
            continue
        region = ann.image.astype(bool)
        assert (ids[region] == 254).all(), f"{item.id}: masks overlap"
        name = "background" if ann.label is None else label_names[ann.label]
        ids[region] = CM.ids[CM.names.index(name)]
    return ids


def _check_masks(dataset, frames, item_id=lambda name: name, uncovered=(0, IGNORE_ID)) -> None:
    """Every class a frame has is its own mask annotation, exactly; what no annotation covers
    is background or ignore (VOC and Cityscapes make no shape of either)."""
    names = [label.name for label in dataset.categories()[AnnotationType.label].items]
    items = {item.id: item for item in dataset}
    assert sorted(items) == sorted(item_id(f.name) for f in frames)
    for frame in frames:
        want = expected(frame)
        got = _ids_from_masks(items[item_id(frame.name)], names, *want.shape)
        covered = got != 254
        np.testing.assert_array_equal(got[covered], want[covered])
        assert np.isin(want[~covered], uncovered).all()


def test_datumaro_reads_the_cvat_zip_as_cvat_does(tmp_path) -> None:
    to, frames, _ = export(tmp_path, "cvat")
    unpacked = tmp_path / "unpacked"
    with zipfile.ZipFile(to) as zf:
        zf.extractall(unpacked)
    assert "voc_segmentation" in Environment().detect_dataset(str(unpacked))
    dataset = Dataset.import_from(str(unpacked), "voc_segmentation")
    _check_masks(dataset, frames)
    # the class masks, decoded with the labelmap's colours by Datumaro's own reader: ignore included
    names = [label.name for label in dataset.categories()[AnnotationType.label].items]
    inverse = dataset.categories()[AnnotationType.mask].inverse_colormap
    lut = np.array([IGNORE_ID if n == "ignored" else CM.ids[CM.names.index(n)] for n in names], np.uint8)
    for frame in frames:
        index = load_mask(str(unpacked / "SegmentationClass" / f"{frame.name}.png"), inverse)
        np.testing.assert_array_equal(lut[index], expected(frame))


def test_datumaro_reads_the_voc_folder(tmp_path) -> None:
    to, frames, _ = export(tmp_path, "voc")
    dataset = Dataset.import_from(str(to), "voc_instance_segmentation")
    _check_masks(dataset, frames)
    for item in dataset:
        assert item.media.data.shape == (*expected(frames[0]).shape, 3)


def test_datumaro_reads_the_coco_file(tmp_path) -> None:
    """Background is an annotated category (id 0, which Datumaro reads as no label), so what no
    annotation covers is exactly the ignore."""
    to, frames, _ = export(tmp_path, "coco")
    dataset = Dataset.import_from(str(to / "annotations" / "instances.json"), "coco_instances")
    _check_masks(dataset, frames, uncovered=(IGNORE_ID,))
    for frame, item in zip(frames, sorted(dataset, key=lambda i: i.id)):
        scores = {a.label: a.attributes["score"] for a in item.annotations if a.type == AnnotationType.mask}
        assert all(0.0 <= s <= 1.0 for s in scores.values()) and len(scores) >= 3
        np.testing.assert_array_equal(item.media.data[:, :, ::-1], frame.image)  # Datumaro's images are BGR


def test_datumaro_reads_the_cityscapes_folder(tmp_path) -> None:
    to, frames, _ = export(tmp_path, "cityscapes")
    assert "cityscapes" in Environment().detect_dataset(str(to))
    dataset = Dataset.import_from(str(to), "cityscapes")
    assert [label.name for label in dataset.categories()[AnnotationType.label].items] == CM.names
    _check_masks(dataset, frames, item_id=lambda name: f"wound/{name}")
