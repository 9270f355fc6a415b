"""labelsynth batch without Ray: discovery, names, markers, resources, the table and dataset.h5."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from labelsynth.batch.discover import BatchError, discover, find_captures, read_capture_list
from labelsynth.batch.marker import is_done, make_marker, write_marker
from labelsynth.batch.merge import merge_labels
from labelsynth.batch.run import check_resources, one_line
from labelsynth.batch.table import BatchRow, write_batch_html, write_batch_json
from labelsynth.classes import ClassMap
from labelsynth.errors import CheckError, LabelsynthError
from labelsynth.export import LabelsDataset, write_labels_h5
from labelsynth.rundir import RunFolder, RunInfo


def _capture(folder: Path, pose: str = "transforms.json") -> Path:
    folder.mkdir(parents=True)
    if pose.startswith("sparse"):  # a COLMAP model in sparse/0 or directly in sparse/
        (folder / pose).mkdir(parents=True)
        (folder / pose / "cameras.txt").write_text("# Camera list\n")
    else:
        (folder / pose).write_text("{}")
    (folder / "images").mkdir()
    (folder / "images" / "a.png").write_bytes(b"x" * 10)
    return folder


def test_import_labelsynth_does_not_import_ray():
    code = ("import sys, labelsynth, labelsynth.cli, labelsynth.batch; "
            "sys.exit(1 if 'ray' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_discover_finds_captures_but_not_inside_them_nor_out(tmp_path):
    root = tmp_path / "root"
    _capture(root / "p1" / "wound")
    _capture(root / "p2" / "wound", "sparse/0")
    _capture(root / "p3", "cameras_sphere.npz")
    _capture(root / "p3" / "nested")  # inside a capture: not searched
    _capture(root / "p4", "sparse")  # a COLMAP model directly in sparse/, as load_capture reads it
    _capture(root / "out" / "captures" / "old")  # the batch's own OUT
    (root / "empty").mkdir()
    (root / "empty_model" / "sparse" / "0").mkdir(parents=True)  # no model in it: load_capture would refuse
    (root / ".hidden").mkdir()
    _capture(root / ".hidden" / "c")
    assert [p.relative_to(root).as_posix() for p in find_captures(root, exclude=root / "out")] == \
        ["p1/wound", "p2/wound", "p3", "p4"]
    jobs = discover(root, root / "out")
    assert [j.name for j in jobs] == ["p1__wound", "p2__wound", "p3", "p4"]  # same folder name: the path decides
    assert [j.name for j in discover(root / "p3")] == ["p3"]  # a capture is its own root


def test_a_colmap_model_directly_in_sparse_is_found_and_loads(tmp_path):
    """Batch and the loaders share one rule (``capture.load.is_capture``): a capture whose COLMAP
    model is in ``sparse/`` (no ``0/``) is found by discovery, listed, and loads."""
    from labelsynth.capture import load_capture

    from ..capture.test_capture_colmap import make_colmap_capture

    cap = make_colmap_capture(tmp_path / "root" / "colmap_flat")
    (cap / "sparse" / "0").rename(cap / "sparse_model")
    (cap / "sparse").rmdir()
    (cap / "sparse_model").rename(cap / "sparse")
    assert (cap / "sparse" / "cameras.txt").is_file()
    assert find_captures(tmp_path / "root") == [cap]
    (tmp_path / "list.txt").write_text("root/colmap_flat\n")
    assert [j.path for j in discover(tmp_path / "list.txt")] == [cap]
    assert load_capture(cap).names == ["a", "b"]


def test_capture_list_file(tmp_path):
    a = _capture(tmp_path / "a")
    _capture(tmp_path / "sub" / "b")
    lst = tmp_path / "list.txt"
    lst.write_text(f"# my captures\n{a}\n\nsub/b   # relative to the list\n")
    assert [j.name for j in discover(lst)] == ["a", "b"]
    lst.write_text("a\nnope\n")
    with pytest.raises(BatchError, match=r"list.txt:2: nope: no such capture folder"):
        read_capture_list(lst)
    (tmp_path / "plain").mkdir()
    lst.write_text("plain\n")
    with pytest.raises(BatchError, match=r"list.txt:1: plain: not a capture"):
        read_capture_list(lst)
    lst.write_text("a\n./a\n")
    with pytest.raises(BatchError, match="listed twice"):
        discover(lst)
    lst.write_text("# nothing\n")
    with pytest.raises(BatchError, match="lists no captures"):
        discover(lst)
    with pytest.raises(BatchError, match="no capture folders found"):
        discover(tmp_path / "plain")
    with pytest.raises(BatchError, match="no such folder or capture list"):
        discover(tmp_path / "missing")


def test_marker_key_follows_inputs_recipe_and_options(tmp_path):
    cap = _capture(tmp_path / "c")
    recipe = {"name": "fast", "geometry": {"iterations": 500}}
    opts = {"labels": None, "seed": 0}
    base = make_marker(cap, recipe, opts).key
    assert make_marker(cap, recipe, opts).key == base  # deterministic
    assert make_marker(cap, {**recipe, "geometry": {"iterations": 501}}, opts).key != base
    assert make_marker(cap, recipe, {**opts, "seed": 1}).key != base
    img = cap / "images" / "a.png"
    img.write_bytes(b"y" * 10)  # same size, new content and mtime
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    changed = make_marker(cap, recipe, opts).key
    assert changed != base
    (cap / "images" / "b.png").write_bytes(b"z")  # a new frame
    assert make_marker(cap, recipe, opts).key not in (base, changed)


def test_is_done_needs_the_marker_and_a_complete_output(tmp_path):
    cap = _capture(tmp_path / "c")
    out, output = tmp_path / "out", tmp_path / "out" / "captures" / "c"
    marker = make_marker(cap, {"name": "fast"}, {})
    for f in ("run.json", "labels.h5", "field.pt"):
        (output / "masks").mkdir(parents=True, exist_ok=True)
        (output / f).write_text("x")
    assert RunFolder(output).is_finished(report=False) and not RunFolder(output).is_finished(report=True)
    assert not is_done(out, "c", marker, output, report=False)  # no marker yet
    write_marker(out, "c", marker)
    assert is_done(out, "c", marker, output, report=False)
    assert not is_done(out, "c", make_marker(cap, {"name": "default"}, {}), output, report=False)
    (output / "labels.h5").unlink()  # removed by hand
    assert not is_done(out, "c", marker, output, report=False)


def test_resource_requests_that_no_node_meets_are_clear_errors():
    assert check_resources(None, 0, 2, 0) == 2  # default 4, capped to the node
    assert check_resources(None, 0, 16, 0) == 4
    assert check_resources(3, 1, 8, 1) == 3
    with pytest.raises(BatchError, match="the Ray cluster has no GPUs"):
        check_resources(1, 1, 8, 0)
    with pytest.raises(BatchError, match="no node has that many GPUs"):
        check_resources(1, 2, 8, 1)
    with pytest.raises(BatchError, match="no node has that many CPUs"):
        check_resources(9, 0, 8, 0)


def test_bad_options_fail_before_any_capture_or_ray(tmp_path):
    from labelsynth.batch import ExpandOptions, run_batch

    with pytest.raises(BatchError, match="--device cuda needs --gpus-per-capture"):
        run_batch(tmp_path, tmp_path / "out", ExpandOptions(device="cuda"))
    with pytest.raises(LabelsynthError, match="--labels must be one of"):
        run_batch(tmp_path, tmp_path / "out", ExpandOptions(labels="all"))
    _capture(tmp_path / "c")
    with pytest.raises(Exception, match="--recipe 'nope': unknown recipe"):
        run_batch(tmp_path, tmp_path / "out", ExpandOptions(recipe="nope"))
    assert not (tmp_path / "out").exists()


def test_one_line_reasons():
    err = CheckError(["a.png: truncated", "b.png: bad id 9"], "2 problems in C")
    assert one_line(err) == "a.png: truncated (and 1 more problem)"
    assert one_line(ValueError("first\nsecond")) == "first"


def test_table_files_are_self_contained(tmp_path):
    rows = [BatchRow("a", "/c/a", "done", seconds=12.3, wound_bed_agreement=0.97, flagged=["f1"]),
            BatchRow("b<x>", "/c/b", "failed", reason="b.png: cannot read image (file is truncated)")]
    write_batch_json(tmp_path, rows, {"recipe": "fast"})
    doc = json.loads((tmp_path / "batch.json").read_text())
    assert doc["counts"] == {"done": 1, "skipped": 0, "failed": 1}
    assert doc["captures"][1]["reason"].endswith("(file is truncated)")
    write_batch_html(tmp_path, rows, {})
    html = (tmp_path / "batch.html").read_text()
    assert "b&lt;x&gt;" in html and "file is truncated" in html and "0.970" in html
    for outside in ("<script", "<link", "src=", "http://", "https://"):
        assert outside not in html


def _labels(path: Path, n: int, h: int, w: int, seed: int, classes: ClassMap) -> dict:
    rng = np.random.default_rng(seed)
    data = {"images": rng.integers(0, 255, (n, h, w, 3), dtype=np.uint8),
            "masks": rng.integers(0, 3, (n, h, w), dtype=np.uint8),
            "confidence": rng.random((n, h, w)).astype(np.float16),
            "names": [f"frame_{i:03d}" for i in range(n)], "annotated": [i == 0 for i in range(n)]}
    write_labels_h5(path, images=data["images"], masks=data["masks"], confidence=data["confidence"],
                    frame_names=data["names"], annotated=data["annotated"], classes=classes)
    return data


def test_merged_dataset_of_captures_of_two_sizes(tmp_path):
    classes = ClassMap.default()
    out = tmp_path / "out"
    a = _labels(out / "captures" / "a" / "labels.h5", 3, 12, 16, 0, classes)
    b = _labels(out / "captures" / "b" / "labels.h5", 2, 20, 10, 1, classes)
    path = merge_labels(out, [("a", out / "captures" / "a" / "labels.h5"), ("b", out / "captures" / "b" / "labels.h5")])
    moved = tmp_path / "elsewhere"
    shutil.move(str(out), moved)  # relative sources: OUT moves as a whole
    ds = LabelsDataset(moved / path.name, uint8=True)
    assert len(ds) == 5 and ds.classes.to_json() == classes.to_json()
    expected = [("a", a, i) for i in range(3)] + [("b", b, i) for i in range(2)]
    for k, (cap, data, i) in enumerate(expected):
        item = ds[k]
        assert item["capture"] == cap and item["name"] == data["names"][i]
        assert np.array_equal(item["image"].permute(1, 2, 0).numpy(), data["images"][i])  # cropped back
        assert np.array_equal(item["mask"].numpy(), data["masks"][i])
        assert np.allclose(item["confidence"].numpy(), data["confidence"][i].astype(np.float32))
        assert bool(item["annotated"]) == data["annotated"][i]
    (moved / "captures" / "b" / "labels.h5").unlink()
    with pytest.raises(Exception, match="which is missing"):
        LabelsDataset(moved / path.name)


def test_merge_refuses_different_class_tables(tmp_path):
    out = tmp_path / "out"
    _labels(out / "captures" / "a" / "labels.h5", 1, 8, 8, 0, ClassMap.default())
    other = ClassMap.from_dict({"classes": [{"id": 0, "name": "background"}, {"id": 1, "name": "skin"},
                                            {"id": 2, "name": "bed", "wound_bed": True}]}, "test")
    _labels(out / "captures" / "b" / "labels.h5", 1, 8, 8, 0, other)
    with pytest.raises(BatchError, match="class table differs"):
        merge_labels(out, [("a", out / "captures" / "a" / "labels.h5"), ("b", out / "captures" / "b" / "labels.h5")])
    assert not (out / "dataset.h5").exists() and not (out / "dataset.h5.partial").exists()


def test_quality_columns_come_from_the_capture_report(tmp_path):
    from labelsynth.batch.table import read_quality

    RunFolder(tmp_path).write_run(RunInfo("/c/a", "annotations", seconds={"geometry": 10.0, "semantics": 5.0,
                                                                        "render": 1.5}))
    (tmp_path / "report.json").write_text(json.dumps({"summary": {
        "num_frames": 6, "median_agreement": {"wound_bed": 0.93}, "median_loo_dice": {"wound_bed": 0.88},
        "flagged": ["frame_003"]}}))
    row = BatchRow("a", "/c/a", "skipped")
    read_quality(tmp_path, row)
    assert (row.seconds, row.frames, row.wound_bed_agreement, row.wound_bed_loo_dice, row.flagged) == \
        (16.5, 6, 0.93, 0.88, ["frame_003"])
    assert "its run took 16 s" in row.line() and "1 flagged" in row.line()
    (tmp_path / "report.json").unlink()  # --no-report: the columns stay empty
    bare = BatchRow("b", "/c/b", "done", seconds=3.0)
    read_quality(tmp_path, bare)
    assert bare.wound_bed_agreement is None and bare.flagged == [] and bare.seconds == 3.0
