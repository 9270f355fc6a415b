"""The fitted surface as a mesh, and one ray per pixel cast onto it.

Volume-rendering every pixel of 50 full-resolution frames is slow on a CPU; the SDF's zero
level set is extracted once (marching cubes, evaluated finely only near the surface) and each
pixel's ray is intersected with it (Embree through trimesh when available). The semantic head
is then evaluated at the hit points, where the rendering weights peak: once per vertex of the
subdivided mesh, blended barycentrically per pixel (``render.field``; ``render.per_pixel``
evaluates it at every hit instead).
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from skimage import measure
from torch.nn import functional as F

from ..cameras import Camera


@torch.no_grad()
def sdf_volume(sdf_fn, resolution: int, device: torch.device, coarse: int = 64) -> np.ndarray:
    """SDF on a ``resolution``^3 grid over [-1,1]^3, evaluated exactly only near the surface.

    A coarse grid finds the cells within two coarse voxels of the zero level set; elsewhere the
    upsampled coarse values are kept (only their sign matters to marching cubes there).
    """
    lin_c = torch.linspace(-1, 1, coarse, device=device)
    pts_c = torch.stack(torch.meshgrid(lin_c, lin_c, lin_c, indexing="ij"), -1).reshape(-1, 3)
    sdf_c = sdf_fn(pts_c).reshape(1, 1, coarse, coarse, coarse)
    vol = F.interpolate(sdf_c, size=(resolution,) * 3, mode="trilinear", align_corners=True)[0, 0]
    near = F.interpolate(
        (sdf_c.abs() < 2.5 * 2.0 / (coarse - 1)).float(), size=(resolution,) * 3, mode="nearest"
    )[0, 0].bool()
    lin = torch.linspace(-1, 1, resolution, device=device)
    idx = torch.nonzero(near)
    if idx.numel():
        pts = lin[idx]
        vol[idx[:, 0], idx[:, 1], idx[:, 2]] = sdf_fn(pts)
    return vol.cpu().numpy()


def extract_mesh(sdf_fn, resolution: int, device: torch.device) -> trimesh.Trimesh:
    """Zero level set of the SDF as a mesh in unit-cube coordinates (normals point outwards)."""
    vol = sdf_volume(sdf_fn, resolution, device)
    if not (vol.min() < 0 < vol.max()):
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    verts, faces, normals, _ = measure.marching_cubes(vol, level=0.0, spacing=(2.0 / (resolution - 1),) * 3)
    verts = verts - 1.0
    # skimage orients faces towards increasing values (outside, sdf > 0) -> keep as is.
    return trimesh.Trimesh(vertices=verts, faces=faces, vertex_normals=normals, process=False)


class SurfaceCaster:
    """Ray casting onto a mesh: Embree (embreex) when installed, trimesh's pure-Python path otherwise.

    Embree is called directly rather than through trimesh's wrapper, which recomputes every hit
    in float64 by intersecting the ray with the triangle's plane, then ``points_to_barycentric``
    recomputed the barycentric coordinates from that point: together more time than Embree's
    own cast (README, Novel views: timing). Embree returns the triangle and the barycentric
    coordinates of the hit; the point is formed from them on the triangle in float64. As in
    trimesh, the mesh is shifted and scaled to a box about 100 wide for float32 precision
    (``rescale=False``: only shifted, for a caller whose meshes are already a few units wide and
    whose output depends on the exact float32 rays: ``evaluation.synth``'s byte-identical captures).
    """

    def __init__(self, mesh: trimesh.Trimesh, *, rescale: bool = True) -> None:
        self.mesh = mesh
        self.empty = len(mesh.faces) == 0
        self._scene = None
        self.intersector = None
        if self.empty:
            return
        self._vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self._faces = np.asarray(mesh.faces, dtype=np.int64)
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:  # embree missing on this platform
            self.intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
            return
        self._origin = self._vertices.min(axis=0)
        self._scale = 100.0 / max(float(np.linalg.norm(np.ptp(self._vertices, axis=0))), 1e-12) if rescale else 1.0
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self._scene, vertices=((self._vertices - self._origin) * self._scale).astype(np.float32),
                     indices=self._faces.astype(np.int32))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(hit mask (N,), hit points (N,3), face index (N,), barycentric coordinates (N,3)) of
        the first intersection per ray (points and coordinates 0, face -1 on a miss)."""
        n = len(origins)
        hit = np.zeros(n, dtype=bool)
        points = np.zeros((n, 3))
        faces = np.full(n, -1, dtype=np.int64)
        bary = np.zeros((n, 3))
        if self.empty or n == 0:
            return hit, points, faces, bary
        if self._scene is None:
            loc, ray_idx, tri_idx = self.intersector.intersects_location(origins, dirs, multiple_hits=False)
            hit[ray_idx] = True
            faces[ray_idx] = tri_idx
            bary[ray_idx] = trimesh.triangles.points_to_barycentric(self.mesh.triangles[tri_idx], loc)
            points[ray_idx] = loc
            return hit, points, faces, bary
        scaled = ((np.asarray(origins, dtype=np.float64) - self._origin) * self._scale).astype(np.float32)
        out = self._scene.run(scaled, np.asarray(dirs, dtype=np.float32), output=1)
        hit = out["primID"] >= 0
        faces[hit] = out["primID"][hit]
        u, v = out["u"][hit].astype(np.float64), out["v"][hit].astype(np.float64)
        b = np.stack([1.0 - u - v, u, v], axis=-1)  # Embree: p = (1-u-v) p0 + u p1 + v p2
        bary[hit] = b
        points[hit] = np.einsum("nk,nkd->nd", b, self._vertices[self._faces[faces[hit]]])
        return hit, points, faces, bary

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(hit mask (N,), hit points (N,3), face index (N,)) for the first intersection per ray."""
        hit, points, faces, _ = self.cast(origins, dirs)
        return hit, points, faces

    def cast_camera(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of every pixel of ``camera`` (row-major); ``cast(*camera.rays())`` for the
        barycentric coordinates too."""
        return self.first_hits(*camera.rays())
