"""The consistency report of an expand run: which input masks disagree, where, and by how much.

``build_report`` is called by ``pipeline.expand``; ``rebuild_report`` redoes it for a
finished output folder (``labelsynth report OUT``).
"""

from .build import build_report, read_field_masks, rebuild_report

__all__ = ["build_report", "read_field_masks", "rebuild_report"]
