"""Issue 31's tiny table capture over several seeds: does the field form a saturated, textureless
top over a white table before a dark backdrop?

    python benchmarks/bench_table.py --work /tmp/bench_table --seeds 0,1,2,3,4 --set geometry.iterations=1000

The capture is the one ``tests/render/test_support.py`` fits (``tests/scenes.py``
``make_table_capture``: 12 frames of 48 px on an arc on the table's near side, frames 0, 4 and 8
annotated, the object's top above z = 0.6 saturated white, the table 0.97, the backdrop 0.03),
expanded with the tests' ``fast`` overrides plus ``--set``. Per seed, scored as the tests score
(the exact scene ray-cast with trimesh):

- top: rays through the saturated top whose fitted surface hit lies within 0.1 of the true one;
- object: the same over all of the object's pixels;
- backdrop as object: pixels of the unannotated frames that see the backdrop, labelled object;
- foreground Dice of the unannotated frames' masks, and the geometry stage's training PSNR.

Prints one row per seed and the means; writes WORK/bench_table.json. Each seed's expand is
cached under WORK/<tag>/seed<N> (a finished one is not redone; the tag names the overrides).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.scenes builds the capture and its exact scene


def score(capture_dir: Path, out: Path) -> dict:
    """``tests.scenes.table_scores`` (what the table test counts), its foreground Dice, and the
    geometry stage's training PSNR and start shape from run.json."""
    from labelsynth.rundir import RunFolder
    from tests.scenes import table_scores

    counts = table_scores(capture_dir, out)
    geometry = RunFolder(out).read_run().geometry
    return {**counts, "dice": 2 * counts["inter"] / max(counts["union"], 1), "psnr": geometry["final_psnr"],
            "init_shape": geometry.get("init_shape")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the capture, the expands and the results")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated fit seeds (default 0,1,2)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe override on top of the tests' (repeatable), e.g. geometry.iterations=1000")
    args = ap.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        sys.exit(f"--seeds: expected comma-separated integers, not '{args.seeds}'")
    if not seeds:
        sys.exit("--seeds: give at least one seed")

    from labelsynth.pipeline import expand
    from tests.conftest import TINY_OVERRIDES
    from tests.scenes import make_table_capture

    args.work.mkdir(parents=True, exist_ok=True)
    case = args.work / "case"
    if not (case / "capture" / "transforms.json").is_file():
        make_table_capture(case)
    overrides = TINY_OVERRIDES + args.overrides
    tag = hashlib.sha1("\n".join(args.overrides).encode()).hexdigest()[:8] if args.overrides else "tests"
    rows = []
    print(f"overrides on the tests' fast recipe: {' '.join(args.overrides) or '(none)'}")
    print("| seed | top rays meeting it | object rays within 0.1 | backdrop labelled object | foreground Dice | PSNR |")
    print("|---|---|---|---|---|---|")
    for seed in seeds:
        out = args.work / tag / f"seed{seed}"
        if not (out / "run.json").is_file():
            expand(case / "capture", out, labels="annotations", recipe="fast", device="cpu", overrides=overrides,
                   progress=False, report=False, seed=seed, force=True)
        r = {"seed": seed, **score(case / "capture", out)}
        rows.append(r)
        print(f"| {seed} | {r['top_hit']} of {r['top']} | {r['object_hit']} of {r['object']} | "
              f"{r['backdrop_object']} of {r['backdrop']} | {r['dice']:.3f} | {r['psnr']:.1f} dB |", flush=True)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("top_hit", "object_hit", "backdrop_object", "dice", "psnr")}
    print(f"| mean | {mean['top_hit']:.0f} | {mean['object_hit']:.0f} | {mean['backdrop_object']:.0f} | "
          f"{mean['dice']:.3f} | {mean['psnr']:.1f} dB |")
    (args.work / "bench_table.json").write_text(json.dumps({"overrides": args.overrides, "rows": rows, "mean": mean},
                                                           indent=2))


if __name__ == "__main__":
    main()
