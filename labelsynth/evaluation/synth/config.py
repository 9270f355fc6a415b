"""What to synthesise (``SynthConfig``), what came out (``SynthResult``), and the class ids of
the synthetic wound (the default class table's)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ...errors import LabelsynthError

BACKGROUND, GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN = 0, 1, 2, 3, 4, 5
WOUND_CLASSES = (GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN)
LAYOUTS = ("one-sided", "all-around")


@dataclass
class SynthConfig:
    """What to synthesise. The same config (seed included) gives byte-identical files."""

    frames: int = 50
    """Frames along the camera path."""
    annotated: int = 4
    """Frames that get an expert annotation (their exact truth), spread along the path (``annotated_indices``)."""
    width: int = 640
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    noise: float = 1.0
    """Strength of the imitation 2D segmenter's errors in predictions/ (0: the predictions are the truth)."""
    seed: int = 0
    """Everything random derives from it: the scene, the path, the lights and each frame's errors."""
    layout: Literal["one-sided", "all-around"] = "one-sided"
    """one-sided: a hand-held arc above a wound on a limb or torso; all-around: a wound wrapped
    around a limb, filmed in one turn around it."""

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise LabelsynthError(f"synth: layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if self.frames < 2:
            raise LabelsynthError(f"synth: need at least 2 frames, got {self.frames}")
        if not 0 <= self.annotated <= self.frames:
            raise LabelsynthError(f"synth: annotated must be in 0..{self.frames}, got {self.annotated}")
        if self.width < 16 or self.height < 16:
            raise LabelsynthError(f"synth: image size must be at least 16x16, got {self.width}x{self.height}")
        if not np.isfinite(self.noise) or self.noise < 0:
            raise LabelsynthError(f"synth: noise must be >= 0, got {self.noise}")


@dataclass
class SynthResult:
    """Where ``synthesize`` wrote the capture and its truth, and which frames are annotated."""

    capture_dir: Path
    truth_dir: Path
    num_frames: int
    annotated: list[str] = field(default_factory=list)
    seconds: float = 0.0

