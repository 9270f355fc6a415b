"""Every option of a run is checked before any training and before OUT or OUT.partial exist:
one line on stderr, exit code 2, no traceback (``options.ExpandOptions``; expand and batch)."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from labelsynth.cli import app
from labelsynth.errors import LabelsynthError
from labelsynth.options import DeviceChoice, ExpandOptions, LabelMode, MeshFormat, OptionError

from .scenes import make_patch_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root, _ = make_patch_capture(tmp_path_factory.mktemp("options"), frames=4, size=24)
    return root


@pytest.fixture
def no_training(monkeypatch):
    """Any training step reached fails the test loudly (not with exit code 2)."""
    import labelsynth.pipeline as pipeline

    def reached(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(pipeline, "fit_geometry", reached)


def _recipe_files(tmp_path):
    listed = tmp_path / "listed.yaml"
    listed.write_text("- geometry: {iterations: 5}\n")
    negative = tmp_path / "negative.yaml"
    negative.write_text("geometry:\n  iterations: -5\n")
    folder = tmp_path / "folder.d"
    folder.mkdir()
    return listed, negative, folder


BAD_EXPAND = [
    (["--mesh-format", "obj"], "--mesh-format must be one of ply, glb, not 'obj'"),
    (["--device", "cuda"], "--device cuda was asked for but torch sees no CUDA device"),
    (["--device", "tpu"], "--device must be one of auto, cpu, cuda, not 'tpu'"),
    (["--labels", "everything"], "--labels must be one of annotations, predictions, both, not 'everything'"),
    (["--mm-per-unit", "0"], "--mm-per-unit must be a finite number > 0, not 0.0"),
    (["--mm-per-unit", "-2"], "--mm-per-unit must be a finite number > 0, not -2.0"),
    (["--mm-per-unit", "nan"], "--mm-per-unit must be a finite number > 0, not nan"),
    (["--seed", "-1"], "--seed must be a whole number in 0..4294967295, not -1"),
    (["--annotated-frames", "every:0"], "--annotated-frames: 'every:0': expected a whole number >= 1 after ':'"),
    (["--annotated-frames", "spread:x"], "--annotated-frames: 'spread:x': expected a whole number >= 1 after ':'"),
    (["--annotated-frames", "a,,b"], "--annotated-frames: empty frame name in 'a,,b'"),
    (["--annotated-frames", "view_00,view_99"], "--annotated-frames: no frame named 'view_99'"),
    (["--set", "geometry.iterations=-5"], "fast.yaml.geometry.iterations: -5 is not >= 1"),
    (["--set", "semantic.dropout=1"], "fast.yaml.semantic.dropout: 1.0 is not in [0, 1)"),
    (["--set", "semantic.lr=["], "--set semantic.lr=[: the value is not valid YAML"),
    (["--set", "semantic.lr"], "--set semantic.lr: not of the form section.key=value"),
    (["--set", "semantic.nope=1"], "fast.yaml.semantic: unknown key 'nope'"),
    (["--recipe", "nope"], "--recipe 'nope': unknown recipe"),
    (["--recipe", "{listed}"], "{listed}: a recipe is a mapping of sections"),
    (["--recipe", "{negative}"], "negative.yaml.geometry.iterations: -5 is not >= 1"),
    (["--recipe", "{folder}"], "{folder}: is a folder, not a recipe file"),
]


@pytest.mark.parametrize("args, message", BAD_EXPAND, ids=[" ".join(a) for a, _ in BAD_EXPAND])
def test_bad_expand_options_fail_at_once(capture, tmp_path, no_training, args, message):
    listed, negative, folder = _recipe_files(tmp_path)
    names = {"listed": listed, "negative": negative, "folder": folder}
    args = [a.format(**names) for a in args]
    message = message.format(**names)
    out = tmp_path / "out"
    base = ["expand", str(capture), "--out", str(out), "--labels", "annotations", "--recipe", "fast"]
    res = CliRunner().invoke(app, base + args)
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"labelsynth: error: {message}"), lines
    assert "Traceback" not in res.output
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_the_same_checks_in_the_library(capture, tmp_path, no_training):
    from labelsynth.pipeline import expand

    with pytest.raises(OptionError, match="--mesh-format must be one of ply, glb"):
        expand(capture, tmp_path / "o", recipe="fast", mesh_format="obj")
    with pytest.raises(LabelsynthError, match="geometry.iterations: -5 is not >= 1"):
        expand(capture, tmp_path / "o", ExpandOptions(recipe="fast", overrides=["geometry.iterations=-5"]))
    with pytest.raises(TypeError):
        expand(capture, tmp_path / "o", no_such_option=1)
    assert not (tmp_path / "o").exists() and not (tmp_path / "o.partial").exists()


def test_options_are_typed_choices():
    opts = ExpandOptions(labels="Both", device="CPU", mesh_format="glb", mm_per_unit=2)
    assert opts.labels is LabelMode.BOTH and opts.device is DeviceChoice.CPU and opts.mesh_format is MeshFormat.GLB
    assert opts.labels == "both" and f"{opts.mesh_format}" == "glb" and opts.mm_per_unit == 2.0
    assert opts.replace(device="auto").device is DeviceChoice.AUTO and opts.device is DeviceChoice.CPU
    with pytest.raises(OptionError, match="--labels must be one of"):
        opts.replace(labels="all")
    assert opts.marker_options() == {"labels": "both", "seed": 0, "annotated_frames": None, "report": True,
                                     "mesh_format": "glb", "mm_per_unit": 2.0}


BAD_BATCH = [
    (["--mesh-format", "obj"], "--mesh-format must be one of ply, glb"),
    (["--set", "geometry.iterations=-5"], "fast.yaml.geometry.iterations: -5 is not >= 1"),
    (["--annotated-frames", "every:0"], "--annotated-frames: 'every:0': expected a whole number >= 1"),
    (["--labels", "all"], "--labels must be one of annotations, predictions, both, not 'all'"),
    (["--set", "render.mesh_resolution=["], "--set render.mesh_resolution=[: the value is not valid YAML"),
]


@pytest.mark.parametrize("args, message", BAD_BATCH, ids=[" ".join(a) for a, _ in BAD_BATCH])
def test_bad_batch_options_fail_before_ray_and_before_out(capture, tmp_path, args, message):
    out = tmp_path / "batch"
    res = CliRunner().invoke(app, ["batch", str(capture.parent), "--out", str(out), "--recipe", "fast", *args])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"labelsynth: error: {message}"), lines
    assert not out.exists()
