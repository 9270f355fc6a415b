"""Image formation shared by both layouts: the background of rays that miss, the vignette,
and Blinn-Phong shading of the surface hits (what a phone camera would record of them).

What the camera alone does to an image (exposure, blur, compression) belongs after this, on
the rendered frame (``writer``), so that the truth, drawn from the same hits, stays exact.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


def background_image(width: int, height: int) -> np.ndarray:
    """The (H,W,3) uint8 colour of rays that miss the body: a dark gradient, vignetted."""
    v = (np.arange(height, dtype=np.float32) + 0.5) / height
    top, bottom = np.array([24, 26, 33], np.float32), np.array([52, 48, 50], np.float32)
    col = top[None, :] * (1 - v[:, None]) + bottom[None, :] * v[:, None]
    img = np.broadcast_to(col[:, None, :], (height, width, 3)) * vignette(width, height)[..., None]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def vignette(width: int, height: int) -> np.ndarray:
    """Brightness factor per pixel (H,W): 1 - 0.18 r^2, r = distance from the centre in half image widths."""
    u = (np.arange(width, dtype=np.float32) + 0.5) / width - 0.5
    v = (np.arange(height, dtype=np.float32) + 0.5) / height - 0.5
    r2 = (u[None, :] ** 2 + (v[:, None] * height / width) ** 2) / 0.25
    return 1.0 - 0.18 * r2


class SurfaceHits(NamedTuple):
    """Surface attributes at the rays' hits (one row per hit)."""

    pos: np.ndarray  # world point
    uv: np.ndarray  # surface coordinates
    normal: np.ndarray  # mesh normal (before bump mapping)
    tu: np.ndarray  # unit tangent along u
    tv: np.ndarray  # unit tangent along v


class Material(NamedTuple):
    """What the textures give at each hit."""

    labels: np.ndarray  # class id
    albedo: np.ndarray  # RGB 0..255
    spec: np.ndarray  # specular strength
    shin: np.ndarray  # shininess
    bump_grad: np.ndarray  # bump-map slope (d/du, d/dv)


def bumped_normal(surf: SurfaceHits, bump_grad: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The mesh normal tilted by the bump map (fine relief the mesh is too coarse to hold),
    turned to face the viewer (rays may graze the far side of a bump)."""
    nrm = surf.normal - bump_grad[:, :1] * surf.tu - bump_grad[:, 1:2] * surf.tv
    nrm /= np.sqrt(np.einsum("ij,ij->i", nrm, nrm))[:, None]
    flip = np.einsum("ij,ij->i", nrm, d) > 0
    nrm[flip] *= -1
    return nrm


def shade(mat: Material, nrm: np.ndarray, view: np.ndarray, lights: dict) -> np.ndarray:
    """Blinn-Phong colour (0..255 float) under the scene's lights plus a weak phone light at the
    camera, so the wet wound bed glints as in a real capture."""
    shin = mat.shin
    light = np.full(len(nrm), lights["ambient"], np.float32)
    spec_acc = np.zeros(len(nrm), np.float32)
    for ldir, power in lights["directional"]:
        ldir = ldir.astype(np.float32)
        ndl = np.clip(nrm @ ldir, 0, None)
        light += power * ndl
        hvec = view + ldir
        hvec /= np.sqrt(np.einsum("ij,ij->i", hvec, hvec))[:, None]
        spec_acc += power * (ndl > 0) * np.clip(np.einsum("ij,ij->i", nrm, hvec), 0, None) ** shin
    ndv = np.clip(np.einsum("ij,ij->i", nrm, view), 0, None)
    light += lights["headlight"] * ndv
    spec_acc += lights["headlight"] * ndv**shin
    return mat.albedo * light[:, None] + 255.0 * (mat.spec * spec_acc)[:, None] * np.array([1.0, 0.97, 0.93], np.float32)

