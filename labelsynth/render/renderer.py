"""Masks from a fitted field: its surface cast into each camera, the head read at the hits.

``FieldRenderer`` owns what rendering caches, and nothing else: the surface mesh (marching
cubes, once), its ray casters, the geometry features at the render mesh's vertices (the
geometry is frozen, so once for every head) and the class logits there of the head last asked
for. It renders with the field's own head or with any other head of the same shape (the
report's leave-one-out heads), never changing the field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from ..cameras import Camera
from ..errors import LabelsynthError
from ..semantics.head import SemanticHead, decide_labels
from .config import RenderConfig
from .field import FittedField, SurfaceMesh
from .support import SurfaceSupport
from .surface import SurfaceCaster, extract_mesh


@dataclass
class FrameRender:
    """Per-pixel results for one frame at full resolution."""

    mask: np.ndarray  # (H, W) uint8 class ids
    confidence: np.ndarray  # (H, W) float32 probability of the label written
    probabilities: np.ndarray | None = None  # (H, W, C) float16 when asked for
    hit: np.ndarray | None = None  # (H, W) bool: the ray met the surface
    points: np.ndarray | None = None  # (H, W, 3) unit-cube hit points (valid where hit)
    unseen: np.ndarray | None = None  # (H, W) bool: hit surface no teaching frame saw (render with support=)

    @property
    def unseen_share(self) -> float | None:
        """Share of the frame's pixels whose surface no teaching frame saw (None: not asked)."""
        return None if self.unseen is None else float(self.unseen.mean())


class FieldRenderer:
    """Renders one ``FittedField`` (see the module's docstring for what it caches)."""

    def __init__(self, field: FittedField) -> None:
        self.field = field
        self._mesh: trimesh.Trimesh | None = None
        self._caster: SurfaceCaster | None = None
        self._render_caster: SurfaceCaster | None = None
        self._vertex_logits: tuple | None = None  # (head, logits (V, C), known (V,))
        self._vertex_features: tuple | None = None  # (features (V, F), known (V,))

    @property
    def config(self) -> RenderConfig:
        return self.field.recipe.render

    # --- surface --------------------------------------------------------------------------
    def mesh(self) -> trimesh.Trimesh:
        """The surface in unit-cube coordinates (cached)."""
        if self._mesh is None:
            stored = self._stored_surface()
            if stored is not None:
                self._mesh = stored.mesh()
            else:
                self._mesh = extract_mesh(self.field.sdf.sdf_batched, self.config.mesh_resolution, self.field.device)
            self._caster = None
        return self._mesh

    def _stored_surface(self) -> SurfaceMesh | None:
        """The field's stored surface when it was extracted as this recipe asks (else None)."""
        stored = self.field.surface
        return stored if stored is not None and stored.resolution == self.config.mesh_resolution else None

    def field_with_surface(self) -> FittedField:
        """The field with the surface this renderer renders (``FittedField.surface``), for
        saving: whoever loads it renders without extracting it again."""
        if self._stored_surface() is not None:
            return self.field
        return dataclasses.replace(self.field, surface=SurfaceMesh.of(self.mesh(), self.config.mesh_resolution))

    def caster(self) -> SurfaceCaster:
        if self._caster is None:
            self._caster = SurfaceCaster(self.mesh())
        return self._caster

    def render_caster(self) -> SurfaceCaster:
        """The surface subdivided ``render.subdivide`` times, so vertices lie ~1-2 px apart."""
        if self._render_caster is None:
            mesh = self.mesh()
            for _ in range(self.config.subdivide if len(mesh.faces) else 0):
                mesh = mesh.subdivide()
            self._render_caster = SurfaceCaster(mesh)
        return self._render_caster

    # --- the head -------------------------------------------------------------------------
    def _head(self, head: SemanticHead | None) -> SemanticHead:
        head = self.field.head if head is None else head
        if head is None:
            raise LabelsynthError("the field has no semantic head (geometry only): run the semantic stage first")
        return head

    def vertex_logits(self, head: SemanticHead | None = None, vertices: np.ndarray | None = None) -> torch.Tensor:
        """Class logits of ``head`` (default: the field's) at the render mesh's vertices, (V, C).

        Evaluated lazily: only the ``vertices`` asked for (all when None) that this head has
        not seen yet, so a frame costs the vertices it sees, and the report's leave-one-out
        heads, each rendering one frame, do not pay for the whole mesh. Rows never asked for
        stay zero. The geometry features at the vertices are cached across heads.
        """
        head = self._head(head)
        n = len(self.render_caster().mesh.vertices)
        if self._vertex_logits is None or self._vertex_logits[0] is not head:
            logits = torch.zeros(n, self.field.classes.num_classes, device=self.field.device)
            self._vertex_logits = (head, logits, np.zeros(n, dtype=bool))
        _, logits, known = self._vertex_logits
        if vertices is not None and known.all():
            return logits
        wanted = np.arange(n) if vertices is None else np.unique(vertices)
        todo = wanted[~known[wanted]]
        if len(todo):
            logits[torch.from_numpy(todo).to(self.field.device)] = self._head_at_vertices(head, todo)
            known[todo] = True
        return logits

    @torch.no_grad()
    def _head_at_vertices(self, head: SemanticHead, todo: np.ndarray) -> torch.Tensor:
        """``head`` at render-mesh vertices ``todo``, their geometry features computed once."""
        sdf, device = self.field.sdf, self.field.device
        verts = self.render_caster().mesh.vertices
        n, fdim = len(verts), sdf.cfg.feature_dim
        if self._vertex_features is None:
            self._vertex_features = (torch.zeros(n, fdim, device=device), np.zeros(n, dtype=bool))
        feats, known = self._vertex_features
        new = todo[~known[todo]]
        chunk = self.config.chunk
        for s in range(0, len(new), chunk):
            idx = new[s : s + chunk]
            pts = torch.as_tensor(np.asarray(verts[idx], dtype=np.float32), device=device)
            feats[torch.from_numpy(idx).to(device)] = sdf.get_sdf(pts)[1]
        known[new] = True
        head.eval()
        out = []
        for s in range(0, len(todo), chunk):
            idx = todo[s : s + chunk]
            pts = torch.as_tensor(np.asarray(verts[idx], dtype=np.float32), device=device)
            out.append(head(feats[torch.from_numpy(idx).to(device)], pts))
        return torch.cat(out)

    @torch.no_grad()
    def logits_at(self, points: np.ndarray | torch.Tensor, head: SemanticHead | None = None) -> torch.Tensor:
        """Class logits (N, C) of ``head`` (default: the field's) at unit-cube points (dropout off)."""
        head = self._head(head)
        head.eval()
        device = self.field.device
        pts = torch.as_tensor(np.asarray(points, dtype=np.float32), device=device)
        out = []
        chunk = self.config.chunk
        for s in range(0, len(pts), chunk):
            p = pts[s : s + chunk]
            _, feature = self.field.sdf.get_sdf(p)
            out.append(head(feature, p))
        if not out:
            return torch.zeros(0, self.field.classes.num_classes, device=device)
        return torch.cat(out)

    def support(self, cameras: list[Camera], masks: list[np.ndarray]) -> SurfaceSupport:
        """What the frames that taught the head (unit-cube cameras, their masks) saw of this
        field's surface: pass it to ``render(..., support=)``."""
        return SurfaceSupport(self.render_caster(), cameras, masks, self.config)

    # --- frames ---------------------------------------------------------------------------
    def render(self, camera_unit: Camera, head: SemanticHead | None = None, *, keep_probabilities: bool = False,
               keep_points: bool = False, support: SurfaceSupport | None = None) -> FrameRender:
        """Mask and confidence for every pixel of a camera given in unit-cube coordinates, by
        ``head`` (default: the field's). With ``support`` (``self.support(...)``), pixels whose
        surface no teaching frame saw are marked (``FrameRender.unseen``) and their confidence
        capped at ``render.unseen_confidence``."""
        classes, cfg = self.field.classes, self.config
        head = self._head(head)
        h, w = camera_unit.height, camera_unit.width
        caster = self.render_caster()
        hit, points, faces, bary = caster.cast(*camera_unit.rays())
        c = classes.num_classes
        probs = np.zeros((h * w, c), dtype=np.float32)
        probs[:, classes.background_index] = 1.0
        if hit.any():
            if cfg.per_pixel:
                logits = self.logits_at(points[hit], head)
            else:
                # Logits at the hit = barycentric blend of the logits at the triangle's vertices:
                # one head evaluation per vertex instead of one per pixel of every frame.
                tri = np.asarray(caster.mesh.faces)[faces[hit]]
                vl = self.vertex_logits(head, tri.ravel())
                logits = (vl[torch.from_numpy(tri).to(vl.device)] * torch.from_numpy(bary[hit]).to(vl)[..., None]).sum(1)
            probs[hit] = torch.softmax(logits, dim=-1).cpu().numpy()
        index = decide_labels(probs, classes, cfg.decision)
        mask = classes.index_to_id_lut()[index].reshape(h, w)
        conf = np.take_along_axis(probs, index[:, None], -1)[:, 0].reshape(h, w)  # of the label written
        unseen = None
        if support is not None:
            unseen = support.unseen(hit, points, faces).reshape(h, w)
            conf = np.where(unseen, np.minimum(conf, cfg.unseen_confidence), conf)
        return FrameRender(
            mask=mask,
            confidence=conf,
            probabilities=probs.reshape(h, w, c).astype(np.float16) if keep_probabilities else None,
            hit=hit.reshape(h, w),
            points=points.reshape(h, w, 3) if keep_points else None,
            unseen=unseen,
        )
