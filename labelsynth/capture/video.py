"""``labelsynth import``: a phone video (or a folder of photos) -> a capture folder with poses.

A video is decoded twice by OpenCV's FFmpeg backend, never held in memory: the first pass
measures every frame (sharpness, camera motion: ``capture.framepick``), the second writes the
chosen ones, resized, to ``CAPTURE/images/`` as PNG. Rotation metadata (a phone filming in
portrait stores landscape pixels and a display matrix) is applied by OpenCV
(``CAP_PROP_ORIENTATION_AUTO``), as players show the video; EXIF orientation of photos likewise.
Then ``estimate_poses`` (pycolmap) writes ``transforms.json``; frames SfM could not register are
removed from images/ (they would have no camera) and reported.

CAPTURE is built in ``CAPTURE.partial`` and renamed when complete; bad input is a one-line
``CaptureError`` naming the source, and then no CAPTURE (nor its partial folder) is left.
Nothing is ever written beside or inside the source.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .. import __version__
from ..errors import CaptureError, LabelsynthError
from ..outdir import building, check_apart, write_text_atomic
from ..progress import make_progress
from .check import check_image_files
from .framepick import MotionTracker, Pick, pick_spread, resize_to, sharpness, thumbnail
from .images import IMAGE_SUFFIXES, list_images, read_image, write_image
from .poses import PoseReport, estimate_poses

IMPORT_FILE = "import.json"
# What the opencv-python-headless wheel's FFmpeg decoded when tried (README, "From a video").
CODECS_READ = "H.264, HEVC, MPEG-4 Part 2, MJPEG, VP8, VP9, AV1, ProRes, MPEG-2, FFV1"


MAX_FRAMES = 100_000
MAX_SIDE = 16384


@dataclass
class ImportConfig:
    """How ``import_capture`` picks and writes frames."""

    frames: int = 50
    """Frames to keep. A video must give this many usable ones (else an error says how many it
    has); a folder keeps at most this many of its photos."""
    max_side: int = 1280
    """Long side of the written frames in pixels (frames are shrunk by area averaging, never enlarged)."""
    poses: bool = True
    """Run structure-from-motion (``labelsynth poses``) on the written frames."""
    blur_floor: float = 0.15
    """A frame less sharp than this share of the 90th percentile of the source's sharpness is
    unusable. Measured on the fox photos at 720x1280: sharp photos 0.40-1.55, a Gaussian blur
    of 1 px 0.10-0.28, of 2 px 0.04-0.06, a 15 px motion blur 0.05-0.10."""
    min_motion: float = 0.004
    """Video: a kept frame whose camera moved less than this share of the image diagonal since
    the previous kept frame is a near-duplicate (a phone held still) and is dropped. Measured at
    320 px: a still frame with half a pixel of jitter and sensor noise moves 0.02-0.1%;
    consecutive fox photos (instant-ngp's pick of distinct views) 0.55-5.8%."""
    motion_step: float = 0.005
    """Video: the motion tracker takes a new reference frame after a move of this share of the
    diagonal; tremor below it never adds up to motion."""
    min_registered: float = 0.5
    """SfM must register at least this share of the written frames, else the import fails."""


@dataclass
class ImportedFrame:
    """One written frame and where it came from."""

    name: str  # image stem in CAPTURE/images
    source_index: int  # video frame number (0-based), or the photo's position in name order
    sharpness: float  # variance of the Laplacian at the written size
    time_s: float | None = None  # video timestamp
    source_name: str | None = None  # the photo's file name


@dataclass
class ImportReport:
    """What an import read, kept, dropped and posed, and how long each step took."""

    source: Path
    capture: Path
    kind: str  # "video" | "photos"
    decoded: int  # frames decoded (video) or photos read
    frames: list[ImportedFrame] = field(default_factory=list)
    blurred: int = 0
    near_duplicates: int = 0
    filled: int = 0  # picks made in the widest gaps after empty or duplicated windows
    fps: float | None = None
    rotation: int = 0  # degrees the video's metadata asked for (applied)
    source_size: tuple[int, int] = (0, 0)  # (width, height) as displayed
    written_size: tuple[int, int] = (0, 0)
    registered: list[str] = field(default_factory=list)
    dropped_by_sfm: list[str] = field(default_factory=list)
    poses: PoseReport | None = None
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        w, h = self.source_size
        what = (f"{self.decoded} frames decoded ({w}x{h}, {self.fps:.3g} fps, rotation {self.rotation} deg)"
                if self.kind == "video" else f"{self.decoded} photos read")
        dropped = [f"{self.blurred} too blurred"]
        if self.kind == "video":
            dropped.append(f"{self.near_duplicates} near-duplicate picks")
        lines = [f"import: {what}; kept {len(self.frames) + len(self.dropped_by_sfm)} at "
                 f"{self.written_size[0]}x{self.written_size[1]} ({', '.join(dropped)})"]
        if self.poses is not None:
            total = len(self.registered) + len(self.dropped_by_sfm)
            lines.append(f"poses: {len(self.registered)}/{total} frames registered, "
                         f"{self.poses.num_points} points, mean reprojection error "
                         f"{self.poses.mean_reprojection_error:.3f} px")
            if self.dropped_by_sfm:
                shown = ", ".join(self.dropped_by_sfm[:8]) + (" ..." if len(self.dropped_by_sfm) > 8 else "")
                lines.append(f"dropped (not registered, removed from images/): {shown}")
        secs = ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items())
        lines.append(f"wrote: {self.capture} ({len(self.frames)} frames; {secs})")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {
            "source": str(self.source), "kind": self.kind, "decoded": self.decoded, "fps": self.fps,
            "rotation": self.rotation, "source_size": list(self.source_size),
            "written_size": list(self.written_size), "blurred": self.blurred,
            "near_duplicates": self.near_duplicates, "filled": self.filled,
            "frames": [dataclasses.asdict(f) for f in self.frames],
            "registered": self.registered, "dropped_by_sfm": self.dropped_by_sfm, "seconds": self.seconds,
        }


# --------------------------------------------------------------------------- video decoding


_CONTAINERS = (  # (offset, magic, name): enough to tell "a video OpenCV cannot decode" from "not a video"
    (4, b"ftyp", "MP4/MOV"), (4, b"moov", "MOV"), (4, b"mdat", "MOV"), (4, b"wide", "MOV"),
    (0, b"\x1a\x45\xdf\xa3", "Matroska/WebM"), (8, b"AVI ", "AVI"), (0, b"FLV", "FLV"),
    (0, b"OggS", "Ogg"), (0, b"\x00\x00\x01\xba", "MPEG-PS"), (0, b"\x30\x26\xb2\x75", "ASF/WMV"),
)


def _container(path: Path) -> str | None:
    """The container a file's first bytes name, or None."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return None
    for offset, magic, name in _CONTAINERS:
        if head[offset:offset + len(magic)] == magic:
            return name
    if head[:1] == b"\x47":
        return "MPEG-TS"
    return None


class VideoReader:
    """A video opened by OpenCV's FFmpeg backend with its rotation metadata applied; frames are
    BGR uint8 as displayed. An unopenable file is a one-line ``CaptureError``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        # FFmpeg's own log lines ("moov atom not found") would interleave with ours; our errors
        # say what failed. Read by OpenCV when it first loads FFmpeg; a user's setting wins.
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        try:
            cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not cap.isOpened():
            container = _container(path)
            if container is None:
                raise CaptureError(f"{path}: not a video (no container OpenCV's FFmpeg can open)")
            raise CaptureError(f"{path}: a {container} file whose video stream OpenCV's FFmpeg cannot decode "
                               f"(it reads {CODECS_READ})")
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # the default; said so that it stays so
        self._cap = cap
        self.rotation = int(round(cap.get(cv2.CAP_PROP_ORIENTATION_META))) % 360
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else None
        count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.frame_count = int(count) if count and np.isfinite(count) and 0 < count < 1e9 else None

    def frames(self, wanted: set[int] | None = None) -> Iterator[tuple[int, float, np.ndarray | None]]:
        """(index, time in seconds, BGR frame) for every frame; with ``wanted``, frames not in
        it are decoded but not converted (None) and reading stops after the last wanted one."""
        last = max(wanted) if wanted else None
        index = 0
        while last is None or index <= last:
            if wanted is None or index in wanted:
                ok, frame = self._cap.read()
            else:
                ok, frame = self._cap.grab(), None
            if not ok:
                return
            yield index, float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0, frame
            index += 1

    def close(self) -> None:
        self._cap.release()

    def __enter__(self) -> "VideoReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- import


def import_capture(source: str | Path, out: str | Path, config: ImportConfig | None = None, *,
                   force: bool = False, progress: bool = True) -> ImportReport:
    """Make the capture folder ``out`` from a video file or a folder of photos (see the module
    docstring); returns what was kept, dropped and posed. ``force`` replaces a non-empty ``out``."""
    config = config or ImportConfig()
    source, out = Path(source), Path(out)
    _check_args(source, out, config)
    with building(out, force=force) as partial:
        images = partial / "images"
        images.mkdir()
        if source.is_dir():
            report = _import_photos(source, images, config, progress)
        else:
            report = _import_video(source, images, config, progress)
        report.capture = out
        if config.poses:
            _run_poses(report, partial, config, progress)
        write_text_atomic(partial / IMPORT_FILE,
                          json.dumps({**report.to_json(), "config": dataclasses.asdict(config),
                                      "labelsynth": __version__}, indent=2))
    return report


def _check_args(source: Path, out: Path, config: ImportConfig) -> None:
    """Every option, and that the source opens (a video's container and stream, a folder's
    photos), before OUT.partial exists: one line naming what is wrong."""
    from ..options import whole_number

    whole_number(config.frames, "--frames", 1, MAX_FRAMES)
    whole_number(config.max_side, "--max-side", 16, MAX_SIDE)
    if not source.exists():
        kind = "a symbolic link that leads nowhere (or to itself)" if source.is_symlink() else "not found"
        raise CaptureError(f"{source}: {kind}")
    if config.poses and config.frames < 3:
        raise LabelsynthError(f"--frames {config.frames}: structure-from-motion needs at least 3 frames "
                              "(or use --no-poses)")
    if source.is_file() and source.suffix.lower() in IMAGE_SUFFIXES:
        raise CaptureError(f"{source}: a single image; give a video or a folder of photos")
    if source.is_dir():
        check_apart(out, {"the photo folder": source})
        # every photo decodes (one line per bad one), now rather than after OUT.partial exists
        check_image_files(list_images(source), source).raise_if_problems()
    else:
        with VideoReader(source) as video:  # the container and the video stream open (no frame decoded)
            if video.frame_count is not None and video.frame_count < config.frames:
                raise CaptureError(f"{source}: has {video.frame_count} frames, fewer than --frames {config.frames}")


def _import_video(source: Path, images: Path, config: ImportConfig, progress: bool) -> ImportReport:
    t0 = time.perf_counter()
    sharp, motion, times = [], [], []
    size = written = (0, 0)
    tracker = MotionTracker(config.motion_step)
    with VideoReader(source) as video, make_progress(progress) as bar:
        task = bar.add_task("decode", total=video.frame_count, status="")
        for _, t, frame in video.frames():
            gray = resize_to(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), config.max_side)
            if not sharp:
                size, written = (frame.shape[1], frame.shape[0]), (gray.shape[1], gray.shape[0])
            sharp.append(sharpness(gray))
            motion.append(tracker.update(thumbnail(gray)))
            times.append(t)
            bar.advance(task)
        fps, rotation = video.fps, video.rotation
    if not sharp:
        raise CaptureError(f"{source}: no frame could be decoded")
    seconds = {"decode": time.perf_counter() - t0}

    pick = pick_spread(np.array(sharp), config.frames, blur_floor=config.blur_floor, motion=np.array(motion),
                       min_motion=config.min_motion)
    if len(pick.chosen) < config.frames:
        raise CaptureError(_too_few(source, len(sharp), pick, config))
    t1 = time.perf_counter()
    chosen = set(pick.chosen)
    kept: list[ImportedFrame] = []
    with VideoReader(source) as video, make_progress(progress) as bar:
        task = bar.add_task("select", total=len(chosen), status="")
        for index, t, frame in video.frames(chosen):
            if frame is None:
                continue
            name = f"frame_{index:06d}"
            write_image(images / f"{name}.png", cv2.cvtColor(resize_to(frame, config.max_side), cv2.COLOR_BGR2RGB))
            kept.append(ImportedFrame(name, index, round(sharp[index], 3), time_s=round(t, 4)))
            bar.advance(task)
    if len(kept) != len(chosen):  # the second decode ended early: the file changed or decodes unreliably
        raise CaptureError(f"{source}: the second reading gave {len(kept)} of the {len(chosen)} chosen frames")
    seconds["select"] = time.perf_counter() - t1
    return ImportReport(source=source, capture=images.parent, kind="video", decoded=len(sharp), frames=kept,
                        blurred=pick.blurred, near_duplicates=pick.near_duplicates,
                        filled=pick.filled, fps=fps, rotation=rotation, source_size=size,
                        written_size=written, seconds=seconds)


def _too_few(source: Path, decoded: int, pick: Pick, config: ImportConfig) -> str:
    return (f"{source}: only {len(pick.chosen)} usable frames for --frames {config.frames} "
            f"({decoded} decoded, {pick.blurred} of them too blurred; the others lie too close together "
            f"on the camera's path: near-duplicates); ask for fewer with --frames")


def _import_photos(source: Path, images: Path, config: ImportConfig, progress: bool) -> ImportReport:
    t0 = time.perf_counter()
    paths = list_images(source)
    sharp = []
    with make_progress(progress) as bar:
        task = bar.add_task("decode", total=len(paths), status="")
        for path in paths:
            gray = cv2.cvtColor(_read_photo(path, config.max_side), cv2.COLOR_RGB2GRAY)
            sharp.append(sharpness(gray))
            bar.advance(task)
    seconds = {"decode": time.perf_counter() - t0}
    pick = pick_spread(np.array(sharp), config.frames, blur_floor=config.blur_floor)
    needed = 3 if config.poses else 1
    if len(pick.chosen) < needed:
        raise CaptureError(f"{source}: only {len(pick.chosen)} usable photos of {len(paths)} "
                           f"({pick.blurred} too blurred); structure-from-motion needs at least 3")
    t1 = time.perf_counter()
    kept = []
    with make_progress(progress) as bar:
        task = bar.add_task("select", total=len(pick.chosen), status="")
        for i in pick.chosen:  # read again rather than hold every photo in memory
            rgb = _read_photo(paths[i], config.max_side)
            write_image(images / f"{paths[i].stem}.png", rgb)
            kept.append(ImportedFrame(paths[i].stem, i, round(sharp[i], 3), source_name=paths[i].name))
            bar.advance(task)
    seconds["select"] = time.perf_counter() - t1
    return ImportReport(source=source, capture=images.parent, kind="photos", decoded=len(paths), frames=kept,
                        blurred=pick.blurred, written_size=(rgb.shape[1], rgb.shape[0]), seconds=seconds)


def _read_photo(path: Path, max_side: int) -> np.ndarray:
    """RGB, upright, at most ``max_side`` on its long side."""
    return resize_to(_upright(read_image(path), path), max_side)


_EXIF_TRANSPOSE = {2: "FLIP_LEFT_RIGHT", 3: "ROTATE_180", 4: "FLIP_TOP_BOTTOM", 5: "TRANSPOSE",
                   6: "ROTATE_270", 7: "TRANSVERSE", 8: "ROTATE_90"}


def _upright(rgb: np.ndarray, path: Path) -> np.ndarray:
    """The photo as a viewer shows it: its EXIF orientation applied (a phone held upright
    stores landscape pixels and an orientation tag)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            orientation = im.getexif().get(0x0112, 1)
    except (OSError, ValueError):
        return rgb
    method = _EXIF_TRANSPOSE.get(orientation)
    if method is None:
        return rgb
    return np.asarray(Image.fromarray(rgb).transpose(getattr(Image.Transpose, method)))


def _run_poses(report: ImportReport, partial: Path, config: ImportConfig, progress: bool) -> None:
    """SfM on the written frames; unregistered frames leave images/ (no camera, and a mask
    made for them later would name a frame the capture lacks)."""
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # unregistered frames: reported below
            poses = estimate_poses(partial, progress=progress)
    except LabelsynthError as exc:
        reason = str(exc).splitlines()[0]
        for prefix in (f"{partial / 'images'}: ", f"{partial}: "):
            reason = reason.removeprefix(prefix)
        raise CaptureError(f"{report.source}: structure-from-motion failed: {reason}") from exc
    total = len(poses.registered) + len(poses.unregistered)
    if len(poses.registered) < config.min_registered * total:
        raise CaptureError(f"{report.source}: structure-from-motion registered only {len(poses.registered)} of "
                           f"{total} frames (at least {config.min_registered:.0%} needed)")
    dropped = set(poses.unregistered)
    for name in dropped:
        (partial / "images" / f"{name}.png").unlink()
    report.frames = [f for f in report.frames if f.name not in dropped]
    report.registered, report.dropped_by_sfm = list(poses.registered), list(poses.unregistered)
    poses.output = report.capture / "transforms.json"
    report.poses = poses
    report.seconds["sfm"] = time.perf_counter() - t0
