"""`expand --geometry`: the masks of a full expand from its own geometry, and a one-line refusal
(before anything is written or fitted) when the images, cameras, geometry recipe or seed changed."""

from __future__ import annotations

import json
import shutil

import cv2
import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth.capture import load_capture
from labelsynth.cli import app
from labelsynth.geometry.config import GeometryConfig
from labelsynth.geometry.fingerprint import GeometryChanged, GeometryFingerprint, require_unchanged
from labelsynth.pipeline import expand
from labelsynth.rundir import RunFolder, load_field

from .conftest import TINY_OVERRIDES

pytestmark = pytest.mark.xdist_group("tiny_expanded")

SET = [a for o in TINY_OVERRIDES for a in ("--set", o)]


def test_the_reused_geometry_gives_the_masks_of_the_full_expand(tiny_expanded, tmp_path):
    """expand A (the shared tiny run, both stages); expand B with --geometry A: the same masks,
    byte for byte, and run.json says where the geometry came from."""
    run = tiny_expanded
    out = tmp_path / "reused"
    result = expand(run.capture_dir, out, labels="annotations", recipe="fast", device="cpu", overrides=TINY_OVERRIDES,
                    report=False, geometry=run.out, progress=False)
    full, reused = RunFolder(run.out), RunFolder(out)
    for name in result.frames:
        assert reused.mask_path(name).read_bytes() == full.mask_path(name).read_bytes(), name
    with h5py.File(full.labels_path) as a, h5py.File(reused.labels_path) as b:
        assert np.array_equal(a["masks"][:], b["masks"][:]) and np.array_equal(a["confidence"][:], b["confidence"][:])
    info = reused.read_run()
    assert info.geometry_from == str(full.field_path.resolve())
    assert info.seconds["geometry"] < full.read_run().seconds["geometry"]  # loaded and checked, not fitted
    assert json.loads(reused.run_path.read_text())["geometry_from"] == info.geometry_from
    assert load_field(reused.field_path).fitted_on == load_field(full.field_path).fitted_on
    assert {p: p.read_bytes() for p in run.capture_dir.rglob("*") if p.is_file()} == run.capture_bytes


def _changed_image(capture):
    path = capture / "images" / "frame_002.png"
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    img[0, 0] = 255 - img[0, 0]
    cv2.imwrite(str(path), img)
    return "images changed since the geometry in", "frame_002 differs"


def _changed_camera(capture):
    path = capture / "transforms.json"
    data = json.loads(path.read_text())
    data["frames"][5]["transform_matrix"][0][3] += 0.01
    path.write_text(json.dumps(data))
    return "cameras changed since the geometry in", "differs"


def _added_frame(capture):
    path = capture / "transforms.json"
    data = json.loads(path.read_text())
    extra = dict(data["frames"][0], file_path="images/frame_999.png")
    shutil.copy(capture / "images" / "frame_000.png", capture / "images" / "frame_999.png")
    data["frames"].append(extra)
    path.write_text(json.dumps(data))
    return "images and cameras changed since the geometry in", "1 frame added (frame_999); cameras: scene box changed"


CHANGES = {
    "image": (_changed_image, []),
    "camera": (_changed_camera, []),
    "added frame": (_added_frame, []),
    "geometry recipe": (None, ["--set", "geometry.iterations=260"]),
    "seed": (None, ["--seed", "2"]),
    "two at once": (_changed_image, ["--seed", "2"]),
}


@pytest.mark.parametrize("kind", list(CHANGES))
def test_a_changed_input_is_refused_before_anything_is_written(tiny_expanded, tmp_path, no_fitting, kind):
    change, extra = CHANGES[kind]
    capture = tmp_path / "capture"
    shutil.copytree(tiny_expanded.capture_dir, capture)
    expected = {"geometry recipe": ("geometry recipe changed since the geometry in", "geometry.iterations 250 -> 260"),
                "seed": ("seed changed since the geometry in", "seed: 0 -> 2"),
                "two at once": ("images and seed changed since the geometry in", "frame_002 differs; seed: 0 -> 2")}.get(kind)
    if change is not None:
        found = change(capture)
        expected = expected or found
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["expand", str(capture), "--out", str(out), "--geometry", str(tiny_expanded.out),
                                   "--labels", "annotations", "--recipe", "fast", "--device", "cpu", *SET, *extra])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"labelsynth: error: {capture}: {expected[0]} {tiny_expanded.out / 'field.pt'}"), lines
    assert expected[1] in lines[0] and "Traceback" not in res.output
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_a_geometry_path_that_is_not_one(tiny_expanded, tmp_path, no_fitting):
    empty = tmp_path / "empty"
    empty.mkdir()
    partial = tmp_path / "half.partial"
    partial.mkdir()
    cases = [(tmp_path / "nowhere", "not found (expected the output folder of labelsynth suggest or expand"),
             (empty, "holds no field.pt"), (partial, "an unfinished run"), (tmp_path / "half", "not finished (only")]
    for path, message in cases:
        res = CliRunner().invoke(app, ["expand", str(tiny_expanded.capture_dir), "--out", str(tmp_path / "out"),
                                       "--geometry", str(path), "--labels", "annotations", "--recipe", "fast", *SET])
        assert res.exit_code == 2, res.output
        assert res.stderr.strip().startswith(f"labelsynth: error: --geometry {path}: {message}"), res.stderr
        assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()


def test_fingerprint_api_for_other_commands(tiny_expanded):
    """What a command reusing a fitted field calls: images and cameras compared, recipe and seed
    only when given; a field from before fingerprints cannot be vouched for."""
    capture = load_capture(tiny_expanded.capture_dir)
    fitted = load_field(RunFolder(tiny_expanded.out).field_path)
    stored = fitted.fitted_on
    current = require_unchanged(stored, capture, where="field.pt")
    assert current.images == stored.images and current.cameras == stored.cameras
    require_unchanged(stored, capture, where="field.pt", geometry=fitted.recipe.geometry, seed=0)
    with pytest.raises(GeometryChanged, match=r"geometry recipe changed .* \(geometry recipe: "
                       r"geometry.cos_anneal_iters 150 -> 300, geometry.iterations 250 -> 1200, .* and \d+ more\)"):
        require_unchanged(stored, capture, where="field.pt", geometry=GeometryConfig(), seed=0)
    with pytest.raises(GeometryChanged, match="field.pt: holds no record of what its geometry was fitted on"):
        require_unchanged(None, capture, where="field.pt")
    assert GeometryFingerprint.from_json(stored.to_json(), "x") == stored
    with pytest.raises(GeometryChanged, match="x: its record of what the geometry was fitted on is not readable"):
        GeometryFingerprint.from_json({**stored.to_json(), "seed": "zero"}, "x")


def test_a_record_from_before_a_recipe_key_existed_matches_that_keys_default(tiny_expanded):
    """A geometry fitted before ``geometry.sdf.plane_normal`` existed was fitted facing the views (the
    default): its record lacks the key, and reusing it needs no refit unless the key is set otherwise."""
    import copy
    import dataclasses

    capture = load_capture(tiny_expanded.capture_dir)
    fitted = load_field(RunFolder(tiny_expanded.out).field_path)
    older = copy.deepcopy(fitted.fitted_on.geometry)
    del older["sdf"]["plane_normal"]
    del older["opacity_warmup"]
    stored = dataclasses.replace(fitted.fitted_on, geometry=older)
    require_unchanged(stored, capture, where="field.pt", geometry=fitted.recipe.geometry, seed=0)
    turned = copy.deepcopy(fitted.recipe.geometry)
    turned.sdf.plane_normal = "camera-axes"
    with pytest.raises(GeometryChanged, match=r"geometry.sdf.plane_normal 'views' -> 'camera-axes'"):
        require_unchanged(stored, capture, where="field.pt", geometry=turned, seed=0)
