"""Stage 2, semantics: a class head trained on the frozen geometry from the labelled frames.

``head`` holds the semantic head, its class weights and the wound-bed decision rule;
``training`` bakes each labelled ray's samples once (the geometry no longer changes) and
trains the head by weighted cross-entropy on the volume-rendered logits.
"""

from .head import CLASS_WEIGHTINGS, DECISION_RULES, SemanticHead, class_weights, decide_labels
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
    "LabelledFrame",
    "SemanticHead",
    "SemanticStats",
    "bake_semantic_rays",
    "class_weights",
    "decide_labels",
    "make_semantic_head",
    "train_semantic",
]
