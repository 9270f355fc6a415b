"""What a phone camera does to the image of a frame, on the image alone: exposure and white
balance that drift along the video (auto-exposure, auto white balance), defocus and motion blur,
and sensor noise. JPEG compression is applied when the frame is written (``writer``).

The truth is untouched: labels and depth come from the geometry, so a blurred or dark frame keeps
its exact masks. Everything here is off by default (``SynthConfig``), so a capture without these
options is byte-identical to one made before they existed.

Random streams (``layouts``): the drifts are smooth curves over the whole path, drawn once from
``default_rng([seed, DRIFT_STREAM])``; a frame's blur direction and length, its defocus and its
noise come from ``default_rng([seed, IMAGE_STREAM, frame])``, so a frame does not depend on the
frames before it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import SynthConfig
from .paths import smooth_curve

REFERENCE_WIDTH = 640.0  # blur lengths are given in pixels of a 640-pixel-wide frame
_SUPERSAMPLE = 8  # kernels are drawn this much finer, then averaged down (anti-aliased)


@dataclass(frozen=True)
class FrameLook:
    """One frame's camera response: what ``apply_camera`` does to its image."""

    gain: float  # exposure gain (2 ** EV)
    white_balance: tuple[float, float, float]  # per-channel (R, G, B) gains
    defocus_radius: float  # pixels at the frame's own width
    motion_length: float  # pixels at the frame's own width
    motion_angle: float  # radians
    noise_sigma: float  # grey levels (0..255), after the exposure gain

    @property
    def identity(self) -> bool:
        return (self.gain == 1.0 and self.white_balance == (1.0, 1.0, 1.0) and self.defocus_radius == 0
                and self.motion_length == 0 and self.noise_sigma == 0)


def image_effects_on(cfg: SynthConfig) -> bool:
    """Whether any image effect is asked for (else images are written exactly as rendered)."""
    return any((cfg.exposure_drift, cfg.white_balance_drift, cfg.defocus_blur, cfg.motion_blur, cfg.sensor_noise))


def drift_curves(cfg: SynthConfig, stream: int) -> tuple[np.ndarray, np.ndarray]:
    """(exposure in EV per frame (N,), white-balance gains per frame (N, 3)): smooth curves along
    the path, slow enough that neighbouring frames look alike, as a phone's auto exposure drifts."""
    n = cfg.frames
    t = np.linspace(0.0, 1.0, n)
    rng = np.random.default_rng([cfg.seed, stream])
    ev = cfg.exposure_drift * smooth_curve(rng, t, (0.6, 1.4, 2.3))
    wb = np.ones((n, 3))
    wb[:, 0] += cfg.white_balance_drift * smooth_curve(rng, t, (0.5, 1.2))  # warmer / colder
    wb[:, 2] -= cfg.white_balance_drift * smooth_curve(rng, t, (0.7, 1.6))
    return ev, wb


def frame_look(cfg: SynthConfig, index: int, ev: np.ndarray, wb: np.ndarray, rng: np.random.Generator) -> FrameLook:
    """Frame ``index``'s camera response; ``rng`` is the frame's own stream (used only when a
    per-frame effect is on, so turning one on does not change the draws of the others)."""
    scale = cfg.width / REFERENCE_WIDTH
    draws = rng.uniform(0.0, 1.0, 3)  # defocus, motion length, motion angle: always three draws
    gain = float(2.0 ** ev[index])
    return FrameLook(
        gain=gain,
        white_balance=tuple(float(x) for x in wb[index]),
        defocus_radius=float(cfg.defocus_blur * scale * draws[0]),
        motion_length=float(cfg.motion_blur * scale * draws[1]),
        motion_angle=float(np.pi * draws[2]),
        noise_sigma=float(cfg.sensor_noise * np.sqrt(gain)),  # a darker scene is brightened with its noise
    )


def _kernel(size: int, draw) -> np.ndarray:
    """A normalised blur kernel of ``size`` x ``size``, drawn ``_SUPERSAMPLE`` times finer by
    ``draw(canvas, centre, scale)`` and averaged down, so short blurs are not rounded to 0 or 1 pixel."""
    s = _SUPERSAMPLE
    canvas = np.zeros((size * s, size * s), np.float32)
    draw(canvas, (size * s - 1) / 2.0, s)
    k = cv2.resize(canvas, (size, size), interpolation=cv2.INTER_AREA)
    total = float(k.sum())
    if total <= 0:
        k = np.zeros((size, size), np.float32)
        k[size // 2, size // 2] = 1.0
        return k
    return k / total


def defocus_kernel(radius: float) -> np.ndarray:
    """A disk (a lens out of focus) of ``radius`` pixels."""
    size = 2 * int(np.ceil(radius)) + 3

    def draw(canvas, c, s):
        cv2.circle(canvas, (int(round(c)), int(round(c))), max(1, int(round(radius * s))), 1.0, -1, cv2.LINE_AA)

    return _kernel(size, draw)


def motion_kernel(length: float, angle: float) -> np.ndarray:
    """A straight streak (the camera moving while the shutter is open) ``length`` pixels long."""
    size = 2 * int(np.ceil(length / 2)) + 3
    dx, dy = np.cos(angle) * length / 2, np.sin(angle) * length / 2

    def draw(canvas, c, s):
        p0 = (int(round(c - dx * s)), int(round(c - dy * s)))
        p1 = (int(round(c + dx * s)), int(round(c + dy * s)))
        cv2.line(canvas, p0, p1, 1.0, max(1, s // 2), cv2.LINE_AA)

    return _kernel(size, draw)


def apply_camera(image: np.ndarray, look: FrameLook, rng: np.random.Generator) -> np.ndarray:
    """The frame's image (RGB uint8) as the phone records it: exposure and white balance (with
    clipping, so highlights burn out), then optical blur (defocus, then motion), then noise."""
    if look.identity:
        return image
    x = image.astype(np.float32)
    x *= np.float32(look.gain) * np.asarray(look.white_balance, np.float32)
    np.clip(x, 0.0, 255.0, out=x)
    if look.defocus_radius >= 0.25:
        x = cv2.filter2D(x, -1, defocus_kernel(look.defocus_radius), borderType=cv2.BORDER_REFLECT)
    if look.motion_length >= 0.5:
        x = cv2.filter2D(x, -1, motion_kernel(look.motion_length, look.motion_angle), borderType=cv2.BORDER_REFLECT)
    if look.noise_sigma > 0:
        x += rng.normal(0.0, look.noise_sigma, x.shape).astype(np.float32)
    return np.clip(np.round(x), 0, 255).astype(np.uint8)
