"""Recipes: every knob of a run, one section per stage, loaded from ``recipes/*.yaml`` and
overridable with ``--set section.key=value``.

A ``Recipe`` only assembles the stages' configs, each of which lives beside its stage
(``geometry.config``, ``semantics.config``, ``render.config``, ``report.config``) with its
defaults, a docstring per field and the range of every number. Those dataclasses are the one
source of the defaults: ``default.yaml`` holds only its name and description, and every other
recipe lists only what differs from them (``tests/test_recipes.py`` enforces both).

Reading a recipe checks everything before any work: an unknown key, a value of the wrong
type, a choice that does not exist, a number out of its range, a file that is not YAML or not
a mapping: each is a one-line ``RecipeError`` naming the file (or the ``--set``) and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .config import build_config
from .errors import RecipeError
from .geometry.config import GeometryConfig
from .render.config import RenderConfig
from .report.config import ReportConfig
from .semantics.config import SemanticConfig

RECIPE_DIR = Path(__file__).resolve().parent / "recipes"


@dataclass
class Recipe:
    """Every knob of a run, one section per stage."""

    name: str = "default"
    """The recipe's name (its file's stem unless the file says otherwise)."""
    description: str = ""
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    """Stage 1: the SDF and colour fitted to the images."""
    semantic: SemanticConfig = field(default_factory=SemanticConfig)
    """Stage 2: the semantic head on the frozen geometry."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """Masks at full resolution."""
    report: ReportConfig = field(default_factory=ReportConfig)
    """The consistency report."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Any, where: str) -> "Recipe":
        """A recipe from a mapping (a recipe file's, or one a run recorded), every key, type,
        choice and range checked; a problem is a one-line ``RecipeError`` starting with ``where``."""
        return build_config(cls, data, where)


def available_recipes() -> list[str]:
    return sorted(p.stem for p in RECIPE_DIR.glob("*.yaml"))


def recipe_path(name_or_path: str | Path) -> Path:
    """The file of a recipe given by name (``recipes/NAME.yaml``) or path; one line if there is none."""
    path = Path(name_or_path)
    if not path.suffix:
        path = RECIPE_DIR / f"{name_or_path}.yaml"
        if not path.exists():
            raise RecipeError(f"--recipe '{name_or_path}': unknown recipe (available: {', '.join(available_recipes())}, "
                              "or a .yaml file)")
    if path.is_dir():
        raise RecipeError(f"{path}: is a folder, not a recipe file (give a recipe name or a .yaml file)")
    if not path.exists():
        raise RecipeError(f"{path}: recipe file not found")
    return path


def load_recipe(name_or_path: str | Path = "default", overrides: list[str] | None = None) -> Recipe:
    """A recipe by name (``recipes/NAME.yaml``) or path, with ``section.key=value`` overrides."""
    path = recipe_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{path}: cannot read the recipe ({getattr(exc, 'strerror', None) or exc})") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        kind = "a list" if isinstance(data, list) else f"a single {type(data).__name__} value"
        raise RecipeError(f"{path}: a recipe is a mapping of sections (geometry:, semantic:, ...), this file holds {kind}")
    for item in overrides or []:
        apply_override(data, item)
    data.setdefault("name", path.stem)
    return Recipe.from_dict(data, path.name)


def apply_override(data: dict, item: str) -> None:
    """Set ``section.key=value`` (the value read as YAML) in a recipe mapping; one line if malformed."""
    key, sep, raw = item.partition("=")
    parts = key.strip().split(".")
    if not sep or not all(parts):
        raise RecipeError(f"--set {item}: not of the form section.key=value")
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise RecipeError(f"--set {item}: the value is not valid YAML ({str(exc).splitlines()[0]})") from None
    node: dict[str, Any] = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise RecipeError(f"--set {item}: '{part}' is not a section")
    node[parts[-1]] = value
