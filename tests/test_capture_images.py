"""read_image: bit depths and channel layouts become (H,W,3) uint8 RGB; sizes are checked."""

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
