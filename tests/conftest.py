"""Shared test fixtures.

The one expensive fixture is ``tiny_expanded``: a synthetic wound capture (8 frames, 96x72,
4 annotated, one annotation deliberately shifted) expanded once with the fast recipe and the
report (leave-one-out included). Tests of the field, the outputs and the report share it, so
the suite fits geometry only once.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

# Tests must never need a display or a GPU.
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("CUDA_VISIBLE_DEVICES", "")
# Under pytest-xdist every worker would start as many compute threads as there are cores, so
# two workers on two cores ran four busy threads: share the cores out instead.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
_THREADS = str(max(1, (os.cpu_count() or 1) // _WORKERS))
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, _THREADS)

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(int(_THREADS))
cv2.setNumThreads(int(_THREADS))

TINY_OVERRIDES = [
    "geometry.iterations=250",
    "geometry.train_scale=1.0",
    "geometry.levels_every=25",
    "semantic.iterations=150",
    "semantic.train_scale=1.0",
    "render.mesh_resolution=128",
]

TINY_EXPAND = ["geometry.iterations=20", "semantic.iterations=10", "render.mesh_resolution=32",
               "geometry.target_samples=1024", "geometry.max_rays=256", "geometry.march_steps=32",
               "geometry.occupancy_resolution=16", "semantic.rays_per_batch=256", "semantic.max_rays_per_frame=500"]
"""Overrides for expands that only have to run end to end (benchmarks and loops in the suite): the
numbers they give mean nothing."""

REPO = Path(__file__).resolve().parents[1]


def run_benchmark(script: str, args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    """``python benchmarks/SCRIPT ARGS`` with this checkout importable; fails the test with the
    output's tail when the script fails."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, str(REPO / "benchmarks" / script), *args], env=env, capture_output=True,
                         text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return res


def load_benchmark(script: str):
    """A benchmark script as a module (benchmarks/ is not a package), for its functions."""
    spec = importlib.util.spec_from_file_location(Path(script).stem, REPO / "benchmarks" / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def no_fitting(monkeypatch):
    """Any fitting reached (either stage) fails the test loudly, not with exit code 2: for checks
    that must come first."""
    import labelsynth.pipeline as pipeline

    def reached(*args, **kwargs):
        raise AssertionError("fitting started")

    monkeypatch.setattr(pipeline, "fit_geometry", reached)
    monkeypatch.setattr(pipeline, "fit_semantics", reached)


@dataclass
class TinyRun:
    capture_dir: Path
    truth_dir: Path
    out: Path
    result: object
    shifted: str  # the annotation that was shifted (must be flagged)
    good: list[str]  # the other annotated frames
    capture_bytes: dict  # every file of the capture before the run


@pytest.fixture(scope="session")
def tiny_expanded(tmp_path_factory) -> TinyRun:
    from labelsynth.evaluation.synth import SynthConfig, synthesize
    from labelsynth.pipeline import expand

    root = tmp_path_factory.mktemp("tiny_expanded")
    syn = synthesize(root / "syn", SynthConfig(frames=8, annotated=4, width=96, height=72, seed=3), progress=False)
    shifted = syn.annotated[1]
    path = syn.capture_dir / "annotations" / f"{shifted}.png"
    cv2.imwrite(str(path), np.roll(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), 24, axis=1))
    before = {p: p.read_bytes() for p in syn.capture_dir.rglob("*") if p.is_file()}
    result = expand(syn.capture_dir, root / "out", labels="annotations", recipe="fast", device="cpu",
                    overrides=TINY_OVERRIDES, progress=False)
    return TinyRun(syn.capture_dir, syn.truth_dir, root / "out", result, shifted,
                   [n for n in syn.annotated if n != shifted], before)
