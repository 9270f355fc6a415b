"""A capture's annotations/ may be a CVAT "Segmentation mask 1.1" zip or a COCO instances JSON,
read in place (nothing extracted or written), labels matched to the class table by name."""

from __future__ import annotations

import io
import json
import zipfile

import cv2
import numpy as np
import pytest

from labelsynth.capture import CaptureError, check_capture, load_capture, validate_capture
from labelsynth.classes import IGNORE_ID, ClassMap
from labelsynth.errors import ClassMapError

from .test_capture_support import H, W, capture_with_annotations, snapshot

CM = ClassMap.default()
# a CVAT task's labels: its own order and colours, background first as CVAT writes it
CVAT_LABELS = [("background", (0, 0, 0)), ("slough", (10, 20, 30)), ("granulation", (250, 50, 83)),
               ("necrotic", (51, 221, 255))]


def _cvat_mask(rng) -> np.ndarray:
    ids = np.zeros((H, W), np.uint8)
    ids[2:12, 3:20] = 1
    ids[10:20, 15:30] = 2
    ids[rng.random((H, W)) < 0.05] = 3
    return ids


def cvat_zip(masks: dict[str, np.ndarray], labels=CVAT_LABELS, listed=("frame_000", "frame_001", "frame_002", "frame_003"),
             prefix: str = "") -> bytes:
    """A zip as CVAT's exporter writes one: RGB colour masks for the annotated frames only."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(prefix + "labelmap.txt", "# label:color_rgb:parts:actions\n"
                    + "".join(f"{n}:{','.join(map(str, c))}::\n" for n, c in labels))
        zf.writestr(prefix + "ImageSets/Segmentation/default.txt", "".join(f"{n}\n" for n in listed))
        colours = np.array([c for _, c in labels], np.uint8)
        for name, label_index in masks.items():
            ok, png = cv2.imencode(".png", colours[label_index][:, :, ::-1])  # cv2 writes BGR
            zf.writestr(f"{prefix}SegmentationClass/{name}.png", png.tobytes())
            ok, png = cv2.imencode(".png", (label_index > 0).astype(np.uint8) * 128)
            zf.writestr(f"{prefix}SegmentationObject/{name}.png", png.tobytes())
    return buf.getvalue()


def _capture(tmp_path, files: dict[str, bytes]):
    return capture_with_annotations(tmp_path / "cap", files)


def test_cvat_zip_is_read_by_label_name(tmp_path) -> None:
    rng = np.random.default_rng(0)
    masks = {"frame_001": _cvat_mask(rng), "frame_003": _cvat_mask(rng)}
    root = _capture(tmp_path, {"task_12_segmentation mask 1.1.zip": cvat_zip(masks, prefix="")})
    before = snapshot(root)
    capture = load_capture(root)
    assert [f.name for f in capture.frames if f.annotation_path is not None] == ["frame_001", "frame_003"]
    to_id = np.array([CM.ids[CM.names.index(n)] for n, _ in CVAT_LABELS], np.uint8)
    for i in (1, 3):
        np.testing.assert_array_equal(capture.load_annotation(i), to_id[masks[capture.frames[i].name]])
    validate_capture(capture)
    report = check_capture(capture)
    assert report.ok and report.cached_masks == 2
    assert snapshot(root) == before


def test_cvat_zip_with_a_top_folder(tmp_path) -> None:
    masks = {"frame_000": _cvat_mask(np.random.default_rng(1))}
    capture = load_capture(_capture(tmp_path, {"t.zip": cvat_zip(masks, prefix="export/")}))
    assert capture.frames[0].annotation_path.name == "frame_000.png"
    assert capture.load_annotation(0).shape == (H, W)


def test_unknown_label_names_are_one_line_listing_them(tmp_path) -> None:
    labels = [*CVAT_LABELS, ("fibrin", (1, 2, 3)), ("Tendon", (4, 5, 6))]
    root = _capture(tmp_path, {"t.zip": cvat_zip({"frame_000": _cvat_mask(np.random.default_rng(2))}, labels)})
    with pytest.raises(ClassMapError, match=r"t\.zip/labelmap\.txt: label\(s\) not in the class table: fibrin, Tendon") as exc:
        load_capture(root)
    assert "\n" not in str(exc.value)


def test_a_mask_of_the_wrong_size_names_the_file_inside_the_zip(tmp_path) -> None:
    small = np.zeros((H - 2, W), np.uint8)
    capture = load_capture(_capture(tmp_path, {"t.zip": cvat_zip({"frame_002": small})}))
    with pytest.raises(CaptureError, match=rf"t\.zip/SegmentationClass/frame_002\.png: mask is {W}x{H - 2}"):
        validate_capture(capture)
    report = check_capture(capture)
    assert len(report.problems) == 1 and "t.zip/SegmentationClass/frame_002.png" in report.problems[0]


def test_a_zip_that_is_not_a_cvat_export(tmp_path) -> None:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("notes.txt", "hello")
    with pytest.raises(CaptureError, match="not a CVAT 'Segmentation mask 1.1' export"):
        load_capture(_capture(tmp_path, {"notes.zip": buf.getvalue()}))


def test_a_frame_with_two_masks_is_an_error(tmp_path) -> None:
    ok, png = cv2.imencode(".png", np.zeros((H, W), np.uint8))
    root = _capture(tmp_path, {"t.zip": cvat_zip({"frame_000": np.zeros((H, W), np.uint8)}), "frame_000.png": png.tobytes()})
    with pytest.raises(CaptureError, match="two masks for frame 'frame_000'"):
        load_capture(root)


def coco_doc() -> dict:
    """A COCO file as CVAT exports one: categories from 1, no background, a polygon and an RLE."""
    from pycocotools import mask as mask_utils

    region = np.zeros((H, W), np.uint8)
    region[12:20, 20:30] = 1
    rle = mask_utils.encode(np.asfortranarray(region))
    return {
        "images": [{"id": 5, "file_name": "frame_002.jpg", "width": W, "height": H},
                   {"id": 6, "file_name": "frame_003.jpg", "width": W, "height": H}],
        "categories": [{"id": 1, "name": "Necrotic"}, {"id": 2, "name": "granulation"}],
        "annotations": [
            {"id": 1, "image_id": 5, "category_id": 2, "iscrowd": 0, "segmentation": [[2, 2, 12, 2, 12, 10, 2, 10]]},
            {"id": 2, "image_id": 5, "category_id": 1, "iscrowd": 1,
             "segmentation": {"size": [H, W], "counts": rle["counts"].decode()}},
        ],
    }


def test_coco_json_is_read_with_pycocotools(tmp_path) -> None:
    from pycocotools.coco import COCO

    doc = coco_doc()
    root = _capture(tmp_path, {"instances_default.json": json.dumps(doc).encode()})
    before = snapshot(root)
    capture = load_capture(root)
    assert [f.name for f in capture.frames if f.annotation_path is not None] == ["frame_002"]  # 003 has none
    coco = COCO()
    coco.dataset = doc
    coco.createIndex()
    want = np.zeros((H, W), np.uint8)  # no background category: what no annotation covers is background
    want[coco.annToMask(coco.anns[1]).astype(bool)] = 1
    want[coco.annToMask(coco.anns[2]).astype(bool)] = 3
    assert (want == 1).sum() > 20 and (want == 3).sum() == 80
    np.testing.assert_array_equal(capture.load_annotation(2), want)
    assert check_capture(capture).ok
    assert snapshot(root) == before


def test_coco_that_annotates_background_leaves_the_rest_ignore(tmp_path) -> None:
    doc = coco_doc()
    doc["categories"].append({"id": 0, "name": "background"})
    doc["annotations"].append({"id": 3, "image_id": 5, "category_id": 0, "iscrowd": 0,
                               "segmentation": [[0, 0, 5, 0, 5, 5, 0, 5]]})
    capture = load_capture(_capture(tmp_path, {"c.json": json.dumps(doc).encode()}))
    mask = capture.load_annotation(2)
    assert (mask == 0).sum() > 0 and (mask == IGNORE_ID).sum() > 0 and (mask == 1).sum() > 0


@pytest.mark.parametrize("change, message", [
    (lambda d: d["categories"].append({"id": 9, "name": "tendon"}), "categories not in the class table: tendon"),
    (lambda d: d.pop("images"), "not a COCO instances file"),
    (lambda d: d["annotations"][0].update(image_id=77), "refers to image 77"),
    (lambda d: d["annotations"][0].update(category_id=8), "has category 8"),
])
def test_bad_coco_files_are_one_line(tmp_path, change, message) -> None:
    doc = coco_doc()
    change(doc)
    with pytest.raises(CaptureError, match=message) as exc:
        load_capture(_capture(tmp_path, {"c.json": json.dumps(doc).encode()}))
    assert "\n" not in str(exc.value) and "c.json" in str(exc.value)


def test_coco_image_of_another_size(tmp_path) -> None:
    doc = coco_doc()
    doc["images"][0]["width"] = W + 4
    capture = load_capture(_capture(tmp_path, {"c.json": json.dumps(doc).encode()}))
    with pytest.raises(CaptureError, match=rf"c\.json/frame_002\.jpg: mask is {W + 4}x{H} but its image is {W}x{H}"):
        capture.load_annotation(2)
