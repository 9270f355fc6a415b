"""Stage 2, semantics: a class head trained on the frozen geometry from the labelled frames.

``config`` holds the stage's recipe section and its named choices; ``head`` the semantic head,
its class weights and the wound-bed decision rule; ``training`` bakes each labelled ray's
samples once (the geometry no longer changes) and trains the head by weighted cross-entropy on
the volume-rendered logits; ``fit`` is the stage as calls that return heads: one head, and the
leave-one-out heads of the report.
"""

from .config import CLASS_WEIGHTINGS, DECISION_RULES, SemanticConfig
from .fit import HeadFit, fit_head, leave_one_out_heads, scaled_config
from .head import SemanticHead, class_weights, decide_labels
from .training import (
    BakedRays,
    LabelledFrame,
    SemanticStats,
    bake_semantic_rays,
    make_semantic_head,
    train_semantic,
)

__all__ = [
    "BakedRays",
    "CLASS_WEIGHTINGS",
    "DECISION_RULES",
    "HeadFit",
    "LabelledFrame",
    "SemanticConfig",
    "SemanticHead",
    "SemanticStats",
    "bake_semantic_rays",
    "class_weights",
    "decide_labels",
    "fit_head",
    "leave_one_out_heads",
    "make_semantic_head",
    "scaled_config",
    "train_semantic",
]
