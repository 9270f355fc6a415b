"""The valid inputs every malformed case starts from, built once per test session without any
training: a tiny capture (4 frames of 40x40, 2 annotated, predictions, truth), a finished
expand output around an untrained field (field.pt, run.json, masks/, labels.h5), an ONNX
segmenter, a train checkpoint, a short video and a folder of photos. Each case gets a fresh
copy (``World.copy``), so a case may break any file of it."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..scenes import make_patch_capture

TINY_FIELD = [  # a field.pt of a few hundred kB: the cases only need it to be valid, not good
    "geometry.sdf.levels=2", "geometry.sdf.log2_table=8", "geometry.sdf.max_resolution=32", "geometry.sdf.hidden=8",
    "geometry.sdf.feature_dim=3", "geometry.sdf.color_hidden=8", "geometry.sdf.outer.levels=2",
    "geometry.sdf.outer.log2_table=6", "geometry.sdf.outer.hidden=8", "geometry.occupancy_resolution=8",
    "semantic.hidden=8", "semantic.position_levels=2", "semantic.position_max_resolution=32",
    "render.mesh_resolution=16",
]


class ColourNet(torch.nn.Module):
    """A 1x1-convolution segmenter at half resolution: small, exportable, deterministic."""

    def __init__(self) -> None:
        super().__init__()
        self.pool = torch.nn.AvgPool2d(2)
        self.conv = torch.nn.Conv2d(3, 2, 1)

    def forward(self, x):
        return self.conv(self.pool(x))


def _export_onnx(path: Path) -> Path:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(ColourNet().eval(), (torch.zeros(1, 3, 32, 32),), str(path), input_names=["pixel_values"],
                          output_names=["logits"], dynamic_axes={"pixel_values": {0: "n", 2: "h", 3: "w"}},
                          dynamo=False)
    return path


def _finished_run(capture: Path, out: Path) -> None:
    """A finished expand OUT around an untrained field (what report and augment read)."""
    from labelsynth.capture import load_capture
    from labelsynth.export import LabelsWriter, write_masks_png
    from labelsynth.geometry.fingerprint import GeometryFingerprint
    from labelsynth.geometry.sampling import OccupancyGrid
    from labelsynth.geometry.sdf import SDFField
    from labelsynth.recipe import load_recipe
    from labelsynth.render.field import FittedField
    from labelsynth.rundir import RunFolder, RunInfo

    cap = load_capture(capture)
    recipe = load_recipe("fast", TINY_FIELD)
    torch.manual_seed(0)
    field = FittedField(SDFField(recipe.geometry.sdf), OccupancyGrid(recipe.geometry.occupancy_resolution),
                        cap.classes, cap.normalization, recipe,
                        fitted_on=GeometryFingerprint.of(cap, recipe.geometry, 0))  # what expand --geometry checks
    field = field.with_head(field.new_head())
    run = RunFolder(out)
    out.mkdir(parents=True)
    run.save_field(field)
    with LabelsWriter(run.labels_path, len(cap), cap.classes, source=str(capture)) as writer:
        for i, frame in enumerate(cap.frames):
            mask = cap.load_prediction(i)
            write_masks_png(run.masks_dir, frame.name, mask, cap.classes)
            writer.add(frame.name, cap.load_image(i), mask, None, frame.annotation_path is not None)
    run.write_run(RunInfo(capture=str(capture), labels="annotations", recipe=recipe.to_dict(), device="cpu"))


def _checkpoint(path: Path, classes) -> None:
    from labelsynth.train.checkpoint import save_checkpoint
    from labelsynth.train.loop import TrainConfig
    from labelsynth.train.model import build_model

    model = build_model("segformer", "b0", classes.num_classes)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, model, optimizer, 1, TrainConfig(arch="segformer", encoder="b0", steps=2), classes,
                    [{"step": 1, "train_loss": 1.0}])


def _video(path: Path, frames: int = 12, size: tuple[int, int] = (64, 48)) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, size)
    rng = np.random.default_rng(0)
    base = (rng.random((size[1] * 2, size[0] * 2, 3)) * 255).astype(np.uint8)
    for i in range(frames):
        writer.write(np.ascontiguousarray(base[i : i + size[1], 2 * i : 2 * i + size[0]]))
    writer.release()
    return path


@dataclass
class World:
    """Paths of one copy of the valid inputs."""

    root: Path

    @property
    def cap(self) -> Path:
        return self.root / "capture"

    @property
    def truth(self) -> Path:
        return self.root / "truth"

    @property
    def run(self) -> Path:
        return self.root / "run"

    @property
    def h5(self) -> Path:
        return self.run / "labels.h5"

    @property
    def model(self) -> Path:
        return self.root / "model.onnx"

    @property
    def ckpt_dir(self) -> Path:
        return self.root / "trained"

    @property
    def video(self) -> Path:
        return self.root / "clip.mp4"

    @property
    def photos(self) -> Path:
        return self.root / "photos"

    @property
    def out(self) -> Path:
        """Where a case's command writes (absent before it runs)."""
        return self.root / "new_out"

    def names(self) -> dict[str, str]:
        return {k: str(getattr(self, k)) for k in ("root", "cap", "truth", "run", "h5", "model", "ckpt_dir", "video",
                                                    "photos", "out")}

    @classmethod
    def build(cls, root: Path) -> "World":
        from labelsynth.capture import load_capture

        world = cls(root)
        capture, truth = make_patch_capture(root, frames=4, size=40, annotated=(0, 2))
        shutil.copytree(truth, capture / "predictions")
        _finished_run(capture, world.run)
        _export_onnx(world.model)
        _checkpoint(world.ckpt_dir / "checkpoint.pt", load_capture(capture).classes)
        _video(world.video)
        shutil.copytree(capture / "images", world.photos)
        return world

    def copy(self, to: Path, *, checkpoint: bool = False) -> "World":
        """A fresh copy whose run.json names the copy's own capture (the 15 MB train checkpoint
        only when asked)."""
        skip = None if checkpoint else shutil.ignore_patterns("trained")
        shutil.copytree(self.root, to, symlinks=True, ignore=skip)
        other = World(to)
        info = json.loads((other.run / "run.json").read_text())
        info["capture"] = str(other.cap)
        (other.run / "run.json").write_text(json.dumps(info, indent=2))
        return other


def snapshot(root: Path) -> dict[bytes, tuple]:
    """Every entry under ``root`` (names as bytes: non-UTF-8 names too; links not followed):
    kind, mode and the SHA-256 of a file's bytes or a link's target."""
    entries: dict[bytes, tuple] = {}
    base = os.fsencode(root)
    for folder, dirs, files in os.walk(base, followlinks=False):
        for name in dirs + files:
            path = os.path.join(folder, name)
            st = os.lstat(path)
            rel = os.path.relpath(path, base)
            if stat.S_ISLNK(st.st_mode):
                entries[rel] = ("link", os.readlink(path))
            elif stat.S_ISDIR(st.st_mode):
                entries[rel] = ("dir", stat.S_IMODE(st.st_mode))
            else:
                with open(path, "rb") as f:
                    entries[rel] = ("file", stat.S_IMODE(st.st_mode), hashlib.sha256(f.read()).hexdigest())
    return entries
