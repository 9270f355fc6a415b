"""The segmenter's input contract: the pixels ``labelsynth train`` trains a model on are the
pixels ``labelsynth segment`` feeds it, and model.onnx says what it needs to be run as is.

One module, so training and inference cannot drift apart:

- the input: NCHW float32 RGB named ``pixel_values``, ImageNet mean/std normalised
  (``normalize``), at the size the model was trained at (``input_size``, ``WxH``);
- the one resize (``resize_image``): area averaging when the frame shrinks (each input pixel
  is the mean of the frame pixels it covers, as a camera at that resolution would see it),
  bilinear when a side grows; class-id masks are never resized here (training resizes its
  targets by nearest neighbour, ``segment`` upsamples logits, not labels);
- the ONNX ``metadata_props`` (``model_metadata``): ``labelsynth_classes`` (the class table,
  ``ClassMap.to_json``), ``labelsynth_id_map`` (model output index -> class id, so ``segment``
  needs no ``--id-map``) and ``labelsynth_input_size`` (``WxH``, ``segment``'s default size).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from ..classes import ClassMap
from ..errors import LabelsynthError

INPUT_NAME = "pixel_values"
OUTPUT_NAME = "logits"
META_CLASSES = "labelsynth_classes"
META_ID_MAP = "labelsynth_id_map"
META_INPUT_SIZE = "labelsynth_input_size"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def parse_input_size(text: str | Sequence[int] | None, *, error: type[Exception] = LabelsynthError,
                     minimum: int = 1, maximum: int = 16384) -> tuple[int, int] | None:
    """``"512x384"`` (width x height), ``"512"`` (square) or ``(512, 384)`` -> ``(512, 384)``;
    None stays None. A malformed or empty size, or a side outside ``minimum..maximum``, raises
    ``error`` (one line naming ``--input-size``)."""
    if text is None:
        return None
    try:
        if isinstance(text, str):
            values = [int(p) for p in text.lower().replace(" ", "").split("x")]
        else:
            values = [int(v) for v in text]
    except (TypeError, ValueError):
        raise error(f"--input-size {text!r}: expected WxH, e.g. 320x240") from None
    if len(values) == 1:
        values = values * 2
    if len(values) != 2:
        raise error(f"--input-size {text!r}: expected WxH, e.g. 320x240")
    if min(values) < minimum:
        raise error(f"--input-size {text!r}: both sides must be at least {minimum} pixel{'s' if minimum > 1 else ''}")
    if max(values) > maximum:
        raise error(f"--input-size {text!r}: both sides must be at most {maximum} pixels")
    return values[0], values[1]


def format_input_size(size: tuple[int, int]) -> str:
    """``(W, H)`` -> ``"WxH"`` (the metadata's and train.json's spelling)."""
    return f"{int(size[0])}x{int(size[1])}"


def resize_image(image: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """An (H, W, 3) uint8 RGB frame at ``size`` (W, H): area averaging when neither side grows,
    bilinear otherwise; unchanged (the same array) when it is that size already or ``size`` is None."""
    if size is None:
        return image
    w, h = int(size[0]), int(size[1])
    if image.shape[:2] == (h, w):
        return image
    shrinking = w <= image.shape[1] and h <= image.shape[0]
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def normalize(image: np.ndarray, mean: Sequence[float] = IMAGENET_MEAN,
              std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (3, H, W) float32: ``(pixel / 255 - mean) / std`` per channel."""
    m, s = np.asarray(mean, dtype=np.float32), np.asarray(std, dtype=np.float32)
    x = (image.astype(np.float32) / 255.0 - m) / s
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def model_input(image: np.ndarray, size: tuple[int, int] | None, mean: Sequence[float] = IMAGENET_MEAN,
                std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """What a model sees for one frame: ``normalize(resize_image(image, size))``, (3, h, w) float32."""
    return normalize(resize_image(image, size), mean, std)


def model_metadata(classes: ClassMap, input_size: tuple[int, int]) -> dict[str, str]:
    """The ONNX ``metadata_props`` of a model trained on ``classes`` at ``input_size`` (W, H)."""
    return {
        META_CLASSES: json.dumps(classes.to_json(), sort_keys=True),
        META_ID_MAP: json.dumps({str(i): int(c) for i, c in enumerate(classes.ids)}),
        META_INPUT_SIZE: format_input_size(input_size),
    }


def metadata_id_map(metadata: Mapping[str, str]) -> dict[int, int] | None:
    """The index -> class id map of a model's metadata (None when it has none); ValueError if
    the entry is not such a map."""
    text = metadata.get(META_ID_MAP)
    if not text:
        return None
    try:
        return {int(k): int(v) for k, v in json.loads(text).items()}
    except (ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"metadata {META_ID_MAP!r} is not an index -> id map ({exc})") from None
