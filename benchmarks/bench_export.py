"""Wall time of exporting 50 frames in every format (target: under 10 s each).

    python benchmarks/bench_export.py [--labels OUT/labels.h5] [--frames 50] [--width 640 --height 480]
                                      [--min-confidence 0.5] [--root /tmp/bench_export]

With ``--labels`` the frames (images, masks, confidence) are read from an expand's labels.h5,
one at a time as ``labelsynth export`` reads them; without it, frames of wound-like blobs
(ellipses of every class on a smooth image, confidence lowest at class borders) are made in memory first,
so the time is the writing alone. Prints each format's seconds, its size on disk and the
ignore pixels.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from labelsynth.classes import ClassMap
from labelsynth.export.formats import EXPORT_FORMATS, ExportFrame, export_frames


def blob_frames(n: int, w: int, h: int, seed: int = 0) -> list[ExportFrame]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    frames = []
    for i in range(n):
        mask = np.zeros((h, w), np.uint8)
        cx, cy = w / 2 + rng.normal(0, w / 20), h / 2 + rng.normal(0, h / 20)
        cv2.ellipse(mask, (int(cx), int(cy)), (w // 4, h // 4), float(rng.uniform(0, 180)), 0, 360, 1, -1)
        for class_id in (2, 3, 4, 5):
            c = (int(cx + rng.normal(0, w / 10)), int(cy + rng.normal(0, h / 10)))
            cv2.ellipse(mask, c, (int(rng.uniform(8, w / 10)), int(rng.uniform(8, h / 10))), 0, 0, 360, class_id, -1)
        edges = (cv2.Canny(mask * 40, 1, 1) == 0).astype(np.uint8)  # the field is least sure at class borders
        conf = (1.0 - 0.6 * np.exp(-cv2.distanceTransform(edges, cv2.DIST_L2, 3) / 4.0)).astype(np.float32)
        image = np.dstack([(xx * 255 // w), (yy * 255 // h), np.full_like(xx, 40 + i)]).astype(np.uint8)
        frames.append(ExportFrame(f"frame_{i:03d}", mask, image, conf, annotated=i % 12 == 0))
    return frames


def h5_frames(path: Path):
    from labelsynth.export import LabelsDataset

    ds = LabelsDataset(path, uint8=True)
    for i in range(len(ds)):
        item = ds[i]
        yield ExportFrame(item["name"], item["mask"].numpy().astype(np.uint8),
                          item["image"].permute(1, 2, 0).numpy(), item["confidence"].numpy(), bool(item["annotated"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--labels", type=Path, help="an expand's labels.h5 (default: blobs made in memory)")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--min-confidence", type=float, default=0.5)
    ap.add_argument("--root", type=Path, default=Path("/tmp/bench_export"))
    args = ap.parse_args()

    if args.labels is not None:
        from labelsynth.export import LabelsDataset

        classes, n = LabelsDataset(args.labels).classes, len(LabelsDataset(args.labels))
        print(f"frames: {args.labels} ({n} frames, read one at a time during each export)")
    else:
        classes, n = ClassMap.default(), args.frames
        t0 = time.perf_counter()
        frames = blob_frames(n, args.width, args.height)
        print(f"frames: {n} blob frames {args.width}x{args.height} made in {time.perf_counter() - t0:.1f} s")
    shutil.rmtree(args.root, ignore_errors=True)
    args.root.mkdir(parents=True)
    for fmt in EXPORT_FORMATS:
        to = args.root / ("export.zip" if fmt == "cvat" else fmt)
        source = h5_frames(args.labels) if args.labels is not None else frames
        t0 = time.perf_counter()
        result = export_frames(source, classes, to, fmt=fmt, min_confidence=args.min_confidence, total=n)
        seconds = time.perf_counter() - t0
        size = to.stat().st_size if to.is_file() else sum(p.stat().st_size for p in to.rglob("*") if p.is_file())
        print(f"{fmt:10s} {seconds:6.2f} s  {size / 2**20:6.1f} MiB  {len(result.frames)} frames, "
              f"{result.ignored_pixels} pixels ignore  ({'met' if seconds < 10 else 'NOT met'}: < 10 s)")


if __name__ == "__main__":
    main()
