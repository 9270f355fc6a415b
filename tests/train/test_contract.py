"""The segmenter contract: a model sees the same pixels in training and in `segment`."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from labelsynth.classes import ClassMap
from labelsynth.errors import LabelsynthError
from labelsynth.export import write_labels_h5
from labelsynth.train.contract import model_input, normalize, parse_input_size, resize_image
from labelsynth.train.data import FrameDataset, TrainError, load_sources, split_by_capture
from labelsynth.train.loop import TrainConfig, _frame_size

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")


class Tiny(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 6, 1)

    def forward(self, pixel_values):
        return self.conv(pixel_values)


def test_a_model_sees_the_same_pixels_in_training_and_in_segment(tmp_path):
    """Frames of 64x48 trained at 40x30 (a shrink by a non-integer factor, where area averaging and
    bilinear give other pixels): the training item's image is exactly what `segment` feeds."""
    from labelsynth.train.export_onnx import export_onnx
    from labelsynth.train.segment import OnnxSegmenter

    classes = ClassMap.default()
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (3, 48, 64, 3), dtype=np.uint8)
    masks = rng.integers(0, 6, (3, 48, 64), dtype=np.uint8)
    h5 = write_labels_h5(tmp_path / "labels.h5", images=images, masks=masks, classes=classes,
                         frame_names=[f"f{i}.png" for i in range(3)])
    cfg = TrainConfig(input_size="40x30")
    loaded, classes = load_sources([h5])
    split = split_by_capture(loaded)
    frames = split.train + split.val
    trained = FrameDataset(frames, classes, size=cfg.resize_to())  # train's items, without augmentation
    export_onnx(Tiny(), tmp_path / "model.onnx", classes, _frame_size(split, cfg))
    seg = OnnxSegmenter(tmp_path / "model.onnx", device="cpu")
    assert seg.input_size == (40, 30)  # from the model's metadata, as `segment` runs it
    for k, fr in enumerate(frames):
        image = images[fr.index]
        seen_in_training = trained[k]["image"].numpy()
        seen_in_segment = seg.preprocess(image)
        assert seen_in_training.shape == seen_in_segment.shape == (3, 30, 40)
        np.testing.assert_array_equal(seen_in_training, seen_in_segment)
        bilinear = normalize(cv2.resize(image, (40, 30), interpolation=cv2.INTER_LINEAR))
        assert np.abs(bilinear - seen_in_segment).max() > 0.1  # the other rule would show other pixels


def test_resize_rule_and_normalisation():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    assert resize_image(image, None) is image and resize_image(image, (40, 30)) is image
    np.testing.assert_array_equal(resize_image(image, (20, 15)), cv2.resize(image, (20, 15), interpolation=cv2.INTER_AREA))
    np.testing.assert_array_equal(resize_image(image, (80, 60)), cv2.resize(image, (80, 60), interpolation=cv2.INTER_LINEAR))
    x = model_input(image, None)
    assert x.shape == (3, 30, 40) and x.dtype == np.float32
    np.testing.assert_allclose(x[:, 3, 5], (image[3, 5] / 255.0 - [0.485, 0.456, 0.406]) / [0.229, 0.224, 0.225],
                               rtol=1e-5)


def test_input_size_parsing():
    assert parse_input_size("512x384") == (512, 384)
    assert parse_input_size("256") == (256, 256)
    assert parse_input_size((32, 24)) == (32, 24)
    assert parse_input_size(None) is None
    for bad in ("axb", "0x10", "1x2x3", "32by24", "", "99999x10"):
        with pytest.raises(LabelsynthError, match="--input-size"):
            parse_input_size(bad)
    with pytest.raises(TrainError, match="at least 16"):
        parse_input_size("8x8", error=TrainError, minimum=16)
