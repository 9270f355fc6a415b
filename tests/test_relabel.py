"""`labelsynth relabel OUT`: the semantic stage again on OUT's frozen geometry after masks changed.

On copies of the shared tiny expand (its OUT and capture are never touched): nothing changed
gives the very masks expand wrote; a corrected annotation gives other masks and run.json and
the report say what changed; a capture whose images or cameras changed is refused; and an
interrupted relabel (an exception mid-way, SIGTERM) leaves the old OUT whole.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth import pipeline
from labelsynth.cli import app
from labelsynth.export import LabelsReader
from labelsynth.geometry.fingerprint import GeometryChanged
from labelsynth.rundir import RunFolder

pytestmark = pytest.mark.xdist_group("tiny_expanded")


def copies(tiny, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of the tiny run's OUT and capture (relabel replaces OUT; tests change the capture)."""
    out, cap = tmp_path / "out", tmp_path / "capture"
    shutil.copytree(tiny.out, out)
    shutil.copytree(tiny.capture_dir, cap)
    return out, cap


def files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def masks_of(out: Path) -> dict[str, np.ndarray]:
    with LabelsReader(out / "labels.h5") as reader:
        h5 = {n: reader.read(i)[1] for i, n in enumerate(reader.frame_names)}
    pngs = RunFolder(out).read_masks(sorted(h5))
    for name, mask in h5.items():
        np.testing.assert_array_equal(pngs[name], mask)  # masks/ and labels.h5 agree
    return pngs


def test_relabel_of_an_unchanged_capture_writes_the_masks_expand_wrote(tiny_expanded, tmp_path):
    out, cap = copies(tiny_expanded, tmp_path)
    before = masks_of(out)
    info = RunFolder(out).read_run()
    result = pipeline.relabel(out, capture=cap, report=False, device="cpu", progress=False)
    after = masks_of(out)
    for name in before:
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    again = RunFolder(out).read_run()
    assert again.relabel["masks_changed"] == [] and result.masks_changed == []
    assert set(again.relabel["pixels_changed"].values()) == {0}
    assert again.relabel["relabels"] == 1
    assert again.label_inputs == info.label_inputs
    assert again.seed == info.seed and again.recipe == info.recipe and again.geometry == info.geometry
    assert set(again.seconds) == {"check", "semantics", "render"}
    assert not (tmp_path / "out.partial").exists() and not (tmp_path / "out.previous").exists()
    assert not (out / "report.json").exists()  # --no-report: no stale report of the old labels
    # the geometry in field.pt is the one expand fitted, tensor for tensor
    old, new = RunFolder(tiny_expanded.out).load_field(), RunFolder(out).load_field()
    for (k, a), (_, b) in zip(old.sdf.state_dict().items(), new.sdf.state_dict().items()):
        assert torch_equal(a, b), k


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


def test_relabel_after_a_corrected_annotation(tiny_expanded, tmp_path):
    """The shifted annotation replaced by the truth: other masks, the change listed in run.json,
    and the report and its page say what moved, frame by frame."""
    tiny = tiny_expanded
    out, cap = copies(tiny, tmp_path)
    before = masks_of(out)
    shutil.copy(tiny.truth_dir / f"{tiny.shifted}.png", cap / "annotations" / f"{tiny.shifted}.png")
    res = CliRunner().invoke(app, ["relabel", str(out), "--capture", str(cap), "--device", "cpu", "--keep-previous"])
    assert res.exit_code == 0, res.output
    assert f"1 input mask(s) changed (annotations/{tiny.shifted})" in res.output
    after = masks_of(out)
    moved = {n: int((after[n] != before[n]).sum()) for n in before}
    assert sum(moved.values()) > 0
    info = RunFolder(out).read_run()
    assert info.relabel["masks_changed"] == [f"annotations/{tiny.shifted}"]
    assert info.relabel["pixels_changed"] == moved
    assert info.label_inputs["annotations"][tiny.shifted] != RunFolder(tiny.out).read_run().label_inputs[
        "annotations"][tiny.shifted]
    report = json.loads((out / "report.json").read_text())
    assert report["summary"]["relabel"]["masks_changed"] == [f"annotations/{tiny.shifted}"]
    assert {f["name"]: f["pixels_changed"] for f in report["frames"]} == moved
    page = (out / "report.html").read_text()
    assert f"annotations/{tiny.shifted}" in page and "px changed" in page and "What the relabel changed" in page
    # --keep-previous: the replaced OUT, whole, beside the new one
    assert files(tmp_path / "out.previous") == files(tiny.out)
    # a second relabel with nothing changed since: nothing listed, nothing moved, counted
    res = CliRunner().invoke(app, ["relabel", str(out), "--capture", str(cap), "--device", "cpu", "--no-report"])
    assert res.exit_code == 0, res.output
    info = RunFolder(out).read_run()
    assert info.relabel["masks_changed"] == [] and set(info.relabel["pixels_changed"].values()) == {0}
    assert info.relabel["relabels"] == 2
    assert not (tmp_path / "out.previous").exists()  # removed once the new OUT was whole


@pytest.mark.parametrize("change", ["image", "camera", "frame"])
def test_relabel_refuses_a_capture_whose_geometry_inputs_changed(tiny_expanded, tmp_path, change):
    tiny = tiny_expanded
    out, cap = copies(tiny, tmp_path)
    name = tiny.result.frames[2]
    if change == "image":
        path = cap / "images" / f"{name}.png"
        img = cv2.imread(str(path))
        img[10:20, 10:20] = 255 - img[10:20, 10:20]
        cv2.imwrite(str(path), img)
        message = f"images changed since the geometry in {out / 'field.pt'} was fitted (images: {name} differs)"
    elif change == "camera":
        tf = json.loads((cap / "transforms.json").read_text())
        frame = next(f for f in tf["frames"] if Path(f["file_path"]).stem == name)
        frame["transform_matrix"][0][3] += 0.01
        (cap / "transforms.json").write_text(json.dumps(tf))
        message = f"(cameras: {name} differs"
    else:
        shutil.copy(cap / "images" / f"{name}.png", cap / "images" / "zz_extra.png")
        tf = json.loads((cap / "transforms.json").read_text())
        tf["frames"].append({**tf["frames"][0], "file_path": "images/zz_extra.png"})
        (cap / "transforms.json").write_text(json.dumps(tf))
        message = "1 frame added (zz_extra)"
    before = files(out)
    res = CliRunner().invoke(app, ["relabel", str(out), "--capture", str(cap), "--device", "cpu"])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "run expand again" in lines[0], res.output
    assert f"changed since the geometry in {out / 'field.pt'} was fitted" in lines[0], res.output
    assert files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture", "out"]


def test_relabel_refuses_bad_options_and_folders_in_one_line(tiny_expanded, tmp_path):
    out, cap = copies(tiny_expanded, tmp_path)
    for args, message in (
        (["relabel", str(out), "--labels", "some"], "--labels must be one of annotations, predictions, both"),
        (["relabel", str(out), "--device", "tpu"], "--device must be one of auto, cpu, cuda"),
        (["relabel", str(tmp_path / "none")], "not found (expected the output folder of labelsynth expand)"),
        (["relabel", str(out), "--capture", str(tmp_path / "gone")], "capture folder not found"),
        (["relabel", str(out), "--capture", str(cap), "--labels", "predictions"], "needs automatic masks, none found"),
    ):
        if "predictions" in args:
            shutil.rmtree(cap / "predictions", ignore_errors=True)
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
        assert message in res.output, res.output
    # a field.pt from before fingerprints were recorded: refused, not guessed
    import torch

    stored = torch.load(out / "field.pt", weights_only=True)
    meta = json.loads(stored["labelsynth_field"])
    assert meta.pop("fitted_on")
    stored["labelsynth_field"] = json.dumps(meta)
    torch.save(stored, out / "field.pt")
    with pytest.raises(GeometryChanged, match="field.pt: holds no record of what its geometry was fitted on .*"
                                              "relabel reuses that geometry: run expand again"):
        pipeline.relabel(out, capture=cap, device="cpu", progress=False)


def test_an_interrupted_relabel_leaves_the_old_out_whole(tiny_expanded, tmp_path, monkeypatch):
    tiny = tiny_expanded
    out, cap = copies(tiny, tmp_path)
    shutil.copy(tiny.truth_dir / f"{tiny.shifted}.png", cap / "annotations" / f"{tiny.shifted}.png")
    before = files(out)
    real = pipeline.render_outputs
    written = []

    def half_then_fail(view, capture, run, **kw):  # masks/ half written, then the run dies
        written.append(run.path)
        from labelsynth.export import write_masks_png

        cams = capture.unit_cameras()
        for i in range(len(capture) // 2):
            write_masks_png(run.masks_dir, capture.names[i], view.render(cams[i]).mask, capture.classes)
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "render_outputs", half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        pipeline.relabel(out, capture=cap, report=False, device="cpu", progress=False)
    assert written == [tmp_path / "out.partial"]  # it was writing beside OUT, never into it
    assert files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture", "out"]
    monkeypatch.setattr(pipeline, "render_outputs", real)


def test_relabel_killed_by_sigterm_leaves_the_old_out_whole(tiny_expanded, tmp_path):
    """SIGTERM while the new OUT is being built: OUT is as it was, and the next relabel
    clears the leftover OUT.partial and finishes."""
    tiny = tiny_expanded
    out, cap = copies(tiny, tmp_path)
    shutil.copy(tiny.truth_dir / f"{tiny.shifted}.png", cap / "annotations" / f"{tiny.shifted}.png")
    before = files(out)
    partial = tmp_path / "out.partial"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "labelsynth.cli", "relabel", str(out), "--capture", str(cap),
                             "--device", "cpu", "--no-report"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while not partial.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert partial.exists(), "relabel never started building OUT.partial"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) != 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert files(out) == before
    assert not (tmp_path / "out.previous").exists()
    res = CliRunner().invoke(app, ["relabel", str(out), "--capture", str(cap), "--device", "cpu", "--no-report"])
    assert res.exit_code == 0, res.output
    assert not partial.exists() and RunFolder(out).read_run().relabel["masks_changed"] == [
        f"annotations/{tiny.shifted}"]
