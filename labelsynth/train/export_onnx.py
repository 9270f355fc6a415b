"""model.onnx that ``labelsynth segment`` runs as it is.

Input ``pixel_values`` (N,3,H,W) float RGB with ImageNet mean/std, dynamic N, H and W;
output ``logits`` (N,C,h,w). The ONNX ``metadata_props`` (class table, index -> class id map,
training input size) and the input's preparation are the segmenter contract (``contract``).
"""

from __future__ import annotations

import copy
import io
import warnings
from pathlib import Path

import torch

from ..classes import ClassMap
from ..outdir import atomic_file
from .contract import INPUT_NAME, OUTPUT_NAME, model_metadata


def export_onnx(model: torch.nn.Module, path: str | Path, classes: ClassMap, input_size: tuple[int, int],
                opset: int = 17) -> Path:
    """Write ``path`` through ``path.partial``; ``input_size`` is (W, H)."""
    import onnx

    path = Path(path)
    net = copy.deepcopy(model).to("cpu").eval()
    w, h = input_size
    dummy = torch.zeros(1, 3, h, w)
    buffer = io.BytesIO()  # exported in memory, written by Python: a full disk is an OSError naming the file
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            net, (dummy,), buffer, input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: "batch", 2: "height", 3: "width"},
                          OUTPUT_NAME: {0: "batch", 2: "logits_height", 3: "logits_width"}},
            opset_version=opset, dynamo=False,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    for key, value in model_metadata(classes, input_size).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    with atomic_file(path) as tmp:
        tmp.write_bytes(proto.SerializeToString())
    return path
