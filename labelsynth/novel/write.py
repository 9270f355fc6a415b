"""OUT/augment: the novel views written like the real frames, and ``augment.h5``.

``augment.h5`` has labels.h5's datasets and attributes (``LabelsWriter``), so ``LabelsDataset``
and ``labelsynth train`` read it unchanged: first the novel views, then the capture's real
frames copied from ``OUT/labels.h5`` (last, so that ``train``'s validation block of a single
source is real frames). Added datasets: ``novel`` (N,) bool, ``valid`` (N,H,W) bool, ``c2w``
(N,4,4) camera-to-world in the capture's world and OpenGL axes (as transforms.json),
``intrinsics`` (N,8) fx fy cx cy k1 k2 p1 p2; the image size is the datasets' H, W.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..cameras import Camera
from ..capture.images import write_image
from ..capture.masks import write_mask
from ..capture.model import SceneNormalization
from ..classes import ClassMap
from ..export import LabelsWriter, write_masks_png
from ..export.labels_h5 import RESERVED_ATTRS, LabelsReader
from ..outdir import ensure_space

AUGMENT_H5 = "augment.h5"
SUMMARY_JSON = "augment.json"
SUBFOLDERS = ("images", "masks", "valid")


def world_camera(camera: Camera, normalization: SceneNormalization) -> Camera:
    """A unit-cube camera back in the capture's world (rotation and intrinsics unchanged)."""
    c2w = camera.c2w.copy()
    c2w[:3, 3] = normalization.to_world(c2w[:3, 3])
    return camera.with_c2w(c2w)


def _intrinsics(camera: Camera) -> list[float]:
    return [camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2, camera.p1, camera.p2]


class AugmentWriter:
    """Streams novel views into ``folder`` (the partial OUT/augment), then the real frames.

    ``add_view`` per novel view, then ``finish`` (copies the real frames from labels.h5 and
    adds the camera, novel and valid datasets); the caller renames the folder.
    """

    def __init__(self, folder: Path, n_views: int, labels_h5: Path, classes: ClassMap,
                 normalization: SceneNormalization, real_cameras: dict[str, Camera], attrs: dict[str, Any]) -> None:
        self.folder = Path(folder)
        for sub in SUBFOLDERS:
            (self.folder / sub).mkdir(parents=True, exist_ok=True)
        self.labels_h5 = Path(labels_h5)
        self.classes = classes
        self.normalization = normalization
        self.real_cameras = real_cameras
        self.real = LabelsReader(self.labels_h5)  # checked now, its frames copied by ``finish``
        self.real_names = self.real.frame_names
        src = self.real.attrs
        missing = [n for n in self.real_names if n not in real_cameras]
        if missing:
            from . import AugmentError

            raise AugmentError(f"{self.labels_h5}: frames {missing[:3]} are not in the capture (a different capture?)")
        extra = {k: v for k, v in src.items() if k not in RESERVED_ATTRS}
        extra.update(attrs)
        self.path = self.folder / AUGMENT_H5
        self.writer = LabelsWriter(self.path, n_frames=n_views + len(self.real_names), classes=classes,
                                   source=src.get("source"), recipe=src.get("recipe"), attrs=extra)
        self.n_views = n_views
        self.cameras: list[Camera] = []  # world, in file order
        self.valid: list[np.ndarray] = []  # packed bits per frame
        self.names: list[str] = []

    def add_view(self, name: str, view, camera_unit: Camera) -> None:
        """One novel view: images/, masks/ (class ids, 255 = not seen), valid/ (0/255) and augment.h5."""
        if name in self.real_cameras:
            from . import AugmentError

            raise AugmentError(f"novel view name {name!r} is also a real frame's name")
        write_image(self.folder / "images" / f"{name}.png", view.image)
        write_masks_png(self.folder / "masks", name, view.mask, self.classes)
        write_mask(self.folder / "valid" / f"{name}.png", view.valid.astype(np.uint8) * 255, palette=False)
        self.writer.add(name, view.image, view.mask, view.confidence, annotated=False)
        self._record(name, world_camera(camera_unit, self.normalization), view.valid)

    def _record(self, name: str, camera: Camera, valid: np.ndarray) -> None:
        self.names.append(name)
        self.cameras.append(camera)
        self.valid.append(np.packbits(valid.reshape(-1)))

    def finish(self, summary: dict[str, Any]) -> Path:
        """Copy the real frames, close augment.h5, add the extra datasets, write augment.json."""
        with self.real:
            for i, name in enumerate(self.real_names):
                image, mask, confidence = self.real.read(i)
                self.writer.add(name, image, mask, confidence.astype(np.float32), bool(self.real.annotated[i]))
                self._record(name, self.real_cameras[name], np.ones(mask.shape, bool))
        self.writer.close()
        n = len(self.names)
        h, w = self.writer.height, self.writer.width
        ensure_space(self.path, n * (h * w + 256), f"the camera and validity datasets of {self.path.name}")
        with h5py.File(self.path, "a") as f:
            f.create_dataset("novel", data=np.arange(n) < self.n_views)
            f.create_dataset("c2w", data=np.stack([c.c2w for c in self.cameras]))
            f.create_dataset("intrinsics", data=np.array([_intrinsics(c) for c in self.cameras], np.float64))
            valid = f.create_dataset("valid", (n, h, w), bool, chunks=(1, h, w), compression="gzip")
            for i, bits in enumerate(self.valid):
                valid[i] = np.unpackbits(bits, count=h * w).astype(bool).reshape(h, w)
        (self.folder / SUMMARY_JSON).write_text(json.dumps(summary, indent=2, default=float))
        return self.path

    def abort(self) -> None:
        self.real.close()
        self.writer.abort()
