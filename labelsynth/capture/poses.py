"""Camera poses for a capture without any: pycolmap structure-from-motion -> transforms.json.

Runs SIFT extraction, matching (exhaustive for small sets, sequential with a wide overlap
for videos; loop detection needs a vocabulary tree, which we cannot assume), and
incremental mapping with one shared camera, all on the CPU in a temporary folder. The only
file written into the capture is ``CAPTURE/transforms.json`` (or the ``out`` path instead).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
import warnings
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import w2c_cv_to_c2w_gl
from ..errors import LabelsynthError
from ..outdir import check_writable, write_text_atomic
from ..progress import console, make_progress
from .check import check_image_files
from .images import list_images

EXHAUSTIVE_BELOW = 40  # frames; above this, sequential matching
SEQUENTIAL_OVERLAP = 20


@dataclass
class PoseReport:
    """What SfM recovered: which frames are posed, how well, and where it was written."""

    output: Path
    registered: list[str] = field(default_factory=list)
    unregistered: list[str] = field(default_factory=list)
    mean_reprojection_error: float = float("nan")
    num_points: int = 0
    camera_model: str = ""
    matching: str = ""
    seconds: float = 0.0

    def summary(self) -> str:
        total = len(self.registered) + len(self.unregistered)
        lines = [
            f"poses: {len(self.registered)}/{total} frames registered ({self.matching} matching), "
            f"{self.num_points} points, mean reprojection error {self.mean_reprojection_error:.3f} px, "
            f"{self.seconds:.1f} s",
            f"wrote: {self.output}",
        ]
        if self.unregistered:
            shown = ", ".join(self.unregistered[:8]) + (" ..." if len(self.unregistered) > 8 else "")
            lines.append(f"not registered (left out of transforms.json): {shown}")
        return "\n".join(lines)


def _resolve_output(capture: Path, out: Path | None) -> Path:
    if out is None:
        return capture / "transforms.json"
    out = Path(out)
    return out if out.suffix.lower() == ".json" else out / "transforms.json"


def _opencv_intrinsics(camera) -> dict:
    """Any pinhole-family COLMAP camera -> nerfstudio OPENCV intrinsics (fl_x fl_y cx cy k1 k2 p1 p2)."""
    p = [float(v) for v in camera.params]
    model = camera.model_name
    k = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, k["k1"] = p[1], p[2], p[3]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, k["k1"], k["k2"] = p[1], p[2], p[3], p[4]
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        k.update(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    else:
        raise LabelsynthError(f"poses: camera model {model} cannot be written as OPENCV")
    # COLMAP and labelsynth both put the centre of the top-left pixel at (0.5, 0.5): no shift.
    return {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
            "w": int(camera.width), "h": int(camera.height), **k}


def _cam_from_world(image) -> tuple[np.ndarray, np.ndarray]:
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method in pycolmap 4, a property before
    m = np.asarray(pose.matrix(), dtype=np.float64)
    return m[:3, :3], m[:3, 3]


def estimate_poses(
    capture: Path,
    *,
    out: Path | None = None,
    force: bool = False,
    matching: str = "auto",
    camera_model: str = "SIMPLE_RADIAL",
    progress: bool = True,
) -> PoseReport:
    """Run SfM on ``CAPTURE/images`` and write ``transforms.json`` (OpenGL camera-to-world).

    ``out`` (a folder or a ``.json`` path) writes there instead of into the capture, plus
    the sparse points as ``points3D.ply`` beside it; ``file_path`` entries stay relative to
    the capture (``images/<name>``) so the file can be dropped into it. Frames that do not
    register are reported and left out, with a warning.
    """
    import pycolmap

    start = time.perf_counter()
    if matching not in ("auto", "sequential", "exhaustive"):
        raise LabelsynthError(f"--matching must be one of auto, sequential, exhaustive, not {matching!r}")
    capture = Path(capture)
    images_dir = capture / "images"
    if not images_dir.is_dir():
        raise LabelsynthError(f"{capture}: no images/ folder")
    paths = list_images(images_dir)  # the frames segment and the loaders see
    names = [p.name for p in paths]
    if len(names) < 3:
        raise LabelsynthError(f"{images_dir}: SfM needs at least 3 images, found {len(names)}")
    target = _resolve_output(capture, out)
    if target.is_dir():
        raise LabelsynthError(f"{target}: is a folder, not a transforms.json to write")
    if target.exists() and not force:
        raise LabelsynthError(f"{target}: exists (use --force to overwrite)")
    check_writable(target)
    check_image_files(paths, capture).raise_if_problems()  # COLMAP would skip a broken frame in silence
    mode = matching if matching != "auto" else ("exhaustive" if len(names) < EXHAUSTIVE_BELOW else "sequential")

    def say(msg: str) -> None:
        if progress:
            console.print(f"[bold]poses[/bold] {msg}")

    pycolmap.set_random_seed(0)
    log_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # keep COLMAP's per-image chatter off the terminal
    try:
        return _run_sfm(pycolmap, capture, images_dir, names, target, out, mode, camera_model, say, start, progress)
    finally:
        pycolmap.logging.minloglevel = log_level


def _run_sfm(pycolmap, capture: Path, images_dir: Path, names: list[str], target: Path, out: Path | None,
             mode: str, camera_model: str, say: Callable[[str], None], start: float,
             progress: bool = True) -> PoseReport:
    """COLMAP's steps in a temporary folder (features, matches, mapping), then the one file kept."""
    with tempfile.TemporaryDirectory(prefix="labelsynth-poses-") as tmp:
        db = Path(tmp) / "database.db"
        with _spinner(progress, f"SfM: SIFT features of {len(names)} images"):
            _extract_features(pycolmap, db, images_dir, names, camera_model, say)
        with _spinner(progress, f"SfM: {mode} matching"):
            _match_features(pycolmap, db, mode, say)
        rec = _largest_reconstruction(pycolmap, db, images_dir, Path(tmp) / "sparse", capture, say,
                                      len(names), progress)
        camera = _shared_camera(rec, capture)
        registered, unregistered, data = _transforms(pycolmap, rec, camera, names, mode)
        _write_transforms(rec, data, target, out)

    if unregistered:
        shown = ", ".join(unregistered[:8]) + (" ..." if len(unregistered) > 8 else "")
        warnings.warn(f"{capture}: {len(unregistered)} frame(s) could not be registered and are left out of "
                      f"{target.name}: {shown}", stacklevel=2)
    return PoseReport(output=target, registered=[Path(n).stem for n in registered],
                      unregistered=[Path(n).stem for n in unregistered],
                      mean_reprojection_error=float(rec.compute_mean_reprojection_error()),
                      num_points=int(rec.num_points3D()), camera_model=camera.model_name, matching=mode,
                      seconds=time.perf_counter() - start)


def _extract_features(pycolmap, db: Path, images_dir: Path, names: list[str], camera_model: str,
                      say: Callable[[str], None]) -> None:
    """SIFT on the CPU for exactly the listed frames, one camera shared by all (one phone)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    say(f"extracting features from {len(names)} images")
    pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def _match_features(pycolmap, db: Path, mode: str, say: Callable[[str], None]) -> None:
    """Exhaustive matching for small sets; for videos, sequential with a wide overlap (loop
    detection would need a vocabulary tree, which we cannot assume)."""
    say(f"{mode} matching")
    match_opts = pycolmap.FeatureMatchingOptions()
    match_opts.use_gpu = False
    if mode == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=match_opts, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.quadratic_overlap = True
        pairing.loop_detection = False
        pycolmap.match_sequential(db, matching_options=match_opts, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)


def _largest_reconstruction(pycolmap, db: Path, images_dir: Path, sparse: Path, capture: Path,
                            say: Callable[[str], None], total: int = 0, progress: bool = False):
    """Incremental mapping (seeded, so reruns agree); the model with the most frames is kept,
    and one with fewer than two frames is an error, since it gives no usable poses. A bar
    counts the images COLMAP registers (a second model, if one is started, counts on)."""
    say("incremental mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = 0
    sparse.mkdir()
    with make_progress(progress) as bar:
        task = bar.add_task("SfM: mapping", total=total or None, status="")
        recs = pycolmap.incremental_mapping(
            db, images_dir, sparse, options=opts,
            initial_image_pair_callback=lambda: bar.advance(task, 2),
            next_image_callback=lambda: bar.advance(task, 1),
        )
    if not recs:
        raise LabelsynthError(f"{capture}: reconstruction failed (no two images could be registered)")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    if rec.num_reg_images() < 2:
        raise LabelsynthError(f"{capture}: reconstruction failed (fewer than 2 images registered)")
    return rec


def _spinner(enabled: bool, text: str):
    """A spinner for a COLMAP step that reports no progress of its own."""
    return console.status(text) if enabled else nullcontext()


def _shared_camera(rec, capture: Path):
    """The one camera every frame shares (transforms.json holds a single set of intrinsics)."""
    cams = {cid: cam for cid, cam in rec.cameras.items()}
    if len(cams) != 1:  # one shared camera was asked for; guard against surprises
        warnings.warn(f"{capture}: SfM produced {len(cams)} cameras; writing the first one as shared",
                      stacklevel=3)  # the line in estimate_poses, as when this was inline in _run_sfm
    return next(iter(cams.values()))


def _transforms(pycolmap, rec, camera, names: list[str], mode: str) -> tuple[list[str], list[str], dict]:
    """(registered names, unregistered names, transforms.json content): OpenGL camera-to-world
    poses of the posed frames in the images' order, with what SfM reported about the run."""
    intr = _opencv_intrinsics(camera)
    posed = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        R, t = _cam_from_world(image)
        posed[image.name] = w2c_cv_to_c2w_gl(R, t)
    registered = [n for n in names if n in posed]
    unregistered = [n for n in names if n not in posed]
    frames = [{"file_path": f"images/{n}", "transform_matrix": [[float(v) for v in row] for row in posed[n]]}
              for n in registered]
    data = {**intr, "frames": frames,
            "sfm": {"tool": f"pycolmap {pycolmap.__version__}", "matching": mode,
                    "registered": len(registered), "unregistered": unregistered,
                    "mean_reprojection_error": float(rec.compute_mean_reprojection_error()),
                    "num_points": int(rec.num_points3D())}}
    return registered, unregistered, data


def _write_transforms(rec, data: dict, target: Path, out: Path | None) -> None:
    """Write transforms.json atomically; outside the capture, the sparse points go beside it
    as points3D.ply (named in the file) so the folder is complete on its own."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if out is not None:
        ply = target.parent / "points3D.ply"
        rec.export_PLY(str(ply))
        data["ply_file_path"] = os.path.relpath(ply, target.parent)
    write_text_atomic(target, json.dumps(data, indent=2))
