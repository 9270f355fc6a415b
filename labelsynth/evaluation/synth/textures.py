"""Procedural textures: smooth value noise and its fractal sums (plain, or periodic along rows
for a texture that wraps around a limb), texture sampling, and the small skin marks that
give feature matching and the field something to hold.

Every function draws from the generator it is given, in a fixed order: the byte-identical
output of ``synthesize`` depends on it.
"""

from __future__ import annotations

import cv2
import numpy as np


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """0 at ``e0``, 1 at ``e1`` (either order), a smooth cubic between."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
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


def fractal_noise(rng: np.random.Generator, shape: tuple[int, int], cells: float, octaves: int = 4, aspect: float = 1.0) -> np.ndarray:
    """Fractal noise: octaves of value noise, each twice as fine and half as strong."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        c = cells * 2**o
        out += amp * value_noise(rng, shape, (c * aspect, c))
        total += amp
        amp *= 0.5
    return out / total


def value_noise_wrap(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
    """As ``value_noise``, periodic along axis 0: row 0 continues row ``shape[0] - 1``.

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


def fractal_noise_wrap(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float], octaves: int = 4,
              aspect: float = 1.0) -> np.ndarray:
    """As ``fractal_noise``, periodic along axis 0; ``cells`` = (rows, columns) features of the first octave."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        out += amp * value_noise_wrap(rng, shape, (cells[0] * 2**o * aspect, cells[1] * 2**o))
        total += amp
        amp *= 0.5
    return out / total


def fold_rows(img: np.ndarray, extra: int) -> np.ndarray:
    """Make an image periodic along axis 0: its last ``extra`` rows are cross-faded into its first.

    ``img`` has N + extra rows; the result has N, and row 0 continues row N - 1.
    """
    n = img.shape[0] - extra
    out = img[:n].copy()
    w = ((np.arange(extra, dtype=np.float32) + 0.5) / extra).reshape(-1, *([1] * (img.ndim - 1)))
    out[:extra] = w * img[:extra] + (1 - w) * img[n: n + extra]
    return out


def pad_rows(tex: np.ndarray) -> np.ndarray:
    """A periodic texture with its last row put before its first and its first after its last."""
    return np.concatenate([tex[-1:], tex, tex[:1]], axis=0)


def bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
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


def remap(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
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



def skin_marks(rng: np.random.Generator, shape: tuple[int, int], extent: tuple[float, float], fine: bool) -> np.ndarray:
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
        pores = value_noise(rng, shape, (ext_v / 0.006, ext_u / 0.006))
        canvas = np.maximum(canvas, 0.3 * smoothstep(1.6, 2.6, pores))
    return cv2.GaussianBlur(canvas, (0, 0), 0.6)

