"""What a run writes for users: ``labels.h5`` (``labels_h5``: its schema, writer and the one
reader), a torch Dataset over it and ``masks/*.png`` (``dataset``), and the labelled surface
mesh with its per-class areas (``mesh``).

``from labelsynth.export import LabelsDataset`` (and the other names below) is a documented
contract: they stay importable from here.
"""

from .dataset import LabelsDataset, write_masks_png
from .labels_h5 import (
    FORMAT,
    FORMAT_VERSION,
    ExportError,
    LabelsReadError,
    LabelsReader,
    LabelsWriter,
    classes_from_attrs,
    read_labels_h5,
    write_labels_h5,
)
from .mesh import MESH_FORMATS, MeshAreas, MeshExport, class_areas, export_labelled_mesh, labelled_mesh

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MESH_FORMATS",
    "ExportError",
    "LabelsDataset",
    "LabelsReadError",
    "LabelsReader",
    "LabelsWriter",
    "MeshAreas",
    "MeshExport",
    "class_areas",
    "classes_from_attrs",
    "export_labelled_mesh",
    "labelled_mesh",
    "read_labels_h5",
    "write_labels_h5",
    "write_masks_png",
]
