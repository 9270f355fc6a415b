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
    """Ray casting onto a mesh (Embree when installed, trimesh's pure-Python path otherwise)."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.mesh = mesh
        self.empty = len(mesh.faces) == 0
        if not self.empty:
            try:
                from trimesh.ray.ray_pyembree import RayMeshIntersector

                self.intersector = RayMeshIntersector(mesh)
            except Exception:  # embree missing on this platform
                self.intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(hit mask (N,), hit points (N,3), face index (N,)) for the first intersection per ray."""
        n = len(origins)
        hit = np.zeros(n, dtype=bool)
        points = np.zeros((n, 3))
        faces = np.full(n, -1, dtype=np.int64)
        if self.empty or n == 0:
            return hit, points, faces
        loc, ray_idx, tri_idx = self.intersector.intersects_location(origins, dirs, multiple_hits=False)
        hit[ray_idx] = True
        points[ray_idx] = loc
        faces[ray_idx] = tri_idx
        return hit, points, faces

    def cast_camera(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of every pixel of ``camera`` (row-major)."""
        o, d = camera.rays()
        return self.first_hits(o, d)
