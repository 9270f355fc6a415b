"""Finding the Ray worker that runs a labelsynth task, among the processes of one Ray node only.

A worker is a descendant of its node's raylet; searching all of /proc for the task's process
title could find another test's or another user's Ray worker (and a test that kills it would
kill the wrong process), so the search starts from the raylet of the node the test owns."""

from __future__ import annotations

import time
from pathlib import Path

TASK_TITLE = "ray::labelsynth-expand"  # Ray's process title while a worker runs our task


def _parents() -> dict[int, int]:
    parents = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid ...: comm may hold spaces and parentheses, so split after the last ')'
        fields = stat.rsplit(")", 1)[1].split()
        parents[int(proc.name)] = int(fields[1])
    return parents


def descendants(root: int) -> set[int]:
    """Every process below ``root`` (children, grandchildren, ...)."""
    children: dict[int, list[int]] = {}
    for pid, ppid in _parents().items():
        children.setdefault(ppid, []).append(pid)
    found, todo = set(), [root]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def raylet_pid(node) -> int:
    """The raylet of a ``ray._private.node.Node`` (this test's local instance or a Cluster node)."""
    return node.all_processes["raylet"][0].process.pid


def local_node():
    """The node of the Ray instance this process started with ``ray.init(address="local")``."""
    import ray

    return ray._private.worker._global_node


def task_pid(raylet: int, timeout: float, title: str = TASK_TITLE) -> int | None:
    """The pid of a worker below ``raylet`` while it runs our task, or None after ``timeout`` s."""
    end = time.time() + timeout
    while True:
        for pid in sorted(descendants(raylet)):
            try:
                if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(title.encode()):
                    return pid
            except OSError:
                pass
        if time.time() >= end:
            return None
        time.sleep(0.2)
