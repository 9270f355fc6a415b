"""``OUT/dataset.h5``: every finished capture's labels.h5 read as one dataset, without a copy.

The frames stay in ``OUT/captures/<name>/labels.h5``; dataset.h5 maps them with HDF5 virtual
datasets (``images``, ``masks``, ``confidence``) whose sources are paths relative to dataset.h5,
so OUT can be moved or mounted elsewhere as a whole. Small per-frame datasets are real copies:
``annotated``, ``frame_names``, ``capture`` (the capture's name for each frame) and
``frame_sizes`` (height, width). Captures of different sizes share one dataset of the largest
size; each frame sits in the top-left corner and the rest reads as the fill values (masks
255 = ignore, images 0, confidence 0): ``LabelsDataset`` and ``labelsynth train`` crop every
frame back to its ``frame_sizes``. The file attributes are labels.h5's (format, class table,
version) plus ``merged`` (JSON: each capture's name, file, first frame and frame count), so
readers of labels.h5 read it unchanged. It is written as ``dataset.h5.partial`` and renamed.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..outdir import atomic_file
from .discover import BatchError

DATASET_FILE = "dataset.h5"
_FILLS = {"images": 0, "masks": 255, "confidence": 0}
_COPIED_ATTRS = ("format", "format_version", "class_names", "class_ids", "class_colors", "wound_bed_ids",
                 "classes_json", "ignore_id", "recipe", "labels", "recipe_name")


def merge_labels(out: Path, captures: list[tuple[str, Path]]) -> Path | None:
    """Write ``out/dataset.h5`` over the (name, labels.h5) pairs, in order; ``None`` (and any
    old dataset.h5 removed) when there is nothing to merge. Class tables must agree."""
    out = Path(out)
    target = out / DATASET_FILE
    if not captures:
        target.unlink(missing_ok=True)
        return None
    infos = []
    for name, path in captures:
        try:
            with h5py.File(path, "r") as f:
                n, h, w = (int(v) for v in f["masks"].shape)
                infos.append({
                    "name": name, "path": Path(path), "frames": n, "height": h, "width": w,
                    "classes_json": str(f.attrs.get("classes_json", "")),
                    "names": [str(s) for s in f["frame_names"].asstr()[()]],
                    "annotated": f["annotated"][()].astype(bool),
                    "dtypes": {k: f[k].dtype for k in _FILLS},
                })
        except (OSError, KeyError) as exc:
            raise BatchError(f"{path}: cannot read it for {DATASET_FILE} ({exc})") from None
    first = infos[0]
    for info in infos[1:]:
        if info["classes_json"] != first["classes_json"]:
            raise BatchError(
                f"{info['path']}: its class table differs from {first['path']}'s; {DATASET_FILE} needs one table "
                "(run the captures with different tables as separate batches)"
            )
    total = sum(i["frames"] for i in infos)
    hmax, wmax = max(i["height"] for i in infos), max(i["width"] for i in infos)
    shapes = {"images": (total, hmax, wmax, 3), "masks": (total, hmax, wmax), "confidence": (total, hmax, wmax)}
    layouts = {k: h5py.VirtualLayout(shape=shapes[k], dtype=first["dtypes"][k]) for k in _FILLS}
    merged, start = [], 0
    for info in infos:
        rel = info["path"].resolve().relative_to(out.resolve()).as_posix()
        n, h, w = info["frames"], info["height"], info["width"]
        for key, layout in layouts.items():
            src_shape = (n, h, w, 3) if key == "images" else (n, h, w)
            src = h5py.VirtualSource(rel, key, shape=src_shape, dtype=info["dtypes"][key])
            layout[start:start + n, :h, :w] = src
        merged.append({"name": info["name"], "file": rel, "first": start, "frames": n, "height": h, "width": w})
        start += n
    with atomic_file(target) as tmp:
        with h5py.File(first["path"], "r") as src, h5py.File(tmp, "w") as f:
            for key in _COPIED_ATTRS:
                if key in src.attrs:
                    f.attrs[key] = src.attrs[key]
            f.attrs["labelsynth_version"] = __version__
            f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.attrs["source"] = str(out.resolve())
            f.attrs["merged"] = json.dumps(merged)
            for key, layout in layouts.items():
                f.create_virtual_dataset(key, layout, fillvalue=_FILLS[key])
            f.create_dataset("annotated", data=np.concatenate([i["annotated"] for i in infos]))
            strings = h5py.string_dtype("utf-8")
            f.create_dataset("frame_names", data=np.array([s for i in infos for s in i["names"]], dtype=object),
                             dtype=strings)
            f.create_dataset("capture", data=np.array([i["name"] for i in infos for _ in range(i["frames"])],
                                                      dtype=object), dtype=strings)
            f.create_dataset("frame_sizes", data=np.array(
                [(i["height"], i["width"]) for i in infos for _ in range(i["frames"])], dtype=np.int32))
    return target
