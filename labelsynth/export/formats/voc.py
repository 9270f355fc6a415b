"""Pascal VOC segmentation, as CVAT's "Segmentation mask 1.1" reads and writes it (a folder for
``voc``, the same files zipped for ``cvat``)::

    labelmap.txt                       name:r,g,b:: per class, in the class table's order
    ImageSets/Segmentation/default.txt the exported frames, one name a line
    SegmentationClass/<name>.png       class masks: palette PNGs, index = class id, colour = the class's
    SegmentationObject/<name>.png      one instance per class present (VOC instance colours)
    JPEGImages/<name>.png              the frames (lossless)
    README.txt                         what this is; flagged frames

The layout is CVAT's documented one (docs.cvat.ai, "Segmentation Mask"); CVAT imports it with
Datumaro's VOC reader, which decodes both mask folders by colour. Ignore (255) is VOC's void:
colour 224,224,192, declared in labelmap.txt as ``ignored`` (Datumaro's name for VOC's 255)
when the export has any; in SegmentationObject it is, like background, instance 0, so CVAT
makes no shape of it. Each class present in a frame is one instance, so CVAT shows one mask
per class per frame to edit.
"""

from __future__ import annotations

import numpy as np

from ...capture.masks import IGNORE_LABEL_NAMES, VOC_BOUNDARY_COLOR, encode_mask_png, labelmap_text
from ...classes import BACKGROUND_ID, IGNORE_ID, ClassMap
from ..dataset import ExportError
from .common import ExportFrame, Sink, checked_mask, layout_of, distinct_colors, png_image

LABELMAP = "labelmap.txt"
IMAGE_SET = "ImageSets/Segmentation/default.txt"
CLASS_DIR = "SegmentationClass"
OBJECT_DIR = "SegmentationObject"
IMAGE_DIR = "JPEGImages"  # VOC's name; the frames in it are PNG (Datumaro and CVAT read any image type)
IGNORE_LABEL = IGNORE_LABEL_NAMES[0]
LAYOUT = layout_of(__doc__)


def voc_colormap(n: int = 256) -> np.ndarray:
    """Pascal VOC's colour map (n, 3): index i's bits spread over r, g, b from the high bit down;
    VOC instance masks and VOC's own class colours use it (index 255 is its void colour)."""
    cmap = np.zeros((n, 3), dtype=np.uint8)
    for i in range(n):
        c, r, g, b = i, 0, 0, 0
        for j in range(8):
            r |= ((c >> 0) & 1) << (7 - j)
            g |= ((c >> 1) & 1) << (7 - j)
            b |= ((c >> 2) & 1) << (7 - j)
            c >>= 3
        cmap[i] = (r, g, b)
    return cmap


def check_classes(classes: ClassMap) -> None:
    """The class table must be writable as VOC colours and a labelmap.txt."""
    distinct_colors(classes, [(VOC_BOUNDARY_COLOR, "VOC's void (ignore) colour")])
    for c in classes.classes:
        if ":" in c.name or "\n" in c.name:
            raise ExportError(f"class table: the name {c.name!r} cannot be written to labelmap.txt (':' separates its fields)")
        if c.name.lower() in IGNORE_LABEL_NAMES:
            raise ExportError(f"class table: the class name {c.name!r} is VOC's name for ignore; rename the class")


class VocWriter:
    """Writes frames one at a time into a sink (folder or zip); ``finish`` adds the lists."""

    def __init__(self, sink: Sink, classes: ClassMap) -> None:
        check_classes(classes)
        self.sink, self.classes = sink, classes
        palette = np.zeros((256, 3), dtype=np.uint8)
        palette[classes.ids] = classes.colors
        palette[IGNORE_ID] = VOC_BOUNDARY_COLOR
        self.class_palette = palette.reshape(-1).tolist()
        self.object_palette = voc_colormap().reshape(-1).tolist()
        self.names: list[str] = []
        self.any_ignore = False

    def add(self, frame: ExportFrame, min_confidence: float | None) -> np.ndarray:
        mask = checked_mask(frame, self.classes, min_confidence)
        self.sink.write(f"{CLASS_DIR}/{frame.name}.png", encode_mask_png(mask, self.class_palette))
        present = [c.id for c in self.classes.classes if c.id != BACKGROUND_ID and (mask == c.id).any()]
        lut = np.zeros(256, dtype=np.uint8)  # background and ignore: instance 0 (no shape)
        for instance, class_id in enumerate(present, start=1):
            lut[class_id] = instance
        self.sink.write(f"{OBJECT_DIR}/{frame.name}.png", encode_mask_png(lut[mask], self.object_palette))
        if frame.image is not None:
            self.sink.write(f"{IMAGE_DIR}/{frame.name}.png", png_image(frame.image))
        self.any_ignore |= bool((mask == IGNORE_ID).any())
        self.names.append(frame.name)
        return mask

    def finish(self, **_: object) -> None:
        entries = [(c.name, tuple(int(v) for v in c.color)) for c in self.classes.classes]
        if self.any_ignore:
            entries.append((IGNORE_LABEL, VOC_BOUNDARY_COLOR))
        self.sink.write(LABELMAP, labelmap_text(entries))  # type: ignore[arg-type]
        self.sink.write(IMAGE_SET, "".join(f"{n}\n" for n in self.names))

    layout = LAYOUT
    ignore_text = (f"255 in {CLASS_DIR}/ (colour {','.join(map(str, VOC_BOUNDARY_COLOR))}, "
                   f"'{IGNORE_LABEL}' in {LABELMAP}); no instance in {OBJECT_DIR}/")
