"""Cross-entropy with 255 ignored plus a soft Dice term, both weighted per pixel.

Weights come from ``data.make_target``: the labels' confidence (when asked) times the
expert-frame weight; ignored pixels weigh 0. Logits at a lower resolution (SegFormer: 1/4)
are upsampled bilinearly to the target, as ``segment`` does at inference.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..classes import IGNORE_ID


def upsample(logits: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(logits.shape[-2:]) == tuple(size):
        return logits
    return F.interpolate(logits, size=size, mode="bilinear", align_corners=False)


def segmentation_loss(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, *,
                      dice_weight: float = 1.0, eps: float = 1.0) -> tuple[torch.Tensor, dict[str, float]]:
    """(N,C,h,w) logits, (N,H,W) long targets (255 = ignore), (N,H,W) weights -> loss, parts.

    CE: sum(w * ce) / sum(w) over labelled pixels. Dice: 1 - mean over the classes present
    in the batch's targets of (2 sum w p y + eps) / (sum w p + sum w y + eps).
    """
    logits = upsample(logits, tuple(target.shape[-2:]))
    valid = target != IGNORE_ID
    w = weight * valid
    total_w = w.sum()
    if total_w <= 0:  # a crop with nothing labelled: no gradient, but keep the graph
        zero = logits.sum() * 0.0
        return zero, {"ce": 0.0, "dice": 0.0}
    safe = torch.where(valid, target, torch.zeros_like(target))
    ce = F.cross_entropy(logits, safe, reduction="none")
    ce = (ce * w).sum() / total_w
    loss = ce
    dice_loss = torch.zeros((), device=logits.device)
    if dice_weight > 0:
        prob = logits.softmax(dim=1)
        onehot = F.one_hot(safe, logits.shape[1]).permute(0, 3, 1, 2).to(prob.dtype)
        wc = w.unsqueeze(1)
        inter = (wc * prob * onehot).sum(dim=(0, 2, 3))
        denom = (wc * prob).sum(dim=(0, 2, 3)) + (wc * onehot).sum(dim=(0, 2, 3))
        present = (wc * onehot).sum(dim=(0, 2, 3)) > 0
        dice = (2 * inter + eps) / (denom + eps)
        dice_loss = 1.0 - dice[present].mean()
        loss = loss + dice_weight * dice_loss
    return loss, {"ce": float(ce.detach()), "dice": float(dice_loss.detach())}


def confusion_counts(pred: torch.Tensor, target: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Per-class (intersection, predicted, true) pixel counts over labelled pixels: (3, C)."""
    valid = target != IGNORE_ID
    p, t = pred[valid], target[valid]
    inter = torch.bincount(t[p == t], minlength=num_classes)[:num_classes]
    npred = torch.bincount(p, minlength=num_classes)[:num_classes]
    ntrue = torch.bincount(t, minlength=num_classes)[:num_classes]
    return torch.stack([inter, npred, ntrue]).cpu()
