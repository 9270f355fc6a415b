"""Mask formats in (ids, palette, RGB via classes.json or labelmap.txt) and out (palette PNG)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from labelsynth.capture import CaptureError, load_capture, read_mask, validate_capture, write_mask
from labelsynth.capture.masks import VOC_BOUNDARY_COLOR, color_table_for
from labelsynth.classes import ClassMap

from .test_capture_support import H, W, make_capture, snapshot

CLASSES = ClassMap.default()


def _ids(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = rng.integers(0, 6, size=(H, W)).astype(np.uint8)
    m[:3, :5] = 255
    return m


def _write_palette(path, indices: np.ndarray, palette: np.ndarray) -> None:
    im = Image.frombytes("P", (indices.shape[1], indices.shape[0]), indices.tobytes())
    im.putpalette(palette.astype(np.uint8).reshape(-1).tolist())
    im.save(path)


def test_single_channel_ids(tmp_path) -> None:
    m = _ids()
    cv2.imwrite(str(tmp_path / "m.png"), m)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_16bit_ids(tmp_path) -> None:
    m = _ids()
    cv2.imwrite(str(tmp_path / "m.png"), m.astype(np.uint16))
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_palette_indices_are_ids(tmp_path) -> None:
    m = _ids()
    rng = np.random.default_rng(1)
    palette = rng.integers(0, 256, size=(256, 3))  # arbitrary colours: indices must win
    _write_palette(tmp_path / "m.png", m, palette)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_palette_voc_style_mapped_by_colour(tmp_path) -> None:
    """VOC/CVAT palette exports: index order is the tool's, colours are the classes'."""
    indices = np.zeros((H, W), np.uint8)
    indices[:, 10:20] = 1
    indices[:, 20:] = 2
    indices[0, :] = 255
    palette = np.zeros((256, 3), np.uint8)
    palette[1] = CLASSES.classes[3].color  # necrotic (id 3) at index 1
    palette[2] = CLASSES.classes[1].color  # granulation (id 1) at index 2
    palette[255] = VOC_BOUNDARY_COLOR
    _write_palette(tmp_path / "m.png", indices, palette)
    out = read_mask(tmp_path / "m.png", (W, H), CLASSES)
    expected = np.choose(np.minimum(indices, 3), [0, 3, 1, 0]).astype(np.uint8)
    expected[indices == 255] = 255
    np.testing.assert_array_equal(out, expected)


def test_write_mask_roundtrip(tmp_path) -> None:
    m = _ids(3)
    write_mask(tmp_path / "out" / "m.png", m, CLASSES)
    with Image.open(tmp_path / "out" / "m.png") as im:
        assert im.mode == "P"
        assert im.getpalette()[3:6] == list(CLASSES.classes[1].color)
        np.testing.assert_array_equal(np.asarray(im), m)
    np.testing.assert_array_equal(read_mask(tmp_path / "out" / "m.png", (W, H), CLASSES), m)


def test_write_mask_duplicate_colours_keep_ids(tmp_path) -> None:
    classes = ClassMap.from_json(_classes_json(tmp_path, [[0, 0, 0], [9, 9, 9], [9, 9, 9]]))
    m = np.tile(np.array([0, 1, 2], np.uint8), (H, W // 3 + 1))[:, :W]
    write_mask(tmp_path / "m.png", m, classes)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), classes), m)


def _classes_json(tmp_path, colors) -> str:
    path = tmp_path / "classes.json"
    path.write_text(json.dumps({"classes": [
        {"id": i, "name": ["background", "wound", "scar"][i], "color": c} for i, c in enumerate(colors)]}))
    return str(path)


def test_rgb_via_class_colours_with_boundary(tmp_path) -> None:
    m = _ids(4)
    rgb = CLASSES.colorize(m)
    rgb[m == 255] = VOC_BOUNDARY_COLOR
    cv2.imwrite(str(tmp_path / "m.png"), rgb[:, :, ::-1])
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_rgba_transparent_is_ignore(tmp_path) -> None:
    m = _ids(5)
    rgba = np.concatenate([CLASSES.colorize(np.where(m == 255, 0, m)), np.full((H, W, 1), 255, np.uint8)], 2)
    rgba[m == 255, :] = (17, 99, 3, 0)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "m.png")
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_grey_rgb_ids(tmp_path) -> None:
    m = _ids(6)
    cv2.imwrite(str(tmp_path / "m.png"), np.repeat(m[:, :, None], 3, 2))
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png", (W, H), CLASSES), m)


def test_rgb_via_labelmap_in_capture(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    (root / "labelmap.txt").write_text(
        "# label:color_rgb:parts:actions\n"
        "background:0,0,0::\n"
        "Granulation:10,200,10::\n"
        "SLOUGH:250,250,0::\n"
        "pen marker:1,2,3::\n"  # not a class: skipped with a warning
    )
    m = np.zeros((H, W), np.uint8)
    m[5:, :10] = 1
    m[5:, 10:] = 2
    m[0, 0] = 255
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[m == 1] = (10, 200, 10)
    rgb[m == 2] = (250, 250, 0)
    rgb[m == 255] = VOC_BOUNDARY_COLOR
    (root / "annotations").mkdir()
    cv2.imwrite(str(root / "annotations" / "frame_001.PNG"), rgb[:, :, ::-1])
    before = snapshot(root)
    with pytest.warns(UserWarning, match="pen marker"):
        cap = load_capture(root)
    assert snapshot(root) == before
    assert cap.has_annotations and not cap.has_predictions
    assert cap.frames[0].annotation_path is None
    assert cap.load_annotation(0) is None
    np.testing.assert_array_equal(cap.load_annotation(1), m)
    validate_capture(cap)


def test_predictions_folder(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=3)
    (root / "predictions").mkdir()
    for i in range(3):
        cv2.imwrite(str(root / "predictions" / f"frame_{i:03d}.png"), _ids(i))
    (root / "predictions" / ".DS_Store").write_bytes(b"junk")
    cap = load_capture(root)
    assert cap.has_predictions and not cap.has_annotations
    np.testing.assert_array_equal(cap.load_prediction(2), _ids(2))


def test_color_table_labelmap_overrides_class_colours(tmp_path) -> None:
    (tmp_path / "labelmap.txt").write_text("necrotic:200,40,40::\n")
    table = color_table_for(CLASSES, tmp_path / "labelmap.txt")
    assert table[(200, 40, 40)] == 3 and table[VOC_BOUNDARY_COLOR] == 255


# --- broken masks: one-line errors naming the file ---------------------------------------------
def _assert_one_line_naming(err, path) -> None:
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg


def test_unknown_id(tmp_path) -> None:
    m = _ids()
    m[4, 4] = 9
    m[5, 5] = 9
    cv2.imwrite(str(tmp_path / "m.png"), m)
    with pytest.raises(CaptureError, match=r"2 pixels .*\(9\)") as err:
        read_mask(tmp_path / "m.png", (W, H), CLASSES)
    _assert_one_line_naming(err, tmp_path / "m.png")


def test_unknown_colour(tmp_path) -> None:
    rgb = CLASSES.colorize(_ids())
    rgb[2:4, 2:5] = (1, 2, 3)
    cv2.imwrite(str(tmp_path / "m.png"), rgb[:, :, ::-1])
    with pytest.raises(CaptureError, match=r"6 pixels .*\(1,2,3\)") as err:
        read_mask(tmp_path / "m.png", (W, H), CLASSES)
    _assert_one_line_naming(err, tmp_path / "m.png")


def test_wrong_size(tmp_path) -> None:
    cv2.imwrite(str(tmp_path / "m.png"), np.zeros((H, W + 1), np.uint8))
    with pytest.raises(CaptureError, match="33x24.*32x24") as err:
        read_mask(tmp_path / "m.png", (W, H), CLASSES)
    _assert_one_line_naming(err, tmp_path / "m.png")


def test_unreadable(tmp_path) -> None:
    (tmp_path / "m.png").write_bytes(b"not a png at all")
    with pytest.raises(CaptureError) as err:
        read_mask(tmp_path / "m.png", (W, H), CLASSES)
    _assert_one_line_naming(err, tmp_path / "m.png")


def test_validate_capture_catches_wrong_size(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=3)
    (root / "annotations").mkdir()
    cv2.imwrite(str(root / "annotations" / "frame_000.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(root / "annotations" / "frame_002.png"), np.zeros((H // 2, W // 2), np.uint8))
    cap = load_capture(root)  # lazy: loading does not decode masks
    with pytest.raises(CaptureError, match="frame_002.png.*16x12") as err:
        validate_capture(cap)
    _assert_one_line_naming(err, root / "annotations" / "frame_002.png")
    with pytest.raises(CaptureError, match="frame_002.png"):
        cap.load_annotation(2)


def test_mask_without_frame(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    (root / "predictions").mkdir()
    cv2.imwrite(str(root / "predictions" / "frame_099.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(CaptureError, match="frame_099") as err:
        load_capture(root)
    _assert_one_line_naming(err, root / "predictions" / "frame_099.png")


def test_jpeg_mask_rejected(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    (root / "annotations").mkdir()
    cv2.imwrite(str(root / "annotations" / "frame_000.jpg"), np.zeros((H, W), np.uint8))
    with pytest.raises(CaptureError, match="PNG"):
        load_capture(root)


def test_mask_of_skipped_frame_is_dropped(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=3)
    (root / "annotations").mkdir()
    cv2.imwrite(str(root / "annotations" / "frame_001.png"), np.zeros((H, W), np.uint8))
    (root / "images" / "frame_001.png").unlink()
    with pytest.warns(UserWarning, match="1 frame"):
        cap = load_capture(root)
    assert cap.names == ["frame_000", "frame_002"] and not cap.has_annotations
