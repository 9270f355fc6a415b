"""The consistency report of an expand run: which input masks disagree, where, and by how much.

``build_report`` receives what it needs from the caller (the field, the masks it learnt
from, a callable that refits it without one frame), so this package imports no
orchestration; ``pipeline.expand`` and ``pipeline.rebuild_report`` call it.
"""

from .build import REPORT_JSON, build_report, read_field_masks

__all__ = ["REPORT_JSON", "build_report", "read_field_masks"]
