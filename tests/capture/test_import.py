"""`labelsynth import`: videos written here with cv2.VideoWriter (MPEG-4 Part 2 in MP4, MJPEG in
AVI) and folders of photos become capture folders; bad input is one line and leaves nothing."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from labelsynth.capture import load_capture
from labelsynth.capture.framepick import MotionTracker, pick_spread, sharpness
from labelsynth.capture.video import ImportConfig, import_capture
from labelsynth.cli import app
from labelsynth.errors import CaptureError
from labelsynth.evaluation.video import tag_rotation


def write_video(path: Path, frames: list[np.ndarray], fourcc: str = "mp4v", fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def texture(seed: int = 0, size: tuple[int, int] = (900, 200)) -> np.ndarray:
    """A wide, richly textured BGR strip for a camera to pan across."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8), (0, 0), 2.0)
    for _ in range(120):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        centre = (int(rng.integers(0, size[0])), int(rng.integers(0, size[1])))
        cv2.circle(img, centre, int(rng.integers(3, 18)), colour, -1)
    return img


def pan(strip: np.ndarray, xs: list[int], width: int = 160, height: int = 120, noise: float = 2.0,
        seed: int = 1) -> list[np.ndarray]:
    """Crops of ``strip`` at horizontal offsets ``xs``, each with fresh sensor noise."""
    rng = np.random.default_rng(seed)
    out = []
    for x in xs:
        crop = strip[:height, x:x + width].astype(np.float32) + rng.normal(0, noise, (height, width, 3))
        out.append(np.clip(crop, 0, 255).astype(np.uint8))
    return out


def files_of(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scene_frames(tmp_path_factory) -> list[np.ndarray]:
    """12 views of a synthetic wound (a real 3D scene SfM can pose), BGR 240x180."""
    from labelsynth.evaluation.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("import_scene")
    syn = synthesize(root / "s", SynthConfig(frames=12, annotated=0, width=240, height=180, seed=5), progress=False)
    return [cv2.imread(str(p)) for p in sorted((syn.capture_dir / "images").iterdir())]


def test_video_import_keeps_the_sharp_frames_and_writes_a_loadable_capture(scene_frames, tmp_path) -> None:
    # every view three times: slightly blurred, sharp, slightly blurred (a hand-held shake)
    frames = []
    for img in scene_frames:
        soft = cv2.GaussianBlur(img, (0, 0), 0.6)
        frames += [soft, img, soft]
    (tmp_path / "in").mkdir()
    video = write_video(tmp_path / "in" / "wound.mp4", frames)
    measured = [sharpness(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)) for f in frames]
    assert all(measured[3 * i + 1] > max(measured[3 * i], measured[3 * i + 2]) for i in range(12))
    before = files_of(video.parent)

    out = tmp_path / "cap"
    report = import_capture(video, out, ImportConfig(frames=10), progress=False)

    assert files_of(video.parent) == before  # nothing written beside the video
    picked = [f.source_index for f in report.frames]
    assert len(picked) + len(report.dropped_by_sfm) == 10
    assert all(i % 3 == 1 for i in picked), picked  # the sharp copy of each view, never a shaken one
    assert len(report.registered) >= 8 and report.poses is not None
    names = sorted(p.stem for p in (out / "images").iterdir())
    assert names == sorted(report.registered) == sorted(f.name for f in report.frames)
    capture = load_capture(out)
    assert [f.name for f in capture.frames] == names and capture.frames[0].size == (240, 180)
    record = json.loads((out / "import.json").read_text())
    assert record["kind"] == "video" and record["decoded"] == 36 and record["config"]["frames"] == 10
    assert not (tmp_path / "cap.partial").exists()


def test_a_phone_held_still_gives_one_frame_not_many(tmp_path) -> None:
    strip = texture()
    # pan 30 frames, hold still 40 frames (noise only), pan 30 more
    xs = [5 * i for i in range(30)] + [150] * 40 + [150 + 5 * i for i in range(1, 31)]
    video = write_video(tmp_path / "still.mp4", pan(strip, xs))
    report = import_capture(video, tmp_path / "cap", ImportConfig(frames=8, poses=False), progress=False)
    picked = [f.source_index for f in report.frames]
    assert len(picked) == 8
    held = [i for i in picked if 30 <= i < 70]
    assert len(held) <= 1, picked  # spread over time, 3 of the 8 would be copies of one view
    offsets = np.array([xs[i] for i in picked], dtype=float)
    assert np.diff(offsets).min() >= 0.01 * np.hypot(160, 120)  # no two kept frames show the same view
    assert np.diff(offsets).max() < 3 * 300 / 8  # and they are spread over the path

    # the motion measure: still frames add nothing, however many; a pan adds its displacement
    tracker = MotionTracker()
    positions = [tracker.update(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)) for f in pan(strip, xs)]
    assert positions[69] - positions[30] < 0.005
    assert positions[29] == pytest.approx(145 / np.hypot(160, 120), rel=0.1)


def test_near_duplicate_picks_are_dropped_and_made_up_elsewhere() -> None:
    # a camera that moves 4% of the diagonal in all, asked for 8 frames: runs 0.5% apart
    motion = np.linspace(0.0, 0.04, 41)
    sharp = 1.0 + np.random.default_rng(0).random(41)
    pick = pick_spread(sharp, 8, blur_floor=0.15, motion=motion, min_motion=0.01)
    assert np.diff(motion[pick.chosen]).min() >= 0.01 - 1e-12
    assert len(pick.chosen) <= 5 and pick.near_duplicates >= 3
    # runs of only blurred frames are made up in the widest gaps along the path, not left short
    motion = np.linspace(0.0, 1.0, 60)
    sharp = np.ones(60)
    sharp[20:40] = 0.05
    pick = pick_spread(sharp, 6, blur_floor=0.15, motion=motion, min_motion=0.01)
    assert len(pick.chosen) == 6 and pick.filled == 2 and pick.blurred == 20
    assert not any(20 <= i < 40 for i in pick.chosen)
    # photos: every usable one when there are few, no motion involved
    assert pick_spread(sharp[15:25], 50, blur_floor=0.15).chosen == [0, 1, 2, 3, 4]


def test_rotation_metadata_is_applied(tmp_path) -> None:
    """A phone filming in portrait stores landscape pixels and a display matrix (tkhd)."""
    frames = pan(texture(2), [4 * i for i in range(12)], noise=0.0)
    for f in frames:
        f[:20, :20] = (0, 0, 255)  # a red mark in the stored top-left corner
    video = tag_rotation(write_video(tmp_path / "portrait.mp4", frames), 90)

    report = import_capture(video, tmp_path / "cap", ImportConfig(frames=4, poses=False), progress=False)
    assert report.rotation == 90 and report.source_size == (120, 160)
    img = cv2.imread(str(tmp_path / "cap" / "images" / f"{report.frames[0].name}.png"))
    assert img.shape[:2] == (160, 120)  # portrait, as a player shows it
    red = (img[..., 2] > 180) & (img[..., 0] < 80) & (img[..., 1] < 80)
    ys, xs = np.nonzero(red)
    assert xs.mean() > 100 and ys.mean() < 20  # turned clockwise: the mark is at the top right


def test_folder_of_photos(tmp_path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    crops = pan(texture(3), [40 * i for i in range(6)], width=200, height=150, noise=0.0)
    for i, img in enumerate(crops):
        if i == 2:
            img = cv2.GaussianBlur(img, (0, 0), 3.0)  # a shaken photo
        rgb = Image.fromarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        exif = Image.Exif()
        if i == 4:
            exif[0x0112] = 6  # shot in portrait: shown turned 90 degrees clockwise
        rgb.save(photos / f"IMG_{i:02d}.jpg", quality=95, exif=exif)
    (photos / "notes.txt").write_text("not a photo")
    before = files_of(photos)

    report = import_capture(photos, tmp_path / "cap", ImportConfig(max_side=100, poses=False), progress=False)
    assert files_of(photos) == before
    names = sorted(p.name for p in (tmp_path / "cap" / "images").iterdir())
    assert names == ["IMG_00.png", "IMG_01.png", "IMG_03.png", "IMG_04.png", "IMG_05.png"]
    assert report.blurred == 1 and report.kind == "photos"
    sizes = {n: cv2.imread(str(tmp_path / "cap" / "images" / n)).shape[:2] for n in names}
    assert sizes["IMG_00.png"] == (75, 100) and sizes["IMG_04.png"] == (100, 75)

    # at most --frames of them, the sharpest of each run in name order
    few = import_capture(photos, tmp_path / "few", ImportConfig(frames=2, poses=False), progress=False)
    assert len(few.frames) == 2


def _shapes(rng: np.random.Generator) -> np.ndarray:
    img = np.full((180, 240, 3), 127, np.uint8)
    for _ in range(60):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.circle(img, (int(rng.integers(0, 240)), int(rng.integers(0, 180))), int(rng.integers(3, 20)), colour, -1)
    return img


def _bad_inputs(root: Path, scene_frames: list[np.ndarray]) -> dict[str, tuple[Path, list[str], str]]:
    """name -> (source, extra CLI args, what the error says)."""
    root.mkdir()
    text = root / "clip.mp4"
    text.write_text("this is not a video\n")
    avi = write_video(root / "mjpeg.avi", pan(texture(4), [0, 4, 8, 12]), fourcc="MJPG")
    avi.write_bytes(avi.read_bytes().replace(b"MJPG", b"ZZZZ"))  # a codec FFmpeg does not know
    still = write_video(root / "still.mp4", pan(texture(5), [10] * 30))
    rng = np.random.default_rng(0)
    half = write_video(root / "half.mp4", scene_frames + [_shapes(rng) for _ in range(14)])
    single = root / "one.png"
    cv2.imwrite(str(single), scene_frames[0])
    return {
        "not a video": (text, [], "not a video"),
        "unreadable codec": (avi, [], "AVI file whose video stream OpenCV's FFmpeg cannot decode"),
        "fewer usable frames": (still, ["--frames", "4", "--no-poses"], "only 1 usable frames for --frames 4"),
        "SfM registers under half": (half, ["--frames", "24"], "registered only"),
        "a single image": (single, [], "a single image"),
        "missing": (root / "nothing.mov", [], "not found"),
    }


def test_bad_input_is_one_line_and_leaves_no_capture(scene_frames, tmp_path) -> None:
    runner = CliRunner()
    for name, (source, args, message) in _bad_inputs(tmp_path / "in", scene_frames).items():
        out = tmp_path / f"cap_{name.replace(' ', '_')}"
        result = runner.invoke(app, ["import", str(source), "--out", str(out), *args])
        errors = [line for line in result.stderr.splitlines() if line.startswith("labelsynth: error:")]
        assert result.exit_code == 2, (name, result.stderr)
        assert len(errors) == 1 and errors[0] == result.stderr.strip().splitlines()[-1], (name, result.stderr)
        assert errors[0].startswith(f"labelsynth: error: {source}: ") and message in errors[0], (name, errors)
        assert not out.exists() and not out.with_name(out.name + ".partial").exists(), name


def test_the_photo_folder_is_never_the_output(tmp_path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    with pytest.raises(Exception, match="inside the photo folder"):
        import_capture(photos, photos / "capture", ImportConfig(poses=False), progress=False)
    assert list(photos.iterdir()) == []
    with pytest.raises(CaptureError, match="no PNG or JPEG"):
        import_capture(photos, tmp_path / "cap", ImportConfig(poses=False), progress=False)
    assert not (tmp_path / "cap").exists() and not (tmp_path / "cap.partial").exists()
