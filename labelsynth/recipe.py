"""Typed recipes: every knob of a run, loaded from ``recipes/*.yaml`` and overridable.

A recipe is a tree of dataclasses; YAML keys that do not exist, or values of the wrong
type, are a one-line RecipeError so a typo never silently falls back to a default.

The dataclasses below are the one source of the defaults: ``default.yaml`` holds only its
name and description, and every other recipe lists only what differs from them
(``tests/test_recipes.py`` enforces both). Values that must be one of a few names are
``typing.Literal`` types, checked at load by ``_check_choices``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

import yaml

from .errors import RecipeError
from .geometry.sdf import SDFConfig
from .semantics.head import ClassWeighting, DecisionRule

RECIPE_DIR = Path(__file__).resolve().parent / "recipes"


@dataclass
class GeometryConfig:
    """Stage 1: fit the SDF and colour to the images."""

    iterations: int = 1200
    train_scale: float = 0.25  # rays come from images resized by this factor
    target_samples: int = 16384  # samples per batch: the ray count adapts to hit it
    max_rays: int = 4096
    lr: float = 1e-2
    lr_final_factor: float = 0.1
    # |grad sdf| = 1 keeps the field a distance function (the occupancy band and the mesh rely
    # on it); NeuS's 0.1 smooths away detail the colour loss asks for within these few
    # iterations (lego: training PSNR 24.2 -> 26.0 dB at 0.05; README, Captures of any shape)
    eikonal_weight: float = 0.05
    eikonal_samples: int = 1024  # points per batch that pay for second derivatives
    cos_anneal_iters: int = 300
    # Sharpness floor grows geometrically from inv_s_start to inv_s_end over the first
    # inv_s_ramp fraction of training; the learned NeuS variance may go sharper still.
    inv_s_start: float = 20.0
    inv_s_end: float = 400.0
    inv_s_ramp: float = 0.6
    march_steps: int = 160
    occupancy_resolution: int = 64
    occupancy_every: int = 25
    occupancy_band: float = 4.0  # band = occupancy_band / inv_s (NeuS sharpness), in unit-cube units
    occupancy_max_band: float = 0.08  # ...but never wider than this
    occupancy_full_every: int = 4  # every k-th update evaluates the whole grid...
    occupancy_margin: float = 0.1  # ...the others only cells whose last |sdf| was this close to the band
    levels_start: int = 4  # progressive hash levels: start with this many...
    levels_every: int = 100  # ...and add one every this many iterations
    # optimiser (Adam over hash table, MLPs and the NeuS variance): the instant-ngp settings
    adam_beta1: float = 0.9
    adam_beta2: float = 0.99
    adam_eps: float = 1e-15
    warmup_iterations: int = 50  # learning rate ramps linearly over these, then decays exponentially
    sdf: SDFConfig = field(default_factory=SDFConfig)


@dataclass
class SemanticConfig:
    """Stage 2: the semantic head, geometry frozen."""

    iterations: int = 800
    rays_per_batch: int = 4096
    # ...but at least this many passes over the labelled rays: with every frame's predictions
    # teaching there are millions of rays, and a head that has seen only part of them can miss
    # a small class outright (README, Benchmarks: necrotic learned or lost by the seed)
    min_epochs: float = 1.0
    lr: float = 5e-3
    hidden: int = 64
    dropout: float = 0.5
    use_position: bool = True  # a small hash grid of position beside the geometry feature
    position_levels: int = 8
    position_log2_table: int = 17
    position_max_resolution: int = 512
    train_scale: float = 0.5  # label pixels sampled at this image scale
    max_rays_per_frame: int = 40000
    max_samples_per_ray: int = 8
    expert_weight: float = 4.0  # with --labels both: weight of annotated frames vs predictions
    # auto | paper | equal-tissue | uniform | inverse-sqrt | inverse (semantic.class_weights);
    # auto = equal-tissue from expert annotations alone, uniform when predictions teach
    class_weighting: ClassWeighting = "auto"
    background_weight: float = 0.1  # these two: the paper scheme only
    tissue_weight_floor: float = 0.1  # w_y = floor + (1 - floor) * N_y / sum N (paper: 0.1 / 0.9)
    # optimiser: Adam, learning rate cosine-annealed from lr to lr * lr_final_factor
    adam_beta1: float = 0.9
    adam_beta2: float = 0.99
    adam_eps: float = 1e-15
    lr_final_factor: float = 0.05


@dataclass
class RenderConfig:
    mesh_resolution: int = 256  # marching-cubes grid over the unit cube
    subdivide: int = 1  # midpoint subdivisions of the mesh before ray casting (4x faces each)
    # wound-bed-first | argmax: how class probabilities become a label (semantic.decide_labels)
    decision: DecisionRule = "wound-bed-first"
    per_pixel: bool = False  # evaluate the head at every pixel's hit (slow) instead of at vertices
    chunk: int = 65536


@dataclass
class ReportConfig:
    """The consistency report (the end of ``expand``; ``labelsynth report`` rebuilds it)."""

    # Each leave-one-view-out refit trains a fresh head (never the full one warm-started: a head
    # that learnt the left-out mask agrees with it) for this fraction of the semantic stage's
    # steps and epochs: it only has to say what the other views predict, not polish a mask
    # (README, Speed: the flags and the LOO Dice at 1.0 and at this value).
    loo_fraction: float = 0.25


@dataclass
class Recipe:
    name: str = "default"
    description: str = ""
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    semantic: SemanticConfig = field(default_factory=SemanticConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    report: ReportConfig = field(default_factory=ReportConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _build(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise RecipeError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise RecipeError(f"{where}: unknown key '{key}' (known: {', '.join(sorted(names))})")
        kwargs[key] = _coerce(hints[key], value, f"{where}.{key}")
    return cls(**{**{f.name: getattr(cls(), f.name) for f in dataclasses.fields(cls)}, **kwargs})


def _coerce(tp, value, where: str):
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in {"true", "false", "1", "0", "yes", "no"}:
            return value.lower() in {"true", "1", "yes"}
        raise RecipeError(f"{where}: expected true/false, got {value!r}")
    if tp in (int, float):
        try:
            if tp is int and isinstance(value, float) and not value.is_integer():
                raise ValueError
            return tp(value)
        except (TypeError, ValueError):
            raise RecipeError(f"{where}: expected a {tp.__name__}, got {value!r}") from None
    if tp is str or get_origin(tp) is Literal:
        return str(value)
    return value


def available_recipes() -> list[str]:
    return sorted(p.stem for p in RECIPE_DIR.glob("*.yaml"))


def load_recipe(name_or_path: str | Path = "default", overrides: list[str] | None = None) -> Recipe:
    """A recipe by name (``recipes/NAME.yaml``) or path, with ``section.key=value`` overrides."""
    path = Path(name_or_path)
    if not path.suffix:
        path = RECIPE_DIR / f"{name_or_path}.yaml"
        if not path.exists():
            raise RecipeError(f"unknown recipe '{name_or_path}' (available: {', '.join(available_recipes())})")
    if not path.exists():
        raise RecipeError(f"{path}: recipe file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from exc
    for item in overrides or []:
        if "=" not in item:
            raise RecipeError(f"override '{item}' is not of the form section.key=value")
        key, raw = item.split("=", 1)
        node: dict[str, Any] = data
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise RecipeError(f"override '{item}': '{part}' is not a section")
        node[parts[-1]] = yaml.safe_load(raw)
    data.setdefault("name", path.stem)
    recipe = _build(Recipe, data, str(path.name))
    _check_choices(recipe, path.name)
    if not 0.0 < recipe.report.loo_fraction <= 1.0:
        raise RecipeError(f"{path.name}.report.loo_fraction: {recipe.report.loo_fraction} is not in (0, 1]")
    if not 0.0 <= recipe.semantic.dropout < 1.0:
        raise RecipeError(f"{path.name}.semantic.dropout: {recipe.semantic.dropout} is not in [0, 1)")
    return recipe


# Choices of fields typed plain ``str`` in modules this one does not own (geometry.sdf): checked
# here like a Literal until their types say it themselves (a Literal type wins over this table).


def choices_of(cls: type, name: str) -> tuple[str, ...] | None:
    """The allowed values of field ``name`` of recipe dataclass ``cls``: its Literal's
    arguments, else None (any value of its type)."""
    tp = get_type_hints(cls).get(name)
    if get_origin(tp) is Literal:
        return tuple(get_args(tp))
    return None


def _check_choices(node: Any, where: str) -> None:
    """Values that must be one of a few names: a typo is an error at load, not mid-run.
    Walks the recipe tree; one line naming the key, the value and the choices."""
    for f in dataclasses.fields(node):
        value = getattr(node, f.name)
        if dataclasses.is_dataclass(value):
            _check_choices(value, f"{where}.{f.name}")
            continue
        allowed = choices_of(type(node), f.name)
        if allowed is not None and value not in allowed:
            raise RecipeError(f"{where}.{f.name}: '{value}' is not one of {', '.join(allowed)}")
