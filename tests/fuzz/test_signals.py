"""Ctrl-C and SIGTERM on a real ``labelsynth`` process: the partial output goes, the exit code says
which signal (130, 143), and a second signal while the first one's cleanup runs exits at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from ..scenes import make_patch_capture

pytestmark = pytest.mark.xdist_group("signals")  # two labelsynth processes at a time at most

ROOT = Path(__file__).resolve().parents[2]
SLOW_EXPAND = ["--recipe", "fast", "--device", "cpu", "--labels", "annotations", "--no-report",
               "--set", "geometry.iterations=100000"]  # runs for hours unless stopped


def _start(args: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    # Ctrl-C as a terminal would give it: a suite started in the background of a script
    # inherits SIGINT ignored, and labelsynth rightly leaves an ignored SIGINT alone.
    return subprocess.Popen([sys.executable, *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(condition, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"exited early ({proc.returncode}): {proc.communicate()[1][-2000:]}")
        if time.monotonic() > end:
            proc.kill()
            raise AssertionError(f"timed out: {proc.communicate()[1][-2000:]}")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    root, _ = make_patch_capture(tmp_path_factory.mktemp("signals"), frames=4, size=24)
    return root


@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGINT, signal.SIGINT)],
                         ids=["SIGTERM", "SIGINT-twice"])
def test_a_signal_during_expand_removes_the_partial_output(capture, tmp_path, signals):
    out = tmp_path / "out"
    partial = tmp_path / "out.partial"
    proc = _start(["-m", "labelsynth.cli", "expand", str(capture), "--out", str(out), *SLOW_EXPAND], tmp_path)
    _wait_for(partial.is_dir, proc)
    time.sleep(1.0)  # into the geometry's training steps
    t0 = time.monotonic()
    for i, sig in enumerate(signals):
        if proc.poll() is None:
            proc.send_signal(sig)
        if i + 1 < len(signals):
            time.sleep(0.2)
    _, err = proc.communicate(timeout=60)
    seconds = time.monotonic() - t0
    name = signals[0].name
    assert proc.returncode in (128 + signals[0], -signals[-1]), (proc.returncode, err[-2000:])
    assert "Traceback" not in err, err[-2000:]
    assert seconds < 20, seconds
    assert not out.exists() and not partial.exists(), sorted(p.name for p in tmp_path.iterdir())
    if len(signals) == 1:
        assert err.strip().splitlines()[-1] == f"labelsynth: interrupted ({name})", err[-500:]


def test_sigterm_during_synth_removes_the_partial_output(tmp_path):
    out = tmp_path / "syn"
    partial = tmp_path / "syn.partial"
    proc = _start(["-m", "labelsynth.cli", "synth", str(out), "--frames", "2000", "--width", "64", "--height", "48"],
                  tmp_path)
    _wait_for(lambda: (partial / "capture" / "images").is_dir() and any((partial / "capture" / "images").iterdir()),
              proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err[-2000:]
    assert err.strip().splitlines()[-1] == "labelsynth: interrupted (SIGTERM)", err[-500:]
    assert not out.exists() and not partial.exists()


def test_a_second_ctrl_c_during_the_cleanup_exits_at_once(tmp_path):
    """The first Ctrl-C starts removing OUT.partial (made slow here, as for a large folder); the
    second does not wait for it. OUT.partial, which never looks finished, is left for the next
    run to clear, and that run starts clean."""
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import shutil, time
        from pathlib import Path
        from labelsynth import outdir

        real = shutil.rmtree
        def slow(path, *args, **kwargs):
            print("cleanup", flush=True)
            time.sleep(60)
            real(path, *args, **kwargs)
        with outdir.building(Path({str(out)!r})) as part:
            (part / "half.txt").write_text("half")
            shutil.rmtree = slow
            print("ready", flush=True)
            time.sleep(60)
    """)
    proc = _start(["-c", script], tmp_path)
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGINT)
    assert proc.stdout.readline().strip() == "cleanup"
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert time.monotonic() - t0 < 10
    assert proc.returncode == 130, err
    assert "SIGINT again: exiting at once" in err
    assert not out.exists()
    from labelsynth.outdir import building, partial_path

    assert partial_path(out).is_dir()  # left unfinished: never mistaken for OUT
    with building(out) as part:
        assert list(part.iterdir()) == []  # the next run clears it
    assert out.is_dir() and not partial_path(out).exists()


def test_signal_handlers_are_restored_and_nested_blocks_share_them():
    from labelsynth.outdir import interruptible

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with interruptible():
        inner = signal.getsignal(signal.SIGTERM)
        assert inner is not before[1]
        with interruptible():
            assert signal.getsignal(signal.SIGTERM) is inner
        assert signal.getsignal(signal.SIGTERM) is inner
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_sigterm_in_process_runs_the_cleanup(tmp_path):
    from labelsynth.outdir import Interrupted, building

    out = tmp_path / "out"
    with pytest.raises(Interrupted) as info:
        with building(out) as part:
            (part / "x").write_text("x")
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises before this ends
    assert info.value.signum == signal.SIGTERM and info.value.exit_code == 143
    assert not out.exists() and not (tmp_path / "out.partial").exists()
