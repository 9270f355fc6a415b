"""``OUT/dataset.h5``: every finished capture's labels.h5 read as one dataset, without a copy.

The frames stay in ``OUT/captures/<name>/labels.h5``; dataset.h5 maps them with HDF5 virtual
datasets whose sources are paths relative to dataset.h5, so OUT can be moved or mounted
elsewhere as a whole. Its format (``capture``, ``frame_sizes``, ``merged`` beside labels.h5's
datasets and attributes) is defined and written by ``export.labels_h5.write_merged``; every
reader of labels.h5 (``LabelsDataset``, ``labelsynth train``, ``read_labels_h5``) reads it
through ``export.labels_h5.LabelsReader``, which crops each frame of a smaller capture back to
its ``frame_sizes`` (never a padded pixel) and refuses the file when a capture's labels.h5 is gone.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import LabelsynthError
from ..export.labels_h5 import LabelsReader, write_merged
from .discover import BatchError

DATASET_FILE = "dataset.h5"


def merge_labels(out: Path, captures: list[tuple[str, Path]]) -> Path | None:
    """Write ``out/dataset.h5`` over the (name, labels.h5) pairs, in order; ``None`` (and any
    old dataset.h5 removed) when there is nothing to merge. Class tables must agree."""
    out = Path(out)
    target = out / DATASET_FILE
    if not captures:
        target.unlink(missing_ok=True)
        return None
    parts: list[tuple[str, LabelsReader]] = []
    try:
        for name, path in captures:
            try:
                parts.append((name, LabelsReader(path)))
            except LabelsynthError as exc:
                raise BatchError(f"{exc}; {DATASET_FILE} not written") from None
        first = parts[0][1]
        for _, reader in parts[1:]:
            if reader.classes.to_json() != first.classes.to_json():
                raise BatchError(
                    f"{reader.path}: its class table differs from {first.path}'s; {DATASET_FILE} needs one table "
                    "(run the captures with different tables as separate batches)"
                )
        return write_merged(target, parts)
    finally:
        for _, reader in parts:
            reader.close()
