"""outdir: an output folder is complete or absent; X.partial never outlives a run."""

from __future__ import annotations

import pytest

from labelsynth.errors import LabelsynthError
from labelsynth.outdir import building, check_out, partial_path, write_text_atomic


def test_built_in_partial_then_renamed(tmp_path) -> None:
    out = tmp_path / "deep" / "out"
    with building(out) as part:
        assert part == partial_path(out) == tmp_path / "deep" / "out.partial"
        assert part.is_dir() and not out.exists()
        (part / "a.txt").write_text("a")
    assert (out / "a.txt").read_text() == "a" and not part.exists()


def test_exception_leaves_out_as_it_was(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("k")
    with pytest.raises(KeyboardInterrupt):
        with building(out, force=True) as part:
            (part / "new.txt").write_text("n")
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_non_empty_out_needs_force_and_is_replaced(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("o")
    with pytest.raises(LabelsynthError, match=r"out: output folder exists and is not empty \(use --force"):
        check_out(out)
    with pytest.raises(LabelsynthError, match="not empty"):
        with building(out):
            pass
    assert not partial_path(out).exists()
    with building(out, force=True) as part:
        (part / "new.txt").write_text("n")
    assert [p.name for p in out.iterdir()] == ["new.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(LabelsynthError, match="file: exists and is not a folder"):
        check_out(tmp_path / "file", force=True)


def test_stale_partial_is_cleared(tmp_path) -> None:
    out = tmp_path / "out"
    partial_path(out).mkdir()
    (partial_path(out) / "stale.txt").write_text("s")
    with building(out) as part:
        assert list(part.iterdir()) == []
    assert list(out.iterdir()) == []


def test_merge_replaces_same_names_and_keeps_others(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.png").write_text("old")
    (out / "notes.txt").write_text("mine")
    with building(out, merge=True) as part:
        (part / "a.png").write_text("new")
        (part / "b.png").write_text("new")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"a.png": "new", "b.png": "new", "notes.txt": "mine"}
    assert not partial_path(out).exists()


def test_write_text_atomic(tmp_path) -> None:
    path = write_text_atomic(tmp_path / "d" / "t.json", "{}")
    assert path.read_text() == "{}" and not partial_path(path).exists()


def test_replacing_swaps_by_renames_and_keeps_the_previous_only_when_asked(tmp_path) -> None:
    from labelsynth.outdir import previous_path

    out = tmp_path / "out"
    out.mkdir()
    (out / "v.txt").write_text("1")
    with building(out, force=True, keep_previous=True) as part:
        (part / "v.txt").write_text("2")
    assert (out / "v.txt").read_text() == "2" and (previous_path(out) / "v.txt").read_text() == "1"
    with building(out, force=True, keep_previous=True) as part:  # one level: the older previous goes
        (part / "v.txt").write_text("3")
    assert (out / "v.txt").read_text() == "3" and (previous_path(out) / "v.txt").read_text() == "2"
    with building(out, force=True) as part:
        (part / "v.txt").write_text("4")
    assert (out / "v.txt").read_text() == "4"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_failed_swap_puts_the_old_out_back(tmp_path, monkeypatch) -> None:
    """The second rename (OUT.partial -> OUT) fails: OUT.previous is renamed back, whole."""
    import os

    from labelsynth import outdir

    out = tmp_path / "out"
    out.mkdir()
    (out / "v.txt").write_text("old")
    real, calls = os.replace, []

    def flaky(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise OSError("disk gone")
        return real(src, dst)

    monkeypatch.setattr(outdir.os, "replace", flaky)
    # the failed write is re-raised as one line naming the folder (outdir's OSError rule)
    with pytest.raises(LabelsynthError, match="out.partial: disk gone"):
        with building(out, force=True) as part:
            (part / "v.txt").write_text("new")
    assert [c[1].name for c in calls] == ["out.previous", "out", "out"]
    assert (out / "v.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
