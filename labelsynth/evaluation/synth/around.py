"""The all-around scene: a wound wrapped around a limb, for a capture filmed in one turn around it."""

from __future__ import annotations

import cv2
import numpy as np

from .scene import OneSidedScene
from .textures import bilinear, fold_rows, fractal_noise_wrap, pad_rows, smoothstep, value_noise_wrap


class AroundScene(OneSidedScene):
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
        self._tex = {name: pad_rows(getattr(self, name)) for name in
                     ("labels", "albedo", "spec", "shin", "bump_grad", "height_geo", "global_albedo")}
        self.tex_shape = self._tex["labels"].shape

    def _cells(self, mult: float) -> tuple[float, float]:
        """Noise features wound_radius / mult apart: (per period along v, per window along u)."""
        return 2 * self.v_half * mult / self.wound_radius, 2 * self.half * mult / self.wound_radius

    def _win_noise(self, rng: np.random.Generator, mult: float) -> np.ndarray:
        return value_noise_wrap(rng, (self.n_v, self.tex_res), self._cells(mult))

    def _win_fbm(self, rng: np.random.Generator, mult: float, octaves: int, aspect: float = 1.0) -> np.ndarray:
        return fractal_noise_wrap(rng, (self.n_v, self.tex_res), self._cells(mult), octaves=octaves, aspect=aspect)

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
        side = smoothstep(-0.5, 0.5, a / hw)

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
        self.global_albedo = fold_rows(g, m)
        U, V = self._window_coords()
        gx, gy = self._global_xy(U, V)
        base = bilinear(pad_rows(self.global_albedo), gx.ravel(), gy.ravel()).reshape(*U.shape, 3)
        m = max(8, self.n_v // 16)
        det = self._skin(rng, (self.n_v + m, self.tex_res), (self.texel * (self.n_v + m), 2 * self.half), tone, fine=True)
        detail = fold_rows(det, m) / np.maximum(tone, 1)
        edge = np.minimum(U + self.half, self.half - U)  # the window has edges along u only
        fade = smoothstep(0.0, 0.25 * self.half, edge)[..., None]
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
