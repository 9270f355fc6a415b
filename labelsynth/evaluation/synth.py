"""Synthetic wound captures with exact truth for every frame.

A procedural wound on a curved body surface (a tapered limb or a gently curved torso patch)
is ray-cast from a hand-held-like camera path (layout "one-sided"), or a wound wrapped around a
limb is filmed in one turn around it (layout "all-around"). Class labels, albedo and relief are functions
of the surface parameters (u, v), so every view agrees on the class of a surface point, and
colour and truth of a pixel come from the same ray hit. Writes::

    OUT/capture/   images/, transforms.json, annotations/ (a few frames), predictions/ (all)
    OUT/truth/     <stem>.png (class ids), depth/<stem>.npy (ray distance), scene.json

Predictions imitate a good but imperfect 2D segmenter whose errors differ from view to view
(boundary offsets and jitter, slough taken for granulation, missed rims and small regions,
false blobs on skin), so that a multi-view method has something to fix.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

import cv2
import numpy as np

from ..cameras import Camera, look_at
from ..capture.images import write_image
from ..capture.masks import write_mask
from ..capture.select import spread_indices
from ..classes import DEFAULT_CLASSES
from ..errors import LabelsynthError
from ..outdir import building
from ..progress import track

BACKGROUND, GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN = 0, 1, 2, 3, 4, 5
WOUND_CLASSES = (GRANULATION, SLOUGH, NECROTIC, EPITHELIAL, UNKNOWN)
LAYOUTS = ("one-sided", "all-around")


@dataclass
class SynthConfig:
    """What to synthesise. The same config (seed included) gives byte-identical files."""

    frames: int = 50
    annotated: int = 4
    width: int = 640
    height: int = 480
    noise: float = 1.0
    seed: int = 0
    layout: Literal["one-sided", "all-around"] = "one-sided"
    """one-sided: a hand-held arc above a wound on a limb or torso; all-around: a wound wrapped
    around a limb, filmed in one turn around it."""

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise LabelsynthError(f"synth: layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if self.frames < 2:
            raise LabelsynthError(f"synth: need at least 2 frames, got {self.frames}")
        if not 0 <= self.annotated <= self.frames:
            raise LabelsynthError(f"synth: annotated must be in 0..{self.frames}, got {self.annotated}")
        if self.width < 16 or self.height < 16:
            raise LabelsynthError(f"synth: image size must be at least 16x16, got {self.width}x{self.height}")
        if not np.isfinite(self.noise) or self.noise < 0:
            raise LabelsynthError(f"synth: noise must be >= 0, got {self.noise}")


@dataclass
class SynthResult:
    capture_dir: Path
    truth_dir: Path
    num_frames: int
    annotated: list[str] = field(default_factory=list)
    seconds: float = 0.0


# ------------------------------------------------------------------------------------------
# small procedural helpers
# ------------------------------------------------------------------------------------------
def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
    """Smooth value noise (about N(0,1)) of ``shape`` with about ``cells`` features per axis."""
    ch = max(2, int(np.ceil(cells[0]))) + 3
    cw = max(2, int(np.ceil(cells[1]))) + 3
    grid = rng.standard_normal((ch, cw)).astype(np.float32)
    # resize so that ``cells`` grid steps span the shape, then crop (extra steps hide the border)
    th = max(shape[0], int(np.ceil(shape[0] * (ch - 1) / max(cells[0], 1e-3))))
    tw = max(shape[1], int(np.ceil(shape[1] * (cw - 1) / max(cells[1], 1e-3))))
    out = cv2.resize(grid, (tw, th), interpolation=cv2.INTER_CUBIC)
    oy, ox = (th - shape[0]) // 2, (tw - shape[1]) // 2
    out = out[oy: oy + shape[0], ox: ox + shape[1]]
    out = out - out.mean()
    return (out / (out.std() + 1e-6)).astype(np.float32)


def _fbm(rng: np.random.Generator, shape: tuple[int, int], cells: float, octaves: int = 4, aspect: float = 1.0) -> np.ndarray:
    """Fractal noise: octaves of value noise, each twice as fine and half as strong."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        c = cells * 2**o
        out += amp * _noise(rng, shape, (c * aspect, c))
        total += amp
        amp *= 0.5
    return out / total


def _noise_wrap(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
    """As ``_noise``, periodic along axis 0: row 0 continues row ``shape[0] - 1``.

    The period holds a whole number of cells; the random grid is tiled three times along the
    rows and resized, and the middle period is kept (cubic interpolation only reaches two
    cells either way, so it sees a periodic grid).
    """
    h, w = shape
    ch = max(2, int(round(cells[0])))
    cw = max(2, int(np.ceil(cells[1]))) + 3
    grid = rng.standard_normal((ch, cw)).astype(np.float32)
    tw = max(w, int(np.ceil(w * (cw - 1) / max(cells[1], 1e-3))))
    out = cv2.resize(np.concatenate([grid, grid, grid], 0), (tw, 3 * h), interpolation=cv2.INTER_CUBIC)
    ox = (tw - w) // 2
    out = out[h: 2 * h, ox: ox + w]
    out = out - out.mean()
    return (out / (out.std() + 1e-6)).astype(np.float32)


def _fbm_wrap(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float], octaves: int = 4,
              aspect: float = 1.0) -> np.ndarray:
    """As ``_fbm``, periodic along axis 0; ``cells`` = (rows, columns) features of the first octave."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        out += amp * _noise_wrap(rng, shape, (cells[0] * 2**o * aspect, cells[1] * 2**o))
        total += amp
        amp *= 0.5
    return out / total


def _fold_rows(img: np.ndarray, extra: int) -> np.ndarray:
    """Make an image periodic along axis 0: its last ``extra`` rows are cross-faded into its first.

    ``img`` has N + extra rows; the result has N, and row 0 continues row N - 1.
    """
    n = img.shape[0] - extra
    out = img[:n].copy()
    w = ((np.arange(extra, dtype=np.float32) + 0.5) / extra).reshape(-1, *([1] * (img.ndim - 1)))
    out[:extra] = w * img[:extra] + (1 - w) * img[n: n + extra]
    return out


def _pad_rows(tex: np.ndarray) -> np.ndarray:
    """A periodic texture with its last row put before its first and its first after its last."""
    return np.concatenate([tex[-1:], tex, tex[:1]], axis=0)


def _bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample ``tex`` (H,W[,C]) at continuous texel coordinates (texel centres at integers)."""
    h, w = tex.shape[:2]
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(y.astype(np.int64), h - 2 if h > 1 else 0)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    if tex.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _remap(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sampling of a float32 texture with OpenCV (fast); points outside clamp to the edge."""
    n = len(x)
    cols = 1024
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, *tex.shape[2:])[:n]


def background_image(width: int, height: int) -> np.ndarray:
    """The (H,W,3) uint8 colour of rays that miss the body: a dark gradient, vignetted."""
    v = (np.arange(height, dtype=np.float32) + 0.5) / height
    top, bottom = np.array([24, 26, 33], np.float32), np.array([52, 48, 50], np.float32)
    col = top[None, :] * (1 - v[:, None]) + bottom[None, :] * v[:, None]
    img = np.broadcast_to(col[:, None, :], (height, width, 3)) * _vignette(width, height)[..., None]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _vignette(width: int, height: int) -> np.ndarray:
    u = (np.arange(width, dtype=np.float32) + 0.5) / width - 0.5
    v = (np.arange(height, dtype=np.float32) + 0.5) / height - 0.5
    r2 = (u[None, :] ** 2 + (v[:, None] * height / width) ** 2) / 0.25
    return 1.0 - 0.18 * r2


def _skin_marks(rng: np.random.Generator, shape: tuple[int, int], extent: tuple[float, float], fine: bool) -> np.ndarray:
    """How much each texel is darkened (0..1): freckles, moles, hairs and (``fine``) pores, the
    small high-contrast features that give feature matching and the field something to hold."""
    h, w = shape
    ext_v, ext_u = extent
    texel = ext_u / w
    canvas = np.zeros(shape, np.uint8)  # darkening amount (x255), drawn anti-aliased
    # freckles and marks (a count proportional to the area, sizes at several scales)
    area = ext_u * ext_v
    n_freckles = int(area * (260 if fine else 120))
    for _ in range(n_freckles):
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.choice([0.0025, 0.004, 0.007, 0.012], p=[0.4, 0.3, 0.2, 0.1]) * rng.uniform(0.7, 1.3)
        cv2.ellipse(canvas, (int(x * 16), int(y * 16)), (max(1, int(r / texel * 16)), max(1, int(r / texel * 16 * rng.uniform(0.6, 1.0)))),
                    float(rng.uniform(0, 180)), 0, 360, int(255 * rng.uniform(0.2, 0.6)), -1, cv2.LINE_AA, 4)
    for _ in range(max(1, int(area * 3))):  # a few moles
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(0.008, 0.02) / texel
        cv2.circle(canvas, (int(x * 16), int(y * 16)), max(1, int(r * 16)), int(255 * rng.uniform(0.6, 0.85)), -1, cv2.LINE_AA, 4)
    # hair-like strokes, roughly along u
    hair = np.zeros(shape, np.uint8)
    for _ in range(int(area * (900 if fine else 300))):
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        length = rng.uniform(0.01, 0.035) / texel
        ang = rng.normal(0.0, 0.35)
        x2, y2 = x + length * np.cos(ang), y + length * np.sin(ang)
        cv2.line(hair, (int(x * 16), int(y * 16)), (int(x2 * 16), int(y2 * 16)), int(255 * rng.uniform(0.25, 0.55)),
                 max(1, int(round(0.0012 / texel))), cv2.LINE_AA, 4)
    canvas = np.maximum(canvas, hair).astype(np.float32) / 255.0
    if fine:  # pores: thresholded fine noise
        pores = _noise(rng, shape, (ext_v / 0.006, ext_u / 0.006))
        canvas = np.maximum(canvas, 0.3 * _smoothstep(1.6, 2.6, pores))
    return cv2.GaussianBlur(canvas, (0, 0), 0.6)


# ------------------------------------------------------------------------------------------
# the scene: surface, wound layout, textures
# ------------------------------------------------------------------------------------------
class _SurfaceHits(NamedTuple):
    """Surface attributes at the rays' hits (one row per hit)."""

    pos: np.ndarray  # world point
    uv: np.ndarray  # surface coordinates
    normal: np.ndarray  # mesh normal (before bump mapping)
    tu: np.ndarray  # unit tangent along u
    tv: np.ndarray  # unit tangent along v


class _Material(NamedTuple):
    """What the textures give at each hit."""

    labels: np.ndarray  # class id
    albedo: np.ndarray  # RGB 0..255
    spec: np.ndarray  # specular strength
    shin: np.ndarray  # shininess
    bump_grad: np.ndarray  # bump-map slope (d/du, d/dv)


class _Scene:
    """Body surface as a displaced parametric grid, with textures over (u, v).

    (u, v) are arc-length-like surface coordinates in world units with the wound centred at
    the origin. Labels, albedo and relief are images over a window ``[-half, half]^2`` of
    (u, v) around the wound; skin outside it comes from a coarser texture over the whole
    domain.
    """

    def __init__(self, rng: np.random.Generator, detail: int) -> None:
        self.kind = "limb" if rng.random() < 0.5 else "torso"
        if self.kind == "limb":
            self.radius = float(rng.uniform(0.4, 0.6))
            self.taper = float(rng.uniform(-0.06, 0.06))  # relative radius change per unit length
            self.u_half, self.v_half = 2.5, float(np.pi * self.radius)
        else:
            self.curv = (float(rng.uniform(1.2, 2.5)), float(rng.uniform(1.8, 4.0)))  # radii of curvature
            self.u_half, self.v_half = 1.6, 1.6
        self.wound_radius = float(rng.uniform(0.10, 0.15))
        self.crater_depth = float(rng.uniform(0.03, 0.06) * 2 * self.wound_radius)
        self.half = 4.0 * self.wound_radius  # texture window half-size
        self.tex_res = int(detail)
        self.texel = 2 * self.half / self.tex_res
        self._layout(rng)
        self._textures(rng)
        self._sampling_textures()
        self._mesh(rng)

    def _sampling_textures(self) -> None:
        """The arrays that rendering samples (here the textures themselves), and their shape."""
        self.tex_shape = self.labels.shape
        self._tex = {"labels": self.labels, "albedo": self.albedo, "spec": self.spec, "shin": self.shin,
                     "bump_grad": self.bump_grad, "height_geo": self.height_geo, "global_albedo": self.global_albedo}

    # --- geometry -------------------------------------------------------------------------
    def surface(self, u: np.ndarray, v: np.ndarray, h: np.ndarray) -> np.ndarray:
        """World points for surface coordinates (u, v) displaced by ``h`` along the base normal."""
        if self.kind == "limb":
            r = self.radius * (1 + self.taper * u) + h
            th = v / self.radius
            return np.stack([u, r * np.sin(th), r * np.cos(th) - self.radius], -1)
        cx, cy = self.curv
        z = -(u * u / (2 * cx) + v * v / (2 * cy)) + h
        return np.stack([u, v, z], -1)

    def _tex_coords(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) -> continuous texel coordinates (x along u, y along v) of the window textures."""
        x = (u + self.half) / self.texel - 0.5
        y = (v + self.half) / self.texel - 0.5
        return x, y

    def _global_xy(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) -> continuous texel coordinates of the global skin texture (sampled as ``_tex``)."""
        gh, gw = self.global_albedo.shape[:2]
        return (u + self.u_half) / (2 * self.u_half) * gw - 0.5, (v + self.v_half) / (2 * self.v_half) * gh - 0.5

    def displacement(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        x, y = self._tex_coords(u, v)
        rows, cols = self.tex_shape
        inside = (x >= 0) & (y >= 0) & (x <= cols - 1) & (y <= rows - 1)
        h = np.zeros(u.shape, np.float64)
        h[inside] = _bilinear(self._tex["height_geo"], x[inside], y[inside])
        return h

    def _mesh(self, rng: np.random.Generator) -> None:
        n = int(np.clip(self.tex_res // 4, 120, 560))
        s = np.linspace(-1.0, 1.0, n)
        a = 3.0
        u1 = self.u_half * np.sinh(a * s) / np.sinh(a)  # finer near the wound
        v1 = self.v_half * np.sinh(a * s) / np.sinh(a)
        U, V = np.meshgrid(u1, v1, indexing="ij")  # (n, n): i along u, j along v
        H = self.displacement(U, V)
        P = self.surface(U, V, H)
        du = np.gradient(P, axis=0)
        dv = np.gradient(P, axis=1)
        self._set_mesh(U, V, P, du, dv)

    def _set_mesh(self, U: np.ndarray, V: np.ndarray, P: np.ndarray, du: np.ndarray, dv: np.ndarray) -> None:
        """Triangulate a (nu, nv) grid of surface points P at (U, V) with tangents du, dv."""
        N = np.cross(du, dv)
        N /= np.linalg.norm(N, axis=-1, keepdims=True)
        self.vertices = P.reshape(-1, 3)
        self.vertex_uv = np.stack([U, V], -1).reshape(-1, 2)
        self.vertex_normals = N.reshape(-1, 3)
        self.vertex_tu = (du / np.linalg.norm(du, axis=-1, keepdims=True)).reshape(-1, 3)
        self.vertex_tv = (dv / np.linalg.norm(dv, axis=-1, keepdims=True)).reshape(-1, 3)
        nu, nv = U.shape
        idx = np.arange(nu * nv).reshape(nu, nv)
        a00, a10, a01, a11 = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
        faces = np.concatenate(
            [np.stack([a00, a10, a11], -1).reshape(-1, 3), np.stack([a00, a11, a01], -1).reshape(-1, 3)]
        )
        self.faces = faces.astype(np.int64)
        self.grid_n = nu
        self._attrs = np.concatenate([self.vertices, self.vertex_uv, self.vertex_normals, self.vertex_tu,
                                      self.vertex_tv], axis=1).astype(np.float32)
        self.center = self.surface(np.zeros(1), np.zeros(1), self.displacement(np.zeros(1), np.zeros(1)))[0]
        self._build_intersector()

    def _build_intersector(self) -> None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._origin = self.vertices.min(axis=0)
            self._embree = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=self._embree, vertices=(self.vertices - self._origin).astype(np.float32),
                         indices=self.faces.astype(np.int32))
        except ImportError:  # pragma: no cover - slow fallback without embree
            import trimesh

            self._embree = None
            self._trimesh = trimesh.Trimesh(self.vertices, self.faces, process=False)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray: (face index or -1, barycentric weights (N,3))."""
        if self._embree is not None:
            res = self._embree.run((origins - self._origin).astype(np.float32), dirs.astype(np.float32), output=1)
            prim = res["primID"].astype(np.int64)
            b1, b2 = res["u"].astype(np.float64), res["v"].astype(np.float64)
            bary = np.stack([1 - b1 - b2, b1, b2], -1)
            return prim, bary
        import trimesh  # pragma: no cover

        prim = np.full(len(origins), -1, np.int64)  # pragma: no cover
        bary = np.zeros((len(origins), 3))  # pragma: no cover
        tri, ray, loc = self._trimesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
        prim[ray] = tri
        bary[ray] = trimesh.triangles.points_to_barycentric(self._trimesh.triangles[tri], loc)
        return prim, bary

    # --- wound layout ---------------------------------------------------------------------
    def _window_coords(self) -> tuple[np.ndarray, np.ndarray]:
        c = (np.arange(self.tex_res) + 0.5) * self.texel - self.half
        U, V = np.meshgrid(c, c, indexing="xy")  # rows along v, columns along u
        return U.astype(np.float32), V.astype(np.float32)

    def _layout(self, rng: np.random.Generator) -> None:
        """Class labels over the texture window, drawn with smooth noise (no hard-coded shapes)."""
        R, n = self.wound_radius, self.tex_res
        U, V = self._window_coords()
        cells = 2 * self.half / R  # noise features about one wound radius apart
        # irregular outline: random anisotropy and rotation, angular harmonics, domain warp
        rot = rng.uniform(0, np.pi)
        elong = rng.uniform(0.7, 1.0)
        a = (np.cos(rot) * U + np.sin(rot) * V) / 1.0
        b = (-np.sin(rot) * U + np.cos(rot) * V) / elong * 0.85
        warp = 0.12 * R
        a = a + warp * _noise(rng, (n, n), (cells * 1.5, cells * 1.5))
        b = b + warp * _noise(rng, (n, n), (cells * 1.5, cells * 1.5))
        phi = np.arctan2(b, a)
        rad = np.ones_like(phi)
        for k in range(2, 7):
            rad += rng.uniform(0.0, 0.16 / k * 2) * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
        rho = np.hypot(a, b) / (R * rad)
        self.rho = rho.astype(np.float32)
        ang = np.arctan2(V, U)
        self.labels = self._draw_tissues(
            rng, U, V, rho, blobs=1,
            noise=lambda mult: _noise(rng, (n, n), (cells * mult, cells * mult)),
            fbm=lambda mult, octaves: _fbm(rng, (n, n), cells * mult, octaves=octaves),
            dist=lambda cu, cv: np.hypot(U - cu, V - cv),
            dist_to=lambda mask: cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5) * self.texel,
            rim_on=lambda: sum(rng.uniform(0.3, 1.0) * np.cos(k * ang + rng.uniform(0, 2 * np.pi)) for k in (1, 2, 3)),
        )  # rows along v, columns along u

    def _draw_tissues(self, rng: np.random.Generator, U: np.ndarray, V: np.ndarray, rho: np.ndarray, *,
                      blobs: int, noise, fbm, dist, dist_to, rim_on) -> np.ndarray:
        """Tissue classes inside the bed ``rho < 1`` (rho: 0 in the middle, 1 on the outline).

        The layout's geometry comes in as callbacks over the texture window: ``noise(mult)`` and
        ``fbm(mult, octaves)`` (smooth noise with features about wound_radius / mult apart),
        ``dist(cu, cv)`` (distance of every texel to a point), ``dist_to(mask)`` (distance to a
        mask), ``rim_on()`` (a smooth field along the outline choosing where the rim is).
        ``blobs`` is how many necrotic and unknown regions may be tried.
        """
        R = self.wound_radius
        bed = rho < 1.0
        labels = np.zeros(bed.shape, np.uint8)
        labels[bed] = GRANULATION
        bed_area = max(1, int(bed.sum()))

        # epithelial rim: a band inside the edge over part of the perimeter, of varying width
        on = rim_on()
        rim_w = np.clip(0.10 + 0.05 * noise(1), 0.05, 0.18)
        rim = bed & (rho > 1.0 - rim_w) & (on > np.quantile(on[bed], rng.uniform(0.15, 0.4)))

        # necrotic: small dark blobs (absent for some seeds)
        inner = bed & (rho < 0.55)
        nec = np.zeros_like(bed)
        for _ in range(blobs):
            if rng.random() < 0.75 and inner.any():
                ys, xs = np.nonzero(inner)
                k = rng.integers(len(ys))
                cu, cv = U[ys[k], xs[k]], V[ys[k], xs[k]]
                r_n = R * rng.uniform(0.17, 0.27)
                d = dist(cu, cv) / r_n + 0.35 * noise(3)
                nec = nec | (bed & (d < 1.0))
        # slough: noisy patches covering 15-30 % of the bed, denser around the necrotic blobs
        sl_field = fbm(1.3, 3)
        if nec.any():
            sl_field = sl_field + 1.2 * np.exp(-dist_to(nec) / (0.25 * R))
        cand = bed & ~rim & ~nec
        target = rng.uniform(0.15, 0.30) * bed_area
        thr = np.quantile(sl_field[cand], 1 - min(0.95, target / max(1, cand.sum()))) if cand.any() else np.inf
        slough = cand & (sl_field > thr)
        # unknown: rare and small
        unk = np.zeros_like(bed)
        for _ in range(blobs):
            if rng.random() < 0.35:
                ys, xs = np.nonzero(bed & (rho > 0.4) & (rho < 0.85))
                if len(ys):
                    k = rng.integers(len(ys))
                    cu, cv = U[ys[k], xs[k]], V[ys[k], xs[k]]
                    d = dist(cu, cv) / (R * rng.uniform(0.08, 0.13)) + 0.3 * noise(4)
                    unk = unk | (bed & (d < 1.0))
        labels[slough] = SLOUGH
        labels[rim] = EPITHELIAL
        labels[nec] = NECROTIC
        labels[unk] = UNKNOWN
        return labels

    # --- textures -------------------------------------------------------------------------
    def _skin_tone(self, rng: np.random.Generator) -> np.ndarray:
        tones = np.array([[232, 196, 170], [214, 170, 138], [190, 140, 105], [150, 102, 72], [110, 74, 52]], np.float32)
        i = rng.uniform(0, len(tones) - 1)
        lo = int(np.floor(i))
        return tones[lo] * (1 - (i - lo)) + tones[min(lo + 1, len(tones) - 1)] * (i - lo)

    def _skin(self, rng: np.random.Generator, shape: tuple[int, int], extent: tuple[float, float], tone: np.ndarray,
              fine: bool) -> np.ndarray:
        """Skin albedo (H,W,3 float32 in 0..255) with features at physical scales (world units)."""
        h, w = shape
        ext_v, ext_u = extent
        img = np.broadcast_to(tone, (h, w, 3)).astype(np.float32).copy()
        # blotchiness and redness at a few scales
        blotch = _fbm(rng, shape, ext_u / 0.25, octaves=3, aspect=ext_v / ext_u)
        red = _fbm(rng, shape, ext_u / 0.12, octaves=2, aspect=ext_v / ext_u)
        img *= (1.0 + 0.07 * blotch)[..., None]
        img += np.array([9, -3, -3], np.float32) * np.clip(red, 0, None)[..., None]
        canvas = _skin_marks(rng, shape, extent, fine)
        brown = np.array([0.55, 0.38, 0.30], np.float32)
        img = img * (1 - canvas[..., None] * (1 - brown))
        return np.clip(img, 0, 255)

    def _window_skin(self, rng: np.random.Generator, tone: np.ndarray) -> np.ndarray:
        """Sets the global skin texture; returns the skin albedo over the texture window."""
        n = self.tex_res
        # global skin over the whole (u, v) domain, about 2 mm texels
        gw = int(np.clip(2 * self.u_half / 0.0025, 256, 2400))
        gh = int(np.clip(2 * self.v_half / 0.0025, 256, 2400))
        if n < 1024:
            gw, gh = max(128, gw // 3), max(128, gh // 3)
        self.global_albedo = self._skin(rng, (gh, gw), (2 * self.v_half, 2 * self.u_half), tone, fine=False)
        # window: global skin resampled + fine detail fading out at the window border
        U, V = self._window_coords()
        gx = (U + self.u_half) / (2 * self.u_half) * gw - 0.5
        gy = (V + self.v_half) / (2 * self.v_half) * gh - 0.5
        base = _bilinear(self.global_albedo, gx.ravel(), gy.ravel()).reshape(n, n, 3)
        detail = self._skin(rng, (n, n), (2 * self.half, 2 * self.half), tone, fine=True) / np.maximum(tone, 1)
        edge = np.minimum(np.minimum(U + self.half, self.half - U), np.minimum(V + self.half, self.half - V))
        fade = _smoothstep(0.0, 0.25 * self.half, edge)[..., None]
        return base * (1 - fade + fade * detail)

    # smooth noise over the texture window, features about wound_radius / mult apart; a blur and
    # a gradient (d/du, d/dv) over it: what a layout with a differently shaped window replaces
    def _win_noise(self, rng: np.random.Generator, mult: float) -> np.ndarray:
        cells = 2 * self.half / self.wound_radius
        return _noise(rng, (self.tex_res, self.tex_res), (cells * mult, cells * mult))

    def _win_fbm(self, rng: np.random.Generator, mult: float, octaves: int, aspect: float = 1.0) -> np.ndarray:
        cells = 2 * self.half / self.wound_radius
        return _fbm(rng, (self.tex_res, self.tex_res), cells * mult, octaves=octaves, aspect=aspect)

    def _blur(self, img: np.ndarray, sigma: float) -> np.ndarray:
        return cv2.GaussianBlur(img, (0, 0), sigma)

    def _grad(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gy, gx = np.gradient(img, self.texel)
        return gx, gy

    def _textures(self, rng: np.random.Generator) -> None:
        """Albedo, gloss and relief over the texture window, all drawn from the class labels."""
        tone = self._skin_tone(rng)
        self.skin_tone = tone
        skin = self._window_skin(rng, tone)
        bumps = self._win_fbm(rng, 12, octaves=2)  # granulation cobbles ~ R/12
        fine = self._win_noise(rng, 30)
        mott = self._win_fbm(rng, 3, octaves=3)
        fib = self._win_fbm(rng, 6, octaves=2, aspect=4.0)
        self.albedo = self._tissue_albedo(skin, bumps, fine, mott, fib)
        # specular strength and shininess per class (wet wound bed, dry skin)
        spec = np.array([0.05, 0.45, 0.28, 0.15, 0.3, 0.25], np.float32)
        shin = np.array([12, 45, 30, 20, 40, 30], np.float32)
        self.spec = spec[self.labels]
        self.shin = shin[self.labels]
        self._relief(rng, bumps, fine)

    def _tissue_albedo(self, skin: np.ndarray, bumps: np.ndarray, fine: np.ndarray, mott: np.ndarray,
                       fib: np.ndarray) -> np.ndarray:
        """Each tissue's colour with its own texture over the skin, and an inflamed halo around
        the wound, so a segmenter sees the cues it would on a real wound."""
        lab = self.labels
        alb = skin.copy()
        m = lab == GRANULATION
        gran = np.array([186, 44, 46], np.float32)
        shade = 0.78 + 0.22 * bumps + 0.06 * mott
        alb[m] = gran * shade[m, None] + np.array([30, 10, 12], np.float32) * _smoothstep(0.8, 1.8, bumps)[m, None]
        m = lab == SLOUGH
        alb[m] = np.array([214, 190, 108], np.float32) * (0.85 + 0.1 * fib[m] + 0.06 * mott[m])[:, None]
        m = lab == NECROTIC
        alb[m] = np.array([48, 34, 30], np.float32) * (0.85 + 0.2 * mott[m] + 0.05 * fine[m])[:, None]
        m = lab == EPITHELIAL
        alb[m] = np.array([228, 158, 160], np.float32) * (0.93 + 0.05 * mott[m])[:, None]
        m = lab == UNKNOWN
        alb[m] = np.array([122, 78, 120], np.float32) * (0.9 + 0.1 * mott[m])[:, None]
        # a reddish inflamed halo on the skin around the wound
        halo = _smoothstep(1.6, 1.0, self.rho) * (lab == BACKGROUND)
        alb = alb * (1 - 0.25 * halo[..., None]) + 0.25 * halo[..., None] * np.array([205, 110, 100], np.float32)
        return np.clip(alb, 0, 255).astype(np.float32)

    def _relief(self, rng: np.random.Generator, bumps: np.ndarray, fine: np.ndarray) -> None:
        """Sets the relief: a crater the mesh carries (``height_geo``, so depth and silhouettes see
        it) and fine bumps only the shading sees (``bump_grad``), too small for the mesh."""
        R, lab = self.wound_radius, self.labels
        d = self.crater_depth
        crater = -d * (1 - _smoothstep(0.82, 1.08, self.rho))
        bed = (lab != BACKGROUND).astype(np.float32)
        bed_s = self._blur(bed, max(1.0, 0.02 * R / self.texel))
        geo = crater + bed_s * (0.18 * d * self._win_fbm(rng, 5, octaves=2) + 0.25 * d * (lab == SLOUGH))
        geo = self._blur(geo.astype(np.float32), max(1.0, 0.01 * R / self.texel))
        self.height_geo = geo.astype(np.float32)
        hb = bed_s * 0.004 * R * (bumps * (lab == GRANULATION) + 0.4 * fine)
        hb = self._blur(hb.astype(np.float32), 1.0)
        gx, gy = self._grad(hb)
        self.bump_grad = np.stack([gx, gy], -1).astype(np.float32)  # d/du, d/dv

    # --- truth summaries --------------------------------------------------------------------
    def _area_step(self) -> int:
        return max(1, self.tex_res // 1024)

    def class_areas(self) -> dict[str, float]:
        """Surface area per class (world units^2), integrating the surface's area element."""
        U, V = self._window_coords()
        step = self._area_step()
        U, V, lab = U[::step, ::step].astype(np.float64), V[::step, ::step].astype(np.float64), self.labels[::step, ::step]
        P = self.surface(U, V, self.displacement(U, V))
        h = self.texel * step
        du = np.gradient(P, h, axis=1)
        dv = np.gradient(P, h, axis=0)
        dA = np.linalg.norm(np.cross(du, dv), axis=-1) * h * h
        names = {c.id: c.name for c in DEFAULT_CLASSES}
        return {names[c]: float(dA[lab == c].sum()) for c in WOUND_CLASSES}

    def describe(self) -> dict:
        d: dict = {"kind": self.kind, "domain_uv_half": [self.u_half, self.v_half],
                   "wound_radius": self.wound_radius, "crater_depth": self.crater_depth,
                   "wound_center": [float(x) for x in self.center], "wound_normal": [0.0, 0.0, 1.0],
                   "mesh_faces": int(len(self.faces)), "texture_window_half": self.half}
        if self.kind == "limb":
            d.update(radius=self.radius, taper=self.taper, axis="x",
                     note="x = u, radius(u) = radius*(1+taper*u) + h, angle = v/radius, top (z) at v=0; world z = r*cos - radius")
        else:
            d.update(curvature_radii=list(self.curv), note="z = -(u^2/(2*r0) + v^2/(2*r1)) + h")
        return d

    # --- rendering -------------------------------------------------------------------------
    def _rays(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre rays as Camera.rays(), with the camera-frame directions cached per intrinsics."""
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2, cam.p1, cam.p2)
        if getattr(self, "_ray_key", None) != key:
            _, self._ray_cam = cam.with_c2w(np.eye(4)).rays()
            self._ray_key = key
        dirs = self._ray_cam @ cam.c2w[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        return np.broadcast_to(cam.c2w[:3, 3], dirs.shape), dirs

    def render(self, cam: Camera, lights: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One ray per pixel centre: (RGB uint8 (H,W,3), class ids uint8 (H,W), depth float32 (H,W))."""
        W, H = cam.width, cam.height
        origins, dirs = self._rays(cam)
        prim, bary = self.intersect(origins, dirs)
        hit = prim >= 0
        surf = self._surface_at(prim[hit], bary[hit])
        d = dirs[hit].astype(np.float32)
        depth = np.full(W * H, np.inf, np.float32)
        depth[hit] = np.einsum("ij,ij->i", surf.pos - origins[hit].astype(np.float32), d)
        mat = self._material(surf.uv)
        nrm = self._bumped_normal(surf, mat.bump_grad, d)
        col = self._shade(mat, nrm, -d, lights)

        img = background_image(W, H).reshape(-1, 3).astype(np.float32)
        vig = _vignette(W, H).reshape(-1)
        img[hit] = col * vig[hit, None]
        rgb = np.clip(np.round(img), 0, 255).astype(np.uint8).reshape(H, W, 3)
        truth = np.zeros(W * H, np.uint8)
        truth[hit] = mat.labels
        return rgb, truth.reshape(H, W), depth.reshape(H, W)

    def _surface_at(self, faces: np.ndarray, bary: np.ndarray) -> _SurfaceHits:
        """The mesh's vertex attributes blended at the hits, so colour and truth share one (u, v)."""
        f = self.faces[faces]
        w = bary.astype(np.float32)
        a = self._attrs
        attrs = a[f[:, 0]] * w[:, :1] + a[f[:, 1]] * w[:, 1:2] + a[f[:, 2]] * w[:, 2:3]
        return _SurfaceHits(pos=attrs[:, 0:3], uv=attrs[:, 3:5], normal=attrs[:, 5:8], tu=attrs[:, 8:11],
                            tv=attrs[:, 11:14])

    def _material(self, uv: np.ndarray) -> _Material:
        """Class, albedo, gloss and bump slope at each hit: the window textures inside the window
        (labels nearest-texel, so truth stays crisp), the global skin texture outside it."""
        x, y = self._tex_coords(uv[:, 0], uv[:, 1])
        rows, cols = self.tex_shape
        tex = self._tex
        n = len(uv)
        inwin = (x >= -0.5) & (y >= -0.5) & (x < cols - 0.5) & (y < rows - 0.5)
        labels = np.zeros(n, np.uint8)
        xi = np.clip(np.floor(x[inwin] + 0.5).astype(np.int64), 0, cols - 1)
        yi = np.clip(np.floor(y[inwin] + 0.5).astype(np.int64), 0, rows - 1)
        labels[inwin] = tex["labels"][yi, xi]

        albedo = np.empty((n, 3), np.float32)
        albedo[inwin] = _remap(tex["albedo"], x[inwin], y[inwin])
        out = ~inwin
        albedo[out] = _remap(tex["global_albedo"], *self._global_xy(uv[out, 0], uv[out, 1]))
        spec = np.full(n, 0.05, np.float32)
        shin = np.full(n, 12.0, np.float32)
        spec[inwin] = tex["spec"][yi, xi]
        shin[inwin] = tex["shin"][yi, xi]
        bump_grad = np.zeros((n, 2), np.float32)
        bump_grad[inwin] = _remap(tex["bump_grad"], x[inwin], y[inwin])
        return _Material(labels=labels, albedo=albedo, spec=spec, shin=shin, bump_grad=bump_grad)

    @staticmethod
    def _bumped_normal(surf: _SurfaceHits, bump_grad: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The mesh normal tilted by the bump map (fine relief the mesh is too coarse to hold),
        turned to face the viewer (rays may graze the far side of a bump)."""
        nrm = surf.normal - bump_grad[:, :1] * surf.tu - bump_grad[:, 1:2] * surf.tv
        nrm /= np.sqrt(np.einsum("ij,ij->i", nrm, nrm))[:, None]
        flip = np.einsum("ij,ij->i", nrm, d) > 0
        nrm[flip] *= -1
        return nrm

    @staticmethod
    def _shade(mat: _Material, nrm: np.ndarray, view: np.ndarray, lights: dict) -> np.ndarray:
        """Blinn-Phong colour (0..255 float) under the scene's lights plus a weak phone light at the
        camera, so the wet wound bed glints as in a real capture."""
        shin = mat.shin
        shade = np.full(len(nrm), lights["ambient"], np.float32)
        spec_acc = np.zeros(len(nrm), np.float32)
        for ldir, power in lights["directional"]:
            ldir = ldir.astype(np.float32)
            ndl = np.clip(nrm @ ldir, 0, None)
            shade += power * ndl
            hvec = view + ldir
            hvec /= np.sqrt(np.einsum("ij,ij->i", hvec, hvec))[:, None]
            spec_acc += power * (ndl > 0) * np.clip(np.einsum("ij,ij->i", nrm, hvec), 0, None) ** shin
        ndv = np.clip(np.einsum("ij,ij->i", nrm, view), 0, None)
        shade += lights["headlight"] * ndv
        spec_acc += lights["headlight"] * ndv**shin
        return mat.albedo * shade[:, None] + 255.0 * (mat.spec * spec_acc)[:, None] * np.array([1.0, 0.97, 0.93],
                                                                                             np.float32)


class _AroundScene(_Scene):
    """A wound wrapped around a limb (layout "all-around"), for a capture filmed all around it.

    The body is the limb tube of the one-sided layout, long enough (u in [-4, 4]) that its open
    ends stay out of view of an orbit near u = 0, and closed along its seam (v = +-pi*radius).
    The wound is a band around the limb: a centre line along u and a half-width
    (``wound_radius``, the band's typical half-width) that vary with the angle v/radius, over a
    fraction ``coverage`` of the circumference with rounded ends, or over all of it (a
    circumferential wound). Inside it, the tissues are drawn as in the one-sided layout.

    The texture window spans u in [-half, half] and the whole circumference in v (rows along v,
    columns along u, square texels); every texture is periodic in v, so labels, colour and
    relief run on across the seam. Rendering samples copies padded by one wrapped row.
    """

    def __init__(self, rng: np.random.Generator, detail: int) -> None:
        self.kind = "limb"
        self.radius = float(rng.uniform(0.4, 0.6))
        self.taper = float(rng.uniform(-0.06, 0.06))  # relative radius change per unit length
        self.u_half, self.v_half = 4.0, float(np.pi * self.radius)
        self.wound_radius = float(rng.uniform(0.12, 0.22))
        self.full_ring = bool(rng.random() < 0.4)
        self.coverage = 1.0 if self.full_ring else float(rng.uniform(0.6, 0.92))
        self.band_angle = float(rng.uniform(-np.pi, np.pi))  # middle of the band (radians around x)
        self.crater_depth = float(rng.uniform(0.03, 0.06) * 2 * self.wound_radius)
        # texel budget: 1.5x the one-sided window's texel count
        self.detail = int(detail)
        period = 2 * self.v_half
        half = 3.6 * self.wound_radius
        texel = float(np.sqrt(2 * half * period / (1.5 * float(detail) ** 2)))
        self.n_v = max(32, int(round(period / texel)))
        self.texel = period / self.n_v
        self.tex_res = int(np.ceil(2 * half / self.texel))  # columns, along u
        self.half = self.tex_res * self.texel / 2  # texture window half-size along u
        self._layout(rng)
        self._textures(rng)
        self._sampling_textures()
        self._mesh(rng)
        self.axis_point = np.array([0.0, 0.0, -self.radius])
        vc = np.array([self.band_angle * self.radius])
        self.center = self.surface(np.zeros(1), vc, self.displacement(np.zeros(1), vc))[0]

    # --- texture window -------------------------------------------------------------------
    def _window_coords(self) -> tuple[np.ndarray, np.ndarray]:
        cu = (np.arange(self.tex_res) + 0.5) * self.texel - self.half
        cv = (np.arange(self.n_v) + 0.5) * self.texel - self.v_half
        U, V = np.meshgrid(cu, cv, indexing="xy")  # rows along v, columns along u
        return U.astype(np.float32), V.astype(np.float32)

    def _tex_coords(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = (u + self.half) / self.texel - 0.5
        y = (v + self.v_half) / self.texel + 0.5  # + 1: the padded row before row 0
        return x, y

    def _global_xy(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gh, gw = self.global_albedo.shape[:2]
        return (u + self.u_half) / (2 * self.u_half) * gw - 0.5, (v + self.v_half) / (2 * self.v_half) * gh + 0.5

    def _sampling_textures(self) -> None:
        self._tex = {name: _pad_rows(getattr(self, name)) for name in
                     ("labels", "albedo", "spec", "shin", "bump_grad", "height_geo", "global_albedo")}
        self.tex_shape = self._tex["labels"].shape

    def _cells(self, mult: float) -> tuple[float, float]:
        """Noise features wound_radius / mult apart: (per period along v, per window along u)."""
        return 2 * self.v_half * mult / self.wound_radius, 2 * self.half * mult / self.wound_radius

    def _win_noise(self, rng: np.random.Generator, mult: float) -> np.ndarray:
        return _noise_wrap(rng, (self.n_v, self.tex_res), self._cells(mult))

    def _win_fbm(self, rng: np.random.Generator, mult: float, octaves: int, aspect: float = 1.0) -> np.ndarray:
        return _fbm_wrap(rng, (self.n_v, self.tex_res), self._cells(mult), octaves=octaves, aspect=aspect)

    def _blur(self, img: np.ndarray, sigma: float) -> np.ndarray:
        p = min(self.n_v, int(np.ceil(4 * sigma)) + 2)
        ext = np.concatenate([img[-p:], img, img[:p]], axis=0)
        return cv2.GaussianBlur(ext, (0, 0), sigma)[p: p + self.n_v]

    def _grad(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gx = np.gradient(img, self.texel, axis=1)
        gy = (np.roll(img, -1, axis=0) - np.roll(img, 1, axis=0)) / (2 * self.texel)
        return gx, gy

    def _wrap_v(self, dv: np.ndarray) -> np.ndarray:
        """A difference along v taken the short way round the limb."""
        return (dv + self.v_half) % (2 * self.v_half) - self.v_half

    def _dist_to(self, mask: np.ndarray) -> np.ndarray:
        p = min(self.n_v, int(np.ceil(3 * self.wound_radius / self.texel)))
        ext = np.concatenate([mask[-p:], mask, mask[:p]], axis=0)
        return cv2.distanceTransform((~ext).astype(np.uint8), cv2.DIST_L2, 5)[p: p + self.n_v] * self.texel

    # --- wound layout ---------------------------------------------------------------------
    def _layout(self, rng: np.random.Generator) -> None:
        """The band's outline from harmonics of the angle and periodic noise; tissues as one-sided."""
        R, r = self.wound_radius, self.radius
        U, V = self._window_coords()
        th = V / np.float32(r)  # angle around the axis, -pi..pi (float32 like the window)
        # centre line meandering along u, half-width varying around the limb
        uc = np.zeros_like(th)
        for k in (1, 2, 3):
            uc += R * rng.uniform(0.0, 0.25 / k) * np.cos(k * th + rng.uniform(0, 2 * np.pi))
        hw = np.ones_like(th)
        for k in range(2, 9):
            hw += rng.uniform(0.0, 0.25 / k) * np.cos(k * th + rng.uniform(0, 2 * np.pi))
        hw = R * np.maximum(hw, 0.6)
        warp = 0.12 * R
        a = U - uc + warp * self._win_noise(rng, 1.5)
        along = warp * self._win_noise(rng, 1.5)
        rho = np.abs(a) / hw
        if not self.full_ring:  # rounded ends: a capsule along v of total length coverage x circumference
            s = np.abs(self._wrap_v(V - self.band_angle * r)) + along
            end = np.maximum(0.0, s - (self.coverage * self.v_half - hw)) / hw
            rho = np.hypot(rho, end)
        self.rho = rho.astype(np.float32)
        # the rim's on/off field: harmonics of the angle, one set per edge, blended across the band
        ks = range(1, 7)
        side = _smoothstep(-0.5, 0.5, a / hw)

        def rim_on() -> np.ndarray:
            lo = sum(rng.uniform(0.3, 1.0) * np.cos(k * th + rng.uniform(0, 2 * np.pi)) for k in ks)
            hi = sum(rng.uniform(0.3, 1.0) * np.cos(k * th + rng.uniform(0, 2 * np.pi)) for k in ks)
            return (1 - side) * lo + side * hi

        bed_area = float((rho < 1.0).sum()) * self.texel**2
        blobs = int(np.clip(round(bed_area / (np.pi * R * R) / 4), 1, 4))  # about one per 4 one-sided wounds
        self.labels = self._draw_tissues(
            rng, U, V, rho, blobs=blobs,
            noise=lambda mult: self._win_noise(rng, mult),
            fbm=lambda mult, octaves: self._win_fbm(rng, mult, octaves=octaves),
            dist=lambda cu, cv: np.hypot(U - cu, self._wrap_v(V - cv)),
            dist_to=self._dist_to, rim_on=rim_on,
        )

    # --- textures -------------------------------------------------------------------------
    def _window_skin(self, rng: np.random.Generator, tone: np.ndarray) -> np.ndarray:
        gw = int(np.clip(2 * self.u_half / 0.0025, 256, 2400))
        gh = int(np.clip(2 * self.v_half / 0.0025, 256, 2400))
        if self.detail < 1024:
            gw, gh = max(128, gw // 3), max(128, gh // 3)
        m = max(4, gh // 16)
        g = self._skin(rng, (gh + m, gw), (2 * self.v_half * (gh + m) / gh, 2 * self.u_half), tone, fine=False)
        self.global_albedo = _fold_rows(g, m)
        U, V = self._window_coords()
        gx, gy = self._global_xy(U, V)
        base = _bilinear(_pad_rows(self.global_albedo), gx.ravel(), gy.ravel()).reshape(*U.shape, 3)
        m = max(8, self.n_v // 16)
        det = self._skin(rng, (self.n_v + m, self.tex_res), (self.texel * (self.n_v + m), 2 * self.half), tone, fine=True)
        detail = _fold_rows(det, m) / np.maximum(tone, 1)
        edge = np.minimum(U + self.half, self.half - U)  # the window has edges along u only
        fade = _smoothstep(0.0, 0.25 * self.half, edge)[..., None]
        return base * (1 - fade + fade * detail)

    # --- geometry -------------------------------------------------------------------------
    def _mesh(self, rng: np.random.Generator) -> None:
        n_v = int(np.clip(self.n_v // 4, 240, 1200))
        step = 2 * self.v_half / n_v
        v1 = -self.v_half + step * np.arange(n_v)
        # along u: even steps over the texture window, then 8 % longer each to the tube's ends
        m = int(np.ceil(self.half / step))
        outer, x, du = [], m * step, step
        while x < self.u_half:
            du *= 1.08
            x = min(self.u_half, x + du)
            outer.append(x)
        outer = np.array(outer)
        u1 = np.concatenate([-outer[::-1], step * np.arange(-m, m + 1), outer])
        U, V = np.meshgrid(u1, v1, indexing="ij")  # (nu, n_v): i along u, j along v
        P = self.surface(U, V, self.displacement(U, V))
        du = np.gradient(P, axis=0)
        dv = 0.5 * (np.roll(P, -1, axis=1) - np.roll(P, 1, axis=1))  # around the closed tube

        def close(a: np.ndarray) -> np.ndarray:  # repeat the first column (v = -pi r) at v = +pi r
            return np.concatenate([a, a[:, :1]], axis=1)

        V = close(V)
        V[:, -1] = self.v_half
        self._set_mesh(close(U), V, close(P), close(du), close(dv))

    # --- truth summaries --------------------------------------------------------------------
    def _area_step(self) -> int:
        return max(1, int(np.ceil(np.sqrt(self.n_v * self.tex_res / 1.5e6))))

    def describe(self) -> dict:
        d = super().describe()
        normal = np.array([0.0, np.sin(self.band_angle), np.cos(self.band_angle)])
        d.update(layout="all-around", wound_normal=[float(x) for x in normal],
                 axis_point=[float(x) for x in self.axis_point], texture_window_half=[self.half, self.v_half],
                 band={"half_width": self.wound_radius, "coverage": self.coverage, "full_ring": self.full_ring,
                       "middle_angle_deg": float(np.rad2deg(self.band_angle))},
                 note="x = u, radius(u) = radius*(1+taper*u) + h, angle = v/radius, top (z) at v=0; world z = r*cos - radius;"
                      " wound_radius = typical half-width of the band along x; wound_center = the band's middle at x=0")
        return d



# ------------------------------------------------------------------------------------------
# cameras
# ------------------------------------------------------------------------------------------
def _smooth_curve(rng: np.random.Generator, t: np.ndarray, freqs: tuple[float, ...]) -> np.ndarray:
    """A smooth random curve in about [-1, 1] over t in [0, 1] (sum of a few sines)."""
    out = np.zeros_like(t)
    total = 0.0
    for f in freqs:
        a = rng.uniform(0.5, 1.0)
        out += a * np.sin(2 * np.pi * f * rng.uniform(0.8, 1.2) * t + rng.uniform(0, 2 * np.pi))
        total += a
    return out / total


def _camera_path(rng: np.random.Generator, scene: _Scene, cfg: SynthConfig) -> tuple[list[Camera], dict]:
    """A hand-held phone path: an arc above the wound with varying elevation, distance and roll."""
    hfov = np.deg2rad(rng.uniform(55, 65))
    fx = cfg.width / (2 * np.tan(hfov / 2))
    frac = rng.uniform(0.25, 0.35)  # wound diameter / image width at the typical distance
    d0 = 2 * scene.wound_radius / (frac * 2 * np.tan(hfov / 2))
    n = cfg.frames
    t = np.linspace(0.0, 1.0, n)
    sweep = np.deg2rad(rng.uniform(200, 300)) * (1 if rng.random() < 0.5 else -1)
    az = rng.uniform(0, 2 * np.pi) + sweep * t + 0.08 * _smooth_curve(rng, t, (1.7, 3.1))
    el_lo, el_hi = np.deg2rad(35), np.deg2rad(80)
    el_curve = 0.5 + 0.5 * _smooth_curve(rng, t, (0.8, 1.3, 2.2))
    el_curve = (el_curve - el_curve.min()) / max(1e-6, np.ptp(el_curve))
    el = el_lo + (el_hi - el_lo) * (0.05 + 0.9 * el_curve)
    dist = d0 * (1 + 0.2 * _smooth_curve(rng, t, (0.9, 1.9)))
    roll = np.deg2rad(6) * _smooth_curve(rng, t, (1.1, 2.7))
    jit = 0.15 * scene.wound_radius
    tx, ty = jit * _smooth_curve(rng, t, (1.3, 2.9)), jit * _smooth_curve(rng, t, (1.6, 3.3))
    c0 = scene.center
    normal, t1, t2 = np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    cams = []
    for i in range(n):
        eye = c0 + dist[i] * (np.cos(el[i]) * (np.cos(az[i]) * t1 + np.sin(az[i]) * t2) + np.sin(el[i]) * normal)
        target = c0 + tx[i] * t1 + ty[i] * t2
        c2w = look_at(eye, target, up=normal)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        c2w[:3, :3] = c2w[:3, :3] @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        cams.append(Camera(cfg.width, cfg.height, fx, fx, cfg.width / 2, cfg.height / 2, c2w))
    info = {"hfov_deg": float(np.rad2deg(hfov)), "typical_distance": float(d0),
            "elevation_deg": [float(np.rad2deg(el.min())), float(np.rad2deg(el.max()))],
            "distance": [float(dist.min()), float(dist.max())], "sweep_deg": float(np.rad2deg(sweep))}
    return cams, info


def _orbit_path(rng: np.random.Generator, scene: _AroundScene, cfg: SynthConfig) -> tuple[list[Camera], dict]:
    """An all-around path: one turn around the limb's axis (world x), always aimed at the axis
    near the wound, with smooth random wobbles in distance, position along the axis, tilt
    (looking a little along the limb) and roll. The axis runs across the image."""
    hfov = np.deg2rad(rng.uniform(55, 65))
    tan = np.tan(hfov / 2)
    fx = cfg.width / (2 * tan)
    r, R = scene.radius, scene.wound_radius
    # distance from the axis: the limb's outline takes 75-95 % of the image height, so the band
    # runs through the frame and the limb's sides show; the region of interest (about the image
    # footprint at the axis) then holds the limb's cross-section with room to spare
    vhalf = np.arctan(tan * cfg.height / cfg.width)
    d0 = float(r / np.sin(rng.uniform(0.75, 0.95) * vhalf))
    n = cfg.frames
    t = np.arange(n) / n
    turn = 2 * np.pi * (1 if rng.random() < 0.5 else -1)
    theta = rng.uniform(-np.pi, np.pi) + turn * t + 0.08 * _smooth_curve(rng, t, (1.7, 3.1))
    dist = d0 * (1 + 0.12 * _smooth_curve(rng, t, (0.9, 1.9)))
    along = 0.5 * R * _smooth_curve(rng, t, (0.7, 1.6))  # aim point along the axis
    tilt = np.deg2rad(rng.uniform(5, 15)) * _smooth_curve(rng, t, (0.8, 1.7))
    roll = np.deg2rad(6) * _smooth_curve(rng, t, (1.1, 2.7))
    x_axis = np.array([1.0, 0, 0])
    cams = []
    for i in range(n):
        radial = np.array([0.0, np.sin(theta[i]), np.cos(theta[i])])
        tangent = np.array([0.0, np.cos(theta[i]), -np.sin(theta[i])])
        target = scene.axis_point + along[i] * x_axis
        eye = target + dist[i] * (np.cos(tilt[i]) * radial + np.sin(tilt[i]) * x_axis)
        c2w = look_at(eye, target, up=tangent)  # image right = +x (the axis)
        cr, sr = np.cos(roll[i]), np.sin(roll[i])
        c2w[:3, :3] = c2w[:3, :3] @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        cams.append(Camera(cfg.width, cfg.height, fx, fx, cfg.width / 2, cfg.height / 2, c2w))
    info = {"kind": "orbit", "axis": "x", "hfov_deg": float(np.rad2deg(hfov)), "typical_distance": float(d0),
            "distance": [float(dist.min()), float(dist.max())],
            "tilt_deg": [float(np.rad2deg(tilt.min())), float(np.rad2deg(tilt.max()))],
            "along_axis": [float(along.min()), float(along.max())], "sweep_deg": float(np.rad2deg(turn)),
            "start_angle_deg": float(np.rad2deg(theta[0]))}
    return cams, info


# ------------------------------------------------------------------------------------------
# predictions: a good but imperfect segmenter
# ------------------------------------------------------------------------------------------
def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _smooth_field(rng: np.random.Generator, h: int, w: int, scale_px: float) -> np.ndarray:
    return _noise(rng, (h, w), (max(1.0, h / scale_px), max(1.0, w / scale_px)))


@dataclass
class _ErrorDraws:
    """The random draws every error step shares, scaled to the frame (one per frame, in order)."""

    rng: np.random.Generator
    shape: tuple[int, int]  # (h, w)
    scale: float  # pixel magnitudes are given for 640-pixel-wide frames
    noise: float

    def radius(self, lo: float = 1.0, hi: float = 4.0) -> int:
        """A morphology radius in pixels, at least 1."""
        return int(max(1, round(self.rng.uniform(lo, hi) * self.scale * self.noise)))

    def smooth_field(self, scale_px: float) -> np.ndarray:
        """Smooth noise over the frame with features about ``scale_px`` pixels apart."""
        return _smooth_field(self.rng, *self.shape, scale_px)

    def partial(self, mask: np.ndarray, lo: float, hi: float) -> np.ndarray:
        """A random smooth part (fraction in [lo, hi]) of ``mask``."""
        if not mask.any():
            return mask
        f = self.smooth_field(25 * self.scale + 3)
        q = np.quantile(f[mask], 1 - self.rng.uniform(lo, hi))
        return mask & (f >= q)


def predict_errors(truth: np.ndarray, on_body: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """A plausible automatic segmentation of one frame: ``truth`` with view-specific errors.

    ``on_body`` marks pixels whose ray hit the body (false wound blobs go on skin there).
    ``noise`` scales every error (0 returns the truth).
    """
    lab = truth.copy()
    if noise <= 0:
        return lab
    draws = _ErrorDraws(rng, lab.shape, lab.shape[1] / 640.0, noise)
    p = min(1.0, noise)
    lab = _jitter_boundaries(lab, draws)
    _misjudge_outline(lab, draws)
    _misjudge_tissue_extents(lab, draws)
    _confuse_tissues(lab, draws, p)
    _miss_small_regions(lab, draws, p)
    _false_blobs(lab, truth, on_body, draws, p)
    return lab


def _jitter_boundaries(lab: np.ndarray, draws: _ErrorDraws) -> np.ndarray:
    """Wavy boundaries: a smooth random displacement field, nearest-neighbour resampling."""
    h, w = draws.shape
    amp = 3.5 * draws.scale * draws.noise
    dx = amp * draws.smooth_field(40 * draws.scale + 4)
    dy = amp * draws.smooth_field(40 * draws.scale + 4)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(lab, gx + dx, gy + dy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def _misjudge_outline(lab: np.ndarray, draws: _ErrorDraws) -> None:
    """The wound-bed outline drawn too big or too small (in place)."""
    bed = lab > 0
    r = draws.radius(2.0, 6.0)
    if draws.rng.random() < 0.5:
        grown = cv2.dilate(bed.astype(np.uint8), _disk(r)).astype(bool) & ~bed
        fill = cv2.dilate(lab, _disk(r))  # some neighbouring tissue id
        lab[grown] = fill[grown]
    else:
        lab[bed & ~cv2.erode(bed.astype(np.uint8), _disk(r)).astype(bool)] = BACKGROUND


def _misjudge_tissue_extents(lab: np.ndarray, draws: _ErrorDraws) -> None:
    """Each tissue grown or shrunk inside the bed, in random order (in place)."""
    bed = lab > 0
    for c in draws.rng.permutation(WOUND_CLASSES):
        m = lab == c
        if not m.any():
            continue
        r = draws.radius(1.0, 3.0)
        if draws.rng.random() < 0.5:
            lab[cv2.dilate(m.astype(np.uint8), _disk(r)).astype(bool) & bed] = c
        else:
            ring = m & ~cv2.erode(m.astype(np.uint8), _disk(r)).astype(bool)
            other = np.where(m, 0, lab).astype(np.uint8)
            fill = cv2.dilate(other, _disk(r + 1))
            lab[ring] = np.where(bed[ring], np.where(fill[ring] > 0, fill[ring], c), BACKGROUND)


def _confuse_tissues(lab: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """A missed stretch of edge and the tissue mix-ups a 2D segmenter makes, each in some views
    only (in place), so that views disagree and a multi-view vote can fix them."""
    rng = draws.rng
    # part of the wound edge missed (glare, shadow)
    if rng.random() < 0.35 * p:
        bed = lab > 0
        inner = cv2.erode(bed.astype(np.uint8), _disk(int(max(2, round(14 * draws.scale))))).astype(bool)
        lab[draws.partial(bed & ~inner, 0.2, 0.5)] = BACKGROUND
    # slough taken for granulation (fully or partly) in a good fraction of the views
    if rng.random() < 0.38 * p:
        lab[draws.partial(lab == SLOUGH, 0.5, 1.0)] = GRANULATION
    # granulation taken for slough in a few
    if rng.random() < 0.12 * p:
        lab[draws.partial(lab == GRANULATION, 0.08, 0.25)] = SLOUGH
    # necrotic taken for slough / granulation
    if rng.random() < 0.2 * p:
        lab[draws.partial(lab == NECROTIC, 0.4, 1.0)] = SLOUGH if rng.random() < 0.6 else GRANULATION
    # epithelial rim missed (part to skin, part to granulation)
    if rng.random() < 0.3 * p:
        lab[draws.partial(lab == EPITHELIAL, 0.4, 1.0)] = BACKGROUND if rng.random() < 0.6 else GRANULATION


def _miss_small_regions(lab: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """Small necrotic, unknown and slough regions taken for granulation now and then (in place)."""
    s = draws.scale
    for c in (NECROTIC, UNKNOWN, SLOUGH):
        m = (lab == c).astype(np.uint8)
        if not m.any():
            continue
        n_cc, cc, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        small = max(30 * s * s, 0.02 * max(1, int((lab > 0).sum())))
        for k in range(1, n_cc):
            if stats[k, cv2.CC_STAT_AREA] < small and draws.rng.random() < 0.5 * p:
                lab[cc == k] = GRANULATION


def _false_blobs(lab: np.ndarray, truth: np.ndarray, on_body: np.ndarray, draws: _ErrorDraws, p: float) -> None:
    """False-positive wound blobs on the skin in a few views (in place)."""
    rng, noise = draws.rng, draws.noise
    h, w = draws.shape
    if rng.random() < 0.25 * p:
        skin = on_body & (truth == BACKGROUND)
        ys, xs = np.nonzero(skin)
        for _ in range(int(rng.integers(1, 3))):
            if not len(ys):
                break
            k = rng.integers(len(ys))
            rx, ry = rng.uniform(0.015, 0.045) * w * np.sqrt(noise), rng.uniform(0.015, 0.045) * w * np.sqrt(noise)
            yy, xx = np.ogrid[:h, :w]
            wobble = 0.35 * _smooth_field(rng, h, w, 10 * draws.scale + 2)
            blob = ((xx - xs[k]) / rx) ** 2 + ((yy - ys[k]) / ry) ** 2 + wobble < 1.0
            lab[blob & skin] = GRANULATION if rng.random() < 0.7 else EPITHELIAL


# ------------------------------------------------------------------------------------------
# the whole capture
# ------------------------------------------------------------------------------------------
def annotated_indices(frames: int, annotated: int) -> list[int]:
    """Evenly spread frame indices (centres of equal segments of the path), the same rule as
    ``--annotated-frames spread:N``."""
    return spread_indices(frames, annotated)


def synthesize(out: Path, cfg: SynthConfig | None = None, *, force: bool = False, progress: bool = True) -> SynthResult:
    """Write a synthetic capture (OUT/capture) and its exact truth (OUT/truth).

    The folder is built in OUT.partial and renamed at the end (``outdir.building``), so an
    interrupted run never leaves an OUT that looks complete. Masks are greyscale class-id PNGs.
    """
    cfg = cfg or SynthConfig()
    out = Path(out)
    start = time.perf_counter()
    with building(out, force=force) as tmp:
        scene, cams, path_info, lights = _scene_and_cameras(np.random.default_rng([cfg.seed, 0]), cfg)
        cap, truth_dir = tmp / "capture", tmp / "truth"
        for d in (cap / "images", cap / "annotations", cap / "predictions", truth_dir / "depth"):
            d.mkdir(parents=True)
        names = [f"frame_{i:03d}" if cfg.frames <= 1000 else f"frame_{i:05d}" for i in range(cfg.frames)]
        ann = set(annotated_indices(cfg.frames, cfg.annotated))
        frames_json = _write_frames(cap, truth_dir, scene, cams, lights, names, ann, cfg, progress)
        c0 = cams[0]
        transforms = {"camera_model": "OPENCV", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx, "cy": c0.cy,
                      "w": cfg.width, "h": cfg.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                      "frames": frames_json}
        (cap / "transforms.json").write_text(json.dumps(transforms, indent=2))
        annotated = [names[i] for i in sorted(ann)]
        meta = {"seed": cfg.seed, "layout": cfg.layout, "config": asdict(cfg), "surface": scene.describe(), "camera_path": path_info,
                "class_areas": scene.class_areas(), "area_units": "world units squared",
                "annotated": annotated, "frames": names,
                "classes": [{"id": c.id, "name": c.name} for c in DEFAULT_CLASSES]}
        (truth_dir / "scene.json").write_text(json.dumps(meta, indent=2))
    return SynthResult(capture_dir=out / "capture", truth_dir=out / "truth", num_frames=cfg.frames,
                       annotated=annotated, seconds=time.perf_counter() - start)


def _scene_and_cameras(rng: np.random.Generator, cfg: SynthConfig) -> tuple[_Scene, list[Camera], dict, dict]:
    """The layout's scene, camera path and lights (scene.json's ``camera_path`` is the path's info);
    both draw from ``rng`` in this order, which the byte-identical-output promise depends on."""
    detail = int(np.clip(3.2 * max(cfg.width, cfg.height), 384, 2048))
    key = np.array([0.35, -0.45, 1.0])
    fill = np.array([-0.6, 0.5, 0.5])
    if cfg.layout == "one-sided":
        scene = _Scene(rng, detail)
        cams, path_info = _camera_path(rng, scene, cfg)
        lights = {"ambient": 0.30, "headlight": 0.12,
                  "directional": [(key / np.linalg.norm(key), 0.62), (fill / np.linalg.norm(fill), 0.18)]}
    else:  # all-around: the underside is seen too, so light comes from below as well
        scene = _AroundScene(rng, detail)
        cams, path_info = _orbit_path(rng, scene, cfg)
        bounce = np.array([0.25, 0.4, -1.0])
        lights = {"ambient": 0.30, "headlight": 0.2,
                  "directional": [(key / np.linalg.norm(key), 0.55), (fill / np.linalg.norm(fill), 0.18),
                                  (bounce / np.linalg.norm(bounce), 0.3)]}
    return scene, cams, path_info, lights


def _write_frames(cap: Path, truth_dir: Path, scene: _Scene, cams: list[Camera], lights: dict, names: list[str],
                  ann: set[int], cfg: SynthConfig, progress: bool) -> list[dict]:
    """Render every frame and write its image, prediction, truth, depth and (if annotated) annotation;
    returns the transforms.json frame entries. Each frame's prediction errors have their own
    seed, so they do not depend on the frames before it."""
    frames_json = []
    for i in track(range(cfg.frames), "synth", enabled=progress):
        cam, name = cams[i], names[i]
        rgb, truth, depth = scene.render(cam, lights)
        pred = predict_errors(truth, np.isfinite(depth), np.random.default_rng([cfg.seed, 1, i]), cfg.noise)
        write_image(cap / "images" / f"{name}.png", rgb)
        write_mask(cap / "predictions" / f"{name}.png", pred)
        write_mask(truth_dir / f"{name}.png", truth)
        np.save(truth_dir / "depth" / f"{name}.npy", depth)
        if i in ann:
            write_mask(cap / "annotations" / f"{name}.png", truth)
        frames_json.append({"file_path": f"images/{name}.png",
                            "transform_matrix": [[float(v) for v in row] for row in cam.c2w]})
    return frames_json


class SynthScene:
    """The scene of a ``synth`` capture rebuilt from its config, to render exact truth (and the
    image) at any camera: novel views are scored against it (``benchmarks/bench_augment.py``).

    The scene and lights are drawn from the same generator as ``synthesize`` draws them, so at a
    frame's own camera ``render`` gives back that frame's image and truth exactly.
    """

    def __init__(self, cfg: SynthConfig) -> None:
        self.config = cfg
        self._scene, self.cameras, _, self._lights = _scene_and_cameras(np.random.default_rng([cfg.seed, 0]), cfg)

    @classmethod
    def from_truth(cls, truth_dir: str | Path) -> "SynthScene":
        """From OUT/truth/scene.json as ``synthesize`` wrote it."""
        path = Path(truth_dir) / "scene.json"
        try:
            config = json.loads(path.read_text())["config"]
            return cls(SynthConfig(**config))
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise LabelsynthError(f"{path}: not a synth scene.json ({exc})") from None

    def render(self, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(RGB uint8 (H,W,3), class ids uint8 (H,W), ray distance float32 (H,W), inf on a miss)
        of a camera in the capture's world coordinates."""
        return self._scene.render(camera, self._lights)
