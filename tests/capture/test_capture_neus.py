"""The NeuS / IDR layout (image/, mask/, cameras_sphere.npz) and ``annotated_frames``.

The captures here are made up (tiny npz files written by the tests): DTU itself may not enter
the repository.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth.cameras import c2w_gl_to_w2c_cv, look_at
from labelsynth.capture import CaptureError, check_capture, load_capture, select_frames
from labelsynth.cli import app
from labelsynth.errors import LabelsynthError

from .test_capture_support import H, W, make_capture, snapshot, write_image

K = np.array([[30.0, 0.0, 15.5], [0.0, 31.0, 12.25], [0.0, 0.0, 1.0]])
SCALE, OFFSET = 2.5, np.array([1.0, -2.0, 0.5])
N = 4


def neus_poses(n: int = N) -> list[np.ndarray]:
    """OpenGL camera-to-world matrices around OFFSET (the unit sphere's centre), all different."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        eye = OFFSET + SCALE * np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0 + 0.2 * i])
        poses.append(look_at(eye, OFFSET))
    return poses


def projection(c2w: np.ndarray, k: np.ndarray = K) -> np.ndarray:
    """P = K [R|t] (3x4) composed by hand from an OpenGL camera-to-world."""
    w2c = c2w_gl_to_w2c_cv(c2w)
    return k @ w2c[:3, :4]


def scale_mat() -> np.ndarray:
    s = np.eye(4)
    s[:3, :3] *= SCALE
    s[:3, 3] = OFFSET
    return s


def object_mask(i: int) -> np.ndarray:
    """0/255, a vertical bar at a column that differs per frame (to see the pairing)."""
    m = np.zeros((H, W), dtype=np.uint8)
    m[4:20, 4 + 6 * i: 8 + 6 * i] = 255
    return m


def make_neus(root: Path, n: int = N, masks: bool = True, mats: dict | None = None, drop: tuple = ()) -> Path:
    """A NeuS capture: image/00000i.png, mask/00i.png (frame 2's single-channel), cameras_sphere.npz.

    Frame 1's P is multiplied by -2 (a projection is defined up to scale, sign included).
    ``mats`` replaces or adds npz entries; ``drop`` removes keys.
    """
    data = {}
    for i, c2w in enumerate(neus_poses(n)):
        write_image(root / "image" / f"{i:06d}.png", seed=i)
        wm = np.eye(4)
        wm[:3] = projection(c2w) * (-2.0 if i == 1 else 1.0)
        data[f"world_mat_{i}"] = wm
        data[f"scale_mat_{i}"] = scale_mat()
        data[f"camera_mat_{i}"] = np.eye(4)  # ignored, as in NeuS
        data[f"world_mat_inv_{i}"] = np.linalg.inv(wm)
        if masks:
            m = object_mask(i)
            img = m if i == 2 else np.repeat(m[:, :, None], 3, axis=2)
            (root / "mask").mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(root / "mask" / f"{i:03d}.png"), img)
    data.update(mats or {})
    for key in drop:
        data.pop(key)
    np.savez(root / "cameras_sphere.npz", **data)
    (root / "image" / "a").write_bytes(b"x")  # DTU ships such a stray file: not an image
    return root


def one_line_error(root: Path, needle: str, path_part: str, **kwargs) -> str:
    with pytest.raises(CaptureError) as err:
        load_capture(root, **kwargs)
    msg = str(err.value)
    assert "\n" not in msg and needle in msg and path_part in msg, msg
    return msg


# --- cameras, normalisation, classes -------------------------------------------------------
def test_cameras_match_the_projections(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    before = snapshot(root)
    cap = load_capture(root)
    assert snapshot(root) == before  # nothing written
    assert cap.source == "cameras_sphere.npz" and len(cap) == N
    assert cap.names == [f"{i:06d}" for i in range(N)]
    point = OFFSET + np.array([0.3, -0.2, 0.4])
    for i, (frame, c2w) in enumerate(zip(cap.frames, neus_poses())):
        cam = frame.camera
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [30.0, 31.0, 15.5, 12.25], rtol=1e-9)
        np.testing.assert_allclose(cam.c2w, c2w, atol=1e-9)
        P = projection(c2w) * (-2.0 if i == 1 else 1.0)
        uvw = P @ np.append(point, 1.0)
        pixel, depth = cam.project(point[None])
        np.testing.assert_allclose(pixel[0], uvw[:2] / uvw[2], atol=1e-9)
        assert depth[0] > 0


def test_normalization_is_the_scale_mat_and_classes_are_object(tmp_path) -> None:
    cap = load_capture(make_neus(tmp_path / "cap"))
    np.testing.assert_allclose(cap.normalization.center, OFFSET)
    assert cap.normalization.scale == pytest.approx(SCALE)
    # the unit sphere of NeuS is the unit sphere here too: its centre maps to 0
    np.testing.assert_allclose(cap.normalization.to_unit(OFFSET + [SCALE, 0, 0]), [1, 0, 0])
    assert cap.classes.names == ["background", "object"] and list(cap.classes.ids) == [0, 1]


def test_classes_json_replaces_the_two_class_table(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    table = {"classes": [{"id": 0, "name": "background"}, {"id": 1, "name": "statue", "color": [9, 9, 9]}]}
    (root / "classes.json").write_text(json.dumps(table))
    assert load_capture(root).classes.names == ["background", "statue"]
    (root / "classes.json").write_text(json.dumps({"classes": [{"id": 0, "name": "bg"}, {"id": 2, "name": "x"}]}))
    one_line_error(root, "class id 1", "classes.json")


# --- masks ---------------------------------------------------------------------------------
def test_masks_pair_by_sorted_order_and_read_as_0_1(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    cap = load_capture(root)
    assert [f.annotation_path.name for f in cap.frames] == ["000.png", "001.png", "002.png", "003.png"]
    assert cap.has_annotations and not cap.has_predictions
    for i in range(N):  # frame 2's mask is single channel, the others 3-channel
        np.testing.assert_array_equal(cap.load_annotation(i), (object_mask(i) > 0).astype(np.uint8))
    report = check_capture(cap)  # the check reads them through the same mask kind
    assert report.ok, report.problems
    assert report.cached_masks == N
    np.testing.assert_array_equal(cap.load_annotation(3), (object_mask(3) > 0).astype(np.uint8))


def test_without_mask_folder_there_are_no_annotations(tmp_path) -> None:
    cap = load_capture(make_neus(tmp_path / "cap", masks=False))
    assert not cap.has_annotations and cap.mask_kinds == {}


def test_annotations_folder_wins_over_mask(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    (root / "annotations").mkdir()
    assert cv2.imwrite(str(root / "annotations" / "000003.png"), np.ones((H, W), np.uint8))
    with pytest.warns(UserWarning, match="mask/ masks are ignored"):
        cap = load_capture(root)
    assert [f.name for f in cap.frames if f.annotation_path is not None] == ["000003"]
    assert cap.mask_kinds == {}
    np.testing.assert_array_equal(cap.load_annotation(3), np.ones((H, W), np.uint8))


def test_transforms_json_wins_over_the_npz(tmp_path) -> None:
    root = make_capture(tmp_path / "cap")
    make_neus(root)
    assert load_capture(root).source == "transforms.json"


# --- broken inputs: one line naming the file -----------------------------------------------
def _broken_mats() -> list:
    P = projection(neus_poses()[0])
    singular = P.copy()
    singular[:, 2] = singular[:, 0]
    nonuniform = scale_mat()
    nonuniform[1, 1] *= 1.5
    other = scale_mat()
    other[:3, 3] += 0.1
    away = projection(look_at(OFFSET + [0, 0, 5.0], OFFSET + [0, 0, 10.0]))
    skewed = projection(neus_poses()[0], K + [[0, 3.0, 0], [0, 0, 0], [0, 0, 0]])
    engulfing = scale_mat()
    engulfing[:3, :3] *= 20  # a sphere around the cameras: scale_mat_i from another world
    return [
        pytest.param({}, ("world_mat_2",), "missing world_mat_2", id="missing-world-mat"),
        pytest.param({}, ("scale_mat_3",), "missing scale_mat_3", id="missing-scale-mat"),
        pytest.param({"world_mat_4": np.eye(4), "scale_mat_4": scale_mat()}, (), "5 world_mat_i for 4 images",
                     id="more-cameras-than-images"),
        pytest.param({"world_mat_1": np.eye(3)}, (), "shape (3, 3)", id="wrong-shape"),
        pytest.param({"world_mat_1": np.full((4, 4), np.nan)}, (), "non-finite", id="non-finite"),
        pytest.param({"world_mat_1": singular}, (), "singular", id="singular"),
        pytest.param({"world_mat_1": away}, (), "behind", id="looks-away"),
        pytest.param({"world_mat_1": skewed}, (), "skew", id="skew"),
        pytest.param({"scale_mat_2": nonuniform}, (), "uniform scale", id="non-uniform-scale-mat"),
        pytest.param({"scale_mat_2": other}, (), "differs from scale_mat_0", id="scale-mats-differ"),
        pytest.param({f"scale_mat_{i}": engulfing for i in range(N)}, (), "4 of 4 cameras lie inside the unit sphere",
                     id="cameras-inside-the-sphere"),
    ]


@pytest.mark.parametrize("mats,drop,needle", _broken_mats())
def test_bad_npz_is_one_line_naming_it(tmp_path, mats, drop, needle) -> None:
    root = make_neus(tmp_path / "cap", mats=mats, drop=drop)
    msg = one_line_error(root, needle, "cameras_sphere.npz")
    if "world_mat_1" in mats:
        assert "world_mat_1" in msg


def test_small_skew_is_ignored(tmp_path) -> None:
    skewed = projection(neus_poses()[1], K + [[0, 1e-3, 0], [0, 0, 0], [0, 0, 0]])
    cap = load_capture(make_neus(tmp_path / "cap", mats={"world_mat_1": skewed}))
    assert cap.frames[1].camera.fx == pytest.approx(30.0)


def test_corrupt_npz(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    npz = root / "cameras_sphere.npz"
    npz.write_bytes(npz.read_bytes()[:200])
    one_line_error(root, "cannot read", str(npz))
    np.save(root / "plain.npy", np.eye(4))
    (root / "plain.npy").replace(npz)
    one_line_error(root, "not an npz archive", str(npz))


def test_fewer_cameras_than_images(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    write_image(root / "image" / "000004.png", seed=9)
    one_line_error(root, "4 world_mat_i for 5 images", "cameras_sphere.npz")


def test_mask_count_must_match(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    (root / "mask" / "003.png").unlink()
    one_line_error(root, "3 masks for 4 images", str(root / "mask"))


def test_no_image_folder(tmp_path) -> None:
    root = make_neus(tmp_path / "cap")
    (root / "image").rename(root / "frames")
    one_line_error(root, "no image/", str(root))
    (root / "frames").rename(root / "images")  # images/ is accepted too
    assert len(load_capture(root)) == N


# --- annotated_frames ----------------------------------------------------------------------
def _annotated_capture(root: Path, n: int = 6, annotated=None) -> Path:
    make_capture(root, n=n)
    (root / "annotations").mkdir()
    for i in range(n) if annotated is None else annotated:
        assert cv2.imwrite(str(root / "annotations" / f"frame_{i:03d}.png"), np.full((H, W), i % 2, np.uint8))
    return root


def _taught(cap) -> list[str]:
    return [f.name for f in cap.frames if f.annotation_path is not None]


@pytest.mark.parametrize(
    "spec,expected",
    [
        (None, [0, 1, 2, 3, 4, 5]),
        ("frame_001,frame_004", [1, 4]),
        ("0, 5", [0, 5]),
        ("frame_003,1,frame_003", [1, 3]),
        (["frame_002", 4], [2, 4]),
        ("every:2", [0, 2, 4]),
        ("every:4", [0, 4]),
        ("spread:2", [1, 4]),
        ("spread:3", [1, 3, 5]),
        ("spread:6", [0, 1, 2, 3, 4, 5]),
    ],
)
def test_annotated_frames_choose_what_teaches(tmp_path, spec, expected) -> None:
    cap = load_capture(_annotated_capture(tmp_path / "cap"), annotated_frames=spec)
    assert _taught(cap) == [f"frame_{i:03d}" for i in expected]
    report = check_capture(cap, labels="annotations", images=False)
    assert report.ok and report.files == len(expected)  # the dropped ones are not even read


def test_dropped_annotations_do_not_teach(tmp_path) -> None:
    from labelsynth.pipeline import labelled_frames, resolve_label_mode
    from labelsynth.recipe import load_recipe

    cap = load_capture(_annotated_capture(tmp_path / "cap"), annotated_frames="spread:2")
    assert resolve_label_mode(cap, None) == "annotations"
    taught = labelled_frames(cap, "annotations", load_recipe("fast"))
    assert [t.name for t in taught] == ["frame_001", "frame_004"]


@pytest.mark.parametrize(
    "spec,needle",
    [
        ("frame_009", "no frame named 'frame_009'"),
        ("frame_001,nope", "no frame named 'nope'"),
        ("6", "frame index 6 out of range"),
        ("-1", "frame index -1 out of range"),
        ("every:0", "every:0"),
        ("spread:x", "spread:x"),
        ("spread:7", "asks for 7 frames"),
        ("frame_001,,2", "empty frame name"),
        ("", "empty frame name"),
    ],
)
def test_bad_annotated_frames_are_one_line(tmp_path, spec, needle) -> None:
    root = _annotated_capture(tmp_path / "cap")
    with pytest.raises(CaptureError) as err:
        load_capture(root, annotated_frames=spec)
    assert needle in str(err.value) and "\n" not in str(err.value)
    assert str(err.value).startswith("--annotated-frames: ")


def test_names_win_over_indices() -> None:
    names = ["000000", "000001", "1", "2"]
    assert select_frames("1", names) == ["1"]  # a name, not index 1
    assert select_frames("000001,0", names) == ["000000", "000001"]
    assert select_frames([], names) == []


def test_chosen_frames_without_annotation_warn(tmp_path) -> None:
    root = _annotated_capture(tmp_path / "cap", annotated=(0, 3))
    with pytest.warns(UserWarning, match="1 of the 2 frames chosen to teach have no annotation"):
        cap = load_capture(root, annotated_frames="0,1")
    assert _taught(cap) == ["frame_000"]


def test_annotated_frames_on_a_neus_capture(tmp_path) -> None:
    cap = load_capture(make_neus(tmp_path / "cap"), annotated_frames="spread:2")
    assert _taught(cap) == ["000001", "000003"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cap = load_capture(tmp_path / "cap", annotated_frames="000003")
    assert _taught(cap) == ["000003"]


# --- the CLI passes it through -------------------------------------------------------------
def test_expand_cli_bad_annotated_frames_fails_before_training(tmp_path) -> None:
    root = _annotated_capture(tmp_path / "cap")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["expand", str(root), "--out", str(out), "--recipe", "fast", "--device", "cpu",
                                      "--annotated-frames", "frame_001,frame_099"])
    assert result.exit_code == 2, result.output
    assert result.stderr.strip() == ("labelsynth: error: --annotated-frames: no frame named 'frame_099' "
                                     "(frames: frame_000, frame_001, frame_002 ...; or give 0-based indices)")
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_expand_cli_trains_only_on_the_chosen_frames(tmp_path, monkeypatch) -> None:
    import labelsynth.pipeline as pipeline

    seen = {}

    def stop(capture, *args, **kwargs):
        seen["taught"] = _taught(capture)
        raise LabelsynthError("stopped before training")

    monkeypatch.setattr(pipeline, "fit_field", stop)
    root = _annotated_capture(tmp_path / "cap")
    result = CliRunner().invoke(app, ["expand", str(root), "--out", str(tmp_path / "out"), "--recipe", "fast",
                                      "--device", "cpu", "--annotated-frames", "every:3"])
    assert result.exit_code == 2 and "stopped before training" in result.stderr
    assert seen["taught"] == ["frame_000", "frame_003"]


def test_bench_cli_passes_annotated_frames(tmp_path) -> None:
    root = _annotated_capture(tmp_path / "cap")
    (root / "predictions").mkdir()
    for i in range(6):
        assert cv2.imwrite(str(root / "predictions" / f"frame_{i:03d}.png"), np.zeros((H, W), np.uint8))
    args = ["bench", str(root), "--truth", str(tmp_path / "no-truth"), "--out", str(tmp_path / "b"), "--device", "cpu"]
    every = CliRunner().invoke(app, args)
    assert every.exit_code == 2 and "every frame is annotated" in every.stderr
    some = CliRunner().invoke(app, [*args, "--annotated-frames", "spread:2"])
    assert some.exit_code == 2 and "truth folder not found" in some.stderr  # got past the annotated frames
