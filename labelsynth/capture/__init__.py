"""Capture folders in: frames, cameras, images, masks, classes and the region of interest.

``load_capture`` is the entry point; ``read_image`` / ``read_mask`` / ``write_mask`` are the
pixel readers and writer shared with the outputs. Nothing here ever writes into a capture.
"""

from ..errors import CaptureError
from .images import read_image
from .load import load_capture, validate_capture
from .masks import read_mask, write_mask
from .model import Capture, Frame, SceneNormalization
from .normalize import region_of_interest

__all__ = [
    "Capture",
    "CaptureError",
    "Frame",
    "SceneNormalization",
    "load_capture",
    "read_image",
    "read_mask",
    "region_of_interest",
    "validate_capture",
    "write_mask",
]
