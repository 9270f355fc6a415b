"""The CUDA path end to end: run only where torch sees a GPU (skipped in CI, which has none).

Run on a GPU machine with ``CUDA_VISIBLE_DEVICES=0 python -m pytest -q tests/test_cuda.py``
(conftest hides GPUs unless the variable is set). What a user does across machines is checked
too: a field fitted on the GPU is relabelled on a CPU, and a segmenter trained on the GPU is
run by ``segment`` (onnxruntime, CPU).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from tests.conftest import TINY_OVERRIDES

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (set CUDA_VISIBLE_DEVICES on a GPU machine)")


@pytest.fixture(scope="module")
def cuda_run(tmp_path_factory):
    from labelsynth.evaluation.synth import SynthConfig, synthesize
    from labelsynth.pipeline import expand

    root = tmp_path_factory.mktemp("cuda")
    syn = synthesize(root / "syn", SynthConfig(frames=8, annotated=4, width=96, height=72, seed=3), progress=False)
    result = expand(syn.capture_dir, root / "out", labels="annotations", recipe="fast", device="cuda",
                    overrides=TINY_OVERRIDES, progress=False)
    return syn, root / "out", result


def _wound_bed_dice(out, truth_dir, names) -> float:
    inter = total = 0
    for name in names:
        pred = cv2.imread(str(out / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED) > 0
        truth = cv2.imread(str(truth_dir / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        truth = (truth > 0) & (truth != 255)
        inter += int((pred & truth).sum())
        total += int(pred.sum() + truth.sum())
    return 2 * inter / max(total, 1)


def test_expand_on_cuda_writes_a_complete_run(cuda_run):
    syn, out, _ = cuda_run
    run = json.loads((out / "run.json").read_text())
    assert run["device"] == "cuda"
    names = [p.stem for p in sorted((syn.capture_dir / "images").iterdir())]
    assert sorted(p.stem for p in (out / "masks").glob("*.png")) == sorted(names)
    unannotated = [n for n in names if n not in syn.annotated]
    assert _wound_bed_dice(out, syn.truth_dir, unannotated) >= 0.9


def test_field_fitted_on_cuda_relabels_on_cpu(cuda_run, tmp_path):
    import shutil

    from labelsynth.pipeline import relabel

    syn, out, _ = cuda_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    relabel(copy, capture=syn.capture_dir, report=False, device="cpu", progress=False)
    names = [p.stem for p in sorted((out / "masks").glob("*.png"))]
    agree = np.mean([
        (cv2.imread(str(out / "masks" / f"{n}.png"), cv2.IMREAD_UNCHANGED)
         == cv2.imread(str(copy / "masks" / f"{n}.png"), cv2.IMREAD_UNCHANGED)).mean()
        for n in names
    ])
    assert agree >= 0.97, f"CPU relabel of a CUDA field agrees with the CUDA masks on {agree:.3f} of the pixels"


def test_segmenter_trained_on_cuda_runs_in_segment(cuda_run, tmp_path):
    from labelsynth.train.loop import TrainConfig, train
    from labelsynth.train.segment import segment_capture

    syn, out, _ = cuda_run
    res = train([out / "labels.h5"], tmp_path / "model", TrainConfig(steps=4, batch_size=2, crop=32, device="cuda",
                                                                     eval_every=100), progress=False, log=lambda m: None)
    assert res.device == "cuda" and res.step == 4
    segment_capture(syn.capture_dir, tmp_path / "model" / "model.onnx", tmp_path / "seg", device="cpu", progress=False)
    masks = sorted((tmp_path / "seg").rglob("*.png"))
    assert len(masks) >= 8
