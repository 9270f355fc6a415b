"""`labelsynth train`: a 2D semantic segmenter trained from labels.h5 files and capture folders.

One module per idea: ``contract`` (the segmenter's input: ONNX metadata keys, ImageNet
normalisation, ``WxH`` sizes and the one resize, shared by training and ``segment``), ``data``
(sources -> frames, the split by capture), ``augment`` (albumentations, imported lazily),
``model`` (SegFormer / U-Net / FPN built from a config, never downloaded), ``loss`` (weighted
cross-entropy + soft Dice), ``loop`` (the optimiser loop, checkpoints, train.json, curves.png),
``export_onnx`` (model.onnx that ``segment`` runs with no ``--id-map``) and ``segment``
(``labelsynth segment``: any ONNX segmenter over a capture's frames, with onnxruntime).
Importing this package imports none of the heavy libraries.
"""

from __future__ import annotations

from .data import TrainError

__all__ = ["TrainError", "TrainConfig", "train"]


def __getattr__(name: str):
    if name in ("TrainConfig", "train", "TrainResult"):
        from . import loop

        return getattr(loop, name)
    raise AttributeError(name)
