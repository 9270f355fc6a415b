"""Many captures, one command: each capture is one Ray task running ``pipeline.expand``.

Ray is imported here only inside the functions, so ``import labelsynth`` (and even
``import labelsynth.batch``) never loads it. Local by default: a Ray instance sized to the
machine's cores is started (no dashboard) and shut down at the end; ``address`` or
``RAY_ADDRESS`` attaches to a running cluster instead (then OUT, the captures and a recipe
file must be on storage every node sees, and every node needs labelsynth installed). An
already initialised Ray (a notebook's ``ray.init()``) is used as it is and left running.

Faults: a capture's user error (``LabelsynthError``, the input check's ``CheckError``) is
caught inside its task and returned as a one-line reason, never retried; any other exception
fails the capture without a retry (``retry_exceptions=False``); a worker that dies (kill -9,
the OOM killer, a lost node) is a system failure that Ray retries ``retries`` times
(``max_retries``). One capture's failure never stops the others.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import CheckError, LabelsynthError
from ..options import DeviceChoice, ExpandOptions, finite_number, whole_number
from ..outdir import check_apart, signal_handlers_kept
from ..progress import make_progress
from ..rundir import RunFolder
from .discover import BatchError, CaptureJob, discover
from .marker import Marker, clear_marker, is_done, make_marker, write_marker
from .merge import merge_labels
from .table import BatchRow, counts, read_quality, write_batch_html, write_batch_json

CAPTURES_DIR = "captures"
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
DEFAULT_CPUS = 4  # per capture, capped to the largest node
MAX_CPUS = 4096
MAX_GPUS = 1024.0
MAX_RETRIES = 100


@dataclass
class BatchResult:
    out: Path
    rows: list[BatchRow]
    dataset: Path | None
    dataset_error: str = ""
    seconds: float = 0.0
    ray_address: str = ""

    @property
    def failed(self) -> list[BatchRow]:
        return [r for r in self.rows if r.status == "failed"]

    @property
    def ok(self) -> bool:
        """No capture failed and the merged dataset was written (when anything finished)."""
        return not self.failed and not self.dataset_error

    def summary(self) -> str:
        c = counts(self.rows)
        ds = f"dataset {self.dataset}" if self.dataset else f"no {self.out / 'dataset.h5'}"
        if self.dataset_error:
            ds += f" ({self.dataset_error})"
        return (f"{c['done']} done, {c['skipped']} skipped, {c['failed']} failed in {self.seconds:.0f} s; "
                f"{ds}; table {self.out / 'batch.json'} and {self.out / 'batch.html'}")


def one_line(exc: BaseException) -> str:
    """A failure's reason as one line (an input check's first problem and how many more)."""
    if isinstance(exc, CheckError):
        more = len(exc.problems) - 1
        return exc.problems[0] + (f" (and {more} more problem{'s' if more > 1 else ''})" if more > 0 else "")
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _set_threads(threads: int) -> None:
    """Compute threads follow the task's CPUs (the env is also set before the worker starts)."""
    import cv2
    import torch

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)


def expand_capture(capture: str, output: str, out_root: str, name: str, options: ExpandOptions,
                   marker: dict[str, Any], threads: int) -> dict[str, Any]:
    """One capture, inside a Ray worker: expand, then the resume marker. User errors come back
    as a ``failed`` result (not an exception) so Ray never retries them."""
    from ..pipeline import expand

    _set_threads(threads)
    t0 = time.time()
    try:
        result = expand(capture, output, options, force=True, progress=False)
    except LabelsynthError as exc:
        return {"status": "failed", "reason": one_line(exc), "seconds": time.time() - t0}
    write_marker(Path(out_root), name, Marker(**marker))
    return {"status": "done", "seconds": time.time() - t0, "frames": len(result.frames), "pid": os.getpid()}


def _connect(address: str | None):
    """(ray, started_here): attach to ``address`` / RAY_ADDRESS, reuse an initialised Ray, or
    start a local one sized to this machine."""
    import logging

    import ray

    if ray.is_initialized():
        if address:
            raise BatchError(f"--address {address}: Ray is already initialised in this process; "
                             "call ray.shutdown() first or leave the address out")
        return ray, False
    address = address or os.environ.get("RAY_ADDRESS") or None
    common = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.WARNING}
    try:
        if address:
            ray.init(address=address, **common)
        else:
            # "local": always a new instance (a bare ray.init() would join any `ray start` on this machine)
            ray.init(address="local", num_cpus=os.cpu_count() or 1, **common)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        hint = ""
        if address and not os.environ.get("RAY_AUTH_MODE"):
            # Ray sends its token to an explicitly named cluster only when asked to.
            hint = (" (a cluster with token authentication, Ray's default, also needs RAY_AUTH_MODE=token and its "
                    "token in ~/.ray/auth_token or RAY_AUTH_TOKEN)")
        raise BatchError(f"cannot start or attach to {where}: {one_line(exc)}{hint}") from None
    return ray, True


_ADDRESS = re.compile(r"^(ray://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):\d{1,5}$")


def check_address(address: str | None) -> None:
    """``--address``: auto, local, HOST:PORT or ray://HOST:PORT (what ``ray.init`` takes); any
    other text is one line now, before discovery and before OUT is touched."""
    if address is None:
        return
    if not isinstance(address, str) or not address.strip():
        raise BatchError("--address must not be empty (leave it out for RAY_ADDRESS or a local instance)")
    if address not in ("auto", "local") and not _ADDRESS.match(address.strip()):
        raise BatchError(f"--address {address!r}: expected HOST:PORT, ray://HOST:PORT, auto or local")


def check_out_apart(out: Path, jobs: list) -> None:
    """OUT is neither a capture of the batch nor inside one: a batch writes nothing into a capture."""
    for job in jobs:
        try:
            check_apart(out, {"the capture": job.path})
        except LabelsynthError as exc:
            raise BatchError(str(exc)) from None


def _largest_node(ray) -> tuple[float, float]:
    """(CPUs, GPUs) of the largest live node: a task asking for more would wait forever."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    cpus = max((n.get("Resources", {}).get("CPU", 0.0) for n in nodes), default=0.0)
    gpus = max((n.get("Resources", {}).get("GPU", 0.0) for n in nodes), default=0.0)
    return cpus, gpus


def check_resources(cpus: float | None, gpus: float, node_cpus: float, node_gpus: float) -> int:
    """The CPUs per capture to ask for; a clear error for a request no node can meet."""
    if gpus < 0:
        raise BatchError(f"--gpus-per-capture must be >= 0, not {gpus}")
    if gpus > 0 and node_gpus == 0:
        raise BatchError(f"--gpus-per-capture {gpus:g}: the Ray cluster has no GPUs; leave it at 0 to run on CPUs")
    if gpus > node_gpus:
        raise BatchError(f"--gpus-per-capture {gpus:g}: no node has that many GPUs (the largest has {node_gpus:g})")
    if cpus is None:
        return max(1, int(min(DEFAULT_CPUS, node_cpus)))
    if cpus < 1:
        raise BatchError(f"--cpus-per-capture must be >= 1, not {cpus}")
    if cpus > node_cpus:
        raise BatchError(f"--cpus-per-capture {cpus}: no node has that many CPUs (the largest has {node_cpus:g})")
    return int(cpus)


def _failure_reason(ray, exc: BaseException, retries: int) -> str:
    """One line for a task that raised or whose worker died."""
    rex = ray.exceptions
    if isinstance(exc, rex.RayTaskError):
        cause = getattr(exc, "cause", None)
        if cause is not None and not isinstance(cause, rex.RayTaskError):
            return f"{type(cause).__name__}: {one_line(cause)}"
        return one_line(exc)
    if isinstance(exc, rex.OutOfMemoryError):
        return f"out of memory: Ray's memory monitor killed the worker (tried {retries + 1} times)"
    if isinstance(exc, (rex.WorkerCrashedError, rex.NodeDiedError)):
        return f"the worker died (tried {retries + 1} times): {type(exc).__name__}"
    return f"{type(exc).__name__}: {one_line(exc)}"


def _recipe_arg(recipe: str) -> str:
    """A recipe file as an absolute path (workers have another working directory); names as they are."""
    p = Path(recipe)
    return str(p.resolve()) if p.suffix and p.exists() else recipe


def run_batch(
    source: str | Path,
    out: str | Path,
    options: ExpandOptions | None = None,
    *,
    address: str | None = None,
    cpus_per_capture: int | None = None,
    gpus_per_capture: float = 0.0,
    retries: int = 2,
    force: bool = False,
    progress: bool = True,
) -> BatchResult:
    """Expand every capture of ``source`` (a root folder or a list file) into OUT/captures/<name>/,
    skip those already done with the same inputs and recipe, write OUT/batch.json/html and
    OUT/dataset.h5. Returns the table; failed captures are rows, not exceptions."""
    t_start = time.time()
    options = options if options is not None else ExpandOptions()
    out = Path(out)
    retries = whole_number(retries, "--retries", 0, MAX_RETRIES)
    if cpus_per_capture is not None:
        cpus_per_capture = whole_number(cpus_per_capture, "--cpus-per-capture", 1, MAX_CPUS)
    gpus_per_capture = finite_number(gpus_per_capture, "--gpus-per-capture", 0.0, MAX_GPUS)
    check_address(address)
    if options.device == DeviceChoice.CUDA and not gpus_per_capture:
        raise BatchError("--device cuda needs --gpus-per-capture: Ray gives a task a GPU only when it reserves one")
    if out.exists() and not out.is_dir():
        raise BatchError(f"{out}: exists and is not a folder")
    options = options.replace(recipe=_recipe_arg(options.recipe))  # the caller's stays as given
    # every option (the recipe: keys, types, ranges) fails before discovery and before Ray starts;
    # the device is the workers' to find
    recipe = options.check(device=False).to_dict()
    jobs = discover(source, out)
    check_out_apart(out, jobs)
    (out / CAPTURES_DIR).mkdir(parents=True, exist_ok=True)

    rows: dict[str, BatchRow] = {}
    todo: list[tuple[CaptureJob, Marker]] = []
    for job in jobs:
        output = out / CAPTURES_DIR / job.name
        marker = make_marker(job.path, recipe, options.marker_options())
        if not force and is_done(out, job.name, marker, output, options.report):
            row = BatchRow(job.name, str(job.path), "skipped", "unchanged since the last run", output=str(output))
            read_quality(output, row)
            rows[job.name] = row
        else:
            clear_marker(out, job.name)
            todo.append((job, marker))

    ray_address = ""
    with make_progress(progress) as bar:
        task = bar.add_task("captures", total=len(jobs), status="")

        def landed(row: BatchRow) -> None:
            if progress:
                bar.console.print(row.line())
            bar.advance(task)

        for row in rows.values():
            landed(row)
        if todo:
            with signal_handlers_kept():  # Ray leaves its SIGTERM handler behind after shutdown
                ray_address = _run_tasks(todo, out, options, rows, bar, task, landed, address=address,
                                         cpus=cpus_per_capture, gpus=gpus_per_capture, retries=retries)
    ordered = [rows[j.name] for j in jobs]

    finished = [(r.name, RunFolder(r.output).labels_path) for r in ordered if r.status in ("done", "skipped")]
    dataset, dataset_error = None, ""
    try:
        dataset = merge_labels(out, finished)
    except LabelsynthError as exc:
        dataset_error = one_line(exc)
        (out / "dataset.h5").unlink(missing_ok=True)
    info = {"source": str(Path(source).resolve()), "out": str(out.resolve()), "recipe": options.recipe,
            "overrides": list(options.overrides), "labels": str(options.labels or "auto"), "report": options.report,
            "ray": ray_address or "local", "seconds": round(time.time() - t_start, 1),
            "dataset": str(dataset) if dataset else "", "dataset_error": dataset_error}
    write_batch_json(out, ordered, info)
    write_batch_html(out, ordered, info)
    return BatchResult(out, ordered, dataset, dataset_error, time.time() - t_start, ray_address)


def _run_tasks(todo: list[tuple[CaptureJob, Marker]], out: Path, options: ExpandOptions, rows: dict[str, BatchRow],
               bar, task, landed, *, address: str | None, cpus: int | None, gpus: float, retries: int) -> str:
    """Submit one task per capture, fill ``rows`` as they land; returns the cluster's address."""
    ray, started = _connect(address)
    try:
        node_cpus, node_gpus = _largest_node(ray)
        ncpu = check_resources(cpus, gpus, node_cpus, node_gpus)
        if gpus == 0 and options.device == DeviceChoice.AUTO:
            options = options.replace(device=DeviceChoice.CPU)  # no GPU reserved: never share one behind Ray's back
        env = {v: str(ncpu) for v in THREAD_VARS}
        remote = ray.remote(expand_capture).options(
            num_cpus=ncpu, num_gpus=gpus, max_retries=retries, retry_exceptions=False,
            runtime_env={"env_vars": env}, name="labelsynth-expand",
        )
        pending = {}
        for job, marker in todo:
            output = out / CAPTURES_DIR / job.name
            ref = remote.remote(str(job.path.resolve()), str(output.resolve()), str(out.resolve()), job.name,
                                options, marker_fields(marker), ncpu)
            pending[ref] = (job, output)
        bar.update(task, status=f"{len(pending)} running or queued")
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                job, output = pending.pop(ref)
                row = BatchRow(job.name, str(job.path), "failed", output=str(output))
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    row.reason = _failure_reason(ray, exc, retries)
                else:
                    row.status, row.reason, row.seconds = res["status"], res.get("reason", ""), res.get("seconds")
                    if row.status == "done":
                        row.frames = res.get("frames")
                        read_quality(output, row)
                rows[job.name] = row
                landed(row)
                bar.update(task, status=f"{len(pending)} left" if pending else "")
        try:
            address_used = ray.get_runtime_context().gcs_address
        except Exception:  # older Ray: the address is only a label in batch.json
            address_used = ""
        return address_used if not started or address or os.environ.get("RAY_ADDRESS") else ""
    finally:
        if started:
            ray.shutdown()


def marker_fields(marker: Marker) -> dict[str, Any]:
    """The marker as plain fields, to send to a worker."""
    return {"inputs": marker.inputs, "recipe": marker.recipe, "options": marker.options, "version": marker.version}
