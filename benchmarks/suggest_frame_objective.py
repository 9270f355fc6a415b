"""Explore a frame-level choice of the frames to annotate on a finished `suggest` output (issue 27).

    python benchmarks/suggest_frame_objective.py /tmp/sugseed/s0/around/suggest --ks 2,3,4

`suggest` scores surface: each point counted once, at the best view a chosen frame has of it.
Here each *frame* is served by its one best teacher: teacher i serves frame j by the share of
j's view of the surface (``SurfaceViews.quality``, per point) that i sees at least as well,
sum_p min(q_i(p), q_j(p)) / sum_p q_j(p); a choice scores the mean over the frames of their best
teacher's share (a facility location over frames). Greedy, then single swaps until none helps
(greedy alone can end below spread:K). Prints the picks and scores next to spread:K's; expand
the picks with `expand --geometry SUGGEST_OUT --annotated-frames ...` to score them
(docs/benchmarks.md, "A lead, not adopted").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def teacher_shares(quality: np.ndarray) -> np.ndarray:
    """(F, F): [i, j] = the share of frame j's view of the surface that frame i sees as well."""
    q = quality.astype(np.float64)
    own = np.maximum(q.sum(axis=1), 1e-12)
    return np.stack([np.minimum(q[i][None], q).sum(axis=1) / own for i in range(len(q))])


def frame_score(shares: np.ndarray, chosen: list[int]) -> float:
    return float(shares[chosen].max(axis=0).mean())


def choose(shares: np.ndarray, k: int) -> list[int]:
    chosen: list[int] = []
    best = np.zeros(shares.shape[1])
    for _ in range(k):
        gains = np.maximum(shares, best[None]).sum(axis=1) - best.sum()
        gains[chosen] = -np.inf
        chosen.append(int(np.argmax(gains)))
        best = np.maximum(best, shares[chosen[-1]])
    score, improved = frame_score(shares, chosen), True
    while improved:
        improved = False
        for slot in range(k):
            for c in range(len(shares)):
                if c in chosen:
                    continue
                trial = chosen[:slot] + [c] + chosen[slot + 1:]
                trial_score = frame_score(shares, trial)
                if trial_score > score + 1e-12:
                    chosen, score, improved = trial, trial_score, True
    return sorted(chosen)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suggest_out", type=Path, help="a finished `labelsynth suggest` output folder")
    ap.add_argument("--ks", default="2,3,4")
    args = ap.parse_args()

    import torch

    from labelsynth.capture import load_capture
    from labelsynth.capture.select import select_frames
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import load_field
    from labelsynth.suggest import CoverageConfig, read_suggestion, surface_views

    capture = load_capture(read_suggestion(args.suggest_out)["capture"])
    view = FieldRenderer(load_field(args.suggest_out / "field.pt", torch.device("cpu")))
    views = surface_views(view.mesh(), capture.unit_cameras(), capture.names, CoverageConfig(), caster=view.caster(),
                          progress=False)
    shares = teacher_shares(views.quality)
    for k in (int(x) for x in args.ks.split(",")):
        picks = choose(shares, k)
        spread = [capture.names.index(n) for n in select_frames(f"spread:{k}", capture.names)]
        print(f"K={k}: {','.join(capture.names[i] for i in picks)}  score {frame_score(shares, picks):.3f}  "
              f"(spread:{k} {','.join(capture.names[i] for i in spread)} {frame_score(shares, spread):.3f})")


if __name__ == "__main__":
    main()
