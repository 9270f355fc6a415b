"""labelsynth batch on real Ray: one local instance (num_cpus=2) for this module, three tiny
captures of which one is broken, a rerun, the merged dataset, a worker killed with -9, and
--address attaching to a `ray start --head` that the test starts and stops itself."""

from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from typer.testing import CliRunner  # noqa: E402

from labelsynth.batch import ExpandOptions, run_batch  # noqa: E402
from labelsynth.batch.discover import BatchError  # noqa: E402
from labelsynth.cli import app  # noqa: E402
from labelsynth.export import LabelsDataset, read_labels_h5  # noqa: E402
from labelsynth.outdir import signal_handlers_kept  # noqa: E402

from .workers import descendants, local_node, raylet_pid, task_pid  # noqa: E402

pytestmark = pytest.mark.xdist_group("ray")

# A few seconds of fitting per capture: enough for every output file, not for good masks.
TINY = ["geometry.iterations=40", "semantic.iterations=30", "geometry.train_scale=1.0", "semantic.train_scale=1.0",
        "render.mesh_resolution=48", "geometry.levels_every=10", "geometry.target_samples=2048",
        "geometry.max_rays=512", "geometry.eikonal_samples=256", "geometry.occupancy_resolution=32",
        "semantic.rays_per_batch=512"]
CLI_ARGS = ["--recipe", "fast", "--labels", "annotations", "--no-report", "--cpus-per-capture", "1",
            *[a for o in TINY for a in ("--set", o)]]


def _options() -> ExpandOptions:
    return ExpandOptions(labels="annotations", recipe="fast", report=False, overrides=list(TINY))


@pytest.fixture(scope="module")
def ray_local():
    with signal_handlers_kept():
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
        yield ray
        ray.shutdown()


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """ROOT with alpha, beta (good) and gamma (one frame's PNG cut in half)."""
    import shutil

    from labelsynth.evaluation.synth import SynthConfig, synthesize

    base = tmp_path_factory.mktemp("batch")
    root = base / "root"
    for seed, name in enumerate(("alpha", "beta", "gamma")):
        made = synthesize(base / f"syn_{name}", SynthConfig(frames=6, annotated=2, width=64, height=48, seed=seed),
                          progress=False)
        shutil.copytree(made.capture_dir, root / name)
    broken = sorted((root / "gamma" / "images").iterdir())[2]
    data = broken.read_bytes()
    broken.write_bytes(data[: len(data) // 2])
    before = {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}
    return root, base, before


@pytest.fixture(scope="module")
def first_run(ray_local, captures):
    root, base, _ = captures
    out = base / "out"
    result = CliRunner().invoke(app, ["batch", str(root), "--out", str(out), *CLI_ARGS])
    return out, result


def test_two_done_one_failed_with_its_reason(first_run, captures):
    out, result = first_run
    root, _, before = captures
    assert result.exit_code == 1, result.output
    assert "gamma" in result.output and "truncated" in result.output
    doc = json.loads((out / "batch.json").read_text())
    rows = {r["name"]: r for r in doc["captures"]}
    assert doc["counts"] == {"done": 2, "skipped": 0, "failed": 1}
    assert rows["alpha"]["status"] == rows["beta"]["status"] == "done"
    assert rows["gamma"]["status"] == "failed"
    assert "frame_002" in rows["gamma"]["reason"] and "truncated" in rows["gamma"]["reason"]
    assert "\n" not in rows["gamma"]["reason"]
    assert "gamma" in (out / "batch.html").read_text()
    for name in ("alpha", "beta"):
        assert (out / "captures" / name / "labels.h5").is_file() and (out / "markers" / f"{name}.json").is_file()
    assert not (out / "captures" / "gamma").exists() and not (out / "markers" / "gamma.json").exists()
    assert not list(out.rglob("*.partial"))
    assert {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()} == before


def test_rerun_skips_the_finished_captures(first_run, captures):
    out, _ = first_run
    root, _, _ = captures
    labels = out / "captures" / "alpha" / "labels.h5"
    stamp = labels.stat().st_mtime_ns
    result = run_batch(root, out, _options(), cpus_per_capture=1, progress=False)
    assert [(r.name, r.status) for r in result.rows] == [("alpha", "skipped"), ("beta", "skipped"), ("gamma", "failed")]
    assert not result.ok and labels.stat().st_mtime_ns == stamp


def test_merged_dataset_reads_every_frame_of_the_two(first_run):
    out, _ = first_run
    ds = LabelsDataset(out / "dataset.h5", uint8=True)
    assert len(ds) == 12
    k = 0
    for name in ("alpha", "beta"):
        src = read_labels_h5(out / "captures" / name / "labels.h5")
        for i, frame in enumerate(src["frame_names"]):
            item = ds[k]
            assert item["capture"] == name and item["name"] == frame
            assert np.array_equal(item["image"].permute(1, 2, 0).numpy(), src["images"][i])
            assert np.array_equal(item["mask"].numpy(), src["masks"][i])
            k += 1
    from labelsynth.train.data import load_sources

    sources, _ = load_sources([out / "dataset.h5"])
    assert sum(len(s) for s in sources) == 12


def test_gpus_on_a_cluster_without_them_is_a_clear_error(ray_local, captures, tmp_path):
    root, _, _ = captures
    with pytest.raises(BatchError, match="the Ray cluster has no GPUs"):
        run_batch(root / "alpha", tmp_path / "out", _options(), gpus_per_capture=1, progress=False)
    with pytest.raises(BatchError, match="no node has that many CPUs"):
        run_batch(root / "alpha", tmp_path / "out", _options(), cpus_per_capture=3, progress=False)


def _kill_worker_during(retries: int, root: Path, out: Path):
    box = {}
    thread = threading.Thread(target=lambda: box.update(result=run_batch(
        root / "alpha", out, _options(), cpus_per_capture=1, retries=retries, force=True, progress=False)))
    thread.start()
    raylet = raylet_pid(local_node())  # only this test's Ray: never a worker of another Ray on the machine
    pid = task_pid(raylet, 120)
    assert pid is not None, "the task never started"
    assert pid in descendants(raylet)
    time.sleep(1.0)
    os.kill(pid, signal.SIGKILL)
    thread.join(300)
    return box["result"].rows[0], pid


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="needs /proc to find the worker")
def test_a_worker_killed_with_minus_9(ray_local, captures, tmp_path):
    root, _, _ = captures
    row, _ = _kill_worker_during(0, root, tmp_path / "no_retry")
    assert row.status == "failed" and "worker died" in row.reason
    assert not (tmp_path / "no_retry" / "captures" / "alpha").exists()  # only alpha.partial, if anything
    row, pid = _kill_worker_during(1, root, tmp_path / "retried")
    assert row.status == "done", row.reason
    assert task_pid(raylet_pid(local_node()), 0.1) != pid
    assert (tmp_path / "retried" / "captures" / "alpha" / "labels.h5").is_file()


def _ray_cli() -> str:
    """The `ray` script of this interpreter's environment (PATH may hold another)."""
    beside = Path(sys.executable).with_name("ray")
    return str(beside) if beside.is_file() else "ray"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_address_attaches_to_a_ray_start_head(captures, tmp_path):
    root, _, _ = captures
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    # Token authentication with a token of this test's own (no ~/.ray/auth_token needed or used);
    # Ray sends a token to a named cluster only when RAY_AUTH_MODE says so.
    env["RAY_AUTH_MODE"], env["RAY_AUTH_TOKEN"] = "token", secrets.token_hex(32)
    head = subprocess.Popen(
        [_ray_cli(), "start", "--head", "--port", str(port), "--num-cpus", "1", "--include-dashboard=false", "--block",
         "--node-ip-address", "127.0.0.1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=env)
    try:
        end = time.time() + 90
        while time.time() < end:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert head.poll() is None, "ray start exited"
            time.sleep(0.5)
        # The broken capture: its task runs on the cluster and fails in its input check within a
        # second, so the test pays for attaching, not for a fit (the first test covers that).
        listing = tmp_path / "list.txt"
        listing.write_text(f"{root / 'gamma'}\n")
        out = tmp_path / "out"
        run = subprocess.run([sys.executable, "-m", "labelsynth.cli", "batch", str(listing), "--out", str(out),
                              "--address", f"127.0.0.1:{port}", *CLI_ARGS],
                             env=env, capture_output=True, text=True, timeout=400)
        assert run.returncode == 1, run.stderr[-2000:]
        doc = json.loads((out / "batch.json").read_text())
        assert doc["ray"].endswith(f":{port}")  # the cluster's, not a local instance
        assert doc["counts"]["failed"] == 1 and "truncated" in doc["captures"][0]["reason"]
    finally:  # stop only what this test started (`ray stop` would stop every Ray on the machine)
        head.send_signal(signal.SIGTERM)
        try:
            head.wait(30)
        except subprocess.TimeoutExpired:
            pass
        time.sleep(2)
        try:
            os.killpg(head.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


_HANDLERS_AFTER_BATCH = """
import signal, sys
from pathlib import Path
from labelsynth.batch import ExpandOptions, run_batch

def handlers():
    return signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)

before = handlers()
run_batch(Path(sys.argv[1]), Path(sys.argv[2]), ExpandOptions(labels="annotations", recipe="fast", report=False),
          cpus_per_capture=1, retries=0, progress=False)
assert handlers() == before, ("batch", before, handlers())
import ray  # the same start and stop without run_batch: Ray leaves its own SIGTERM handler behind
ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
ray.shutdown()
assert handlers() != before, "Ray no longer changes the handlers: this test no longer checks anything"
"""


def test_batch_puts_back_the_signal_handlers_ray_replaces(captures, tmp_path):
    """A batch that starts its own Ray leaves the process's SIGINT/SIGTERM handlers as it found them
    (Ray's driver keeps its SIGTERM handler after shutdown), so a later in-process expand still
    cleans up after SIGTERM. In a fresh process: this module's Ray is already initialised here."""
    root, _, _ = captures
    listing = tmp_path / "list.txt"
    listing.write_text(f"{root / 'gamma'}\n")  # fails its input check at once: the test pays for Ray only
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    run = subprocess.run([sys.executable, "-c", _HANDLERS_AFTER_BATCH, str(listing), str(tmp_path / "out")],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
