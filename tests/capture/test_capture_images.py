"""read_image, list_images, write_mask: bit depths and channel layouts become (H,W,3) uint8 RGB; sizes are checked."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from labelsynth.capture import CaptureError, read_image
from labelsynth.capture.images import image_size


def test_bgr_becomes_rgb(tmp_path) -> None:
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 0] = 200  # blue in OpenCV's order
    cv2.imwrite(str(tmp_path / "a.png"), bgr)
    img = read_image(tmp_path / "a.png", (5, 4))
    assert img.shape == (4, 5, 3) and img.dtype == np.uint8
    assert img[0, 0].tolist() == [0, 0, 200]
    assert image_size(tmp_path / "a.png") == (5, 4)


def test_grayscale_and_16bit(tmp_path) -> None:
    grey = np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000
    cv2.imwrite(str(tmp_path / "g16.png"), grey)
    img = read_image(tmp_path / "g16.png", (5, 4))
    assert img.dtype == np.uint8 and img.shape == (4, 5, 3)
    np.testing.assert_array_equal(img[..., 0], np.round(grey / 257).astype(np.uint8))
    np.testing.assert_array_equal(img[..., 0], img[..., 2])


@pytest.mark.parametrize("white", [True, False])
def test_rgba_composited(tmp_path, white) -> None:
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 2] = 100  # red
    bgra[0, 0, 3] = 0
    bgra[0, 1, 3] = 255
    bgra[1, 0, 3] = 128
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    img = read_image(tmp_path / "a.png", (2, 2), white_background=white)
    bg = 255 if white else 0
    assert img[0, 0].tolist() == [bg, bg, bg]
    assert img[0, 1].tolist() == [100, 0, 0]
    a = 128 / 255
    assert img[1, 0].tolist() == [round(100 * a + bg * (1 - a)), round(bg * (1 - a)), round(bg * (1 - a))]


def test_errors_name_the_file(tmp_path) -> None:
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"a\.png.*5x4.*6x4"):
        read_image(tmp_path / "a.png", (6, 4))
    (tmp_path / "b.jpg").write_bytes(b"garbage")
    with pytest.raises(CaptureError, match=r"b\.jpg"):
        read_image(tmp_path / "b.jpg")
    with pytest.raises(CaptureError, match=r"c\.png"):
        read_image(tmp_path / "c.png")


def test_list_images_one_rule(tmp_path) -> None:
    """The lister every command shares: PNG/JPEG of any suffix case, sorted, hidden files skipped,
    duplicate stems and empty or missing folders are one-line errors naming the path."""
    from labelsynth.capture import list_images

    d = tmp_path / "images"
    d.mkdir()
    for name in ("b.PNG", "a.jpg", "c.jpeg", "._a.png", "notes.txt"):
        (d / name).write_bytes(b"x")
    (d / "sub.png").mkdir()
    assert [p.name for p in list_images(d)] == ["a.jpg", "b.PNG", "c.jpeg"]
    (d / "a.png").write_bytes(b"x")
    with pytest.raises(CaptureError, match=r"a\.png: same stem as a\.jpg"):
        list_images(d)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CaptureError, match="empty: no PNG or JPEG images"):
        list_images(empty)
    with pytest.raises(CaptureError, match="nowhere: images folder not found"):
        list_images(tmp_path / "nowhere")


def test_capture_white_background_follows_the_loader(tmp_path) -> None:
    """segment composites RGBA frames on the background load_capture would choose."""
    import json

    from labelsynth.capture.load import capture_white_background

    assert capture_white_background(tmp_path) is False  # no poses yet: black
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert capture_white_background(tmp_path) is True  # Blender style
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "white_background": False}))
    assert capture_white_background(tmp_path) is False
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 50, "frames": []}))
    assert capture_white_background(tmp_path) is False


def test_write_mask_grey_and_palette(tmp_path) -> None:
    """One mask writer: greyscale ids (outputs) read back the same by OpenCV, PIL and read_mask;
    the palette variant reads back as ids through read_mask."""
    from PIL import Image

    from labelsynth.capture import read_mask, write_mask
    from labelsynth.classes import ClassMap

    classes = ClassMap.default()
    m = np.zeros((6, 7), np.uint8)
    m[1:3, 2:5] = 2
    m[5, :] = 255
    grey = write_mask(tmp_path / "sub" / "g.png", m)
    assert grey == tmp_path / "sub" / "g.png"
    np.testing.assert_array_equal(cv2.imread(str(grey), cv2.IMREAD_UNCHANGED), m)
    with Image.open(grey) as im:
        assert im.mode == "L"
    np.testing.assert_array_equal(read_mask(grey, (7, 6), classes), m)
    pal = write_mask(tmp_path / "p.png", m, classes)
    with Image.open(pal) as im:
        assert im.mode == "P"
    np.testing.assert_array_equal(read_mask(pal, (7, 6), classes), m)
    with pytest.raises(ValueError, match="class table"):
        write_mask(tmp_path / "x.png", m, palette=True)
