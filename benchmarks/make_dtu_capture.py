"""A NeuS-layout folder (DTU / BlendedMVS as NeuS ships them) -> a labelsynth capture folder.

    python benchmarks/make_dtu_capture.py /data/DTU/dtu_scan65 /tmp/dtu65 --annotated 3 [--scale 0.5]

writes, and reads the source only:

    OUT/capture/transforms.json   nerfstudio layout, per-frame PINHOLE intrinsics, OpenGL c2w
    OUT/capture/images/           the frames, copied as they are (or resized by --scale: DTU's
                                  1600x1200 at 0.5 is the 800x600 that SDF methods train on)
    OUT/capture/annotations/      <stem>.png 0/1 id masks for N frames spread over the sequence
    OUT/capture/classes.json      background (0), object (1)
    OUT/truth/<stem>.png          0/1 id masks for every frame (to score the other frames)

so the transforms.json path can be tried on real data (``labelsynth expand OUT/capture``).
The cameras are the NeuS loader's, in the npz's world; the unit sphere is kept in
transforms.json as ``neus_unit_sphere`` for reference only: a transforms.json capture finds
its region of interest from the cameras.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import cv2

from labelsynth.capture import load_capture, select_frames, write_mask


def make_capture(src: Path, out: Path, annotated: int, force: bool = False, scale: float = 1.0) -> list[str]:
    """Write OUT/capture and OUT/truth from the NeuS folder ``src``; returns the annotated names.

    ``scale`` resizes frames (area), masks (nearest) and intrinsics alike (``Camera.scaled``)."""
    cap = load_capture(src)
    if not cap.has_annotations:
        sys.exit(f"{src}: no mask/ folder, so no truth to write")
    if out.exists():
        if not force:
            sys.exit(f"{out}: exists (use --force to replace it)")
        shutil.rmtree(out)
    annotated_names = select_frames(f"spread:{annotated}", cap.names, "--annotated") if annotated else []
    capture_dir, truth_dir = out / "capture", out / "truth"
    (capture_dir / "images").mkdir(parents=True)
    frames = []
    for i, frame in enumerate(cap.frames):
        cam = frame.camera
        target = capture_dir / "images" / frame.image_path.name
        if scale == 1.0:
            shutil.copyfile(frame.image_path, target)
        else:
            cam = cam.scaled(scale)
            target = target.with_suffix(".png")
            small = cv2.resize(cap.load_image(i), (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(target), cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
        frames.append({
            "file_path": f"images/{target.name}",
            "transform_matrix": cam.c2w.tolist(),
            "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
        })
        mask = cap.load_annotation(i)
        if scale != 1.0:
            mask = cv2.resize(mask, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        write_mask(truth_dir / f"{frame.name}.png", mask, cap.classes)
        if frame.name in annotated_names:
            write_mask(capture_dir / "annotations" / f"{frame.name}.png", mask, cap.classes)
    transforms = {"camera_model": "PINHOLE", "frames": frames,
                  "neus_unit_sphere": cap.normalization.to_json(), "source": str(src.resolve())}
    (capture_dir / "transforms.json").write_text(json.dumps(transforms, indent=1))
    (capture_dir / "classes.json").write_text(json.dumps(cap.classes.to_json(), indent=1))
    return annotated_names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, help="NeuS-layout folder: image/, mask/, cameras_sphere.npz")
    ap.add_argument("out", type=Path, help="folder to create: OUT/capture and OUT/truth")
    ap.add_argument("--annotated", type=int, default=3, help="frames with annotations, spread over the sequence")
    ap.add_argument("--force", action="store_true", help="replace OUT if it exists")
    ap.add_argument("--scale", type=float, default=1.0, help="resize the frames, masks and cameras by this factor")
    args = ap.parse_args()
    if not 0 < args.scale <= 1:
        sys.exit(f"--scale {args.scale}: expected a factor in (0, 1]")
    if args.out.resolve().is_relative_to(args.src.resolve()):
        sys.exit(f"{args.out}: must not be inside the source {args.src}")
    names = make_capture(args.src, args.out, args.annotated, args.force, args.scale)
    print(f"capture: {args.out / 'capture'} ({len(list((args.out / 'capture' / 'images').iterdir()))} frames, "
          f"annotated: {', '.join(names) or 'none'})")
    print(f"truth:   {args.out / 'truth'}")


if __name__ == "__main__":
    main()
