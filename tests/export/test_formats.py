"""Exports for annotation tools and trainers (CVAT, VOC, COCO, Cityscapes): each read back exactly,
by labelsynth's capture loader and by readers nobody here wrote (pycocotools; Datumaro, CVAT's
own dataset library, in ``test_formats_datumaro.py``)."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
from PIL import Image

from labelsynth.capture import load_capture
from labelsynth.capture.masks import VOC_BOUNDARY_COLOR, parse_labelmap
from labelsynth.classes import IGNORE_ID, ClassInfo, ClassMap
from labelsynth.export import ExportError
from labelsynth.export.formats import ExportFrame, choose_frames, export_frames
from labelsynth.export.formats.voc import voc_colormap

from ..capture.test_capture_support import H, W, capture_with_annotations, snapshot

CM = ClassMap.default()
C = 0.3  # --min-confidence of the tests


def tiny_frames(n: int = 3, seed: int = 0) -> list[ExportFrame]:
    """Frames of the capture tests' size: blobs of every class, a random confidence."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        mask = np.zeros((H, W), np.uint8)
        mask[3:20, 4:28] = 1 + i % 5
        mask[8:14, 10:30] = 3
        mask[0:4, 0:6] = 5
        mask[20:, 28:] = 2
        conf = rng.uniform(0.0, 1.0, size=(H, W)).astype(np.float32)
        image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        frames.append(ExportFrame(f"frame_{i:03d}", mask, image, conf, annotated=i == 0))
    return frames


def expected(frame: ExportFrame, min_confidence: float | None = C) -> np.ndarray:
    m = frame.mask.copy()
    if min_confidence is not None:
        m[frame.confidence < min_confidence] = IGNORE_ID
    return m


def export(tmp_path, fmt: str, frames=None, **kw):
    frames = tiny_frames() if frames is None else frames
    to = tmp_path / ("export.zip" if fmt == "cvat" else f"export_{fmt}")
    kw.setdefault("min_confidence", C)
    result = export_frames(frames, CM, to, fmt=fmt, flagged=["frame_001"], source="OUT", name="wound", **kw)
    return to, frames, result


def capture_with(tmp_path, annotations: dict[str, bytes]):
    """A 4-frame capture (frame_000..003) whose annotations/ holds the given files."""
    return capture_with_annotations(tmp_path / "cap", annotations)


# --- the capture loader reads the cvat zip, the voc masks and the COCO file back exactly -----------
@pytest.mark.parametrize("fmt", ["cvat", "coco", "voc"])
def test_capture_loader_reads_the_export_back(tmp_path, fmt) -> None:
    to, frames, result = export(tmp_path, fmt)
    assert result.frames == [f.name for f in frames]
    assert result.ignored_pixels == sum(int((f.confidence < C).sum()) for f in frames) > 0
    if fmt == "cvat":
        root = capture_with(tmp_path, {"review.zip": to.read_bytes()})
    elif fmt == "coco":
        root = capture_with(tmp_path, {"instances.json": (to / "annotations" / "instances.json").read_bytes()})
    else:  # a VOC folder's class masks, copied in as they are
        root = capture_with(tmp_path, {p.name: p.read_bytes() for p in (to / "SegmentationClass").iterdir()})
    before = snapshot(root)
    capture = load_capture(root)
    assert [f.name for f in capture.frames if f.annotation_path is not None] == [f.name for f in frames]
    for i, frame in enumerate(frames):
        np.testing.assert_array_equal(capture.load_annotation(i), expected(frame))
    assert capture.load_annotation(3) is None
    assert snapshot(root) == before  # read in place: nothing extracted, nothing written


def test_cityscapes_label_ids_are_the_masks(tmp_path) -> None:
    to, frames, _ = export(tmp_path, "cityscapes")
    gt = to / "gtFine" / "train" / "wound"
    for frame in frames:
        for suffix in ("labelIds", "labelTrainIds"):
            with Image.open(gt / f"{frame.name}_gtFine_{suffix}.png") as im:
                assert im.mode == "L"
                np.testing.assert_array_equal(np.asarray(im), expected(frame))
        with Image.open(to / "leftImg8bit" / "train" / "wound" / f"{frame.name}_leftImg8bit.png") as im:
            np.testing.assert_array_equal(np.asarray(im.convert("RGB")), frame.image)
        with Image.open(gt / f"{frame.name}_gtFine_color.png") as im:
            np.testing.assert_array_equal(np.asarray(im), CM.colorize(expected(frame)))
    lines = (to / "label_colors.txt").read_text().splitlines()
    assert lines[3] == "40 30 30 necrotic" and len(lines) == 6


def test_pycocotools_decodes_the_coco_rle(tmp_path) -> None:
    from pycocotools.coco import COCO

    to, frames, _ = export(tmp_path, "coco")
    coco = COCO(str(to / "annotations" / "instances.json"))
    assert {c["id"]: c["name"] for c in coco.loadCats(coco.getCatIds())} == {c.id: c.name for c in CM.classes}
    assert coco.dataset["info"]["flagged_frames"] == ["frame_001"]
    assert coco.dataset["info"]["min_confidence"] == C
    by_name = {im["file_name"]: im for im in coco.loadImgs(coco.getImgIds())}
    for frame in frames:
        image = by_name[f"{frame.name}.png"]
        assert (image["width"], image["height"]) == (W, H)
        ids = np.full((H, W), IGNORE_ID, np.uint8)  # what no annotation covers is ignore
        anns = coco.loadAnns(coco.getAnnIds(imgIds=image["id"]))
        assert len(anns) == len({a["category_id"] for a in anns})  # one annotation per class region
        for ann in anns:
            region = coco.annToMask(ann).astype(bool)
            assert not (ids[region] != IGNORE_ID).any()  # regions do not overlap
            ids[region] = ann["category_id"]
            assert ann["area"] == region.sum() and ann["iscrowd"] == 0
            assert ann["score"] == pytest.approx(frame.confidence[region].mean(), abs=1e-4)
            x, y, w, h = ann["bbox"]
            ys, xs = np.nonzero(region)
            assert (x, y, x + w, y + h) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
        np.testing.assert_array_equal(ids, expected(frame))
        with Image.open(to / "images" / image["file_name"]) as im:
            np.testing.assert_array_equal(np.asarray(im.convert("RGB")), frame.image)


# --- the CVAT zip against CVAT's documented "Segmentation mask 1.1" layout ------------------------
def test_cvat_zip_has_cvats_documented_layout(tmp_path) -> None:
    """docs.cvat.ai, Segmentation Mask: labelmap.txt (label:r,g,b:parts:actions, background
    black), ImageSets/Segmentation/<subset>.txt (names without extension), SegmentationClass/
    and SegmentationObject/ PNGs of one or three channels whose colours are the labelmap's."""
    to, frames, _ = export(tmp_path, "cvat")
    with zipfile.ZipFile(to) as zf:
        names = set(zf.namelist())
        stems = [f.name for f in frames]
        assert {"labelmap.txt", "ImageSets/Segmentation/default.txt"} <= names
        assert {f"SegmentationClass/{s}.png" for s in stems} | {f"SegmentationObject/{s}.png" for s in stems} <= names
        assert zf.read("ImageSets/Segmentation/default.txt").decode().split() == stems
        text = zf.read("labelmap.txt").decode()
        lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
        assert all(len(ln.split(":")) == 4 for ln in lines)  # name:color:parts:actions
        labelmap = dict(parse_labelmap(text, "labelmap.txt"))
        assert labelmap["background"] == (0, 0, 0)
        assert {n: labelmap[n] for n in CM.names} == {c.name: c.color for c in CM.classes}
        assert labelmap["ignored"] == VOC_BOUNDARY_COLOR  # declared: the export has ignore pixels
        colours = {rgb: name for name, rgb in labelmap.items()}
        inst_colours = {tuple(c) for c in voc_colormap()[: len(CM.classes)]}
        for frame in frames:
            with Image.open(zf.open(f"SegmentationClass/{frame.name}.png")) as im:
                rgb = np.asarray(im.convert("RGB"))
            used = {tuple(int(v) for v in px) for px in np.unique(rgb.reshape(-1, 3), axis=0)}
            assert used <= set(colours)
            want = expected(frame)
            for name, colour in labelmap.items():
                class_id = IGNORE_ID if name == "ignored" else CM.ids[CM.names.index(name)]
                np.testing.assert_array_equal((rgb == colour).all(axis=2), want == class_id)
            with Image.open(zf.open(f"SegmentationObject/{frame.name}.png")) as im:
                inst = np.asarray(im.convert("RGB"))
            used = {tuple(int(v) for v in px) for px in np.unique(inst.reshape(-1, 3), axis=0)}
            assert used <= inst_colours
            # background and ignore are no instance (black); each class present is one instance
            np.testing.assert_array_equal((inst == 0).all(axis=2), np.isin(want, [0, IGNORE_ID]))
            present = [c for c in CM.ids if c != 0 and (want == c).any()]
            assert len(used - {(0, 0, 0)}) == len(present)
        assert "frame_001" in zf.read("README.txt").decode().split("review them first")[1]


def test_no_min_confidence_keeps_every_label(tmp_path) -> None:
    to, frames, result = export(tmp_path, "cvat", min_confidence=None)
    assert result.ignored_pixels == 0
    with zipfile.ZipFile(to) as zf:
        assert "ignored" not in dict(parse_labelmap(zf.read("labelmap.txt").decode(), "labelmap.txt"))
    capture = load_capture(capture_with(tmp_path, {"r.zip": to.read_bytes()}))
    np.testing.assert_array_equal(capture.load_annotation(1), frames[1].mask)


def test_frames_without_images_or_confidence(tmp_path) -> None:
    frames = [ExportFrame(f.name, f.mask) for f in tiny_frames(2)]
    to, _, _ = export(tmp_path, "coco", frames=frames)
    doc = json.loads((to / "annotations" / "instances.json").read_text())
    assert "score" not in doc["annotations"][0] and not (to / "images").exists()
    capture = load_capture(capture_with(tmp_path, {"c.json": (to / "annotations" / "instances.json").read_bytes()}))
    np.testing.assert_array_equal(capture.load_annotation(0), frames[0].mask)


# --- choosing frames, refusing what cannot be written, atomicity ---------------------------------
def test_choose_frames() -> None:
    names, annotated = ["a", "b", "c"], [True, False, False]
    assert choose_frames(names, annotated, "all", None) == names
    assert choose_frames(names, annotated, "unannotated", None) == ["b", "c"]
    assert choose_frames(names, annotated, "flagged", ["c", "a"]) == ["a", "c"]
    with pytest.raises(ExportError, match="no consistency report"):
        choose_frames(names, annotated, "flagged", None)
    with pytest.raises(ExportError, match="flagged none"):
        choose_frames(names, annotated, "flagged", [])
    with pytest.raises(ExportError, match="expected one of"):
        choose_frames(names, annotated, "some", None)


def test_refusals_are_one_line(tmp_path) -> None:
    frames = tiny_frames(1)
    with pytest.raises(ExportError, match=r"\.zip file"):
        export_frames(frames, CM, tmp_path / "out", fmt="cvat")
    with pytest.raises(ExportError, match="--format"):
        export_frames(frames, CM, tmp_path / "out", fmt="yolo")
    same = ClassMap(CM.classes[:2] + (ClassInfo(2, "slough", CM.classes[1].color, True),))
    with pytest.raises(ExportError, match="'slough' and 'granulation' share the colour"):
        export_frames(frames[:0], same, tmp_path / "x.zip", fmt="cvat")
    bad = ExportFrame("f", np.full((H, W), 9, np.uint8))
    with pytest.raises(ExportError, match=r"frame 'f': class ids \[9\]"):
        export_frames([bad], CM, tmp_path / "v", fmt="voc")
    with pytest.raises(ExportError, match="no frame to export"):
        export_frames([], CM, tmp_path / "v", fmt="voc")
    to, _, _ = export(tmp_path, "voc")
    with pytest.raises(Exception, match="not empty"):
        export(tmp_path, "voc")
    export(tmp_path, "voc", force=True)
    zipped, _, _ = export(tmp_path, "cvat")
    with pytest.raises(ExportError, match="--force"):
        export(tmp_path, "cvat")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export.zip", "export_voc"]


@pytest.mark.parametrize("fmt", ["cvat", "coco"])
def test_an_interrupted_export_leaves_nothing_that_looks_finished(tmp_path, fmt) -> None:
    def frames():
        yield from tiny_frames(2)
        raise KeyboardInterrupt

    to = tmp_path / ("e.zip" if fmt == "cvat" else "e")
    with pytest.raises(KeyboardInterrupt):
        export_frames(frames(), CM, to, fmt=fmt)
    assert list(tmp_path.iterdir()) == []
    # an earlier export of the same name survives an interrupted replacement
    export_frames(tiny_frames(1), CM, to, fmt=fmt)
    before = to.read_bytes() if to.is_file() else (to / "annotations" / "instances.json").read_bytes()
    with pytest.raises(KeyboardInterrupt):
        export_frames(frames(), CM, to, fmt=fmt, force=True)
    after = to.read_bytes() if to.is_file() else (to / "annotations" / "instances.json").read_bytes()
    assert after == before and sorted(p.name for p in tmp_path.iterdir()) == [to.name]
