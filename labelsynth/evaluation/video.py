"""Videos made for tests and benchmarks: frames encoded as a phone would (H.264 in MP4, by PyAV)
and a phone's portrait rotation tag.

A phone filming upright stores landscape pixels and a display matrix in the MP4's track header
(``tkhd``) that players (and OpenCV's FFmpeg backend) apply; ``tag_rotation`` writes that
matrix, since neither PyAV nor OpenCV's writer can.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path

import numpy as np

# tkhd matrices (a, b, u, c, d, v, x, y, w in 16.16 / 2.30 fixed point) that display the stored
# pixels turned clockwise by the key in degrees; 90 is what a phone held upright writes.
_MATRICES = {
    0: (65536, 0, 0, 0, 65536, 0, 0, 0, 1 << 30),
    90: (0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30),
    180: (-65536, 0, 0, 0, -65536, 0, 0, 0, 1 << 30),
    270: (0, -65536, 0, 65536, 0, 0, 0, 0, 1 << 30),
}


def tag_rotation(path: str | Path, clockwise_degrees: int) -> Path:
    """Set the display rotation of an MP4/MOV's (first) video track, in place."""
    path = Path(path)
    data = bytearray(path.read_bytes())
    at = data.find(b"tkhd")
    if at < 0:
        raise ValueError(f"{path}: no tkhd box (not an MP4/MOV file)")
    version = data[at + 4]
    # after 'tkhd': version+flags (4), times and ids (20 or 32), reserved (8), layer, group,
    # volume, reserved (8), then the 3x3 matrix
    matrix_at = at + 4 + 4 + (32 if version == 1 else 20) + 8 + 8
    data[matrix_at:matrix_at + 36] = struct.pack(">9i", *_MATRICES[clockwise_degrees % 360])
    path.write_bytes(bytes(data))
    return path


def encode_video(path: str | Path, frames: Iterable[np.ndarray], fps: float = 30.0, *, codec: str = "libx264",
                 crf: int = 18, preset: str = "veryfast") -> Path:
    """Encode RGB uint8 frames (all one size, even sides) with PyAV (``pip install av``)."""
    try:
        import av
    except ImportError as exc:  # a development tool: tests write videos with OpenCV instead
        raise RuntimeError("encode_video needs PyAV: pip install av") from exc
    path = Path(path)
    with av.open(str(path), "w") as container:
        stream = None
        for rgb in frames:
            if stream is None:
                stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
                stream.width, stream.height = rgb.shape[1], rgb.shape[0]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": str(crf), "preset": preset}
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")):
                container.mux(packet)
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    return path
