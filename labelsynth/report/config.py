"""The report's knobs (recipe section ``report``)."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import OpenUnitInterval


@dataclass
class ReportConfig:
    """The consistency report (the end of ``expand``; ``labelsynth report`` rebuilds it)."""

    loo_fraction: OpenUnitInterval = 0.25
    """Each leave-one-view-out refit trains a fresh head (never the full one warm-started: a head
    that learnt the left-out mask agrees with it) for this fraction of the semantic stage's
    steps and epochs: it only has to say what the other views predict, not polish a mask
    (README, Speed: the flags and the LOO Dice at 1.0 and at this value)."""
