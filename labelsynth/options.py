"""The options of one run (``expand``, every capture of a ``batch``, ``suggest``): typed, checked when made.

``ExpandOptions`` is what the CLI parses, ``pipeline.expand`` runs and ``batch`` hands each
capture. A value that is not one of its choices is a one-line ``OptionError`` as soon as the
options are made; ``ExpandOptions.check`` then checks what needs more than the value (the
recipe file and every key, type and range in it, the device, the frame selector's syntax)
before any capture is read, any training step is taken and before OUT or OUT.partial exists.
``SuggestOptions`` does the same for ``suggest``; both share ``FitOptions`` (recipe, device,
seed, overrides).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, TypeVar

import numpy as np

from .capture.select import check_frame_spec
from .device import pick_device
from .errors import LabelsynthError
from .recipe import Recipe, load_recipe

C = TypeVar("C", bound="Choice")


class OptionError(LabelsynthError, ValueError):
    """An option with a value it cannot take (one line naming the option)."""


class Choice(str, Enum):
    """A named choice: compares, prints and serialises as its value (``"ply" == MeshFormat.PLY``)."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    @classmethod
    def choices(cls) -> tuple[str, ...]:
        return tuple(c.value for c in cls)

    @classmethod
    def parse(cls: type[C], value: Any, option: str) -> C:
        """``value`` (a member or its text) as a member; otherwise one line naming ``option``."""
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).strip().lower()) if isinstance(value, str) else cls(value)
        except ValueError:
            raise OptionError(f"{option} must be one of {', '.join(cls.choices())}, not '{value}'") from None


class LabelMode(Choice):
    """Which masks teach the semantic stage."""

    ANNOTATIONS = "annotations"
    PREDICTIONS = "predictions"
    BOTH = "both"


class DeviceChoice(Choice):
    """Where a run computes; ``auto`` = CUDA when torch sees it (``device.pick_device``)."""

    AUTO = "auto"
    CPU = "cpu"
    CUDA = "cuda"


class MeshFormat(Choice):
    """The labelled mesh's file format: mesh.ply is always written, glb adds mesh.glb."""

    PLY = "ply"
    GLB = "glb"


SEED_MAX = 2**32 - 1
"""Seeds are 0..2^32-1: numpy's seeding takes no more (torch's would)."""


def whole_number(value: Any, option: str, low: int = 0, high: int | None = None) -> int:
    """``value`` as an int in ``low..high``; otherwise one line naming ``option`` and the range.
    Every count, size and seed a command takes goes through it (the CLI's integers included:
    a number beyond the range is refused before any work, not met as an overflow or an
    allocation of terabytes)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low \
            or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in {low}..{high}"
        raise OptionError(f"{option} must be a whole number {bound}, not {_shown(value)}")
    return int(value)


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:12]}... ({len(text)} characters)"


def finite_number(value: Any, option: str, low: float | None = None, high: float | None = None, *,
                  low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a finite float within the bounds (open or closed); NaN and infinities never
    pass. Otherwise one line naming ``option`` and what it must be."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        parts = []
        if low is not None:
            parts.append(f"{'>' if low_open else '>='} {low:g}")
        if high is not None:
            parts.append(f"{'<' if high_open else '<='} {high:g}")
        raise OptionError(f"{option} must be a finite number{' ' + ' and '.join(parts) if parts else ''}, "
                          f"not {_shown(value)}")
    return float(value)


def positive_number(value: Any, option: str) -> float:
    """``value`` as a finite float > 0; otherwise one line naming ``option``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise OptionError(f"{option} must be a finite number > 0, not {value!r}")
    return float(value)


def seed_value(value: Any, option: str = "--seed") -> int:
    """A random seed: a whole number in 0..2^32-1 (``SEED_MAX``)."""
    return whole_number(value, option, 0, SEED_MAX)


def given_text(value: Any, option: str) -> str | None:
    """An optional text option: None when not given; given, it must say something (an empty
    ``--id-map ""`` is a mistake, not a default)."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise OptionError(f"{option} must not be empty (leave the option out for its default)")
    return value


@dataclass
class FitOptions:
    """What every command that fits a field shares: how stage 1 (and 2) are fitted."""

    recipe: str = "default"
    """A recipe name (``recipes/NAME.yaml``) or a YAML file."""
    device: DeviceChoice = DeviceChoice.AUTO
    seed: int = 0
    overrides: list[str] = field(default_factory=list)
    """``section.key=value`` recipe overrides (``--set``)."""

    def __post_init__(self) -> None:
        self.device = DeviceChoice.parse(self.device, "--device")
        self.seed = seed_value(self.seed)
        if not isinstance(self.recipe, str) or not self.recipe.strip():
            raise OptionError(f"--recipe must be a recipe name or a YAML file, not {self.recipe!r}")
        if self.overrides is None:
            self.overrides = []
        if isinstance(self.overrides, str) or not all(isinstance(o, str) for o in self.overrides):
            raise OptionError("--set takes section.key=value texts")
        self.overrides = list(self.overrides)

    def replace(self: F, **changes: Any) -> F:
        """A copy with some options changed (checked again)."""
        return dataclasses.replace(self, **changes)

    def load_recipe(self) -> Recipe:
        """The recipe these options name, with their overrides (``recipe.load_recipe``)."""
        return load_recipe(self.recipe, self.overrides)

    def check(self, *, device: bool = True) -> Recipe:
        """Check what needs more than the values, before any work: the recipe (file, keys,
        types, ranges) and (``device``) that the device exists here. Returns the recipe."""
        recipe = self.load_recipe()
        if device:
            pick_device(self.device.value)
        return recipe


F = TypeVar("F", bound=FitOptions)


@dataclass
class ExpandOptions(FitOptions):
    """Everything that decides one expand besides the capture and OUT (the CLI's expand options)."""

    labels: LabelMode | None = None
    """What teaches; None: both when both folders exist, else whichever exists."""
    annotated_frames: str | list[str] | None = None
    """Only these frames' annotations teach (``capture.select``); None: all."""
    report: bool = True
    """Write the consistency report and the labelled mesh."""
    mesh_format: MeshFormat = MeshFormat.PLY
    mm_per_unit: float | None = None
    """Millimetres per scene unit: the report's class areas in mm² too."""

    def __post_init__(self) -> None:
        if self.labels is not None:
            self.labels = LabelMode.parse(self.labels, "--labels")
        super().__post_init__()
        self.mesh_format = MeshFormat.parse(self.mesh_format, "--mesh-format")
        if self.mm_per_unit is not None:
            self.mm_per_unit = positive_number(self.mm_per_unit, "--mm-per-unit")

    def check(self, *, device: bool = True) -> Recipe:
        """As ``FitOptions.check``, and the frame selector's syntax. ``batch`` leaves the device
        to each worker's node."""
        recipe = super().check(device=False)
        if self.annotated_frames is not None:
            check_frame_spec(self.annotated_frames)
        if device:
            pick_device(self.device.value)
        return recipe

    def marker_options(self) -> dict[str, Any]:
        """The options that change a capture's output (``batch``'s resume marker; the recipe is
        hashed on its own)."""
        return {"labels": None if self.labels is None else self.labels.value, "seed": self.seed,
                "annotated_frames": self.annotated_frames, "report": self.report,
                "mesh_format": self.mesh_format.value, "mm_per_unit": self.mm_per_unit}


MAX_ANNOTATE = 6
"""The most frames ``suggest`` names (the method learns from 2-4 annotated frames)."""
SUGGEST_OBJECTIVES = ("surface", "frames")
"""What ``suggest``'s choice maximises (``SuggestOptions.objective``)."""


@dataclass
class SuggestOptions(FitOptions):
    """The options of ``labelsynth suggest``: how many frames to name, and how stage 1 is fitted
    (recipe, overrides, device, seed: a later ``expand --geometry`` must use the same)."""

    annotate: int = 3
    """How many frames to suggest for annotation (1..``MAX_ANNOTATE``)."""
    objective: str = "surface"
    """What the chosen frames maximise (``suggest.coverage``): ``surface``, the share of the surface
    seen, each point at its best chosen view (greedy); ``frames``, the mean over the frames of the
    share of each one's view that its best chosen frame sees (greedy, then swaps)."""

    def __post_init__(self) -> None:
        k = self.annotate
        if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_ANNOTATE:
            raise OptionError(f"--annotate must be a whole number in 1..{MAX_ANNOTATE}, not {k!r}")
        if self.objective not in SUGGEST_OBJECTIVES:
            raise OptionError(f"--objective must be one of {', '.join(SUGGEST_OBJECTIVES)}, not {self.objective!r}")
        super().__post_init__()
