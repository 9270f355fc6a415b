"""The one-sided scene: a procedural wound on a curved body surface (a tapered limb or a gently
curved torso patch), as a displaced parametric mesh with textures over its surface
coordinates (u, v), and its rendering: one ray per pixel centre, cast with
``render.surface.SurfaceCaster``.

Class labels, albedo and relief are functions of (u, v), so every view agrees on the class of
a surface point, and colour and truth of a pixel come from the same ray hit.
``around.AroundScene`` reuses all of it for a wound wrapped around a limb.
"""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

from ...cameras import Camera
from ...classes import DEFAULT_CLASSES
from ...render.surface import SurfaceCaster
from .config import BACKGROUND, EPITHELIAL, GRANULATION, NECROTIC, SLOUGH, UNKNOWN, WOUND_CLASSES
from .shading import Material, SurfaceHits, background_image, bumped_normal, shade, vignette
from .textures import bilinear, fractal_noise, remap, skin_marks, smoothstep, value_noise


class OneSidedScene:
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
        h[inside] = bilinear(self._tex["height_geo"], x[inside], y[inside])
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
        self._caster = SurfaceCaster(trimesh.Trimesh(self.vertices, self.faces, process=False), rescale=False)

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
        a = a + warp * value_noise(rng, (n, n), (cells * 1.5, cells * 1.5))
        b = b + warp * value_noise(rng, (n, n), (cells * 1.5, cells * 1.5))
        phi = np.arctan2(b, a)
        rad = np.ones_like(phi)
        for k in range(2, 7):
            rad += rng.uniform(0.0, 0.16 / k * 2) * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
        rho = np.hypot(a, b) / (R * rad)
        self.rho = rho.astype(np.float32)
        ang = np.arctan2(V, U)
        self.labels = self._draw_tissues(
            rng, U, V, rho, blobs=1,
            noise=lambda mult: value_noise(rng, (n, n), (cells * mult, cells * mult)),
            fbm=lambda mult, octaves: fractal_noise(rng, (n, n), cells * mult, octaves=octaves),
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
        blotch = fractal_noise(rng, shape, ext_u / 0.25, octaves=3, aspect=ext_v / ext_u)
        red = fractal_noise(rng, shape, ext_u / 0.12, octaves=2, aspect=ext_v / ext_u)
        img *= (1.0 + 0.07 * blotch)[..., None]
        img += np.array([9, -3, -3], np.float32) * np.clip(red, 0, None)[..., None]
        canvas = skin_marks(rng, shape, extent, fine)
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
        base = bilinear(self.global_albedo, gx.ravel(), gy.ravel()).reshape(n, n, 3)
        detail = self._skin(rng, (n, n), (2 * self.half, 2 * self.half), tone, fine=True) / np.maximum(tone, 1)
        edge = np.minimum(np.minimum(U + self.half, self.half - U), np.minimum(V + self.half, self.half - V))
        fade = smoothstep(0.0, 0.25 * self.half, edge)[..., None]
        return base * (1 - fade + fade * detail)

    # smooth noise over the texture window, features about wound_radius / mult apart; a blur and
    # a gradient (d/du, d/dv) over it: what a layout with a differently shaped window replaces
    def _win_noise(self, rng: np.random.Generator, mult: float) -> np.ndarray:
        cells = 2 * self.half / self.wound_radius
        return value_noise(rng, (self.tex_res, self.tex_res), (cells * mult, cells * mult))

    def _win_fbm(self, rng: np.random.Generator, mult: float, octaves: int, aspect: float = 1.0) -> np.ndarray:
        cells = 2 * self.half / self.wound_radius
        return fractal_noise(rng, (self.tex_res, self.tex_res), cells * mult, octaves=octaves, aspect=aspect)

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
        alb[m] = gran * shade[m, None] + np.array([30, 10, 12], np.float32) * smoothstep(0.8, 1.8, bumps)[m, None]
        m = lab == SLOUGH
        alb[m] = np.array([214, 190, 108], np.float32) * (0.85 + 0.1 * fib[m] + 0.06 * mott[m])[:, None]
        m = lab == NECROTIC
        alb[m] = np.array([48, 34, 30], np.float32) * (0.85 + 0.2 * mott[m] + 0.05 * fine[m])[:, None]
        m = lab == EPITHELIAL
        alb[m] = np.array([228, 158, 160], np.float32) * (0.93 + 0.05 * mott[m])[:, None]
        m = lab == UNKNOWN
        alb[m] = np.array([122, 78, 120], np.float32) * (0.9 + 0.1 * mott[m])[:, None]
        # a reddish inflamed halo on the skin around the wound
        halo = smoothstep(1.6, 1.0, self.rho) * (lab == BACKGROUND)
        alb = alb * (1 - 0.25 * halo[..., None]) + 0.25 * halo[..., None] * np.array([205, 110, 100], np.float32)
        return np.clip(alb, 0, 255).astype(np.float32)

    def _relief(self, rng: np.random.Generator, bumps: np.ndarray, fine: np.ndarray) -> None:
        """Sets the relief: a crater the mesh carries (``height_geo``, so depth and silhouettes see
        it) and fine bumps only the shading sees (``bump_grad``), too small for the mesh."""
        R, lab = self.wound_radius, self.labels
        d = self.crater_depth
        crater = -d * (1 - smoothstep(0.82, 1.08, self.rho))
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
        hit, _, faces, bary = self._caster.cast(origins, dirs)
        surf = self._surface_at(faces[hit], bary[hit])
        d = dirs[hit].astype(np.float32)
        depth = np.full(W * H, np.inf, np.float32)
        depth[hit] = np.einsum("ij,ij->i", surf.pos - origins[hit].astype(np.float32), d)
        mat = self._material(surf.uv)
        nrm = bumped_normal(surf, mat.bump_grad, d)
        col = shade(mat, nrm, -d, lights)

        img = background_image(W, H).reshape(-1, 3).astype(np.float32)
        vig = vignette(W, H).reshape(-1)
        img[hit] = col * vig[hit, None]
        rgb = np.clip(np.round(img), 0, 255).astype(np.uint8).reshape(H, W, 3)
        truth = np.zeros(W * H, np.uint8)
        truth[hit] = mat.labels
        return rgb, truth.reshape(H, W), depth.reshape(H, W)

    def _surface_at(self, faces: np.ndarray, bary: np.ndarray) -> SurfaceHits:
        """The mesh's vertex attributes blended at the hits, so colour and truth share one (u, v)."""
        f = self.faces[faces]
        w = bary.astype(np.float32)
        a = self._attrs
        attrs = a[f[:, 0]] * w[:, :1] + a[f[:, 1]] * w[:, 1:2] + a[f[:, 2]] * w[:, 2:3]
        return SurfaceHits(pos=attrs[:, 0:3], uv=attrs[:, 3:5], normal=attrs[:, 5:8], tu=attrs[:, 8:11],
                            tv=attrs[:, 11:14])

    def _material(self, uv: np.ndarray) -> Material:
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
        albedo[inwin] = remap(tex["albedo"], x[inwin], y[inwin])
        out = ~inwin
        albedo[out] = remap(tex["global_albedo"], *self._global_xy(uv[out, 0], uv[out, 1]))
        spec = np.full(n, 0.05, np.float32)
        shin = np.full(n, 12.0, np.float32)
        spec[inwin] = tex["spec"][yi, xi]
        shin[inwin] = tex["shin"][yi, xi]
        bump_grad = np.zeros((n, 2), np.float32)
        bump_grad[inwin] = remap(tex["bump_grad"], x[inwin], y[inwin])
        return Material(labels=labels, albedo=albedo, spec=spec, shin=shin, bump_grad=bump_grad)

