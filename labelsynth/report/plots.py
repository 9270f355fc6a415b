"""Report figures as PNG bytes (matplotlib, Agg backend: no display, no files on disk)."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..classes import WOUND_BED, ClassMap  # noqa: E402

DPI = 96


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _color(classes: ClassMap, name: str) -> tuple[float, float, float]:
    for c in classes.classes:
        if c.name == name:
            return tuple(np.asarray(c.color, dtype=float) / 255.0)
    return (0.3, 0.3, 0.3)


def agreement_plot(frames: Sequence[dict], keys: Sequence[str], classes: ClassMap) -> bytes:
    """Per-frame wound-bed Dice of each input against the field, and leave-one-out Dice."""
    names = [f["name"] for f in frames]
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(names) + 2), 3.2))
    by_source = {"annotation": ("o", "tab:blue"), "prediction": (".", "tab:orange")}
    for source, (marker, color) in by_source.items():
        y = [f.get("agreement_by_source", {}).get(source, {}).get(WOUND_BED, np.nan) for f in frames]
        if np.isfinite(np.asarray(y, dtype=float)).any():
            ax.plot(x, y, marker, color=color, label=f"{source} vs field", linestyle="none")
    y = [f.get("loo_dice", {}).get(WOUND_BED, np.nan) if f.get("loo_dice") else np.nan for f in frames]
    if np.isfinite(np.asarray(y, dtype=float)).any():
        ax.plot(x, y, "D", color="tab:green", label="leave-one-out (annotation)", linestyle="none", markersize=7)
    for i, f in enumerate(frames):
        if f.get("flagged"):
            ax.axvline(i, color="tab:red", alpha=0.25, linewidth=6)
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("wound bed Dice")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("Agreement of the inputs with the field (red band: flagged)")
    return _png(fig)


def class_area_plot(names: Sequence[str], pixels: Sequence[dict[str, int]], classes: ClassMap) -> bytes:
    """Pixels per tissue class in the field's mask of every frame (should vary smoothly)."""
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(names) + 2), 3.2))
    for i in classes.wound_bed_indices:
        name = classes.classes[i].name
        y = np.array([p.get(name, 0) for p in pixels], dtype=float)
        if y.any():
            ax.plot(x, y, "-o", markersize=3, color=_color(classes, name), label=name)
    ax.set_ylabel("pixels")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    ax.set_title("Class area per frame in the field's masks")
    return _png(fig)


def pairwise_heatmap(views: Sequence[str], matrix: Sequence[Sequence[float | None]]) -> bytes:
    """Wound-bed Dice between pairs of labelled frames where they see the same surface."""
    n = len(views)
    m = np.array([[np.nan if v is None else v for v in row] for row in matrix], dtype=float).reshape(n, n)
    size = min(12.0, max(3.5, 0.3 * n + 2))
    fig, ax = plt.subplots(figsize=(size + 1, size))
    cmap = plt.get_cmap("RdYlGn").with_extremes(bad="#dddddd")
    im = ax.imshow(np.ma.masked_invalid(m), vmin=0, vmax=1, cmap=cmap)
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    fs = 8 if n <= 20 else 5
    ax.set_xticklabels(views, rotation=90, fontsize=fs)
    ax.set_yticklabels(views, fontsize=fs)
    if n <= 12:
        for i in range(n):
            for j in range(n):
                if np.isfinite(m[i, j]) and i != j:
                    ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="wound bed Dice")
    ax.set_title("Cross-view consistency of the inputs (grey: no shared surface)")
    return _png(fig)


def pixels_changed_plot(names: Sequence[str], changed: Sequence[int], sizes: Sequence[int]) -> bytes:
    """Per frame, the share of pixels whose class a relabel changed (what a fix did to every frame)."""
    x = np.arange(len(names))
    share = 100.0 * np.asarray(changed, dtype=float) / np.maximum(np.asarray(sizes, dtype=float), 1.0)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(names) + 2), 3.0))
    ax.bar(x, share, color="tab:purple")
    ax.set_ylabel("% of pixels")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title("Pixels whose class changed since the previous run (relabel)")
    return _png(fig)
