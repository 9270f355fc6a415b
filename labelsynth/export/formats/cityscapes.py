"""Cityscapes-style folders: label-id PNGs named after their frames, as torchvision, mmsegmentation
and Datumaro find them::

    leftImg8bit/<split>/<city>/<name>_leftImg8bit.png         the frames
    gtFine/<split>/<city>/<name>_gtFine_labelIds.png          class ids, 255 = ignore
    gtFine/<split>/<city>/<name>_gtFine_labelTrainIds.png     the same ids (labelsynth's ids are train ids)
    gtFine/<split>/<city>/<name>_gtFine_color.png             the class colours, to look at
    label_colors.txt                                          "r g b name" per id (Datumaro's label map)
    README.txt                                                what this is; flagged frames

``<split>`` is ``train`` and ``<city>`` the capture's name. Cityscapes' own labelIds number
its 34 classes and keep trainIds for training with 255 as ignore; labelsynth has one table
whose ids already play the train ids' part, so both files hold them (torchvision reads
``labelIds``, mmsegmentation and Datumaro ``labelTrainIds``). label_colors.txt lists every id
from 0 to the largest, so a reader that counts lines finds each class at its id; ids the
table skips are named ``unused_<id>``.
"""

from __future__ import annotations

import re

import numpy as np

from ...capture.masks import encode_mask_png
from ...classes import ClassMap
from .common import ExportFrame, Sink, checked_mask, layout_of, png_image

SPLIT = "train"
LABEL_COLORS = "label_colors.txt"
UNUSED_COLOR = (128, 128, 128)
LAYOUT = layout_of(__doc__)


def city_name(name: str | None) -> str:
    """A folder name for the capture (Cityscapes' city level): letters, digits, - and _ only."""
    safe = re.sub(r"[^A-Za-z0-9_-]+", "_", name or "").strip("_")
    return safe or "capture"


class CityscapesWriter:
    """Writes frames one at a time; ``finish`` writes label_colors.txt."""

    layout = LAYOUT
    ignore_text = "255 in *_labelIds.png and *_labelTrainIds.png"

    def __init__(self, sink: Sink, classes: ClassMap, city: str | None = None) -> None:
        self.sink, self.classes = sink, classes
        self.city = city_name(city)
        self.names: list[str] = []

    def add(self, frame: ExportFrame, min_confidence: float | None) -> np.ndarray:
        import cv2

        mask = checked_mask(frame, self.classes, min_confidence)
        where = f"{SPLIT}/{self.city}/{frame.name}"
        ids = encode_mask_png(mask)
        self.sink.write(f"gtFine/{where}_gtFine_labelIds.png", ids)
        self.sink.write(f"gtFine/{where}_gtFine_labelTrainIds.png", ids)
        ok, color = cv2.imencode(".png", np.ascontiguousarray(self.classes.colorize(mask)[:, :, ::-1]))
        self.sink.write(f"gtFine/{where}_gtFine_color.png", color.tobytes())
        if frame.image is not None:
            self.sink.write(f"leftImg8bit/{where}_leftImg8bit.png", png_image(frame.image))
        self.names.append(frame.name)
        return mask

    def finish(self, **_: object) -> None:
        by_id = {c.id: c for c in self.classes.classes}
        lines = []
        for i in range(int(self.classes.ids.max()) + 1):
            c = by_id.get(i)
            rgb, name = (c.color, re.sub(r"\s+", "_", c.name)) if c else (UNUSED_COLOR, f"unused_{i}")
            lines.append(f"{rgb[0]} {rgb[1]} {rgb[2]} {name}")
        self.sink.write(LABEL_COLORS, "\n".join(lines) + "\n")
