"""Which surface the teaching frames saw: the support behind each rendered label.

The semantic head paints every point of the surface, but it only learnt where a frame with a
mask (an expert annotation, or a prediction where those teach) looked. Surface no teaching frame
saw (the table in front of the object, the far side, the underside) gets whatever class its
neighbours' features suggest: a guess, not a label. ``SurfaceSupport`` tells the two apart by
shadow mapping: each teaching frame's depth map is cast once from the fitted surface; a surface
point is *seen* by a frame when it projects inside the frame onto a pixel its mask labels (not
ignore), faces the camera, and lies no deeper than the frame's own first hit there (within
``render.support_tolerance_px`` pixels' footprint). ``FieldRenderer.render(..., support=)``
caps the confidence of every pixel whose surface no teaching frame saw at
``render.unseen_confidence``, so labels.h5 and the exports' ``--min-confidence`` treat it as
the guess it is, and reports the share of each frame's pixels that is (``FrameRender.unseen``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera
from ..classes import IGNORE_ID
from .config import RenderConfig
from .surface import SurfaceCaster


@dataclass
class _Teacher:
    camera: Camera  # at the support's scale
    depth: np.ndarray  # (H, W) float64 view-axis depth of the first hit; inf where the ray missed
    labelled: np.ndarray  # (H, W) bool: the mask labels this pixel (not ignore)


class SurfaceSupport:
    """Shadow maps of the frames that taught the head, cast on one surface (the renderer's)."""

    def __init__(self, caster: SurfaceCaster, cameras: Sequence[Camera], masks: Sequence[np.ndarray],
                 config: RenderConfig) -> None:
        if len(cameras) != len(masks):
            raise ValueError(f"{len(cameras)} cameras but {len(masks)} masks")
        self.config = config
        self._normals = np.asarray(caster.mesh.face_normals) if not caster.empty else np.zeros((0, 3))
        self.teachers: list[_Teacher] = []
        for cam, mask in zip(cameras, masks):
            scale = min(1.0, config.support_size / max(cam.width, cam.height))
            small = cam.scaled(scale) if scale < 1.0 else cam
            hit, points, _, _ = caster.cast(*small.rays())
            _, depth = small.project(points)
            depth = np.where(hit, depth, np.inf).reshape(small.height, small.width)
            labelled = np.asarray(mask) != IGNORE_ID
            if labelled.shape != (small.height, small.width):
                labelled = cv2.resize(labelled.astype(np.uint8), (small.width, small.height),
                                      interpolation=cv2.INTER_NEAREST) > 0
            self.teachers.append(_Teacher(small, depth, labelled))

    def unseen(self, hit: np.ndarray, points: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(N,) bool over a cast's rays (``SurfaceCaster.cast`` of the same surface): the ray hit
        surface no teaching frame saw."""
        unseen = np.zeros(len(hit), dtype=bool)
        unseen[hit] = ~self.seen(points[hit], faces[hit])
        return unseen

    def seen(self, points: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: surface points (unit cube) at least one teaching frame saw. ``faces`` (the
        caster's face index of each point) adds the facing test (a thin sheet's back is unseen)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        seen = np.zeros(len(points), dtype=bool)
        tol_px = self.config.support_tolerance_px
        for t in self.teachers:
            todo = np.flatnonzero(~seen)
            if not len(todo):
                break
            cam, p = t.camera, points[todo]
            uv, z = cam.project(p)
            u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            inside = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
            ok = np.zeros(len(todo), dtype=bool)
            ui, vi, zi = u[inside], v[inside], z[inside]
            # a pixel's footprint at depth z is z / f: the tolerance grows with distance
            tol = tol_px * zi / min(cam.fx, cam.fy)
            ok[inside] = t.labelled[vi, ui] & (zi <= t.depth[vi, ui] + tol)
            if faces is not None and len(self._normals):
                f = np.asarray(faces)[todo]
                towards = np.einsum("nd,nd->n", self._normals[np.clip(f, 0, None)], cam.center - p)
                ok &= (f < 0) | (towards > 0)
            seen[todo[ok]] = True
        return seen
