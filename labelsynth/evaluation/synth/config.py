"""What to synthesise (``SynthConfig``), what came out (``SynthResult``), and the class ids of
the synthetic wound (the default class table's)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ...errors import LabelsynthError

BACKGROUND, GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN = 0, 1, 2, 3, 4, 5
WOUND_CLASSES = (GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN)
LAYOUTS = ("one-sided", "all-around")
MAX_FRAMES = 10_000
MAX_SIDE = 8192


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
        from ...options import finite_number, seed_value, whole_number

        if self.layout not in LAYOUTS:
            raise LabelsynthError(f"--layout must be one of {', '.join(LAYOUTS)}, not {self.layout!r}")
        self.frames = whole_number(self.frames, "--frames", 2, MAX_FRAMES)
        self.annotated = whole_number(self.annotated, "--annotated", 0, self.frames)
        self.width = whole_number(self.width, "--width", 16, MAX_SIDE)
        self.height = whole_number(self.height, "--height", 16, MAX_SIDE)
        self.noise = finite_number(self.noise, "--noise", 0.0)
        self.seed = seed_value(self.seed)


@dataclass
class SynthResult:
    """Where ``synthesize`` wrote the capture and its truth, and which frames are annotated."""

    capture_dir: Path
    truth_dir: Path
    num_frames: int
    annotated: list[str] = field(default_factory=list)
    seconds: float = 0.0

