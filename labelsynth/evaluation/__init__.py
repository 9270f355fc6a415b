"""Evaluation and baselines, not the product path: synthetic captures with exact truth
(``synth``), scores (``metrics``), annotation perturbations (``perturb``), the 3D/2D vote
baseline (``fusion``) and the benchmark that runs them against the field (``bench``). The 2D
ONNX segmenter (``segment``) is product: ``labelsynth.train.segment``.

``bench`` orchestrates whole runs through ``labelsynth.pipeline``, so it is loaded only when
one of its names is asked for: importing this package never imports the orchestration.
"""

from .fusion import FusedLabels, fuse_labels, fusion_baseline, render_labels, view_votes
from .metrics import METRICS, WOUND_BED, Counts, Scores, confusion_matrix, frame_counts, score_frames
from .perturb import PERTURBATIONS, apply_perturbation
from .synth import SynthConfig, SynthResult, synthesize

_BENCH = ("bench_markdown", "bench_plot", "run_bench")


def __getattr__(name: str):
    if name in _BENCH:
        from . import bench

        return getattr(bench, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "METRICS",
    "PERTURBATIONS",
    "WOUND_BED",
    "Counts",
    "FusedLabels",
    "Scores",
    "SynthConfig",
    "SynthResult",
    "apply_perturbation",
    "bench_markdown",
    "bench_plot",
    "confusion_matrix",
    "frame_counts",
    "fuse_labels",
    "fusion_baseline",
    "render_labels",
    "run_bench",
    "score_frames",
    "synthesize",
    "view_votes",
]
