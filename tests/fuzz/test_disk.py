"""A really full and a really read-only disk, not a patched write: a tiny tmpfs mounted in a
private mount namespace (``unshare``; nothing outside the test sees it), or, where mount
namespaces are not allowed, a per-process file size limit (RLIMIT_FSIZE: writes fail with
EFBIG). The command fails in one line naming the path, and leaves nothing on that disk."""

from __future__ import annotations

import os
import resource
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ..scenes import make_patch_capture

pytestmark = pytest.mark.xdist_group("signals")  # with the other tests that start labelsynth processes

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--recipe", "fast", "--device", "cpu", "--labels", "annotations", "--no-report",
        "--set", "geometry.iterations=2", "--set", "semantic.iterations=2", "--set", "render.mesh_resolution=16"]


def _unshare() -> list[str] | None:
    """The unshare command that gives this process a private mount namespace, or None."""
    for cmd in (["unshare", "--mount", "--propagation", "private"], ["unshare", "--map-root-user", "--mount",
                                                                       "--propagation", "private"]):
        try:
            probe = subprocess.run([*cmd, "sh", "-c", "mount -t tmpfs -o size=16k tmpfs /tmp && true"],
                                   capture_output=True, timeout=20)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if probe.returncode == 0:
            return cmd
    return None


UNSHARE = _unshare()
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def _on_tmpfs(tmp_path: Path, size: str, args: list[str], *, read_only: bool = False) -> tuple[int, str, list[str]]:
    """Run ``labelsynth ARGS`` with ``{disk}`` in them a fresh tmpfs of ``size``; returns the exit
    code, stderr and what the tmpfs holds afterwards."""
    disk, err, listing = tmp_path / "disk", tmp_path / "stderr.txt", tmp_path / "listing.txt"
    disk.mkdir()
    cli = " ".join(shlex.quote(a.replace("{disk}", str(disk))) for a in [sys.executable, "-m", "labelsynth.cli", *args])
    script = (f"mount -t tmpfs -o size={size}{',ro' if read_only else ''} tmpfs {shlex.quote(str(disk))} || exit 97\n"
              f"{cli} 2> {shlex.quote(str(err))}\nrc=$?\nls -A {shlex.quote(str(disk))} > {shlex.quote(str(listing))}\n"
              "exit $rc\n")
    proc = subprocess.run([*UNSHARE, "sh", "-c", script], env=ENV, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode != 97, proc.stderr
    return proc.returncode, err.read_text(), listing.read_text().split()


def _with_file_size_limit(tmp_path: Path, limit: int, args: list[str]) -> tuple[int, str, list[str]]:
    disk = tmp_path / "disk"
    disk.mkdir()

    def limit_writes() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run([sys.executable, "-m", "labelsynth.cli", *[a.replace("{disk}", str(disk)) for a in args]],
                          env=ENV, cwd=tmp_path, capture_output=True, text=True, timeout=300, preexec_fn=limit_writes)
    return proc.returncode, proc.stderr, sorted(p.name for p in disk.iterdir())


def _one_error_line(stderr: str, *texts: str, after_work: bool = False) -> str:
    """The one error line (``after_work``: the last line, after the progress lines of work done)."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    if after_work:
        lines = lines[-1:]
        assert not any(ln.startswith("labelsynth: error: ") for ln in stderr.splitlines()[:-1]), stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("labelsynth: error: "), stderr[-3000:]
    assert "Traceback" not in stderr
    for text in texts:
        assert text.lower() in lines[0].lower(), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    root, _ = make_patch_capture(tmp_path_factory.mktemp("disk"), frames=4, size=24)
    return root


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_synth_on_a_full_disk(tmp_path):
    args = ["synth", "{disk}/syn", "--frames", "6", "--width", "64", "--height", "48"]
    if UNSHARE:
        rc, err, left = _on_tmpfs(tmp_path, "96k", args)
        _one_error_line(err, f"{tmp_path}/disk/syn.partial", "no space left on")
    else:
        rc, err, left = _with_file_size_limit(tmp_path, 4096, args)
        _one_error_line(err, f"{tmp_path}/disk/syn.partial", "too large")
    assert rc == 2 and left == []


def test_expand_on_a_disk_without_room_fails_before_training(tmp_path, capture):
    before = _files(capture)
    if not UNSHARE:  # no disk to fill: a file size limit fails the first large write (field.pt) instead
        rc, err, left = _with_file_size_limit(tmp_path, 4096, ["expand", str(capture), "--out", "{disk}/out", *TINY])
        _one_error_line(err, f"{tmp_path}/disk/out.partial/field.pt", "too large", after_work=True)
    else:
        rc, err, left = _on_tmpfs(tmp_path, "1m", ["expand", str(capture), "--out", "{disk}/out", *TINY])
        _one_error_line(err, f"{tmp_path}/disk/out", "not enough free space")
        assert "geometry" not in err
    assert rc == 2 and left == []
    assert _files(capture) == before


@pytest.mark.skipif(UNSHARE is None, reason="needs a mount namespace (unshare) for a read-only file system")
def test_expand_on_a_read_only_disk(tmp_path, capture):
    rc, err, left = _on_tmpfs(tmp_path, "1m", ["expand", str(capture), "--out", "{disk}/out", *TINY], read_only=True)
    _one_error_line(err, f"{tmp_path}/disk", "read-only file system")
    assert rc == 2 and left == []
