"""The saved field (conftest.tiny_expanded's field.pt) reloads and renders the masks it wrote;
field.pt is read without unpickling code (a tampered, truncated or foreign file is one line),
and a file from before format version 2 is converted."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from labelsynth.capture import load_capture
from labelsynth.render.renderer import FieldRenderer
from labelsynth.rundir import FIELD_VERSION, RunFolder, RunFolderError, load_field, save_field

# All tests using the shared tiny run go to one xdist worker, so it is fitted once.
pytestmark = pytest.mark.xdist_group("tiny_expanded")


def _masks_of(fitted, capture) -> dict[str, np.ndarray]:
    view = FieldRenderer(fitted)
    return {n: view.render(c).mask for n, c in zip(capture.names, capture.unit_cameras())}


def test_the_saved_field_re_renders_exactly_the_masks_it_wrote(tiny_expanded):
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    fitted = load_field(run.out / "field.pt", torch.device("cpu"))
    saved = RunFolder(run.out).read_masks(cap.names)
    again = _masks_of(fitted, cap)
    assert all(np.array_equal(again[n], saved[n]) for n in cap.names)


def test_a_saved_and_loaded_field_renders_the_same_masks(tiny_expanded, tmp_path):
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    fitted = load_field(run.out / "field.pt")
    path = save_field(fitted, tmp_path / "again.pt")
    assert not (tmp_path / "again.pt.partial").exists()
    again = load_field(path)
    first, second = _masks_of(fitted, cap), _masks_of(again, cap)
    assert all(np.array_equal(first[n], second[n]) for n in cap.names)
    # the file is tensors plus JSON: it loads with torch's weights-only reader
    state = torch.load(path, weights_only=True)
    meta = json.loads(state["labelsynth_field"])
    assert meta["format"] == "labelsynth-field" and meta["version"] == FIELD_VERSION and meta["has_head"]
    assert all(isinstance(v, torch.Tensor) for v in state["tensors"].values())


def test_a_geometry_only_field_round_trips(tiny_expanded, tmp_path):
    fitted = load_field(tiny_expanded.out / "field.pt").with_head(None)
    again = load_field(save_field(fitted, tmp_path / "geometry.pt"))
    assert again.head is None
    with pytest.raises(Exception, match="no semantic head"):
        FieldRenderer(again).render(load_capture(tiny_expanded.capture_dir).unit_cameras()[0])


def _old_format(path) -> dict:
    """The pre-version-2 layout: a pickled dict of state dicts and plain values."""
    state = torch.load(path, weights_only=True)
    meta, tensors = json.loads(state["labelsynth_field"]), state["tensors"]
    part = lambda p: {k[len(p) + 1:]: v for k, v in tensors.items() if k.startswith(p + ".")}  # noqa: E731
    return {"sdf": part("sdf"), "head": part("head"), "grid": {**meta["state"]["grid"], **part("grid")},
            "classes": meta["classes"], "normalization": meta["normalization"], "recipe": meta["recipe"]}


def test_an_old_format_field_is_converted_and_renders_the_same(tiny_expanded, tmp_path):
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    torch.save(_old_format(run.out / "field.pt"), tmp_path / "old.pt")
    old = load_field(tmp_path / "old.pt")
    new = load_field(run.out / "field.pt")
    first, second = _masks_of(old, cap), _masks_of(new, cap)
    assert all(np.array_equal(first[n], second[n]) for n in cap.names)


def test_a_field_saved_before_the_outer_background_still_loads(tiny_expanded, tmp_path):
    run = tiny_expanded
    state = _old_format(run.out / "field.pt")
    state["sdf"] = {k: v for k, v in state["sdf"].items() if not k.startswith("outer.")}
    del state["sdf"]["inv_s_floor"]  # from before the sharpness floor too
    del state["recipe"]["geometry"]["sdf"]["background"], state["recipe"]["geometry"]["sdf"]["outer"]
    torch.save(state, tmp_path / "old.pt")
    fitted = load_field(tmp_path / "old.pt", torch.device("cpu"))
    assert fitted.sdf.outer is None and fitted.recipe.geometry.sdf.background == "env"
    cam = load_capture(run.capture_dir).unit_cameras()[0]
    assert FieldRenderer(fitted).render(cam).mask.shape == (cam.height, cam.width)


class _Writes:
    def __init__(self, target) -> None:
        self.target = str(target)

    def __reduce__(self):
        import pathlib

        return (pathlib.Path(self.target).write_text, ("pwned",))


def _tampered(path, target) -> None:
    """A field.pt whose unpickling (with weights_only=False) writes ``target``."""
    state = torch.load(path, weights_only=True)
    state["payload"] = _Writes(target)
    torch.save(state, path)


def test_a_tampered_field_runs_nothing_on_load(tiny_expanded, tmp_path):
    path, target = tmp_path / "field.pt", tmp_path / "pwned.txt"
    shutil.copy(tiny_expanded.out / "field.pt", path)
    _tampered(path, target)
    torch.load(path, weights_only=False)  # the payload works when unpickled without restriction...
    assert target.read_text() == "pwned"
    target.unlink()
    with pytest.raises(RunFolderError) as err:  # ...and labelsynth never does that
        load_field(path)
    assert not target.exists()
    msg = str(err.value)
    assert msg.startswith(f"{path}: refused") and "labelsynth expand" in msg and "\n" not in msg


def _cli_lines(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.strip()]


@pytest.mark.parametrize("command", [["report", "--no-loo"], ["augment", "--views", "2"]])
def test_report_and_augment_refuse_a_tampered_field(tiny_expanded, tmp_path, command):
    """A field.pt altered to write a file when unpickled: neither command runs it (exit 2, one line)."""
    from typer.testing import CliRunner

    from labelsynth.cli import app

    out, target = tmp_path / "out", tmp_path / "pwned.txt"
    shutil.copytree(tiny_expanded.out, out)
    _tampered(out / "field.pt", target)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    res = CliRunner().invoke(app, [command[0], str(out), *command[1:], "--device", "cpu"])
    assert res.exit_code == 2, res.output
    assert not target.exists()
    lines = _cli_lines(res)
    assert len(lines) == 1 and lines[0].startswith(f"labelsynth: error: {out / 'field.pt'}: refused"), lines
    assert "Traceback" not in res.output
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before  # nothing written in OUT


@pytest.mark.parametrize("command", [["report", "--no-loo"], ["augment", "--views", "2"]])
def test_a_truncated_field_is_one_line(tiny_expanded, tmp_path, command):
    from typer.testing import CliRunner

    from labelsynth.cli import app

    out = tmp_path / "out"
    shutil.copytree(tiny_expanded.out, out)
    data = (out / "field.pt").read_bytes()
    (out / "field.pt").write_bytes(data[: len(data) // 2])
    res = CliRunner().invoke(app, [command[0], str(out), *command[1:], "--device", "cpu"])
    assert res.exit_code == 2, res.output
    lines = _cli_lines(res)
    assert len(lines) == 1 and lines[0].startswith(f"labelsynth: error: {out / 'field.pt'}: truncated or not a "
                                                   "labelsynth field file"), lines
    assert "Traceback" not in res.output


def test_foreign_empty_and_newer_files_are_one_line(tiny_expanded, tmp_path):
    cases = {}
    cases["empty.pt"] = b""
    cases["text.pt"] = b"not a torch file at all\n"
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    torch.save({"weight": torch.zeros(3)}, tmp_path / "state_dict.pt")
    torch.save([1, 2, 3], tmp_path / "list.pt")
    state = torch.load(tiny_expanded.out / "field.pt", weights_only=True)
    meta = json.loads(state["labelsynth_field"])
    torch.save({**state, "labelsynth_field": json.dumps({**meta, "version": FIELD_VERSION + 1})}, tmp_path / "newer.pt")
    torch.save({**state, "labelsynth_field": "{not json"}, tmp_path / "badjson.pt")
    sdf = {k: v for k, v in state["tensors"].items() if k != "sdf.encoding.table"}
    torch.save({**state, "tensors": sdf}, tmp_path / "missing.pt")
    bad_recipe = {**meta, "recipe": {**meta["recipe"], "geometry": {**meta["recipe"]["geometry"], "iterations": -1}}}
    torch.save({**state, "labelsynth_field": json.dumps(bad_recipe)}, tmp_path / "badrecipe.pt")
    expected = {
        "empty.pt": "truncated or not a labelsynth field file",
        "text.pt": "not a labelsynth field file",
        "state_dict.pt": "not a labelsynth field file (no field description in it)",
        "list.pt": "not a labelsynth field file (no field description in it)",
        "newer.pt": "written by a newer labelsynth",
        "badjson.pt": "not a labelsynth field file (its description is not readable)",
        "missing.pt": "its tensors do not fit the recipe it records",
        "badrecipe.pt": "recipe.geometry.iterations: -1 is not >= 1",
        "absent.pt": "not found",
    }
    for name, start in expected.items():
        with pytest.raises(RunFolderError if name != "badrecipe.pt" else Exception) as err:
            load_field(tmp_path / name)
        msg = str(err.value)
        assert msg.startswith(f"{tmp_path / name}: ") and start in msg and "\n" not in msg, (name, msg)


def test_the_embree_cast_agrees_with_trimesh_and_its_barycentric_coordinates_give_the_hit():
    import trimesh

    from labelsynth.render.surface import SurfaceCaster

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    rng = np.random.default_rng(0)
    origins = rng.normal(size=(400, 3))
    origins = 2.0 * origins / np.linalg.norm(origins, axis=1, keepdims=True)
    targets = rng.uniform(-0.7, 0.7, size=(400, 3))  # some rays miss the sphere
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit, points, faces, bary = SurfaceCaster(mesh).cast(origins, dirs)
    from trimesh.ray.ray_pyembree import RayMeshIntersector  # trimesh's wrapper: float64 plane hits

    slow = RayMeshIntersector(mesh)
    loc, ray, tri = slow.intersects_location(origins, dirs, multiple_hits=False)
    expected = np.zeros(len(origins), bool)
    expected[ray] = True
    assert 0 < hit.sum() < len(hit)
    assert np.array_equal(hit, expected)
    assert np.array_equal(faces[ray], tri) and np.all(faces[~hit] == -1)
    assert np.abs(points[ray] - loc).max() < 1e-5
    assert np.allclose(bary[hit].sum(1), 1.0) and bary[hit].min() > -1e-5
    corners = mesh.vertices[mesh.faces[faces[hit]]]
    assert np.allclose(np.einsum("nk,nkd->nd", bary[hit], corners), points[hit])


def test_field_pt_keeps_the_surface_it_was_rendered_with(tiny_expanded, tmp_path, monkeypatch):
    """expand stores the extracted surface in field.pt: a later render (relabel, report) reads it
    instead of running marching cubes again, and renders the same masks; a stored surface that
    is not a mesh is one line."""
    import labelsynth.render.renderer as renderer

    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    fitted = load_field(run.out / "field.pt")
    assert fitted.surface is not None and fitted.surface.resolution == fitted.recipe.render.mesh_resolution
    saved = RunFolder(run.out).read_masks(cap.names)

    def extract(*args, **kwargs):
        raise AssertionError("marching cubes ran again")

    monkeypatch.setattr(renderer, "extract_mesh", extract)
    again = _masks_of(fitted, cap)
    assert all(np.array_equal(again[n], saved[n]) for n in cap.names)
    monkeypatch.undo()
    # another mesh resolution: extracted, not the stored one
    import dataclasses

    other = dataclasses.replace(fitted.recipe.render, mesh_resolution=fitted.surface.resolution // 2)
    view = FieldRenderer(dataclasses.replace(fitted, recipe=dataclasses.replace(fitted.recipe, render=other)))
    assert len(view.mesh().vertices) != len(fitted.surface.vertices)
    # faces pointing past the vertices: refused in one line
    state = torch.load(run.out / "field.pt", weights_only=True)
    state["tensors"]["surface.faces"][0, 0] = len(state["tensors"]["surface.vertices"]) + 5
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(RunFolderError, match=r"bad\.pt: its stored surface is not a mesh of its field") as err:
        load_field(tmp_path / "bad.pt")
    assert "\n" not in str(err.value)
