"""A torch Dataset over labels.h5, and the PNG masks of the output folder.

The file itself (schema, writer, the one reader) is ``labels_h5``; ``LabelsDataset`` is that
reader seen as a ``torch.utils.data.Dataset``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..capture.masks import write_mask
from ..classes import ClassMap
from .labels_h5 import ExportError, LabelsReader, as_mask, check_mask_ids, valid_id_table


class LabelsDataset(torch.utils.data.Dataset):
    """One frame of labels.h5 per item, for training a 2D segmenter.

    Safe with ``DataLoader(num_workers>=2)``: the file is read through ``LabelsReader`` (checked
    when the dataset is made; one HDF5 handle per process, never pickled). Items: ``image``
    float32 (3,H,W) in [0,1] (uint8 with ``uint8=True``), ``mask`` int64 (H,W) class ids (255 =
    ignore), ``confidence`` float32 (H,W), ``annotated`` bool tensor, ``name`` str, ``index`` int
    (and ``capture`` str from a batch's merged dataset.h5, whose frames come cropped to their
    own size, never padded).

    ``transform`` is called as ``transform(image=HxWx3 uint8, mask=HxW uint8)`` and must
    return a dict with ``image`` and ``mask`` (albumentations style, numpy or tensors).
    Confidence is passed too, as ``confidence=``, when the transform declares it, e.g.
    ``A.Compose([...], additional_targets={"confidence": "mask"})``; a transform that
    changes the frame size without it is an error rather than a silently misaligned map.
    """

    def __init__(
        self,
        path: str | Path,
        transform: Callable[..., Mapping[str, Any]] | None = None,
        uint8: bool = False,
    ) -> None:
        self.path = Path(path)
        self.transform = transform
        self.uint8 = uint8
        self.reader = LabelsReader(self.path)
        self.height, self.width = self.reader.height, self.reader.width
        self.attrs = self.reader.attrs
        self.frame_names = self.reader.frame_names
        self.capture_names = self.reader.capture_names

    @property
    def classes(self) -> ClassMap:
        return self.reader.classes

    def __len__(self) -> int:
        return len(self.reader)

    def close(self) -> None:
        self.reader.close()

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self.reader)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        i = int(index) % n
        image, mask, conf = self.reader.read(i)
        conf = conf.astype(np.float32)
        if self.transform is not None:
            kwargs: dict[str, Any] = {"image": image, "mask": mask}
            wants_conf = "confidence" in (getattr(self.transform, "additional_targets", None) or {})
            if wants_conf:
                kwargs["confidence"] = conf
            out = self.transform(**kwargs)
            image, mask = out["image"], out["mask"]
            if wants_conf:
                conf = out["confidence"]
            if tuple(np.shape(conf))[-2:] != tuple(np.shape(mask))[-2:]:
                raise ExportError(
                    "the transform changed the frame size but not the confidence map; build it with "
                    "additional_targets={'confidence': 'mask'}"
                )
        return {
            "image": self._image_tensor(image),
            "mask": torch.as_tensor(np.asarray(mask)).long(),
            "confidence": torch.as_tensor(np.asarray(conf, dtype=np.float32)),
            "annotated": torch.tensor(bool(self.reader.annotated[i])),
            "name": self.frame_names[i],
            "index": i,
            **({"capture": self.capture_names[i]} if self.capture_names is not None else {}),
        }

    def _image_tensor(self, image: Any) -> torch.Tensor:
        if isinstance(image, torch.Tensor):
            t = image
            if t.ndim == 3 and t.shape[0] not in (1, 3) and t.shape[-1] in (1, 3):
                t = t.permute(2, 0, 1)
        else:
            t = torch.from_numpy(np.ascontiguousarray(np.asarray(image).transpose(2, 0, 1)))
        if t.dtype == torch.uint8 and not self.uint8:
            return t.float().div_(255.0)
        return t.contiguous()


# --- PNG masks ---------------------------------------------------------------------------
def write_masks_png(out_dir: str | Path, name: str, mask: np.ndarray, classes: ClassMap | None = None) -> Path:
    """Write ``out_dir/<stem of name>.png``: an 8-bit single-channel (greyscale) PNG of class ids.

    Why not a palette PNG: OpenCV expands palettes to BGR colours even with
    ``IMREAD_UNCHANGED``, so ids would come back only through PIL; PNG does not allow a
    palette on a greyscale image. A plain greyscale PNG returns the ids with both
    ``np.array(PIL.Image.open(p))`` and ``cv2.imread(p, cv2.IMREAD_UNCHANGED)``. Use
    ``ClassMap.colorize`` for a colour view. ``classes`` (if given) validates the ids.
    The file is written by ``capture.masks.write_mask``, the one mask writer.
    """
    what = f"mask {name!r}"
    mask = as_mask(mask, what)
    if classes is not None:
        check_mask_ids(mask, valid_id_table(classes), what)
    return write_mask(Path(out_dir) / f"{Path(name).stem}.png", mask, palette=False)
