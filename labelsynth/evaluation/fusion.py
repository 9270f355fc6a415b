"""The paper's "3D/2D" baseline: per-view 2D masks voted onto a mesh, then projected back.

Following the paper (and Chierchia et al., Wound3DAssist) each *vertex* of the scene mesh gets a
weighted majority vote over the views that see it, the weight being how squarely the view sees
the surface there (|cos| between the pixel ray and the surface normal), so grazing views, whose
2D labels smear over a large patch of surface, count less; views more grazing than a cut-off
angle do not vote at all. Visibility is exact first-hit ray casting (``SurfaceCaster``): a pixel
votes only for the surface its ray meets first, so occluded surface is never labelled by a view
that cannot see it.

Votes are cast from the pixels of every ``stride``-th row and column (the full masks are not
needed to label a mesh whose triangles span several pixels) and split between the three
vertices of the hit triangle by barycentric weight. Labels are rendered back at full
resolution: each pixel's ray hits a triangle, the vertices' vote shares are interpolated at
the hit point and the largest wins; rays that miss the mesh are background.

Everything is vectorised (``np.bincount`` over ``vertex * C + class``); the only Python loop
is over views.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from ..cameras import Camera
from ..classes import ClassMap
from ..errors import LabelsynthError
from ..progress import track
from ..render.surface import SurfaceCaster

if TYPE_CHECKING:  # pragma: no cover
    from ..capture.model import Capture, SceneNormalization
    from ..render.renderer import FieldRenderer

DEFAULT_CUTOFF_DEG = 75.0
DEFAULT_STRIDE = 2
DEFAULT_FILL_ITERATIONS = 3


@dataclass
class FusedLabels:
    """Weighted votes per vertex of ``mesh`` (unit-cube coordinates) and what follows from them."""

    mesh: trimesh.Trimesh
    classes: ClassMap
    votes: np.ndarray  # (V, C) summed vote weight per vertex and class index
    views: int = 0  # views that cast at least one vote
    caster: SurfaceCaster | None = field(default=None, repr=False)

    @cached_property
    def vertex_shares(self) -> np.ndarray:
        """(V, C) votes normalised per vertex; all zeros for a vertex no view voted for
        (computed once: every rendered frame needs it)."""
        total = self.votes.sum(1, keepdims=True)
        return np.divide(self.votes, total, out=np.zeros_like(self.votes), where=total > 0)

    @property
    def vertex_labels(self) -> np.ndarray:
        """(V,) winning class index per vertex, -1 where nobody voted."""
        lab = self.votes.argmax(1)
        lab[self.votes.sum(1) <= 0] = -1
        return lab

    @property
    def face_labels(self) -> np.ndarray:
        """(F,) class index per face: the winner of its vertices' summed vote shares;
        background for a face none of whose vertices got a vote."""
        faces = np.asarray(self.mesh.faces, dtype=np.int64)
        if len(faces) == 0:
            return np.zeros(0, dtype=np.int64)
        share = self.vertex_shares[faces].sum(1)
        lab = share.argmax(1)
        lab[share.sum(1) <= 0] = self.classes.background_index
        return lab

    def _caster(self) -> SurfaceCaster:
        if self.caster is None:
            self.caster = SurfaceCaster(self.mesh)
        return self.caster

    def render(self, camera_unit: Camera) -> np.ndarray:
        """(H, W) uint8 class ids for every pixel of a unit-cube camera (misses: background)."""
        return render_labels(self, camera_unit)


def _pixel_centres(camera: Camera, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel centres of every ``stride``-th row and column: (N,2) coordinates, rows, cols."""
    stride = max(1, int(stride))
    off = stride // 2  # the middle pixel of each stride x stride block
    cols = np.arange(off, camera.width, stride)
    rows = np.arange(off, camera.height, stride)
    if len(cols) == 0:
        cols = np.array([0])
    if len(rows) == 0:
        rows = np.array([0])
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    return np.stack([cc + 0.5, rr + 0.5], axis=-1), rr, cc


def _surface_normals(mesh: trimesh.Trimesh, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Unit normals at hit points: vertex normals interpolated (smooth on marching-cubes
    staircases), the flat face normal where they cancel out."""
    tri = np.asarray(mesh.faces, dtype=np.int64)[faces]
    n = (bary[:, :, None] * np.asarray(mesh.vertex_normals)[tri]).sum(1)
    norm = np.linalg.norm(n, axis=1)
    bad = norm < 1e-8
    if bad.any():
        n[bad] = np.asarray(mesh.face_normals)[faces[bad]]
        norm[bad] = np.linalg.norm(n[bad], axis=1)
    return n / np.maximum(norm, 1e-12)[:, None]


def _barycentric(bary: np.ndarray) -> np.ndarray:
    """(N,3) barycentric weights of hits (``SurfaceCaster.cast``), clipped to [0,1] and summing to 1."""
    if len(bary) == 0:
        return np.zeros((0, 3))
    bary = np.clip(np.nan_to_num(bary, nan=1.0 / 3.0), 0.0, 1.0)
    s = bary.sum(1, keepdims=True)
    return np.where(s > 0, bary / np.maximum(s, 1e-12), 1.0 / 3.0)


def view_votes(
    caster: SurfaceCaster,
    camera_unit: Camera,
    mask: np.ndarray,
    classes: ClassMap,
    *,
    cutoff_deg: float = DEFAULT_CUTOFF_DEG,
    stride: int = DEFAULT_STRIDE,
) -> np.ndarray:
    """(V, C) votes of one view: |cos|-weighted, split by barycentric weight over the hit
    triangle's vertices. Ignore pixels, unknown ids, misses and views more grazing than
    ``cutoff_deg`` cast nothing."""
    mesh = caster.mesh
    nv, c = len(mesh.vertices), classes.num_classes
    votes = np.zeros((nv, c))
    mask = np.asarray(mask)
    if mask.shape != (camera_unit.height, camera_unit.width):
        raise ValueError(f"mask shape {mask.shape} does not match the camera ({camera_unit.height}, {camera_unit.width})")
    if caster.empty:
        return votes
    pix, rows, cols = _pixel_centres(camera_unit, stride)
    cls = classes.id_to_index_lut()[mask[rows, cols].astype(np.int64)]
    use = cls >= 0
    if not use.any():
        return votes
    origins, dirs = camera_unit.rays(pix[use])
    hit, _, faces, bary = caster.cast(origins, dirs)
    if not hit.any():
        return votes
    cls, dirs, faces = cls[use][hit], dirs[hit], faces[hit]
    bary = _barycentric(bary[hit])
    cos = np.abs((_surface_normals(mesh, faces, bary) * dirs).sum(1))
    ok = cos >= np.cos(np.deg2rad(cutoff_deg)) - 1e-9
    if not ok.any():
        return votes
    tri = np.asarray(mesh.faces, dtype=np.int64)[faces[ok]]
    weight = cos[ok, None] * bary[ok]
    idx = tri * c + cls[ok, None]
    votes += np.bincount(idx.ravel(), weights=weight.ravel(), minlength=nv * c).reshape(nv, c)
    return votes


def _fill_unvoted(mesh: trimesh.Trimesh, votes: np.ndarray, iterations: int) -> np.ndarray:
    """Give vertices without votes the mean vote share of their voted neighbours.

    Small triangles can fall between the sampled pixels of every view although they are
    visible; a few rings of neighbour filling keeps them from rendering as holes. Surface
    that no view saw at all stays unlabelled beyond those rings.
    """
    if iterations <= 0 or len(mesh.faces) == 0:
        return votes
    edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    total = votes.sum(1)
    share = np.divide(votes, total[:, None], out=np.zeros_like(votes), where=total[:, None] > 0)
    known = total > 0
    for _ in range(iterations):
        if known.all():
            break
        acc = np.zeros_like(share)
        cnt = np.zeros(len(share))
        for a, b in ((edges[:, 0], edges[:, 1]), (edges[:, 1], edges[:, 0])):
            k = known[b] & ~known[a]
            a_k, b_k = a[k], b[k]
            cnt += np.bincount(a_k, minlength=len(share))
            for j in range(share.shape[1]):
                acc[:, j] += np.bincount(a_k, weights=share[b_k, j], minlength=len(share))
        new = (~known) & (cnt > 0)
        if not new.any():
            break
        share[new] = acc[new] / cnt[new, None]
        known = known | new
    out = votes.copy()
    filled = known & (total <= 0)
    # a small weight: filled vertices only ever decide where no real vote exists
    out[filled] = share[filled] * 1e-6
    return out


def fuse_labels(
    mesh: trimesh.Trimesh,
    cameras_unit: Mapping[str, Camera],
    masks: Mapping[str, np.ndarray],
    classes: ClassMap,
    *,
    cutoff_deg: float = DEFAULT_CUTOFF_DEG,
    stride: int = DEFAULT_STRIDE,
    fill_iterations: int = DEFAULT_FILL_ITERATIONS,
    caster: SurfaceCaster | None = None,
    progress: bool = False,
) -> FusedLabels:
    """Weighted majority vote of the given masks (``{frame name: class ids}``) onto ``mesh``.

    ``cameras_unit`` maps frame names to unit-cube cameras; a mask whose frame has no camera
    is an error. ``cutoff_deg`` is the most grazing angle (between ray and normal) that still
    votes; ``stride`` samples every stride-th pixel row/column for the vote.
    """
    if not 0.0 <= cutoff_deg <= 90.0:
        raise LabelsynthError(f"fusion cut-off angle must be within 0..90 degrees, got {cutoff_deg}")
    caster = caster if caster is not None else SurfaceCaster(mesh)
    votes = np.zeros((len(mesh.vertices), classes.num_classes))
    views = 0
    for name in track(list(masks), "3D/2D votes", enabled=progress):
        if name not in cameras_unit:
            raise LabelsynthError(f"fusion: no camera for the mask of frame '{name}'")
        v = view_votes(caster, cameras_unit[name], masks[name], classes, cutoff_deg=cutoff_deg, stride=stride)
        if v.any():
            views += 1
        votes += v
    votes = _fill_unvoted(mesh, votes, fill_iterations)
    return FusedLabels(mesh=mesh, classes=classes, votes=votes, views=views, caster=caster)


def render_labels(fused: FusedLabels, camera_unit: Camera) -> np.ndarray:
    """Full-resolution (H, W) uint8 class ids: vertex vote shares interpolated at each pixel's
    first hit; rays that miss, or hit surface nobody voted for, are background."""
    h, w = camera_unit.height, camera_unit.width
    classes = fused.classes
    bg = classes.ids[classes.background_index]
    out = np.full(h * w, bg, dtype=np.uint8)
    caster = fused._caster()
    if caster.empty:
        return out.reshape(h, w)
    hit, _, faces, bary = caster.cast(*camera_unit.rays())
    if hit.any():
        f = faces[hit]
        bary = _barycentric(bary[hit])
        tri = np.asarray(fused.mesh.faces, dtype=np.int64)[f]
        share = (bary[:, :, None] * fused.vertex_shares[tri]).sum(1)
        idx = share.argmax(1)
        idx[share.sum(1) <= 0] = classes.background_index
        out[hit] = classes.index_to_id_lut()[idx]
    return out.reshape(h, w)


def load_mesh_unit(path: str | Path, normalization: "SceneNormalization") -> trimesh.Trimesh:
    """A user mesh in world coordinates (any format trimesh reads), mapped to the unit cube."""
    path = Path(path)
    if not path.is_file():
        raise LabelsynthError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for bad files
        raise LabelsynthError(f"{path}: cannot read mesh ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise LabelsynthError(f"{path}: no triangles in mesh")
    return trimesh.Trimesh(vertices=normalization.to_unit(loaded.vertices), faces=np.asarray(loaded.faces), process=False)


def fusion_baseline(
    source: "FieldRenderer | trimesh.Trimesh",
    capture: "Capture",
    masks: Mapping[str, np.ndarray],
    *,
    frames: Iterable[str] | None = None,
    cutoff_deg: float = DEFAULT_CUTOFF_DEG,
    stride: int = DEFAULT_STRIDE,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """The 3D/2D baseline on a capture: vote ``masks`` onto the mesh, render ``frames``.

    ``source`` is a fitted field's renderer (its marching-cubes mesh and caster are reused) or a
    mesh in unit-cube coordinates (see ``load_mesh_unit``). ``frames`` defaults to every frame.
    """
    if isinstance(source, trimesh.Trimesh):
        mesh, caster = source, SurfaceCaster(source)
    else:
        mesh, caster = source.mesh(), source.caster()
    cams = dict(zip(capture.names, capture.unit_cameras()))
    fused = fuse_labels(mesh, cams, masks, capture.classes, cutoff_deg=cutoff_deg, stride=stride,
                        caster=caster, progress=progress)
    names: Sequence[str] = list(capture.names if frames is None else frames)
    return {n: render_labels(fused, cams[n]) for n in track(names, "3D/2D render", enabled=progress)}
