"""The run folder's contract without a fit: file names, "finished or not", run.json's schema.
(field.pt's format is tested on a real field in tests/render/test_field.py.)"""

from __future__ import annotations

import json

import pytest

from labelsynth.rundir import RunFolder, RunFolderError, RunInfo


def _finished(path, report: bool = False) -> RunFolder:
    run = RunFolder(path)
    run.masks_dir.mkdir(parents=True)
    for p in (run.labels_path, run.field_path) + ((run.report_json,) if report else ()):
        p.write_bytes(b"x")
    run.write_run(RunInfo(capture="/data/cap", labels="both"))
    return run


def test_file_names_are_the_documented_ones(tmp_path):
    run = RunFolder(tmp_path / "OUT")
    names = [p.relative_to(run.path).as_posix() for p in
             (run.masks_dir, run.mask_path("000"), run.labels_path, run.report_json, run.report_html,
              run.mesh_path(), run.mesh_path("glb"), run.field_path, run.run_path)]
    assert names == ["masks", "masks/000.png", "labels.h5", "report.json", "report.html", "mesh.ply", "mesh.glb",
                     "field.pt", "run.json"]


def test_finished_means_every_file_of_an_expand(tmp_path):
    run = _finished(tmp_path / "out")
    assert run.is_finished() and not run.is_finished(report=True)
    run.check_finished()
    with pytest.raises(RunFolderError, match=r"report\.json: not found \(.* is not a finished labelsynth expand output\)"):
        run.check_finished(report=True)
    run.labels_path.unlink()
    assert not run.is_finished()
    partial = tmp_path / "half.partial"
    partial.mkdir()
    for out, message in ((tmp_path / "half", "not finished (only"), (partial, "an unfinished expand"),
                         (tmp_path / "nowhere", "not found (expected the output folder of labelsynth expand)"),
                         (run.field_path, "not a folder")):
        with pytest.raises(RunFolderError) as err:
            RunFolder(out).check_finished()
        assert str(err.value).startswith(f"{out}: ") and message in str(err.value)


def test_run_json_round_trips_in_its_documented_layout(tmp_path):
    info = RunInfo(capture="/data/cap", labels="annotations", recipe={"name": "fast"}, annotated_frames=["a", "b"],
                   device="cpu", seed=3, seconds={"geometry": 2.0, "render": 1.0}, geometry={"init_shape": "plane"},
                   semantic={"iterations": 5}, report_seconds={"mesh": 0.5})
    run = RunFolder(tmp_path)
    run.write_run(info)
    data = json.loads(run.run_path.read_text())
    assert list(data) == ["version", "capture", "labels", "annotated_frames", "recipe", "device", "seed", "seconds",
                          "geometry", "semantic", "report_seconds"]
    back = run.read_run()
    assert back == info and back.total_seconds == 3.0
    bare = RunInfo.from_json({"capture": "/c", "labels": "both"}, "x")  # what older runs may lack is defaulted
    assert bare.seed == 0 and bare.annotated_frames is None and bare.report_seconds is None
    assert bare.geometry_from is None
    reused = RunInfo(capture="/c", labels="both", geometry_from="/runs/a/field.pt")  # expand --geometry
    run.write_run(reused)
    assert json.loads(run.run_path.read_text())["geometry_from"] == "/runs/a/field.pt" and run.read_run() == reused


@pytest.mark.parametrize("text, problem", [
    ("[1, 2]", "expected a JSON object"),
    ("{}", "no 'capture'"),
    ('{"capture": "/c", "labels": "all"}', "labels 'all'"),
    ('{"capture": "/c", "labels": "both", "seed": "x"}', "'seed' is not a whole number"),
    ('{"capture": "/c", "labels": "both", "annotated_frames": "a"}', "'annotated_frames' is not a list"),
    ('{"capture": "/c", "labels": "both", "seconds": {"a": "x"}}', "'seconds' is not a mapping of numbers"),
    ('{"capture": "/c", "labels": "both", "recipe": 3}', "'recipe' is not a mapping"),
    ('{"capture": "/c", "labels": "both", "geometry_from": 3}', "'geometry_from' is not a path"),
    ("{not json", "not a labelsynth run file (Expecting property name"),
])
def test_a_foreign_or_broken_run_json_is_one_line(tmp_path, text, problem):
    run = RunFolder(tmp_path)
    run.run_path.write_text(text)
    with pytest.raises(RunFolderError) as err:
        run.read_run()
    msg = str(err.value)
    assert msg.startswith(f"{run.run_path}: not a labelsynth run file") and problem in msg and "\n" not in msg


def test_the_report_summary_reader_forgives(tmp_path):
    run = RunFolder(tmp_path)
    assert run.read_report_summary() == {}
    run.report_json.write_text("[]")
    assert run.read_report_summary() == {}
    run.report_json.write_text(json.dumps({"summary": {"flagged": ["a"]}}))
    assert run.read_report_summary() == {"flagged": ["a"]}


def test_a_field_fits_only_the_capture_it_was_fitted_to(tmp_path):
    from types import SimpleNamespace

    import numpy as np

    from labelsynth.capture.model import SceneNormalization
    from labelsynth.classes import ClassInfo, ClassMap

    run = RunFolder(tmp_path / "out")
    norm = SceneNormalization(center=np.zeros(3), scale=1.0)
    capture = SimpleNamespace(root=tmp_path / "cap", classes=ClassMap.default(), normalization=norm)
    fitted = SimpleNamespace(head=object(), classes=ClassMap.default(), normalization=norm)
    run.check_fits(fitted, capture)
    geometry_only = SimpleNamespace(head=None, classes=ClassMap.default(), normalization=norm)
    run.check_fits(geometry_only, capture, need_head=False)  # what `expand --geometry` will hand over
    with pytest.raises(RunFolderError, match=r"field\.pt: the field has no semantic head"):
        run.check_fits(geometry_only, capture)
    moved = SimpleNamespace(head=object(), classes=ClassMap.default(),
                            normalization=SceneNormalization(center=np.ones(3), scale=1.0))
    with pytest.raises(RunFolderError, match="its cameras are not those the field was fitted to"):
        run.check_fits(moved, capture)
    two = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "wound", (255, 0, 0), True)))
    with pytest.raises(RunFolderError, match="its class table differs from the field's"):
        run.check_fits(SimpleNamespace(head=object(), classes=two, normalization=norm), capture)


def test_what_a_run_read_is_recorded_and_compared(tmp_path):
    """label_inputs (decoded masks) and what changed; an older run.json's geometry_inputs are
    ignored (the images and cameras a geometry was fitted on are field.pt's ``fitted_on``)."""
    import shutil

    import cv2
    import numpy as np

    from labelsynth.capture import load_capture
    from labelsynth.geometry.config import GeometryConfig
    from labelsynth.geometry.fingerprint import GeometryChanged, GeometryFingerprint, require_unchanged
    from labelsynth.rundir import changed_label_inputs, label_inputs

    from .capture.test_capture_support import capture_with_annotations

    cap_dir = capture_with_annotations(tmp_path / "cap", {})
    first = load_capture(cap_dir)
    name, size = first.frames[0].name, first.frames[0].size
    mask = np.zeros((size[1], size[0]), np.uint8)
    mask[2:6, 2:9] = 1
    cv2.imwrite(str(cap_dir / "annotations" / f"{name}.png"), mask)
    cap = load_capture(cap_dir)
    info = RunInfo(capture=str(cap_dir), labels="annotations", label_inputs=label_inputs(cap))
    run = RunFolder(tmp_path / "out")
    run.path.mkdir()
    run.write_run(info)
    back = run.read_run()
    assert back == info
    assert back.label_inputs == {"annotations": {name: back.label_inputs["annotations"][name]}, "predictions": {}}
    # a run.json of an earlier version with geometry_inputs: read, the key ignored
    data = json.loads(run.run_path.read_text())
    data["geometry_inputs"] = {"images": {name: "0" * 64}, "cameras": {name: "0" * 64}}
    run.run_path.write_text(json.dumps(data))
    assert run.read_run() == info and "geometry_inputs" not in info.to_json()
    fitted_on = GeometryFingerprint.of(cap, GeometryConfig(), 0)
    require_unchanged(fitted_on, cap, where="field.pt")  # the same capture fits
    # the same ids saved as a palette PNG: the same mask; another id: changed; a new mask: added
    from PIL import Image

    pal = Image.fromarray(mask, mode="P")
    pal.putpalette([0, 0, 0, 200, 40, 40] + [0] * 762)
    pal.save(cap_dir / "annotations" / f"{name}.png")
    assert changed_label_inputs(back.label_inputs, label_inputs(load_capture(cap_dir))) == []
    mask[0, 0] = 2
    cv2.imwrite(str(cap_dir / "annotations" / f"{name}.png"), mask)
    other = cap.frames[1].name
    cv2.imwrite(str(cap_dir / "annotations" / f"{other}.png"), mask)
    assert changed_label_inputs(back.label_inputs, label_inputs(load_capture(cap_dir))) == [
        f"annotations/{name}", f"annotations/{other}"]
    assert changed_label_inputs(None, {"annotations": {"a": "x"}}) == ["annotations/a"]
    # a changed image is refused in one line naming the frame
    img = cap_dir / "images" / f"{cap.frames[2].name}.png"
    shutil.copy(cap_dir / "images" / f"{cap.frames[3].name}.png", img)
    with pytest.raises(GeometryChanged, match=rf"images changed since .* \(images: {cap.frames[2].name} differs\)"
                       ) as err:
        require_unchanged(fitted_on, load_capture(cap_dir), where="field.pt")
    assert "\n" not in str(err.value)


def test_a_run_caught_between_its_two_renames_says_so(tmp_path):
    run = _finished(tmp_path / "out.previous")
    with pytest.raises(RunFolderError, match=r"out: not found, but .*out\.previous holds the run it was replacing"):
        RunFolder(tmp_path / "out").check_finished()
    assert run.is_finished()
