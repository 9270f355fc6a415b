"""The contact sheet: the suggested frames (and spread:K's, for comparison) with what each adds.

Each frame is shown small with its pixels tinted where they see the fitted surface: green where
the frame shows surface no earlier frame of its row shows as well (strength: the share it adds),
blue where an earlier frame of the row already shows it. A plot beside them gives the coverage
of k frames, k = 1..6, for both ways of choosing.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import trimesh

from ..cameras import Camera
from ..progress import track
from ..render.surface import SurfaceCaster
from .coverage import SurfaceViews, view_density

THUMB_WIDTH = 240
NEW = np.array([0.1, 0.85, 0.2])
SEEN = np.array([0.2, 0.45, 1.0])


def overlay(image: np.ndarray, camera: Camera, earlier: list[Camera], mesh: trimesh.Trimesh, caster: SurfaceCaster,
            views: SurfaceViews, tolerance: float) -> np.ndarray:
    """``image`` (RGB uint8, the frame of ``camera``) at thumbnail size, tinted (module docstring)."""
    scale = min(1.0, THUMB_WIDTH / camera.width)
    cam = camera.scaled(scale)
    thumb = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0
    hit, points, faces = caster.first_hits(*cam.rays())
    if not hit.any():
        return (thumb * 255).round().astype(np.uint8)
    pts, normals = points[hit], np.asarray(mesh.face_normals[faces[hit]], dtype=np.float64)
    own = np.minimum(view_density(pts, normals, camera, caster, tolerance) / views.reference, 1.0)
    before = np.zeros(len(pts))
    for other in earlier:
        before = np.maximum(before, np.minimum(view_density(pts, normals, other, caster, tolerance) / views.reference, 1.0))
    gain = np.clip(own - before, 0.0, 1.0)
    shared = np.minimum(own, before)
    flat = thumb.reshape(-1, 3)
    px = flat[hit]
    a_new, a_seen = 0.6 * gain[:, None], 0.5 * shared[:, None]
    px = px * (1 - a_new) + a_new * NEW
    px = px * (1 - a_seen) + a_seen * SEEN
    flat[hit] = px
    return (thumb * 255).round().astype(np.uint8)


def contact_sheet(path: Path, rows: list[tuple[str, list[int], list[float]]], images: list[np.ndarray],
                  cameras: list[Camera], mesh: trimesh.Trimesh, caster: SurfaceCaster, views: SurfaceViews,
                  curves: dict[str, list[float]], tolerance: float, *, progress: bool = True) -> Path:
    """Write the sheet as PNG: ``rows`` of (title, frame indices in order of choice, each one's
    gain), their ``images`` and unit-cube ``cameras`` by frame index, and ``curves`` (label ->
    coverage of k = 1.. frames)."""
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    k = max(len(r[1]) for r in rows)
    aspect = cameras[0].height / cameras[0].width
    fig = Figure(figsize=(2.4 * k + 3.6, 2.4 * aspect * len(rows) + 1.0))
    grid = fig.add_gridspec(len(rows), k + 1, width_ratios=[1.0] * k + [1.5], wspace=0.15)
    jobs = [(r, c) for r, (_, order, _) in enumerate(rows) for c in range(len(order))]
    for r, c in track(jobs, "contact sheet", enabled=progress):
        title, order, gains = rows[r]
        i = order[c]
        ax = fig.add_subplot(grid[r, c])
        ax.imshow(overlay(images[i], cameras[i], [cameras[j] for j in order[:c]], mesh, caster, views, tolerance))
        ax.set_title(f"{views.names[i]}\n+{100 * gains[c]:.0f}% of the surface", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        if c == 0:
            ax.set_ylabel(title, fontsize=9)
    ax = fig.add_subplot(grid[:, k])
    ax.yaxis.set_label_position("right")
    ax.yaxis.tick_right()
    for label, values in curves.items():
        ax.plot(range(1, len(values) + 1), [100 * v for v in values], "-o", markersize=4, label=label)
    ax.set_xlabel("frames annotated")
    ax.set_ylabel("surface shown (% of what all frames show)")
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.suptitle("green: surface the frame adds; blue: already shown by an earlier frame of its row", fontsize=9)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    return path
