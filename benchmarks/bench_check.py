"""Wall time of the input check that expand, bench and report run before any training.

    labelsynth synth /tmp/chk50 --frames 50                     # 50 frames at 640x480, ~40 s
    python benchmarks/bench_check.py /tmp/chk50/capture [--workers N] [--repeat 3]

Prints the files checked, the problems found and the time of each repeat (the first one
reads the files from disk if they are not in the page cache, the later ones from memory).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from labelsynth.capture import check_capture, load_capture


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--labels", default="both", choices=["annotations", "predictions", "both"])
    ap.add_argument("--workers", type=int, default=None, help="threads (default: the usable CPUs, at most 8)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    t0 = time.perf_counter()
    capture = load_capture(args.capture)
    print(f"load_capture: {time.perf_counter() - t0:.2f} s, {len(capture)} frames "
          f"({capture.frames[0].size[0]}x{capture.frames[0].size[1]})")
    for i in range(args.repeat):
        capture.mask_cache.clear()
        rep = check_capture(capture, labels=args.labels, workers=args.workers)
        print(f"check {i + 1}: {rep.files} files, {len(rep.problems)} problems, {rep.cached_masks} masks cached, "
              f"{rep.seconds:.2f} s")
    for p in rep.problems[:10]:
        print("  " + p)


if __name__ == "__main__":
    main()
