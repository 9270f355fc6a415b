"""Helpers that build tiny capture folders for the capture tests (no tests in this module)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

from labelsynth.cameras import look_at

W, H = 32, 24


def write_image(path: Path, w: int = W, h: int = H, channels: int = 3, seed: int = 0) -> np.ndarray:
    """Write a random image (BGR/BGRA/gray as OpenCV stores it) and return the stored array."""
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels == 1 else (h, w, channels)
    img = rng.integers(0, 256, size=shape, dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)
    return img


def ring_poses(n: int = 4, radius: float = 3.0, height: float = 1.0) -> list[np.ndarray]:
    """Object-centric cameras on a ring, all looking at the origin."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        poses.append(look_at([radius * np.cos(a), radius * np.sin(a), height], [0.0, 0.0, 0.0]))
    return poses


def make_capture(
    root: Path,
    n: int = 4,
    intrinsics: dict | None = None,
    per_frame: list[dict] | None = None,
    ext: str = ".png",
    file_path_fmt: str = "images/frame_{i:03d}{ext}",
    write_ext: str | None = None,
    channels: int = 3,
    extra: dict | None = None,
    json_name: str = "transforms.json",
) -> Path:
    """A capture with ``n`` ring cameras and random images; returns ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    intr = {"fl_x": 30.0, "fl_y": 31.0, "cx": 16.0, "cy": 12.0, "w": W, "h": H} if intrinsics is None else intrinsics
    frames = []
    for i, pose in enumerate(ring_poses(n)):
        rel = file_path_fmt.format(i=i, ext=ext)
        actual = rel.removeprefix("./")
        if write_ext is not None:
            actual = actual + write_ext
        write_image(root / actual, channels=channels, seed=i)
        frame = {"file_path": rel, "transform_matrix": pose.tolist()}
        if per_frame is not None:
            frame.update(per_frame[i])
        frames.append(frame)
    data = {**intr, **(extra or {}), "frames": frames}
    (root / json_name).write_text(json.dumps(data, indent=1))
    return root


def capture_with_annotations(root: Path, files: dict[str, bytes], n: int = 4) -> Path:
    """A capture of ``n`` frames (frame_000, ...) whose annotations/ holds ``files`` (name -> bytes)."""
    make_capture(root, n=n)
    (root / "annotations").mkdir()
    for name, data in files.items():
        (root / "annotations" / name).write_bytes(data)
    return root


def snapshot(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``root`` (to prove nothing was written)."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }
