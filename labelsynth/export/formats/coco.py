"""COCO instances with RLE masks, one annotation per class present in a frame::

    annotations/instances.json   images, categories (the class table), annotations, info
    images/<name>.png            the frames (lossless)
    README.txt                   what this is; flagged frames

Each annotation is the region of one class in one frame, as compressed RLE encoded by
pycocotools (``segmentation``, with ``area`` and ``bbox`` from pycocotools too), ``iscrowd`` 0
(COCO-Stuff's convention for region masks), and ``score``: labelsynth's mean confidence over
the region. Category ids are the class ids, background (0) included: pixels no annotation
covers are ignore (below ``--min-confidence``, or unlabelled in the masks), which is how
labelsynth's own capture loader reads the file back. ``info`` names the flagged frames.
Datumaro finds the images beside ``annotations/`` (``images/``).
"""

from __future__ import annotations

import json
from datetime import datetime, timezone

import numpy as np

from ... import __version__
from ...classes import WOUND_BED, ClassMap
from .common import ExportFrame, Sink, checked_mask, layout_of, png_image

INSTANCES = "annotations/instances.json"
IMAGE_DIR = "images"
LAYOUT = layout_of(__doc__)


class CocoWriter:
    """Collects one frame at a time; ``finish`` writes instances.json."""

    layout = LAYOUT
    ignore_text = "left out (no annotation covers the pixel)"

    def __init__(self, sink: Sink, classes: ClassMap) -> None:
        self.sink, self.classes = sink, classes
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        self.names: list[str] = []

    def add(self, frame: ExportFrame, min_confidence: float | None) -> np.ndarray:
        from pycocotools import mask as mask_utils

        mask = checked_mask(frame, self.classes, min_confidence)
        image_id = len(self.images) + 1
        file_name = f"{frame.name}.png"
        self.images.append({"id": image_id, "file_name": file_name, "width": int(mask.shape[1]),
                            "height": int(mask.shape[0])})
        if frame.image is not None:
            self.sink.write(f"{IMAGE_DIR}/{file_name}", png_image(frame.image))
        conf = None if frame.confidence is None else np.asarray(frame.confidence, dtype=np.float32)
        for c in self.classes.classes:
            region = mask == c.id
            if not region.any():
                continue
            rle = mask_utils.encode(np.asfortranarray(region.astype(np.uint8)))
            ann = {
                "id": len(self.annotations) + 1,
                "image_id": image_id,
                "category_id": int(c.id),
                "segmentation": {"size": [int(v) for v in rle["size"]], "counts": rle["counts"].decode("ascii")},
                "area": float(mask_utils.area(rle)),
                "bbox": [float(v) for v in mask_utils.toBbox(rle)],
                "iscrowd": 0,
            }
            if conf is not None:
                ann["score"] = round(float(conf[region].mean()), 4)
            self.annotations.append(ann)
        self.names.append(frame.name)
        return mask

    def finish(self, *, flagged: list[str], min_confidence: float | None, source: str | None) -> None:
        wound_bed = set(self.classes.wound_bed_ids)
        categories = [{"id": int(c.id), "name": c.name, "supercategory": WOUND_BED if c.id in wound_bed else c.name,
                       "color": [int(v) for v in c.color]} for c in self.classes.classes]
        info = {
            "description": "labelsynth export" + (f" of {source}" if source else ""),
            "version": __version__,
            "contributor": "labelsynth",
            "date_created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "flagged_frames": list(flagged),
            "min_confidence": min_confidence,
            "ignore": "pixels no annotation covers",
            "score": "mean labelsynth confidence over the annotation's pixels",
        }
        doc = {"info": info, "licenses": [], "images": self.images, "annotations": self.annotations,
               "categories": categories}
        self.sink.write(INSTANCES, json.dumps(doc))
