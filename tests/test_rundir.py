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


@pytest.mark.parametrize("text, problem", [
    ("[1, 2]", "expected a JSON object"),
    ("{}", "no 'capture'"),
    ('{"capture": "/c", "labels": "all"}', "labels 'all'"),
    ('{"capture": "/c", "labels": "both", "seed": "x"}', "'seed' is not a whole number"),
    ('{"capture": "/c", "labels": "both", "annotated_frames": "a"}', "'annotated_frames' is not a list"),
    ('{"capture": "/c", "labels": "both", "seconds": {"a": "x"}}', "'seconds' is not a mapping of numbers"),
    ('{"capture": "/c", "labels": "both", "recipe": 3}', "'recipe' is not a mapping"),
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
