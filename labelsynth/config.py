"""Typed configs: the range markers each component's config uses, and the one builder that turns
a plain mapping (YAML, a run's recorded recipe) into a config, checking every key, type,
choice and range.

Each stage keeps its config dataclass with the stage (``geometry.config.GeometryConfig`` with
``geometry.sdf.SDFConfig`` and ``geometry.background.OuterConfig``,
``semantics.config.SemanticConfig``, ``render.config.RenderConfig``,
``report.config.ReportConfig``), nerfstudio style: one docstring per attribute, numeric fields
typed ``Annotated[int, Range(...)]`` so a value out of its range is a one-line error when the
recipe is read, not a crash (or a silent nonsense run) minutes into training; a config may add
``validate()`` for relations between its fields (raising ``ValueError("field: problem")``).
``recipe.py`` assembles them into a ``Recipe``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from .errors import RecipeError

T = TypeVar("T")


@dataclass(frozen=True)
class Range:
    """The interval a numeric config value must lie in (``None``: unbounded on that side)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False  # low itself excluded
    high_open: bool = False  # high itself excluded

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        if self.high is not None and (value > self.high or (self.high_open and value == self.high)):
            return False
        return True

    def broken_by(self, value: float) -> str:
        """The bound ``value`` breaks, as text (``>= 1``; a count's far ceiling is named only
        when it is the one broken)."""
        if self.high is not None and self.high >= MAX_COUNT and self.low is not None:
            if math.isfinite(value) and value > self.high:
                return f"<= {self.high:.0f}"
            return str(Range(self.low, None, self.low_open))
        return str(self)

    def __str__(self) -> str:
        if self.high is None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        if self.low is None:
            return f"{'<' if self.high_open else '<='} {self.high:g}"
        return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"


# The ranges most fields need: counts of at least one, values above zero, fractions.
MAX_COUNT = 10**9
"""No count, size or number of steps goes beyond this: a larger one is a typo (or an overflow
of the 64-bit integers torch indexes with), refused when the recipe is read."""
Count = Annotated[int, Range(1, MAX_COUNT)]
"""A whole number in 1..10^9 (iterations, samples, sizes)."""
NonNegativeInt = Annotated[int, Range(0, MAX_COUNT)]
Positive = Annotated[float, Range(0.0, low_open=True)]
"""A finite float > 0 (learning rates, weights that must act, sharpness)."""
NonNegative = Annotated[float, Range(0.0)]
UnitInterval = Annotated[float, Range(0.0, 1.0)]
"""A fraction in [0, 1]."""
OpenUnitInterval = Annotated[float, Range(0.0, 1.0, low_open=True)]
"""A fraction in (0, 1]: a scale or share that must keep something."""
Momentum = Annotated[float, Range(0.0, 1.0, high_open=True)]
"""An Adam beta (or a dropout probability) in [0, 1)."""
HashTableLog2 = Annotated[int, Range(4, 24)]
"""log2 of a hash table's size: 16 entries to 16 M (beyond, one level alone takes gigabytes)."""


def range_of(cls: type, name: str) -> Range | None:
    """The ``Range`` declared on field ``name`` of config dataclass ``cls``, if any."""
    tp = get_type_hints(cls, include_extras=True).get(name)
    if get_origin(tp) is Annotated:
        return next((m for m in tp.__metadata__ if isinstance(m, Range)), None)
    return None


def choices_of(cls: type, name: str) -> tuple[str, ...] | None:
    """The allowed values of field ``name`` of config dataclass ``cls``: its Literal's
    arguments, else None (any value of its type)."""
    tp = get_type_hints(cls).get(name)
    if get_origin(tp) is Literal:
        return tuple(get_args(tp))
    return None


def build_config(cls: type[T], data: Any, where: str) -> T:
    """``cls`` (a config dataclass) from a mapping: every key must be a field, every value of
    its field's type, one of its choices and in its range; missing keys keep the defaults.
    Nested configs are built the same way. Any problem is a one-line ``RecipeError`` that
    starts with ``where`` and names the dotted key."""
    if not isinstance(data, dict):
        raise RecipeError(f"{where}: expected a mapping of keys to values, got {_kind(data)}")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise RecipeError(f"{where}: unknown key '{key}' (known: {', '.join(sorted(fields))})")
        kwargs[key] = _value(cls, key, hints[key], value, f"{where}.{key}")
    config = cls(**kwargs)
    _relations(config, where)
    return config


def with_defaults(stored: Any, defaults: Any) -> Any:
    """A recorded config (a plain mapping) with every key it lacks, at any depth, taken from
    ``defaults`` (``dataclasses.asdict`` of the config today): a run recorded before a key existed
    ran as that key's default, so comparing it with today's settings must not see a change."""
    if not (isinstance(stored, dict) and isinstance(defaults, dict)):
        return stored
    return {**defaults, **{key: with_defaults(value, defaults.get(key)) for key, value in stored.items()}}


def _relations(config: Any, where: str) -> None:
    """A config's ``validate()`` (relations between its fields), its ValueError made one line."""
    validate = getattr(config, "validate", None)
    if validate is not None:
        try:
            validate()
        except ValueError as exc:
            raise RecipeError(f"{where}.{exc}") from None


def _value(cls: type, name: str, tp: Any, value: Any, where: str) -> Any:
    if dataclasses.is_dataclass(tp):
        return build_config(tp, value, where)
    value = _coerce(tp, value, where)
    allowed = choices_of(cls, name)
    if allowed is not None and value not in allowed:
        raise RecipeError(f"{where}: '{value}' is not one of {', '.join(allowed)}")
    limits = range_of(cls, name)
    if limits is not None and not limits.contains(value):
        raise RecipeError(f"{where}: {_shown(value)} is not {limits.broken_by(value)}")
    return value


def _coerce(tp: Any, value: Any, where: str) -> Any:
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in {"true", "false", "1", "0", "yes", "no"}:
            return value.lower() in {"true", "1", "yes"}
        raise RecipeError(f"{where}: expected true/false, got {_shown(value)}")
    if tp in (int, float):
        if isinstance(value, bool) or isinstance(value, (dict, list)):
            raise RecipeError(f"{where}: expected {_NUMBER[tp]}, got {_shown(value)}")
        try:
            if tp is int and isinstance(value, float) and not value.is_integer():
                raise ValueError
            number = tp(value)
        except (TypeError, ValueError, OverflowError):
            raise RecipeError(f"{where}: expected {_NUMBER[tp]}, got {_shown(value)}") from None
        if tp is float and not math.isfinite(number):
            raise RecipeError(f"{where}: expected a finite number, got {_shown(value)}")
        return number
    if tp is str or get_origin(tp) is Literal:
        if isinstance(value, (dict, list)) or value is None:
            raise RecipeError(f"{where}: expected a text value, got {_shown(value)}")
        return str(value)
    return value


_NUMBER = {int: "a whole number", float: "a number"}


def _kind(value: Any) -> str:
    return {list: "a list", str: "a text value", type(None): "nothing"}.get(type(value), type(value).__name__)


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
