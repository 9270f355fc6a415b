"""``labelsynth batch``: many captures through ``expand`` as Ray tasks, resumable, with one
merged dataset. Importing this package does not import Ray (only ``run_batch`` does)."""

from .discover import BatchError, CaptureJob, discover
from .merge import DATASET_FILE, merge_labels
from ..options import ExpandOptions
from .run import BatchResult, run_batch
from .table import BatchRow, rich_table

__all__ = ["DATASET_FILE", "BatchError", "BatchResult", "BatchRow", "CaptureJob", "ExpandOptions", "discover",
           "merge_labels", "rich_table", "run_batch"]
