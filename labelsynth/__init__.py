"""labelsynth: view-consistent segmentation masks for every frame of a capture from a 3D semantic field."""

__version__ = "0.1.0"
