"""Class ids, names, colours and the wound-bed grouping (the contract in the README, "The capture folder").

A capture may carry a ``classes.json`` that replaces the default wound table; a two-class
table (background + object) turns labelsynth into a foreground-mask tool.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ClassMapError

IGNORE_ID = 255
WOUND_BED = "wound_bed"  # the aggregate of the wound-bed classes (a reserved class name)
BACKGROUND_ID = 0
CLASSES_FILE = "classes.json"  # a capture's optional class table


@dataclass(frozen=True)
class ClassInfo:
    id: int
    name: str
    color: tuple[int, int, int]
    wound_bed: bool = False


DEFAULT_CLASSES: tuple[ClassInfo, ...] = (
    ClassInfo(0, "background", (0, 0, 0), False),
    ClassInfo(1, "granulation", (200, 40, 40), True),
    ClassInfo(2, "slough", (230, 210, 60), True),
    ClassInfo(3, "necrotic", (40, 30, 30), True),
    ClassInfo(4, "epithelial", (240, 150, 200), True),
    ClassInfo(5, "unknown", (150, 60, 200), True),
)


@dataclass(frozen=True)
class ClassMap:
    """The classes of one capture.

    Ids need not be contiguous in files, but the field predicts ``len(classes)`` logits in
    the order of ``classes``; ``index_of`` / ``ids`` translate between the two.
    """

    classes: tuple[ClassInfo, ...] = field(default_factory=lambda: DEFAULT_CLASSES)

    def __post_init__(self) -> None:
        ids = [c.id for c in self.classes]
        if len(ids) < 2:
            raise ClassMapError("a class map needs at least two classes (background and one more)")
        if len(set(ids)) != len(ids):
            raise ClassMapError(f"duplicate class ids: {ids}")
        if any(not 0 <= i < IGNORE_ID for i in ids):
            raise ClassMapError(f"class ids must be in 0..254 (255 means ignore): {ids}")
        if BACKGROUND_ID not in ids:
            raise ClassMapError("class id 0 (background) is required")

    # --- construction -------------------------------------------------------------------
    @classmethod
    def default(cls) -> "ClassMap":
        return cls(DEFAULT_CLASSES)

    @classmethod
    def from_dict(cls, data: object, where: str = "class table", what: str = "class table") -> "ClassMap":
        """The one parser of a class table: ``{"classes": [{"id", "name", "color"?, "wound_bed"?}, ...]}``
        or the bare list, as ``to_json`` writes it (classes.json, labels.h5's ``classes_json``,
        field.pt). A missing colour gets a stable fallback. ``where`` names the source and
        ``what`` the kind of table in the one-line ``ClassMapError``."""
        try:
            entries = data["classes"] if isinstance(data, dict) else data  # type: ignore[index]
            if not isinstance(entries, (list, tuple)):
                raise TypeError("expected a list of classes")
            classes = tuple(
                ClassInfo(
                    id=int(e["id"]),
                    name=str(e["name"]),
                    color=_color(e.get("color"), int(e["id"])),
                    wound_bed=bool(e.get("wound_bed", False)),
                )
                for e in entries
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ClassMapError(f"{where}: not a valid {what} ({exc})") from exc
        try:
            return cls(classes)
        except ClassMapError as exc:
            raise ClassMapError(f"{where}: {exc}") from exc

    @classmethod
    def from_file(cls, path: str | Path) -> "ClassMap":
        """A ``classes.json`` file (``from_dict``); errors name the file."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ClassMapError(f"{path}: not a valid classes.json ({exc})") from exc
        return cls.from_dict(data, str(path), CLASSES_FILE)

    from_json = from_file  # the older name, kept for callers

    @classmethod
    def of_capture(cls, root: str | Path, fallback: "ClassMap | None" = None) -> "ClassMap":
        """A capture's class table: ``ROOT/classes.json`` if present, else ``fallback`` (a
        layout's own table, e.g. NeuS's background/object), else the default wound table."""
        path = Path(root) / CLASSES_FILE
        if path.is_file():
            return cls.from_file(path)
        return fallback or cls.default()

    def to_json(self) -> dict:
        return {
            "classes": [
                {"id": c.id, "name": c.name, "color": list(c.color), "wound_bed": c.wound_bed}
                for c in self.classes
            ]
        }

    # --- lookups ------------------------------------------------------------------------
    @property
    def ids(self) -> np.ndarray:
        return np.array([c.id for c in self.classes], dtype=np.int64)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.classes]

    @property
    def colors(self) -> np.ndarray:
        return np.array([c.color for c in self.classes], dtype=np.uint8)

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def background_index(self) -> int:
        return self.index_of(BACKGROUND_ID)

    @property
    def wound_bed_indices(self) -> list[int]:
        """Indices (into ``classes``) of the classes aggregated into the wound bed.

        A table without any ``wound_bed`` flag (e.g. background + object) treats every
        non-background class as foreground, so the binary output still means something.
        """
        flagged = [i for i, c in enumerate(self.classes) if c.wound_bed]
        if flagged:
            return flagged
        return [i for i, c in enumerate(self.classes) if c.id != BACKGROUND_ID]

    @property
    def wound_bed_ids(self) -> list[int]:
        return [self.classes[i].id for i in self.wound_bed_indices]

    def index_of(self, class_id: int) -> int:
        for i, c in enumerate(self.classes):
            if c.id == class_id:
                return i
        raise KeyError(class_id)

    def name_of(self, class_id: int) -> str:
        return self.classes[self.index_of(class_id)].name

    def id_to_index_lut(self) -> np.ndarray:
        """256-entry table: class id -> index, ignore (and unknown ids) -> -1."""
        lut = np.full(256, -1, dtype=np.int64)
        for i, c in enumerate(self.classes):
            lut[c.id] = i
        return lut

    def index_to_id_lut(self) -> np.ndarray:
        return self.ids.astype(np.uint8)

    def palette(self) -> list[int]:
        """A 768-entry PIL/PNG palette: class colours at their ids, grey for ignore."""
        pal = np.zeros((256, 3), dtype=np.uint8)
        for c in self.classes:
            pal[c.id] = c.color
        pal[IGNORE_ID] = (128, 128, 128)
        return pal.reshape(-1).tolist()

    def colorize(self, mask: np.ndarray) -> np.ndarray:
        """Class-id mask (H,W) -> RGB image (H,W,3); ignore pixels grey."""
        pal = np.asarray(self.palette(), dtype=np.uint8).reshape(256, 3)
        return pal[mask]


def _color(value: object, class_id: int) -> tuple[int, int, int]:
    if value is None:
        return _fallback_color(class_id)
    rgb = tuple(int(v) for v in value)  # type: ignore[union-attr]
    if len(rgb) != 3 or not all(0 <= v <= 255 for v in rgb):
        raise ValueError(f"colour of class {class_id} must be r,g,b in 0..255, got {list(rgb)}")
    return rgb  # type: ignore[return-value]


def _fallback_color(class_id: int) -> tuple[int, int, int]:
    rng = np.random.default_rng(class_id + 7)
    return tuple(int(v) for v in rng.integers(40, 255, size=3))


def parse_id_pairs(text: str | Mapping, value: Callable[[str], object], option: str, shape: str, example: str,
                   error: type[Exception]) -> list[tuple[int, object]]:
    """``"a:b,c:d"`` (or a mapping) -> [(a, value(b)), ...]: the command-line form of per-class
    values (``segment --id-map``, ``train --class-weights``); a malformed item raises ``error``
    with one line naming the option."""
    if isinstance(text, Mapping):
        return [(int(k), value(v)) for k, v in text.items()]
    pairs = []
    for item in text.replace(" ", "").split(","):
        if not item:
            continue
        key, sep, val = item.partition(":")
        try:
            if not sep:
                raise ValueError
            pairs.append((int(key), value(val)))
        except ValueError:
            raise error(f"{option} {text!r}: expected {shape} pairs, e.g. {example}") from None
    return pairs
