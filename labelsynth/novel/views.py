"""One novel view: its mask from the field, its colours from the real frames that see each point.

Why image-based blending and not the field's colour head: the geometry was fitted on rays from
frames downscaled ``geometry.train_scale`` times, so the colour head is smooth at full
resolution, while the real frames hold every detail. Each novel pixel's ray is cast onto the
fitted surface (the same cast that gives its label, ``FieldRenderer.render``); the hit point is
projected into the real frames nearest in viewing angle, kept where a frame's own depth map
(the same surface cast from that frame) says nothing lies in front of it, and their colours are
blended, the smallest angle weighing most. ``benchmarks/bench_augment.py`` measures this
against the colour head (leave-one-frame-out PSNR/SSIM; README, "Novel views").

Pixels whose surface point no real frame sees, and rays that miss the surface in a direction
no real frame saw empty, are not invented: their colour is 0, their label 255 (ignore) and
their validity False. A missed ray's label is background (the field's rule: nothing inside the
box), its colour is what real frames show in that direction where they too see nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from ..cameras import Camera
from ..classes import IGNORE_ID
from ..geometry.training import render_rays_rgb
from ..render.field import FittedField
from ..render.renderer import FieldRenderer

METHODS = ("blend", "head")
FAR = 1.0e3  # a missed ray's colour is looked up at this distance (unit cube = 2 wide): a direction


@dataclass
class BlendConfig:
    """How real frames are picked and mixed (the defaults were chosen by bench_augment.py)."""

    candidates: int = 6  # real frames considered per view: the nearest in viewing direction
    blend: int = 2  # frames mixed per pixel: the ones with the smallest angle that see the point
    sharpness_deg: float = 2.0  # weight = 1 / (angle + this)^2
    depth_tolerance: float = 0.01  # visible if |depth map - distance| < this * distance + 3 pixels
    far_resolution: float = 0.5  # penalty (in degrees per 1% farther) for a frame farther from the point


@dataclass
class NovelView:
    """One rendered view at full resolution."""

    image: np.ndarray  # (H,W,3) uint8, 0 where not valid
    mask: np.ndarray  # (H,W) uint8 class ids, 255 where not valid
    confidence: np.ndarray  # (H,W) float32, 0 where not valid
    valid: np.ndarray  # (H,W) bool: some real frame saw this pixel's surface point (or its empty direction)
    hit: np.ndarray  # (H,W) bool: the ray met the fitted surface

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())


@dataclass
class Lookup:
    """Colour and visibility of points in the real frames (only where some frame sees them)."""

    rgb: torch.Tensor  # (P,3) float in [0,255]
    seen: torch.Tensor  # (P,) bool


class RealFrames:
    """The real frames as blending sources: unit-cube cameras, images and depth maps.

    A depth map is the distance along each pixel's ray to the fitted surface (inf where the
    ray misses), from the same cast as the novel views, so a point and a real frame's view of
    it are compared on one surface.
    """

    def __init__(self, view: FieldRenderer, cameras: list[Camera], images: list[np.ndarray],
                 cfg: BlendConfig | None = None, *, depth: list[np.ndarray] | None = None, progress: bool = False) -> None:
        from ..progress import track

        self.view = view
        self.cfg = cfg or BlendConfig()
        self.cameras = list(cameras)
        self.images = [torch.from_numpy(np.ascontiguousarray(im.transpose(2, 0, 1))) for im in images]  # uint8
        if depth is None:
            depth = [self.depth_map(c) for c in track(self.cameras, "depth of the real frames", enabled=progress)]
        self.depth = [torch.from_numpy(np.where(np.isfinite(d), d, FAR * 10).astype(np.float32)) for d in depth]
        self.centers = np.stack([c.center for c in self.cameras])
        self.forwards = np.stack([c.forward for c in self.cameras])
        self._centres_t = torch.from_numpy(self.centers.astype(np.float32))
        self._rotations_t = torch.from_numpy(np.stack([c.w2c[:3, :3] for c in self.cameras]).astype(np.float32))

    def depth_map(self, camera: Camera) -> np.ndarray:
        """(H,W) float32 distance to the fitted surface along each pixel's ray, inf on a miss."""
        o, d = camera.rays()
        hit, points, _ = self.view.render_caster().first_hits(o, d)
        dist = np.full(len(o), np.inf, np.float32)
        dist[hit] = np.linalg.norm(points[hit] - o[hit], axis=-1)
        return dist.reshape(camera.height, camera.width)

    def __len__(self) -> int:
        return len(self.cameras)

    # --- choosing frames ---------------------------------------------------------------------
    def candidates(self, camera: Camera, target: np.ndarray, exclude: set[int] = frozenset()) -> list[int]:
        """The real frames that look at ``target`` from the directions nearest the novel camera's."""
        k = min(self.cfg.candidates, len(self) - len(exclude))
        to_novel = _unit(camera.center - target)
        to_real = _unit(self.centers - target)
        cosang = to_real @ to_novel
        order = [int(i) for i in np.argsort(-cosang) if int(i) not in exclude]
        return order[:k]

    # --- looking points up ---------------------------------------------------------------------
    def _project(self, j: int, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(grid coords (P,2) for grid_sample, in-frame (P,), distance from frame j's centre (P,),
        offset from that centre (P,3)) of unit-cube points (P,3); torch for speed,
        ``Camera.project`` where there is distortion."""
        cam = self.cameras[j]
        rel = points - self._centres_t[j]
        dist = rel.norm(dim=-1)
        if cam.is_distorted:
            pix_np, z_np = cam.project(points.double().numpy())
            pix, z = torch.from_numpy(pix_np).float(), torch.from_numpy(z_np).float()
            gx, gy = 2 * pix[:, 0] / cam.width - 1, 2 * pix[:, 1] / cam.height - 1
        else:
            pc = rel @ self._rotations_t[j].T  # camera axes (OpenGL: the camera looks down -z)
            z = -pc[:, 2]
            inv = 1.0 / torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
            # pixel x = fx * X / z + cx, y = -fy * Y / z + cy, then to grid_sample's [-1, 1]
            gx = pc[:, 0] * inv * (2 * cam.fx / cam.width) + (2 * cam.cx / cam.width - 1)
            gy = pc[:, 1] * inv * (-2 * cam.fy / cam.height) + (2 * cam.cy / cam.height - 1)
        inside = (z > 1e-6) & (gx >= -1) & (gx < 1) & (gy >= -1) & (gy < 1)
        grid = torch.stack([gx, gy], -1) * inside[:, None]
        return grid, inside, dist, rel

    def _sample(self, j: int, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frame j's colour (bilinear, (P,3)) and depth (nearest, (P,)) at grid coordinates."""
        g = grid.view(1, 1, -1, 2)
        rgb = F.grid_sample(self.images[j][None].float(), g, mode="bilinear", padding_mode="border", align_corners=False)
        depth = F.grid_sample(self.depth[j][None, None], g, mode="nearest", padding_mode="border", align_corners=False)
        return rgb[0, :, 0].T, depth[0, 0, 0]

    def lookup_points(self, points: np.ndarray, eye: np.ndarray, frames: list[int]) -> Lookup:
        """Colours of surface points seen from ``eye``: the ``cfg.blend`` frames among ``frames``
        that see each point with the smallest angle to the novel ray, weighted by that angle."""
        cfg = self.cfg
        p = len(points)
        if p == 0 or not frames:
            return Lookup(torch.zeros(p, 3), torch.zeros(p, dtype=torch.bool))
        pts = torch.from_numpy(np.asarray(points, dtype=np.float32))
        offset = pts - torch.from_numpy(np.asarray(eye, dtype=np.float32))
        eye_dist = offset.norm(dim=-1).clamp_min(1e-6)
        view = offset / eye_dist[:, None]
        cost = torch.full((len(frames), p), float("inf"))
        colours = torch.zeros(len(frames), p, 3)
        for k, j in enumerate(frames):
            grid, inside, dist, rel = self._project(j, pts)
            rgb, depth = self._sample(j, grid)
            footprint = 3.0 * dist / self.cameras[j].fx
            visible = inside & ((depth - dist).abs() < cfg.depth_tolerance * dist + footprint)
            cos = (rel * view).sum(-1) / dist.clamp_min(1e-6)
            angle = torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))
            farther = (dist / eye_dist - 1.0).clamp_min(0) * 100.0 * cfg.far_resolution
            cost[k] = torch.where(visible, angle + farther, torch.full_like(angle, float("inf")))
            colours[k] = rgb
        return _blend(cost, colours, cfg)

    def lookup_directions(self, dirs: np.ndarray, eye: np.ndarray, frames: list[int]) -> Lookup:
        """Colours of rays that miss the surface: what the frames show in that direction where
        they too miss it (nearest frames first), a direction being a point far away."""
        cfg = self.cfg
        p = len(dirs)
        if p == 0 or not frames:
            return Lookup(torch.zeros(p, 3), torch.zeros(p, dtype=torch.bool))
        d = torch.from_numpy(np.asarray(dirs, dtype=np.float32))
        cost = torch.full((len(frames), p), float("inf"))
        colours = torch.zeros(len(frames), p, 3)
        for k, j in enumerate(frames):
            cam = self.cameras[j]
            grid, inside, _, _ = self._project(j, self._centres_t[j] + FAR * d)
            rgb, depth = self._sample(j, grid)
            empty = inside & (depth >= FAR)  # that frame's ray in this direction misses the surface too
            gap = float(np.linalg.norm(cam.center - eye))
            cost[k] = torch.where(empty, torch.full((p,), gap * 100.0 + k), torch.full((p,), float("inf")))
            colours[k] = rgb
        return _blend(cost, colours, cfg)


def _blend(cost: torch.Tensor, colours: torch.Tensor, cfg: BlendConfig) -> Lookup:
    """Per point: the ``cfg.blend`` lowest finite costs, weighted 1 / (cost + sharpness)^2."""
    k = min(cfg.blend, cost.shape[0])
    best, idx = torch.topk(cost, k, dim=0, largest=False)
    w = torch.where(torch.isfinite(best), 1.0 / (best + cfg.sharpness_deg) ** 2, torch.zeros_like(best))
    total = w.sum(0)
    seen = total > 0
    picked = torch.gather(colours, 0, idx[..., None].expand(-1, -1, 3))
    rgb = (picked * w[..., None]).sum(0) / total.clamp_min(1e-12)[:, None]
    return Lookup(rgb, seen)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def render_view(view: FieldRenderer, real: RealFrames, camera: Camera, *, method: str = "blend",
                exclude: set[int] = frozenset()) -> NovelView:
    """Image, mask, confidence and validity of one unit-cube camera.

    ``exclude``: real frames not to blend from (leave-one-frame-out in the benchmark).
    ``method``: ``blend`` (real frames' colours) or ``head`` (the field's colour head,
    volume-rendered); either way only pixels some real frame sees are valid.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
    h, w = camera.height, camera.width
    r = view.render(camera, keep_points=True)
    hit = r.hit.reshape(-1)
    points = r.points.reshape(-1, 3)
    _, dirs = camera.rays()
    target = np.median(points[hit], axis=0) if hit.any() else camera.center + camera.forward
    frames = real.candidates(camera, target, exclude)
    rgb = torch.zeros(h * w, 3)
    valid = torch.zeros(h * w, dtype=torch.bool)
    hit_t = torch.from_numpy(hit)
    on = real.lookup_points(points[hit], camera.center, frames)
    off = real.lookup_directions(dirs[~hit], camera.center, frames)
    rgb[hit_t], valid[hit_t] = on.rgb, on.seen
    rgb[~hit_t], valid[~hit_t] = off.rgb, off.seen
    if method == "head":
        rgb = colour_head(view.field, camera).reshape(-1, 3)
    valid_np = valid.numpy().reshape(h, w)
    image = np.where(valid_np[..., None], rgb.numpy().reshape(h, w, 3).round().clip(0, 255), 0).astype(np.uint8)
    mask = np.where(valid_np, r.mask, IGNORE_ID).astype(np.uint8)
    conf = np.where(valid_np, r.confidence, 0.0).astype(np.float32)
    return NovelView(image, mask, conf, valid_np, r.hit.reshape(h, w))


@torch.no_grad()
def colour_head(fitted: FittedField, camera: Camera, chunk: int = 8192) -> torch.Tensor:
    """(H*W,3) colours in [0,255] volume-rendered by the field's colour head (the comparison
    the benchmark makes; slow on a CPU at full resolution)."""
    o, d = camera.rays()
    o_t = torch.from_numpy(o.astype(np.float32)).to(fitted.device)
    d_t = torch.from_numpy(d.astype(np.float32)).to(fitted.device)
    out = []
    for s in range(0, len(o_t), chunk):
        rgb, _, _ = render_rays_rgb(fitted.sdf, fitted.grid, o_t[s:s + chunk], d_t[s:s + chunk], 1.0,
                                    fitted.recipe.geometry.march_steps, train=False)
        out.append(rgb.float().cpu())
    return torch.cat(out) * 255.0
