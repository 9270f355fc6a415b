"""Recipes: the dataclasses are the one source of the defaults; every recipe loads, uses only
known keys, and lists only what differs; choices are checked at load."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
import yaml

from labelsynth.config import choices_of
from labelsynth.errors import RecipeError
from labelsynth.recipe import RECIPE_DIR, Recipe, available_recipes, load_recipe

REPO = Path(__file__).resolve().parent.parent


def _yaml(name: str) -> dict:
    return yaml.safe_load((RECIPE_DIR / f"{name}.yaml").read_text()) or {}


def _walk_keys(data: dict, cls: type, where: str) -> list[str]:
    """Every key of ``data`` as a dotted path, checked to exist in the dataclass ``cls``."""
    names = {f.name for f in dataclasses.fields(cls)}
    keys = []
    for key, value in data.items():
        assert key in names, f"{where}: unknown key {key!r}"
        default = getattr(cls(), key)
        if dataclasses.is_dataclass(default):
            assert isinstance(value, dict), f"{where}.{key}: expected a section"
            keys += _walk_keys(value, type(default), f"{where}.{key}")
        else:
            keys.append(f"{where}.{key}")
    return keys


def _get(obj, dotted: str):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_every_recipe_loads_with_known_keys() -> None:
    names = available_recipes()
    assert {"default", "fast", "quality", "paper"} <= set(names)
    for name in names:
        data = _yaml(name)
        _walk_keys(data, Recipe, name)  # every key exists
        r = load_recipe(name)
        assert r.name == name and r.description


def test_default_yaml_is_the_dataclass_defaults() -> None:
    data = _yaml("default")
    assert set(data) <= {"name", "description"}, "default.yaml must not repeat values: the dataclasses hold them"
    r = load_recipe("default")
    assert r.to_dict() == Recipe(name="default", description=r.description).to_dict()
    assert r.geometry.target_samples == 16384  # what default.yaml ran before the defaults moved


@pytest.mark.parametrize("name", ["fast", "quality", "paper"])
def test_other_recipes_list_only_what_differs(name: str) -> None:
    defaults = Recipe()
    for key in _walk_keys(_yaml(name), Recipe, name):
        path = key.split(".", 1)[1]
        if path in ("name", "description"):
            continue
        assert _get(load_recipe(name), path) != _get(defaults, path), f"{key} repeats the default"


def test_optimiser_settings_are_recipe_values() -> None:
    r = load_recipe("default")
    for section in (r.geometry, r.semantic):
        assert (section.adam_beta1, section.adam_beta2, section.adam_eps) == (0.9, 0.99, 1e-15)
    assert r.geometry.warmup_iterations == 50 and r.semantic.lr_final_factor == 0.05
    r = load_recipe("fast", ["geometry.adam_eps=1e-8", "semantic.adam_beta2=0.999"])
    assert r.geometry.adam_eps == 1e-8 and r.semantic.adam_beta2 == 0.999


@pytest.mark.parametrize(
    "override, key",
    [
        ("semantic.class_weighting=balanced", "semantic.class_weighting"),
        ("render.decision=vote", "render.decision"),
        ("geometry.sdf.init_shape=cube", "geometry.sdf.init_shape"),
        ("geometry.sdf.background=none", "geometry.sdf.background"),
    ],
)
def test_bad_choice_is_one_line(override: str, key: str) -> None:
    with pytest.raises(RecipeError) as info:
        load_recipe("fast", [override])
    msg = str(info.value)
    assert msg.startswith(f"fast.yaml.{key}: '") and "is not one of" in msg and "\n" not in msg


def test_choices_come_from_the_types() -> None:
    from labelsynth.render.config import RenderConfig
    from labelsynth.semantics.config import CLASS_WEIGHTINGS, DECISION_RULES, SemanticConfig

    assert choices_of(SemanticConfig, "class_weighting") == CLASS_WEIGHTINGS
    assert choices_of(RenderConfig, "decision") == DECISION_RULES
    assert choices_of(SemanticConfig, "lr") is None
    for value in CLASS_WEIGHTINGS:
        assert load_recipe("fast", [f"semantic.class_weighting={value}"]).semantic.class_weighting == value


def test_top_level_recipes_folder(monkeypatch) -> None:
    """README: the recipes are also reachable as ``recipes/`` from the repository root."""
    top = REPO / "recipes"
    if not top.exists():
        pytest.skip("not a source checkout")
    assert top.resolve() == RECIPE_DIR.resolve()
    assert all(os.path.exists(p) for p in top.iterdir())  # no broken links inside
    monkeypatch.chdir(REPO)
    assert load_recipe("recipes/fast.yaml").to_dict() == load_recipe("fast").to_dict()


def test_recipes_load_and_reject_typos():
    for name in ("default", "fast", "quality", "paper"):
        r = load_recipe(name)
        assert r.geometry.iterations > 0 and r.semantic.dropout == pytest.approx(0.5)
    r = load_recipe("fast", ["geometry.iterations=7", "semantic.use_position=false"])
    assert r.geometry.iterations == 7 and r.semantic.use_position is False
    with pytest.raises(RecipeError, match="unknown key 'iteratons'"):
        load_recipe("fast", ["geometry.iteratons=7"])
    with pytest.raises(RecipeError, match="expected a whole number"):
        load_recipe("fast", ["geometry.iterations=many"])
    with pytest.raises(RecipeError, match="unknown recipe"):
        load_recipe("no-such-recipe")
    with pytest.raises(RecipeError, match="class_weighting: 'balanced' is not one of"):
        load_recipe("fast", ["semantic.class_weighting=balanced"])


@pytest.mark.parametrize("value", ["0", "1.5", "-0.1"])
def test_loo_fraction_out_of_range_is_one_line(value):
    with pytest.raises(RecipeError, match=r"report\.loo_fraction") as err:
        load_recipe("default", [f"report.loo_fraction={value}"])
    assert "\n" not in str(err.value)


def _numeric_fields(cls: type, where: str):
    """(dotted key, owning dataclass, field name) of every int/float field of the recipe tree."""
    from typing import get_type_hints

    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            yield from _numeric_fields(tp, f"{where}.{f.name}")
        elif tp in (int, float):
            yield f"{where}.{f.name}", cls, f.name


def test_every_number_of_every_config_has_a_range_that_holds_its_default():
    from labelsynth.config import range_of

    fields = list(_numeric_fields(Recipe, "recipe"))
    assert len(fields) > 50
    for key, cls, name in fields:
        limits = range_of(cls, name)
        assert limits is not None, f"{key} has no range"
        assert limits.contains(getattr(cls(), name)), f"{key}: its default is out of its own range {limits}"


@pytest.mark.parametrize("override, message", [
    ("geometry.iterations=-5", "fast.yaml.geometry.iterations: -5 is not >= 1"),
    ("geometry.iterations=0", "fast.yaml.geometry.iterations: 0 is not >= 1"),
    ("semantic.lr=0", "fast.yaml.semantic.lr: 0.0 is not > 0"),
    ("geometry.train_scale=1.5", "fast.yaml.geometry.train_scale: 1.5 is not in (0, 1]"),
    ("semantic.tissue_weight_floor=-0.1", "fast.yaml.semantic.tissue_weight_floor: -0.1 is not in [0, 1]"),
    ("geometry.adam_beta2=1", "fast.yaml.geometry.adam_beta2: 1.0 is not in [0, 1)"),
    ("geometry.sdf.log2_table=40", "fast.yaml.geometry.sdf.log2_table: 40 is not in [4, 24]"),
    ("render.subdivide=9", "fast.yaml.render.subdivide: 9 is not in [0, 4]"),
    ("semantic.lr=.nan", "fast.yaml.semantic.lr: expected a finite number, got nan"),
    ("geometry.eikonal_weight=.inf", "fast.yaml.geometry.eikonal_weight: expected a finite number, got inf"),
    ("geometry.iterations=true", "fast.yaml.geometry.iterations: expected a whole number, got True"),
    ("geometry.iterations=[1, 2]", "fast.yaml.geometry.iterations: expected a whole number, got [1, 2]"),
    ("geometry.sdf.max_resolution=8", "fast.yaml.geometry.sdf.max_resolution: 8 is below base_resolution 16"),
    ("geometry=3", "fast.yaml.geometry: expected a mapping of keys to values, got int"),
    ("semantic.class_weighting=[a]", "fast.yaml.semantic.class_weighting: expected a text value, got ['a']"),
    ("semantic.lr=[", "--set semantic.lr=[: the value is not valid YAML"),
    ("semantic.lr", "--set semantic.lr: not of the form section.key=value"),
    ("semantic..lr=3", "--set semantic..lr=3: not of the form section.key=value"),
    ("geometry.iterations.x=3", "--set geometry.iterations.x=3: 'iterations' is not a section"),
])
def test_bad_values_are_one_line_naming_the_key(override, message):
    with pytest.raises(RecipeError) as err:
        load_recipe("fast", ["geometry.iterations=7", override])
    text = str(err.value)
    assert text.startswith(message) and "\n" not in text, text


def test_bad_recipe_files_are_one_line(tmp_path):
    listed = tmp_path / "list.yaml"
    listed.write_text("- geometry\n- semantic\n")
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("42\n")
    broken = tmp_path / "broken.yaml"
    broken.write_text("geometry: [\n")
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00geometry")
    folder = tmp_path / "recipes.d"
    folder.mkdir()
    cases = [
        (listed, f"{listed}: a recipe is a mapping of sections (geometry:, semantic:, ...), this file holds a list"),
        (scalar, f"{scalar}: a recipe is a mapping of sections"),
        (broken, f"{broken}: not valid YAML"),
        (binary, f"{binary}: cannot read the recipe"),
        (folder, f"{folder}: is a folder, not a recipe file"),
        (tmp_path / "gone.yaml", f"{tmp_path / 'gone.yaml'}: recipe file not found"),
    ]
    for path, start in cases:
        with pytest.raises(RecipeError) as err:
            load_recipe(path)
        assert str(err.value).startswith(start) and "\n" not in str(err.value), str(err.value)


def test_a_recipe_from_a_mapping_is_checked_like_a_file():
    """``Recipe.from_dict`` is the public builder (field.pt's recorded recipe goes through it)."""
    r = Recipe.from_dict({"name": "x", "semantic": {"dropout": 0.25}}, "here")
    assert r.semantic.dropout == 0.25 and r.geometry == Recipe().geometry
    with pytest.raises(RecipeError, match=r"^here\.semantic\.dropout: 1\.5 is not in \[0, 1\)$"):
        Recipe.from_dict({"semantic": {"dropout": 1.5}}, "here")
