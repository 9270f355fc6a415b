"""model.onnx that ``labelsynth segment`` runs as it is.

Input ``pixel_values`` (N,3,H,W) float RGB with ImageNet mean/std, dynamic N, H and W;
output ``logits`` (N,C,h,w). The ONNX ``metadata_props`` carry (all JSON or text):

- ``labelsynth_classes``: the class table (``ClassMap.to_json``),
- ``labelsynth_id_map``: model output index -> class id (``segment`` needs no ``--id-map``),
- ``labelsynth_input_size``: ``WxH`` the model was trained at (``segment``'s default size).
"""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path

import torch

from ..classes import ClassMap
from ..outdir import atomic_file

META_CLASSES = "labelsynth_classes"
META_ID_MAP = "labelsynth_id_map"
META_INPUT_SIZE = "labelsynth_input_size"


def export_onnx(model: torch.nn.Module, path: str | Path, classes: ClassMap, input_size: tuple[int, int],
                opset: int = 17) -> Path:
    """Write ``path`` through ``path.partial``; ``input_size`` is (W, H)."""
    import onnx

    path = Path(path)
    net = copy.deepcopy(model).to("cpu").eval()
    w, h = input_size
    dummy = torch.zeros(1, 3, h, w)
    with atomic_file(path) as tmp:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                net, (dummy,), str(tmp), input_names=["pixel_values"], output_names=["logits"],
                dynamic_axes={"pixel_values": {0: "batch", 2: "height", 3: "width"},
                              "logits": {0: "batch", 2: "logits_height", 3: "logits_width"}},
                opset_version=opset, dynamo=False,
            )
        proto = onnx.load(str(tmp))
        meta = {
            META_CLASSES: json.dumps(classes.to_json(), sort_keys=True),
            META_ID_MAP: json.dumps({str(i): int(c) for i, c in enumerate(classes.ids)}),
            META_INPUT_SIZE: f"{w}x{h}",
        }
        for key, value in meta.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, str(tmp))
    return path
