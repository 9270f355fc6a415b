"""Which containers and codecs `labelsynth import` reads: each is written by PyAV (its own FFmpeg)
and read back by the installed OpenCV's FFmpeg backend, as `import` reads it; then the phone
rotation tags (90, 180, 270 degrees) are checked against where the pixels land.

    python benchmarks/probe_codecs.py [--work /tmp/probe_codecs]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from labelsynth.capture.video import VideoReader
from labelsynth.errors import CaptureError
from labelsynth.evaluation.video import tag_rotation

# (container suffix, PyAV encoder, pixel format, codec tag or None, what a user would call it)
COMBINATIONS = [
    ("mp4", "libx264", "yuv420p", None, "H.264"), ("mov", "libx264", "yuv420p", None, "H.264"),
    ("mkv", "libx264", "yuv420p", None, "H.264"), ("avi", "libx264", "yuv420p", None, "H.264"),
    ("mp4", "libx264", "yuv420p10le", None, "H.264 10-bit"),
    ("mp4", "libx265", "yuv420p", None, "HEVC"), ("mov", "libx265", "yuv420p10le", "hvc1", "HEVC 10-bit, hvc1 (iPhone)"),
    ("mkv", "libx265", "yuv420p", None, "HEVC"),
    ("mp4", "mpeg4", "yuv420p", None, "MPEG-4 Part 2"), ("avi", "mpeg4", "yuv420p", None, "MPEG-4 Part 2"),
    ("avi", "mjpeg", "yuvj420p", None, "MJPEG"), ("mov", "mjpeg", "yuvj420p", None, "MJPEG"),
    ("webm", "libvpx", "yuv420p", None, "VP8"),
    ("webm", "libvpx-vp9", "yuv420p", None, "VP9"), ("mp4", "libvpx-vp9", "yuv420p", None, "VP9"),
    ("mp4", "libsvtav1", "yuv420p", None, "AV1"), ("mkv", "libsvtav1", "yuv420p", None, "AV1"),
    ("webm", "libsvtav1", "yuv420p", None, "AV1"),
    ("mov", "prores_ks", "yuv422p10le", None, "ProRes 422 10-bit"),
    ("mkv", "mpeg2video", "yuv420p", None, "MPEG-2"), ("mkv", "ffv1", "yuv420p", None, "FFV1"),
]
W, H, N = 320, 240, 12


def frames() -> list[np.ndarray]:
    out = []
    for i in range(N):
        img = np.zeros((H, W, 3), np.uint8)
        img[:] = (40, 80, 160)
        cv2.rectangle(img, (10 + 5 * i, 60), (60 + 5 * i, 140), (255, 255, 255), -1)
        img[:40, :40] = (255, 0, 0)  # a red mark at the stored top-left (RGB)
        out.append(img)
    return out


def write(path: Path, codec: str, pix_fmt: str, tag: str | None) -> None:
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=10)
        stream.width, stream.height, stream.pix_fmt = W, H, pix_fmt
        if tag:
            stream.codec_tag = tag
        for img in frames():
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def read_back(path: Path) -> tuple[int, np.ndarray | None, int]:
    with VideoReader(path) as video:
        first, count = None, 0
        for _, _, frame in video.frames():
            first = frame if first is None else first
            count += 1
        return count, first, video.rotation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("/tmp/probe_codecs"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"OpenCV {cv2.__version__}")
    print("| container | codec | frames read | colour right |\n|---|---|---|---|")
    for suffix, codec, pix_fmt, tag, name in COMBINATIONS:
        path = args.work / f"{codec}_{pix_fmt}.{suffix}"
        try:
            write(path, codec, pix_fmt, tag)
        except Exception as exc:  # noqa: BLE001 - an encoder this PyAV lacks: say so, go on
            print(f"| {suffix} | {name} | not written ({type(exc).__name__}) | |")
            continue
        try:
            count, first, _ = read_back(path)
        except CaptureError as exc:
            print(f"| {suffix} | {name} | no: {exc} | |")
            continue
        red = first is not None and first[20, 20, 2] > 200 and first[20, 20, 0] < 60
        print(f"| {suffix.upper()} | {name} | {count}/{N} | {'yes' if red else 'no'} |")
    plain = args.work / "libx264_yuv420p.mp4"
    for degrees in (90, 180, 270):
        tagged = args.work / f"rotated_{degrees}.mp4"
        tagged.write_bytes(plain.read_bytes())
        tag_rotation(tagged, degrees)
        _, first, rotation = read_back(tagged)
        ys, xs = np.nonzero((first[..., 2] > 200) & (first[..., 0] < 60))
        print(f"rotation tag {degrees} deg clockwise: OpenCV reports {rotation}, frame {first.shape[1]}x{first.shape[0]}, "
              f"red mark centred at ({xs.mean():.0f}, {ys.mean():.0f})")


if __name__ == "__main__":
    main()
