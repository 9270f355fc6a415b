"""The segmenter, built from a config by a well-kept library; no weights are ever downloaded.

- ``segformer`` (default): HF transformers' SegFormer built from ``SegformerConfig``
  (``--encoder b0``, the 3.7 M-parameter MiT-b0, or ``b1``); logits at 1/4 resolution.
- ``unet`` / ``fpn``: segmentation-models-pytorch with ``encoder_weights=None``
  (``--encoder resnet18``, ``mobilenet_v2``, ...); needs a torchvision built for the
  installed torch (``pip install segmentation-models-pytorch``).

Every model takes ``pixel_values`` (N,3,H,W, ImageNet-normalised RGB) and returns logits
(N,C,h,w); the loss and ``segment`` upsample them to the frame size.
"""

from __future__ import annotations

import os

import torch
from torch import nn

from .data import TrainError

ARCHS = ("segformer", "unet", "fpn")
DEFAULT_ENCODER = {"segformer": "b0", "unet": "resnet18", "fpn": "resnet18"}
SEGFORMER_SIZES = {
    "b0": dict(hidden_sizes=[32, 64, 160, 256], depths=[2, 2, 2, 2], decoder_hidden_size=256),
    "b1": dict(hidden_sizes=[64, 128, 320, 512], depths=[2, 2, 2, 2], decoder_hidden_size=256),
}


class SegformerLogits(nn.Module):
    """SegFormer with a plain ``forward(pixel_values) -> logits`` (what ONNX export traces)."""

    def __init__(self, num_classes: int, size: str) -> None:
        super().__init__()
        os.environ.setdefault("HF_HUB_OFFLINE", "1")  # built from a config: nothing to fetch, ever
        from transformers import SegformerConfig, SegformerForSemanticSegmentation

        cfg = SegformerConfig(num_labels=num_classes, **SEGFORMER_SIZES[size])
        self.net = SegformerForSemanticSegmentation(cfg)

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        return self.net(pixel_values=pixel_values).logits


class SmpLogits(nn.Module):
    def __init__(self, arch: str, encoder: str, num_classes: int) -> None:
        super().__init__()
        try:
            import segmentation_models_pytorch as smp
        except Exception as exc:  # missing, or a torchvision that does not match torch
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise TrainError(
                f"--arch {arch}: segmentation-models-pytorch is not usable here ({reason}); install it with a "
                "torchvision built for your torch, or use --arch segformer"
            ) from None
        cls = {"unet": smp.Unet, "fpn": smp.FPN}[arch]
        try:
            self.net = cls(encoder_name=encoder, encoder_weights=None, in_channels=3, classes=num_classes)
        except (KeyError, ValueError) as exc:
            raise TrainError(f"--encoder {encoder!r}: not an encoder segmentation-models-pytorch knows ({exc})") from None

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        return self.net(pixel_values)


def resolve_encoder(arch: str, encoder: str | None) -> str:
    if arch not in ARCHS:
        raise TrainError(f"--arch {arch!r}: expected one of {', '.join(ARCHS)}")
    encoder = encoder or DEFAULT_ENCODER[arch]
    if arch == "segformer" and encoder not in SEGFORMER_SIZES:
        raise TrainError(f"--encoder {encoder!r}: SegFormer sizes are {', '.join(SEGFORMER_SIZES)}")
    return encoder


def build_model(arch: str, encoder: str | None, num_classes: int) -> nn.Module:
    encoder = resolve_encoder(arch, encoder)
    if arch == "segformer":
        return SegformerLogits(num_classes, encoder)
    return SmpLogits(arch, encoder, num_classes)


def input_multiple(arch: str) -> int:
    """Frame sides the model needs to be divisible by (U-Net/FPN: 32; SegFormer: any)."""
    return 1 if arch == "segformer" else 32
