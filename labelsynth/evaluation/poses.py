"""Estimated camera poses against reference ones, as far as SfM can recover them: up to a
similarity (scale, rotation, translation) of the world.

The similarity is fitted to the camera centres (Umeyama, by scikit-image); each frame's error is
then the angle between its aligned estimated orientation and the reference one, and the
distance between its aligned centre and the reference centre as a share of the reference path's
size. Both sides must use the same camera axes (``transforms.json``: OpenGL, x right, y up,
looking down -z), since a change of world cannot turn one camera convention into the other.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


def frame_poses(transforms: dict) -> dict[str, np.ndarray]:
    """Image stem of each frame's ``file_path`` -> its 4x4 camera-to-world matrix."""
    return {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], dtype=np.float64)
            for f in transforms["frames"]}


@dataclass
class PoseErrors:
    names: list[str]  # frames in both sets, in the reference's order
    rotation_deg: np.ndarray  # per frame
    centre: np.ndarray  # per frame, aligned centre distance / reference path size
    scale: float  # estimated world -> reference world


def pose_errors(reference: dict[str, np.ndarray], estimate: dict[str, np.ndarray]) -> PoseErrors:
    """Per-frame errors of ``estimate`` after the similarity that best maps its camera centres
    onto ``reference``'s (both: name -> 4x4 camera-to-world); at least 3 shared frames."""
    from skimage.transform import SimilarityTransform

    names = [n for n in reference if n in estimate]
    if len(names) < 3:
        raise ValueError(f"pose_errors: {len(names)} frames in common; at least 3 are needed")
    ref_c = np.array([reference[n][:3, 3] for n in names])
    est_c = np.array([estimate[n][:3, 3] for n in names])
    if hasattr(SimilarityTransform, "from_estimate"):  # scikit-image >= 0.26
        fit = SimilarityTransform.from_estimate(est_c, ref_c)
    else:
        fit = SimilarityTransform(dimensionality=3)
        fit.estimate(est_c, ref_c)
    m = np.asarray(fit.params)
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    rot = m[:3, :3] / scale
    errors = []
    for n in names:
        rel = (rot @ estimate[n][:3, :3]).T @ reference[n][:3, :3]
        errors.append(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
    aligned = est_c @ m[:3, :3].T + m[:3, 3]
    size = float(np.linalg.norm(ref_c.max(0) - ref_c.min(0)))
    return PoseErrors(names, np.array(errors), np.linalg.norm(aligned - ref_c, axis=1) / size, scale)
