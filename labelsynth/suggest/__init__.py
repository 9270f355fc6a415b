"""Which frames to annotate, before any annotation exists (``labelsynth suggest``).

The geometry stage needs no labels, so it is fitted first (and saved, for ``expand --geometry``);
``coverage`` then ranks frames by the surface they add (greedy coverage of samples of the fitted
surface, each counted once at the best view any chosen frame has of it) or, with
``objective="frames"``, by how well each frame's view is seen by one chosen frame, and ``sheet`` draws the
chosen frames with what each adds. ``run.suggest`` is the command as a library call.
"""

from .coverage import CoverageConfig, Pick, SurfaceViews, surface_views
from .run import SHEET_PNG, SUGGEST_JSON, SuggestResult, default_out, read_suggestion, suggest

__all__ = [
    "SHEET_PNG",
    "SUGGEST_JSON",
    "CoverageConfig",
    "Pick",
    "SuggestResult",
    "SurfaceViews",
    "default_out",
    "read_suggestion",
    "suggest",
    "surface_views",
]
