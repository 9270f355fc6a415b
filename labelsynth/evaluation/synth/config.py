"""What to synthesise (``SynthConfig``), what came out (``SynthResult``), and the class ids of
the synthetic wound (the default class table's)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Literal

from ...errors import LabelsynthError

BACKGROUND, GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN = 0, 1, 2, 3, 4, 5
WOUND_CLASSES = (GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN)
LAYOUTS = ("one-sided", "all-around", "all-around-uneven")
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
    layout: Literal["one-sided", "all-around", "all-around-uneven"] = "one-sided"
    """one-sided: a hand-held arc above a wound on a limb or torso; all-around-uneven: the all-around
    turn, dwelling on one side of the limb (``paths.turn_progress``); all-around: a wound wrapped
    around a limb, filmed in one turn around it."""

    # --- what a phone does to the frames (all off by default; ``phone()`` turns on a mix) -------
    # The truth stays exact: labels and depth come from the geometry. The image effects change
    # images/ only; distance and zoom change the cameras, which transforms.json records.
    exposure_drift: float = 0.0
    """Auto exposure drifting along the video: each frame's exposure is a smooth curve of the path
    position within +-this many stops (EV; 0.5: gains 0.71..1.41); highlights clip."""
    white_balance_drift: float = 0.0
    """Auto white balance drifting along the video: red and blue gains move smoothly within
    1 +- this (0.05: +-5%)."""
    defocus_blur: float = 0.0
    """Largest defocus blur (a disk) radius, in pixels of a 640-pixel-wide frame; each frame's is
    uniform in 0..this."""
    motion_blur: float = 0.0
    """Longest motion-blur streak, in pixels of a 640-pixel-wide frame; each frame's is uniform in
    0..this, in a random direction (a hand-held phone at video shutter speeds)."""
    sensor_noise: float = 0.0
    """Sensor noise: Gaussian, this many grey levels (0..255) at unit exposure gain, growing with
    the square root of the gain (a dark frame brightened brings its noise up)."""
    jpeg_quality: int = 0
    """0: images/ are PNG (exact pixels); 1..100: images/ are JPEG at this quality (8x8 block
    artefacts and chroma subsampling, as a phone's frames)."""
    distance_change: float = 0.0
    """The camera's distance to the wound changes along the path, beyond the path's own +-20%
    wobble: a smooth factor between 1/(1+this) and 1+this (0.3: 0.77..1.3)."""
    zoom: float = 0.0
    """The focal length changes along the path (zooming in and out): a smooth factor between
    1/(1+this) and 1+this; every frame's intrinsics are written to transforms.json."""

    @classmethod
    def phone(cls, **overrides) -> "SynthConfig":
        """A realistic phone-video mix of every effect (the CLI's ``--phone``); ``overrides``
        replace any field, e.g. ``SynthConfig.phone(seed=3, jpeg_quality=0)``."""
        return cls(**{**PHONE, **overrides})

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
        limits = {"exposure_drift": 3.0, "white_balance_drift": 0.5, "defocus_blur": 40.0, "motion_blur": 80.0,
                  "sensor_noise": 50.0, "distance_change": 1.0, "zoom": 1.0}
        for name, top in limits.items():
            setattr(self, name, finite_number(getattr(self, name), "--" + name.replace("_", "-"), 0.0, top))
        self.jpeg_quality = whole_number(self.jpeg_quality, "--jpeg-quality", 0, 100)

    @property
    def varied(self) -> dict[str, float]:
        """The phone options that are on (name -> value)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name in PHONE and getattr(self, f.name)}


PHONE = {"exposure_drift": 0.5, "white_balance_drift": 0.05, "defocus_blur": 2.0, "motion_blur": 8.0,
         "sensor_noise": 2.0, "jpeg_quality": 80, "distance_change": 0.3, "zoom": 0.25}
"""``SynthConfig.phone()``: hand-held video frames of a wound (exposure within +-0.5 EV, white
balance +-5%, defocus up to 2 px, motion blur up to 8 px at 640 px wide, noise sigma 2, JPEG
quality 80, distance 0.77..1.3x and focal length 0.8..1.25x along the path)."""


@dataclass
class SynthResult:
    """Where ``synthesize`` wrote the capture and its truth, and which frames are annotated."""

    capture_dir: Path
    truth_dir: Path
    num_frames: int
    annotated: list[str] = field(default_factory=list)
    seconds: float = 0.0

