"""Augmentation (albumentations 2.x): flips, scale/rotate/shift, a fixed-size crop, colour
jitter, blur and noise. The mask and the weight map move with the image (nearest-neighbour
interpolation, so class ids are never blended); pixels that padding or rotation bring in are
ignore (255) with weight 0.

albumentations is imported here only, lazily: 2.0.8 checks PyPI for a newer version on import
unless ``NO_ALBUMENTATIONS_UPDATE`` is set, and no labelsynth command may reach the network.
"""

from __future__ import annotations

import os

from ..classes import IGNORE_ID


def _albumentations():
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")
    import albumentations as A

    return A


def build_augment(crop: int, *, seed: int | None = None, geometric: bool = True, photometric: bool = True):
    """The training transform: called as ``t(image=, mask=, weight=)``; ``mask`` is uint8
    target indices (255 = ignore), ``weight`` float32 per-pixel weights. Output is
    ``crop`` x ``crop`` (frames smaller than the crop are padded with ignore)."""
    import cv2

    A = _albumentations()
    steps = []
    if geometric:
        steps += [
            A.HorizontalFlip(p=0.5),
            A.Affine(scale=(0.75, 1.33), translate_percent=(-0.05, 0.05), rotate=(-20, 20),
                     interpolation=cv2.INTER_LINEAR, mask_interpolation=cv2.INTER_NEAREST,
                     border_mode=cv2.BORDER_CONSTANT, fill=0, fill_mask=IGNORE_ID, p=0.7),
        ]
    steps += [
        A.PadIfNeeded(min_height=crop, min_width=crop, border_mode=cv2.BORDER_CONSTANT, fill=0, fill_mask=IGNORE_ID),
        A.RandomCrop(height=crop, width=crop),
    ]
    if photometric:
        steps += [
            A.ColorJitter(brightness=(0.8, 1.2), contrast=(0.8, 1.2), saturation=(0.8, 1.2), hue=(-0.03, 0.03), p=0.5),
            A.GaussianBlur(blur_limit=(3, 5), p=0.2),
            A.GaussNoise(std_range=(0.01, 0.05), p=0.2),
        ]
    return A.Compose(steps, additional_targets={"weight": "mask"}, mask_interpolation=cv2.INTER_NEAREST, seed=seed)
