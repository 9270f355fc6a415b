"""Scores against truth: ``labelsynth.metrics`` under its older name (benchmarks and notebooks
import it from here). The report and training use the same module, so it lives beside them."""

from ..metrics import METRICS, WOUND_BED, Counts, Scores, confusion_matrix, frame_counts, score_frames

__all__ = ["METRICS", "WOUND_BED", "Counts", "Scores", "confusion_matrix", "frame_counts", "score_frames"]
