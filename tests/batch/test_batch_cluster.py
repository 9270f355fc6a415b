"""labelsynth batch on a Ray cluster of several nodes, simulated on this machine
(``ray.cluster_utils.Cluster``: a head without CPUs and two worker nodes of one CPU each, every
node its own raylet). One node is removed while it runs a capture: Ray retries that capture on
the node that is left, and the batch ends with every capture done and one merged dataset."""

from __future__ import annotations

import json
import os
import threading

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from ray.cluster_utils import Cluster  # noqa: E402

from labelsynth.batch import ExpandOptions, run_batch  # noqa: E402
from labelsynth.export import LabelsDataset, read_labels_h5  # noqa: E402
from labelsynth.outdir import signal_handlers_kept  # noqa: E402

from .workers import raylet_pid, task_pid  # noqa: E402

pytestmark = pytest.mark.xdist_group("ray")  # one Ray at a time in the suite

TINY = ["geometry.iterations=40", "semantic.iterations=30", "geometry.train_scale=1.0", "semantic.train_scale=1.0",
        "render.mesh_resolution=48", "geometry.levels_every=10", "geometry.target_samples=2048",
        "geometry.max_rays=512", "geometry.eikonal_samples=256", "geometry.occupancy_resolution=32",
        "semantic.rays_per_batch=512"]
NODE = {"num_cpus": 1, "object_store_memory": 80 * 1024**2}


@pytest.fixture
def cluster():
    with signal_handlers_kept():  # the in-process head node and the driver each install a SIGTERM handler
        c = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "object_store_memory": 80 * 1024**2,
                                                          "include_dashboard": False})
        nodes = [c.add_node(**NODE), c.add_node(**NODE)]
        c.wait_for_nodes()
        ray.init(address=c.address, log_to_driver=False)
        try:
            yield c, nodes
        finally:
            ray.shutdown()
            c.shutdown()


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    import shutil

    from labelsynth.evaluation.synth import SynthConfig, synthesize

    base = tmp_path_factory.mktemp("cluster")
    for seed, name in enumerate(("north", "south")):
        made = synthesize(base / f"syn_{name}", SynthConfig(frames=5, annotated=2, width=48, height=40, seed=seed),
                          progress=False)
        shutil.copytree(made.capture_dir, base / "root" / name)
    return base / "root", base


def test_a_node_removed_mid_batch_has_its_capture_retried_on_the_other(cluster, captures):
    c, nodes = cluster
    root, base = captures
    out = base / "out"
    box: dict = {}
    options = ExpandOptions(labels="annotations", recipe="fast", report=False, overrides=list(TINY), device="cpu")
    thread = threading.Thread(target=lambda: box.update(result=run_batch(
        root, out, options, cpus_per_capture=1, retries=2, progress=False)))
    thread.start()
    # the worker node that runs a capture first (each node runs one at a time: one CPU each)
    victim = pid = None
    for _ in range(600):
        for node in nodes:
            pid = task_pid(raylet_pid(node), 0.0)
            if pid is not None:
                victim = node
                break
        if victim is not None:
            break
        thread.join(0.2)
    assert victim is not None, "no capture started on a worker node"
    os.kill(pid, 0)  # its worker still runs the capture...
    finished = [p.name for p in (out / "captures").iterdir() if not p.name.endswith(".partial")]
    assert len(finished) < 2, finished  # ...which has not landed: what follows is a retry
    c.remove_node(victim, allow_graceful=False)  # the node goes, with the capture it was fitting
    thread.join(600)
    assert not thread.is_alive(), "the batch did not finish"
    result = box["result"]
    assert [(r.name, r.status) for r in result.rows] == [("north", "done"), ("south", "done")], \
        [(r.name, r.status, r.reason) for r in result.rows]
    assert not list(out.rglob("*.partial"))
    doc = json.loads((out / "batch.json").read_text())
    assert doc["counts"] == {"done": 2, "skipped": 0, "failed": 0}
    ds = LabelsDataset(out / "dataset.h5", uint8=True)
    assert len(ds) == 10
    k = 0
    for name in ("north", "south"):
        src = read_labels_h5(out / "captures" / name / "labels.h5")
        for i, frame in enumerate(src["frame_names"]):
            item = ds[k]
            assert item["capture"] == name and item["name"] == frame
            assert np.array_equal(item["mask"].numpy(), src["masks"][i])
            k += 1
