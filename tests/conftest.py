"""Shared test fixtures."""

import os

# Tests must never need a display or a GPU, and should not fight over the 2 CPU cores.
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("CUDA_VISIBLE_DEVICES", "")
