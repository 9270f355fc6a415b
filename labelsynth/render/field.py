"""A fitted semantic field: geometry + semantic head + what is needed to render and to reload."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..cameras import Camera
from ..capture.model import SceneNormalization
from ..classes import ClassMap
from ..geometry.sampling import OccupancyGrid
from ..geometry.sdf import SDFField
from ..recipe import Recipe, _build
from ..semantics.head import SemanticHead, decide_labels
from ..semantics.training import BakedRays, make_semantic_head
from .surface import SurfaceCaster, extract_mesh


@dataclass
class FrameRender:
    """Per-pixel results for one frame at full resolution."""

    mask: np.ndarray  # (H, W) uint8 class ids
    confidence: np.ndarray  # (H, W) float32 max class probability
    probabilities: np.ndarray | None = None  # (H, W, C) float16 when asked for
    hit: np.ndarray | None = None  # (H, W) bool: the ray met the surface
    points: np.ndarray | None = None  # (H, W, 3) unit-cube hit points (valid where hit)


@dataclass
class SemanticField:
    sdf: SDFField
    head: SemanticHead | None
    grid: OccupancyGrid
    classes: ClassMap
    normalization: SceneNormalization
    recipe: Recipe
    device: torch.device
    baked: "BakedRays | None" = field(default=None, repr=False)  # semantic training rays, for refits
    _mesh: trimesh.Trimesh | None = field(default=None, repr=False)
    _caster: SurfaceCaster | None = field(default=None, repr=False)
    _render_caster: SurfaceCaster | None = field(default=None, repr=False)
    _vertex_logits: tuple | None = field(default=None, repr=False)  # (head, logits (V, C), known (V,))
    _vertex_features: tuple | None = field(default=None, repr=False)  # (features (V, F), known (V,))

    # --- surface --------------------------------------------------------------------------
    def mesh(self) -> trimesh.Trimesh:
        """The surface in unit-cube coordinates (cached)."""
        if self._mesh is None:
            self._mesh = extract_mesh(self.sdf.sdf_batched, self.recipe.render.mesh_resolution, self.device)
            self._caster = None
        return self._mesh

    def caster(self) -> SurfaceCaster:
        if self._caster is None:
            self._caster = SurfaceCaster(self.mesh())
        return self._caster

    def render_caster(self) -> SurfaceCaster:
        """The surface subdivided ``render.subdivide`` times, so vertices lie ~1-2 px apart."""
        if self._render_caster is None:
            mesh = self.mesh()
            for _ in range(self.recipe.render.subdivide if len(mesh.faces) else 0):
                mesh = mesh.subdivide()
            self._render_caster = SurfaceCaster(mesh)
        return self._render_caster

    def vertex_logits(self, vertices: np.ndarray | None = None) -> torch.Tensor:
        """Class logits at the render mesh's vertices for the current head, (V, C).

        Evaluated lazily: only the ``vertices`` asked for (all when None) that the current head
        has not seen yet, so a frame costs the vertices it sees, and the report's leave-one-out
        heads, each rendering one frame, do not pay for the whole mesh. Rows never asked for
        stay zero. The geometry features at the vertices are cached across heads (the geometry
        is frozen once the semantic stage starts).
        """
        n = len(self.render_caster().mesh.vertices)
        if self._vertex_logits is None or self._vertex_logits[0] is not self.head:
            logits = torch.zeros(n, self.classes.num_classes, device=self.device)
            self._vertex_logits = (self.head, logits, np.zeros(n, dtype=bool))
        _, logits, known = self._vertex_logits
        wanted = np.arange(n) if vertices is None else np.unique(vertices)
        todo = wanted[~known[wanted]]
        if len(todo):
            logits[torch.from_numpy(todo).to(self.device)] = self._head_at_vertices(todo)
            known[todo] = True
        return logits

    @torch.no_grad()
    def _head_at_vertices(self, todo: np.ndarray) -> torch.Tensor:
        """The head at render-mesh vertices ``todo``, their geometry features computed once."""
        assert self.head is not None, "the semantic stage has not been trained"
        verts = self.render_caster().mesh.vertices
        n, fdim = len(verts), self.sdf.cfg.feature_dim
        if self._vertex_features is None:
            self._vertex_features = (torch.zeros(n, fdim, device=self.device), np.zeros(n, dtype=bool))
        feats, known = self._vertex_features
        new = todo[~known[todo]]
        chunk = self.recipe.render.chunk
        for s in range(0, len(new), chunk):
            idx = new[s : s + chunk]
            pts = torch.as_tensor(np.asarray(verts[idx], dtype=np.float32), device=self.device)
            feats[torch.from_numpy(idx).to(self.device)] = self.sdf.get_sdf(pts)[1]
        known[new] = True
        self.head.eval()
        out = []
        for s in range(0, len(todo), chunk):
            idx = todo[s : s + chunk]
            pts = torch.as_tensor(np.asarray(verts[idx], dtype=np.float32), device=self.device)
            out.append(self.head(feats[torch.from_numpy(idx).to(self.device)], pts))
        return torch.cat(out)

    # --- semantics ------------------------------------------------------------------------
    @torch.no_grad()
    def logits_at(self, points: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Class logits (N, C) at unit-cube points (dropout off)."""
        assert self.head is not None, "the semantic stage has not been trained"
        self.head.eval()
        pts = torch.as_tensor(np.asarray(points, dtype=np.float32), device=self.device)
        out = []
        chunk = self.recipe.render.chunk
        for s in range(0, len(pts), chunk):
            p = pts[s : s + chunk]
            _, feature = self.sdf.get_sdf(p)
            out.append(self.head(feature, p))
        if not out:
            return torch.zeros(0, self.classes.num_classes, device=self.device)
        return torch.cat(out)

    def render(self, camera_unit: Camera, keep_probabilities: bool = False, keep_points: bool = False) -> FrameRender:
        """Mask and confidence for every pixel of a camera given in unit-cube coordinates."""
        h, w = camera_unit.height, camera_unit.width
        caster = self.render_caster()
        hit, points, faces, bary = caster.cast(*camera_unit.rays())
        c = self.classes.num_classes
        probs = np.zeros((h * w, c), dtype=np.float32)
        probs[:, self.classes.background_index] = 1.0
        if hit.any():
            if self.recipe.render.per_pixel:
                logits = self.logits_at(points[hit])
            else:
                # Logits at the hit = barycentric blend of the logits at the triangle's vertices:
                # one head evaluation per vertex instead of one per pixel of every frame.
                tri = np.asarray(caster.mesh.faces)[faces[hit]]
                vl = self.vertex_logits(tri.ravel())
                logits = (vl[torch.from_numpy(tri).to(vl.device)] * torch.from_numpy(bary[hit]).to(vl)[..., None]).sum(1)
            probs[hit] = torch.softmax(logits, dim=-1).cpu().numpy()
        index = decide_labels(probs, self.classes, self.recipe.render.decision)
        mask = self.classes.index_to_id_lut()[index].reshape(h, w)
        conf = np.take_along_axis(probs, index[:, None], -1)[:, 0].reshape(h, w)  # of the label written
        return FrameRender(
            mask=mask,
            confidence=conf,
            probabilities=probs.reshape(h, w, c).astype(np.float16) if keep_probabilities else None,
            hit=hit.reshape(h, w),
            points=points.reshape(h, w, 3) if keep_points else None,
        )

    # --- persistence ----------------------------------------------------------------------
    def save(self, path: Path) -> None:
        torch.save(
            {
                "sdf": self.sdf.state_dict(),
                "head": None if self.head is None else self.head.state_dict(),
                "grid": self.grid.state_dict(),
                "classes": self.classes.to_json(),
                "normalization": self.normalization.to_json(),
                "recipe": self.recipe.to_dict(),
            },
            path,
        )

    @classmethod
    def load(cls, path: Path, device: torch.device) -> "SemanticField":
        state = torch.load(path, map_location=device, weights_only=False)
        recipe = _build(Recipe, state["recipe"], str(path))
        if not any(k.startswith("outer.") for k in state["sdf"]):
            recipe.geometry.sdf.background = "env"  # files from before the outer background
        classes = ClassMap.from_dict(state["classes"], str(path), "class table of the field")
        sdf = SDFField(recipe.geometry.sdf).to(device)
        sdf_state = state["sdf"]
        sdf_state.setdefault("inv_s_floor", torch.tensor(1.0))  # files from before the floor existed
        sdf.load_state_dict(sdf_state)
        sdf.eval()
        grid = OccupancyGrid(state["grid"]["resolution"], device)
        grid.load_state_dict(state["grid"])
        head = None
        if state["head"] is not None:
            head = make_semantic_head(sdf, classes, recipe.semantic)
            head.load_state_dict(state["head"])
            head.eval()
        return cls(sdf, head, grid, classes, SceneNormalization.from_json(state["normalization"]), recipe, device)
