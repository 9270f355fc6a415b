"""The in-memory capture: frames, cameras, lazily loaded images and masks, the scene box."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..classes import ClassMap
from ..errors import CaptureError  # noqa: F401  (re-exported)


@dataclass(frozen=True)
class SceneNormalization:
    """Maps world coordinates to the unit cube [-1, 1]^3 the field lives in.

    ``x_unit = (x_world - center) / scale``. The region of interest (ROI) is the cube of
    half-size ``scale`` around ``center``; see ``capture.normalize.region_of_interest``
    for how it is chosen (a NeuS capture brings its own: its unit sphere, ``capture.neus``). Outputs (meshes, areas) are mapped back with ``to_world``.
    """

    center: np.ndarray  # (3,)
    scale: float

    def to_unit(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - self.center) / self.scale

    def to_world(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) * self.scale + self.center

    def camera_to_unit(self, camera: Camera) -> Camera:
        c2w = camera.c2w.copy()
        c2w[:3, 3] = self.to_unit(c2w[:3, 3])
        return camera.with_c2w(c2w)

    def to_json(self) -> dict:
        return {"center": [float(v) for v in self.center], "scale": float(self.scale)}

    @classmethod
    def from_json(cls, data: dict) -> "SceneNormalization":
        return cls(center=np.asarray(data["center"], dtype=np.float64), scale=float(data["scale"]))


@dataclass
class Frame:
    """One frame of the capture. Pixel data is read on demand, never cached here."""

    name: str  # image stem: the key shared by images/, annotations/, predictions/, masks/
    image_path: Path
    camera: Camera  # world coordinates, as in the capture's files
    annotation_path: Path | None = None
    prediction_path: Path | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.camera.width, self.camera.height


@dataclass
class Capture:
    """A capture folder as read (never written) by labelsynth."""

    root: Path
    frames: list[Frame]
    classes: ClassMap = field(default_factory=ClassMap.default)
    normalization: SceneNormalization | None = None
    points: np.ndarray | None = None  # (P,3) sparse SfM points in world coordinates, if any
    # Colour -> class id table for RGB masks (from classes.json colours or a CVAT labelmap.txt).
    color_table: dict[tuple[int, int, int], int] | None = None
    white_background: bool = False  # RGBA images are composited on white (Blender scenes) or black
    source: str = "transforms.json"
    # Mask folder -> how its pixels are coded (``capture.masks`` kinds); folders not listed hold
    # class-id / palette / colour masks ("classes"). A NeuS capture's mask/ is "binary".
    mask_kinds: dict[Path, str] = field(default_factory=dict)
    # Masks decoded by ``capture.check.check_capture``, by path: the training stages take them
    # from here instead of decoding every file a second time. Images are never kept (too big).
    mask_cache: dict[Path, tuple[tuple[int, int], np.ndarray]] = field(default_factory=dict, repr=False, compare=False)
    mask_cache_limit: int = field(default=512 * 2**20, repr=False, compare=False)  # bytes

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.frames]

    @property
    def has_annotations(self) -> bool:
        return any(f.annotation_path is not None for f in self.frames)

    @property
    def has_predictions(self) -> bool:
        return any(f.prediction_path is not None for f in self.frames)

    def frame(self, name: str) -> Frame:
        for f in self.frames:
            if f.name == name:
                return f
        raise KeyError(name)

    def mask_kind(self, path: str | Path) -> str:
        """How the mask file ``path`` is coded: its folder's kind, else "classes"."""
        return self.mask_kinds.get(Path(path).parent, "classes")

    # Pixel loaders: implemented in capture.images / capture.masks, bound here for convenience.
    def load_image(self, index: int) -> np.ndarray:
        """(H,W,3) uint8 RGB of frame ``index`` (alpha composited)."""
        from .images import read_image

        return read_image(self.frames[index].image_path, self.frames[index].size, self.white_background)

    def load_annotation(self, index: int) -> np.ndarray | None:
        """(H,W) uint8 class ids of the expert mask, 255 = ignore; None if not annotated."""
        f = self.frames[index]
        return None if f.annotation_path is None else self.read_mask_file(f.annotation_path, f.size)

    def load_prediction(self, index: int) -> np.ndarray | None:
        """(H,W) uint8 class ids of the automatic mask; None if there is none."""
        f = self.frames[index]
        return None if f.prediction_path is None else self.read_mask_file(f.prediction_path, f.size)

    def read_mask_file(self, path: str | Path, size: tuple[int, int] | None) -> np.ndarray:
        """A mask with this capture's classes and colours: from the cache when the check has
        decoded it already and the file has not changed since, else from the file (a copy
        either way, so callers may modify it)."""
        from . import masks  # the module, not the function: tests patch masks.read_mask

        path = Path(path)
        hit = self.mask_cache.get(path)
        if hit is not None:
            stamp, mask = hit
            if file_stamp(path) == stamp and (size is None or mask.shape == (int(size[1]), int(size[0]))):
                return mask.copy()
        return masks.read_mask(path, size, self.classes, self.color_table, kind=self.mask_kind(path))

    def cache_mask(self, path: str | Path, mask: np.ndarray, stamp: tuple[int, int] | None = None) -> bool:
        """Keep a decoded mask for ``read_mask_file`` while the cache stays under
        ``mask_cache_limit`` bytes; returns whether it was kept. ``stamp`` = the file's
        (mtime_ns, size) when it was read (taken now if not given)."""
        path = Path(path)
        stamp = stamp if stamp is not None else file_stamp(path)
        used = sum(m.nbytes for p, (_, m) in self.mask_cache.items() if p != path)
        if stamp is None or used + mask.nbytes > self.mask_cache_limit:
            return False
        self.mask_cache[path] = (stamp, mask)
        return True

    def unit_cameras(self) -> list[Camera]:
        """Cameras in the normalised unit-cube coordinates the field uses."""
        assert self.normalization is not None
        return [self.normalization.camera_to_unit(f.camera) for f in self.frames]


def file_stamp(path: Path) -> tuple[int, int] | None:
    """(mtime_ns, size) of a file, to notice one that changed after it was cached; for a mask
    inside an annotation export (``capture.archives``), the export file's."""
    try:
        st = os.stat(path)
    except OSError:
        from .archives import container_of

        where = container_of(path)
        if where is None:
            return None
        try:
            st = os.stat(where[0])
        except OSError:
            return None
    return st.st_mtime_ns, st.st_size
