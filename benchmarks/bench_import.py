"""`labelsynth import` on a phone-like video made from real photographs.

Data: the instant-ngp fox (50 photographs at 1080x1920 with published poses in transforms.json:
the folder ``data/nerf/fox`` of the public repository NVlabs/instant-ngp). Keep it outside the
repository, e.g. /work/data/fox.

Part ``fox``: the photos in name order become an H.264 MP4 at 30 fps as a phone would store a
portrait video (landscape pixels, turned back upright by the track's rotation tag); each photo is
three frames, shaken (a motion blur), sharp, shaken. ``import --frames 40`` reads it back. Printed:
the share of the kept frames that are the sharp copies, the share registered by SfM (target
>= 90%), and the poses against the published ones after a similarity alignment of the camera
centres (target: median rotation error <= 2 degrees; both are OpenGL camera-to-world).

Part ``time``: a 30 s 1080p video (900 frames, stored 1920x1080 with the rotation tag) made from
the same photos: each photo held for 18 frames with a hand-held shake (a small random-walk
shift and roll, a motion blur on about a third of the frames) and cross-faded into the next over
the last 6; ``import`` with the default 50 frames, timed per step (decode, select, sfm).

    nice -n 5 python benchmarks/bench_import.py --fox /work/data/fox --work /tmp/bench_import
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np

from labelsynth.capture.video import ImportConfig, import_capture
from labelsynth.evaluation.poses import frame_poses, pose_errors
from labelsynth.evaluation.video import encode_video, tag_rotation


def motion_blur(rgb: np.ndarray, length: int, angle: float) -> np.ndarray:
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0
    rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle, 1.0)
    kernel = cv2.warpAffine(kernel, rot, (length, length))
    return cv2.filter2D(rgb, -1, kernel / kernel.sum())


def stored_as_phone(rgb: np.ndarray) -> np.ndarray:
    """Portrait pixels as a phone stores them: turned a quarter counter-clockwise (landscape);
    ``tag_rotation(path, 90)`` makes players turn them back."""
    return np.ascontiguousarray(np.rot90(rgb, k=1))


def load_photos(fox: Path) -> tuple[list[str], list[np.ndarray], dict]:
    transforms = json.loads((fox / "transforms.json").read_text())
    paths = sorted((fox / "images").glob("*.jpg"))
    photos = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in paths]
    return [p.stem for p in paths], photos, transforms


def bench_fox(fox: Path, work: Path, frames: int) -> dict:
    names, photos, transforms = load_photos(fox)
    video = work / "fox.mp4"
    t0 = time.perf_counter()

    def frames_of_video():
        for rgb in photos:
            stored = stored_as_phone(rgb)
            yield motion_blur(stored, 9, 20.0)
            yield stored
            yield motion_blur(stored, 9, -30.0)

    encode_video(video, frames_of_video(), fps=30.0)
    tag_rotation(video, 90)
    print(f"fox: {len(photos)} photos -> {video} ({3 * len(photos)} frames, H.264, rotation tag 90), "
          f"{time.perf_counter() - t0:.1f} s to encode")

    load0 = os.getloadavg()[0]
    report = import_capture(video, work / "fox_capture", ImportConfig(frames=frames), force=True)
    load1 = os.getloadavg()[0]
    print(report.summary())

    chosen = [f.source_index for f in report.frames]
    all_chosen = chosen + [int(n.split("_")[1]) for n in report.dropped_by_sfm]
    sharp_share = float(np.mean([i % 3 == 1 for i in all_chosen]))
    registered = len(report.registered) / len(all_chosen)
    est = json.loads((work / "fox_capture" / "transforms.json").read_text())
    estimate = {names[int(n.split("_")[1]) // 3]: m for n, m in frame_poses(est).items()}
    reference = frame_poses(transforms)
    errors = pose_errors(reference, estimate)
    scale = transforms["w"] / est["w"]
    result = {
        "frames_asked": frames, "kept": len(all_chosen), "sharp_copies": sharp_share,
        "registered": len(report.registered), "registered_share": registered,
        "rotation_error_deg": {"median": float(np.median(errors.rotation_deg)),
                               "p90": float(np.percentile(errors.rotation_deg, 90)),
                               "max": float(errors.rotation_deg.max())},
        "centre_error_share_of_path": {"median": float(np.median(errors.centre)), "max": float(errors.centre.max())},
        "focal_px_at_published_size": {"estimated": est["fl_x"] * scale, "published": transforms["fl_x"]},
        "written_size": list(report.written_size), "rotation_tag": report.rotation,
        "seconds": report.seconds, "loadavg_1min": [load0, load1],
    }
    print(f"fox: kept {len(all_chosen)} frames, {sharp_share:.0%} of them the sharp copy of their photo; "
          f"registered {len(report.registered)}/{len(all_chosen)} ({registered:.0%}; target >= 90%)")
    print(f"fox: rotation error after a similarity alignment: median {result['rotation_error_deg']['median']:.3f} deg "
          f"(target <= 2), p90 {result['rotation_error_deg']['p90']:.3f}, max {result['rotation_error_deg']['max']:.3f}; "
          f"centre error median {result['centre_error_share_of_path']['median']:.4f} of the path's size; "
          f"focal {est['fl_x'] * scale:.1f} px vs published {transforms['fl_x']:.1f} px at 1080x1920")
    return result


def bench_time(fox: Path, work: Path, seconds: float, frames: int, seed: int = 0) -> dict:
    _, photos, _ = load_photos(fox)
    fps = 30.0
    total = int(round(seconds * fps))
    per_photo = total / len(photos)
    rng = np.random.default_rng(seed)
    video = work / "phone_30s.mp4"
    t0 = time.perf_counter()

    def frames_of_video():
        shift, roll = np.zeros(2), 0.0
        for t in range(total):
            u = t / per_photo
            i = min(int(u), len(photos) - 1)
            a = u - i
            rgb = photos[i]
            if a > 2 / 3 and i + 1 < len(photos):  # cross-fade into the next photo
                w = (a - 2 / 3) * 3
                rgb = cv2.addWeighted(photos[i], 1 - w, photos[i + 1], w, 0)
            shift = 0.9 * shift + rng.normal(0, 1.5, 2)  # hand-held shake: a damped random walk
            roll = 0.9 * roll + rng.normal(0, 0.1)
            h, w_ = rgb.shape[:2]
            m = cv2.getRotationMatrix2D((w_ / 2, h / 2), roll, 1.0)
            m[:, 2] += shift
            rgb = cv2.warpAffine(rgb, m, (w_, h), borderMode=cv2.BORDER_REFLECT)
            if rng.random() < 1 / 3:
                rgb = motion_blur(rgb, int(rng.integers(5, 16)), float(rng.uniform(0, 180)))
            yield stored_as_phone(rgb)

    encode_video(video, frames_of_video(), fps=fps, crf=20)
    tag_rotation(video, 90)
    print(f"time: {total} frames (1920x1080 stored, rotation tag 90) -> {video}, "
          f"{time.perf_counter() - t0:.1f} s to make and encode")
    load0 = os.getloadavg()[0]
    t1 = time.perf_counter()
    report = import_capture(video, work / "phone_capture", ImportConfig(frames=frames), force=True)
    wall = time.perf_counter() - t1
    load1 = os.getloadavg()[0]
    print(report.summary())
    result = {"video_seconds": seconds, "decoded": report.decoded, "frames": frames,
              "registered": len(report.registered), "dropped_by_sfm": len(report.dropped_by_sfm),
              "seconds": report.seconds, "wall_s": wall, "loadavg_1min": [load0, load1], "cpus": os.cpu_count()}
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in report.seconds.items())
    print(f"time: {seconds:.0f} s of 1080p video, {frames} frames: {wall:.1f} s in all ({steps}); "
          f"registered {len(report.registered)}/{len(report.registered) + len(report.dropped_by_sfm)}; "
          f"load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fox", type=Path, default=Path("/work/data/fox"), help="instant-ngp's data/nerf/fox")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_import"))
    parser.add_argument("--part", choices=["fox", "time", "all"], default="all")
    parser.add_argument("--frames", type=int, default=40, help="frames the fox video is imported with")
    parser.add_argument("--seconds", type=float, default=30.0, help="length of the timed video")
    parser.add_argument("--time-frames", type=int, default=50, help="frames the timed video is imported with")
    args = parser.parse_args()
    if not (args.fox / "transforms.json").is_file():
        raise SystemExit(f"{args.fox}: no transforms.json (instant-ngp's data/nerf/fox expected)")
    args.work.mkdir(parents=True, exist_ok=True)
    record = args.work / "bench_import.json"
    results = json.loads(record.read_text()) if record.is_file() else {}  # one part at a time keeps the other's
    if args.part in ("fox", "all"):
        results["fox"] = bench_fox(args.fox, args.work, args.frames)
    if args.part in ("time", "all"):
        results["time"] = bench_time(args.fox, args.work, args.seconds, args.time_frames)
    record.write_text(json.dumps(results, indent=2))
    print(f"wrote {record}")


if __name__ == "__main__":
    main()
