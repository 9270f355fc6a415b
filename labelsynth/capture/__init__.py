"""Capture folders in: frames, cameras, images, masks, classes and the region of interest.

``load_capture`` is the entry point (``find_pose_source`` / ``is_capture``: what it accepts as a capture folder); ``check_capture`` decodes every input a run will read
before it trains; ``estimate_poses`` (``poses``) gives a capture without cameras its poses by
pycolmap structure-from-motion; ``import_capture`` (``import``) makes a capture from a video or
a folder of photos; ``list_images`` / ``read_image`` / ``read_mask`` / ``write_mask`` are the
one lister, pixel readers and mask writer shared by every command and the outputs; ``select_frames`` reads the ``annotated_frames`` spec.
Nothing here ever writes into a capture.
"""

from ..errors import CaptureError, CheckError
from .check import CheckReport, ExtraMask, check_capture
from .images import list_images, read_image
from .load import find_pose_source, is_capture, load_capture, validate_capture
from .masks import read_mask, write_mask
from .model import Capture, Frame, SceneNormalization
from .normalize import region_of_interest
from .poses import PoseReport, estimate_poses
from .select import select_frames
from .video import ImportConfig, ImportReport, import_capture

__all__ = [
    "Capture",
    "CaptureError",
    "CheckError",
    "CheckReport",
    "ExtraMask",
    "Frame",
    "ImportConfig",
    "ImportReport",
    "PoseReport",
    "SceneNormalization",
    "check_capture",
    "estimate_poses",
    "find_pose_source",
    "import_capture",
    "is_capture",
    "list_images",
    "load_capture",
    "read_image",
    "read_mask",
    "region_of_interest",
    "select_frames",
    "validate_capture",
    "write_mask",
]
