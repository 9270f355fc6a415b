"""transforms.json dialects: nerfstudio (shared / per-frame intrinsics), Blender, instant-ngp."""

from __future__ import annotations

import json
import math
import warnings

import cv2
import numpy as np
import pytest

from labelsynth.capture import CaptureError, load_capture, validate_capture
from labelsynth.classes import ClassInfo, ClassMap

from .test_capture_support import H, W, make_capture, ring_poses, snapshot, write_image


def test_nerfstudio_shared_intrinsics_with_distortion(tmp_path) -> None:
    intr = {"camera_model": "OPENCV", "fl_x": 30.0, "fl_y": 31.0, "cx": 15.5, "cy": 12.5, "w": W, "h": H,
            "k1": -0.1, "k2": 0.01, "p1": 0.001, "p2": -0.002}
    root = make_capture(tmp_path / "cap", intrinsics=intr)
    before = snapshot(root)
    cap = load_capture(root)
    assert snapshot(root) == before  # nothing written into the capture
    assert cap.names == ["frame_000", "frame_001", "frame_002", "frame_003"]
    cam = cap.frames[0].camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (W, H, 30.0, 31.0, 15.5, 12.5)
    assert (cam.k1, cam.k2, cam.p1, cam.p2) == (-0.1, 0.01, 0.001, -0.002)
    np.testing.assert_allclose(cam.c2w, ring_poses(4)[0])
    assert cap.source == "transforms.json" and not cap.white_background
    img = cap.load_image(2)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    stored = cv2.imread(str(cap.frames[2].image_path))
    np.testing.assert_array_equal(img, stored[:, :, ::-1])
    assert cap.normalization is not None and cap.points is None


def test_nerfstudio_per_frame_intrinsics(tmp_path) -> None:
    per_frame = [{"fl_x": 20.0 + i, "fl_y": 20.0 + i, "cx": 16, "cy": 12, "w": W, "h": H} for i in range(3)]
    root = make_capture(tmp_path / "cap", n=3, intrinsics={"camera_model": "OPENCV"}, per_frame=per_frame)
    cap = load_capture(root)
    assert [f.camera.fx for f in cap.frames] == [20.0, 21.0, 22.0]


def test_per_frame_values_override_shared(tmp_path) -> None:
    intr = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16, "cy": 12, "w": W, "h": H}
    per_frame = [{}, {"fl_x": 40.0}]
    root = make_capture(tmp_path / "cap", n=2, intrinsics=intr, per_frame=per_frame)
    cap = load_capture(root)
    assert [f.camera.fx for f in cap.frames] == [30.0, 40.0]
    assert [f.camera.fy for f in cap.frames] == [30.0, 30.0]


@pytest.mark.parametrize("model,extra", [("PINHOLE", {}), ("OPENCV", {"k3": 0.0, "k4": 0.0, "k1": 0.05})])
def test_pinhole_and_zero_k3_accepted(tmp_path, model, extra) -> None:
    intr = {"camera_model": model, "fl_x": 30.0, "fl_y": 30.0, "cx": 16, "cy": 12, "w": W, "h": H, **extra}
    cap = load_capture(make_capture(tmp_path / "cap", n=2, intrinsics=intr))
    assert cap.frames[0].camera.k1 == extra.get("k1", 0.0)


@pytest.mark.parametrize(
    "intr,needle",
    [
        ({"camera_model": "OPENCV_FISHEYE", "k3": 0.1}, "OPENCV_FISHEYE"),
        ({"camera_model": "OPENCV", "k3": 0.2}, "k3"),
    ],
)
def test_unsupported_models_rejected(tmp_path, intr, needle) -> None:
    intr = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16, "cy": 12, "w": W, "h": H, **intr}
    root = make_capture(tmp_path / "cap", n=2, intrinsics=intr)
    with pytest.raises(CaptureError, match=needle) as err:
        load_capture(root)
    assert "transforms.json" in str(err.value) and "\n" not in str(err.value)


def test_blender_style(tmp_path) -> None:
    """NeRF-synthetic: camera_angle_x, no w/h, './train/r_0' without extension, RGBA on white."""
    angle = 0.6911112070083618
    root = make_capture(
        tmp_path / "lego", n=3, intrinsics={"camera_angle_x": angle}, file_path_fmt="./train/r_{i}",
        write_ext=".png", channels=4, extra={"aabb_scale": 16}, json_name="transforms_train.json",
    )
    # a fully transparent pixel must come out white
    rgba = cv2.imread(str(root / "train" / "r_0.png"), cv2.IMREAD_UNCHANGED)
    rgba[0, 0, 3] = 0
    rgba[0, 1, 3] = 255
    cv2.imwrite(str(root / "train" / "r_0.png"), rgba)
    cap = load_capture(root)
    assert cap.names == ["r_0", "r_1", "r_2"] and cap.white_background
    cam = cap.frames[0].camera
    assert (cam.width, cam.height) == (W, H)
    assert cam.fx == pytest.approx(0.5 * W / math.tan(0.5 * angle)) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (W / 2, H / 2)
    img = cap.load_image(0)
    assert img.shape == (H, W, 3)
    np.testing.assert_array_equal(img[0, 0], [255, 255, 255])
    np.testing.assert_array_equal(img[0, 1], rgba[0, 1, 2::-1])


def test_camera_angle_y_and_explicit_black_background(tmp_path) -> None:
    root = make_capture(
        tmp_path / "cap", n=2, intrinsics={"camera_angle_x": 1.0, "camera_angle_y": 0.8},
        file_path_fmt="images/{i}.jpg", ext="", channels=4, extra={"white_background": False},
    )
    # JPEG cannot hold alpha: the file has 3 channels; this checks angle_y and the flag.
    cap = load_capture(root)
    cam = cap.frames[0].camera
    assert cam.fy == pytest.approx(0.5 * H / math.tan(0.4))
    assert not cap.white_background


def test_png_extension_variants_and_dot_slash(tmp_path) -> None:
    root = tmp_path / "cap"
    frames = []
    for i, (rel, actual) in enumerate([("./images/a", "images/a.JPG"), ("images/b.png", "images/b.png"),
                                       ("images/c", "images/c.jpeg")]):
        write_image(root / actual, seed=i)
        frames.append({"file_path": rel, "transform_matrix": ring_poses(3)[i].tolist()})
    (root / "transforms.json").write_text(json.dumps({"fl_x": 20, "w": W, "h": H, "frames": frames}))
    cap = load_capture(root)
    assert cap.names == ["a", "b", "c"]
    assert cap.frames[0].image_path.name == "a.JPG"


def test_missing_images_warn_once_and_skip(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=4)
    (root / "images" / "frame_001.png").unlink()
    (root / "images" / "frame_003.png").unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cap = load_capture(root)
    assert cap.names == ["frame_000", "frame_002"]
    msgs = [str(w.message) for w in caught if "missing" in str(w.message)]
    assert len(msgs) == 1 and "2 frame(s)" in msgs[0]


def test_all_images_missing_is_an_error(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    for p in (root / "images").iterdir():
        p.unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(CaptureError, match="none of the 2 posed frames"):
            load_capture(root)


@pytest.mark.parametrize(
    "text,needle",
    [
        ('{"frames": [', "not valid JSON"),
        ('{"fl_x": 20}', "frames"),
        ('{"fl_x": 20, "w": 32, "h": 24, "frames": [{"file_path": "images/frame_000.png", '
         '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}, '
         '{"file_path": "images/frame_001.png", "transform_matrix": [[1,0,0],[0,1,0]]}]}', "frame 1"),
        ('{"fl_x": 20, "w": 32, "h": 24, "frames": [{"file_path": "images/frame_000.png", '
         '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,NaN]]}]}', "frame 0"),
        ('{"w": 32, "h": 24, "frames": [{"file_path": "images/frame_000.png", '
         '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "focal length"),
    ],
)
def test_malformed_transforms(tmp_path, text, needle) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    (root / "transforms.json").write_text(text)
    with pytest.raises(CaptureError, match=needle) as err:
        load_capture(root)
    msg = str(err.value)
    assert "transforms.json" in msg and "\n" not in msg


def test_duplicate_stems_rejected(tmp_path) -> None:
    root = tmp_path / "cap"
    frames = []
    for i, rel in enumerate(["images/a.png", "more/a.jpg"]):
        write_image(root / rel, seed=i)
        frames.append({"file_path": rel, "transform_matrix": ring_poses(2)[i].tolist()})
    (root / "transforms.json").write_text(json.dumps({"fl_x": 20, "w": W, "h": H, "frames": frames}))
    with pytest.raises(CaptureError, match="unique"):
        load_capture(root)


def test_image_size_mismatch_names_file(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    write_image(root / "images" / "frame_001.png", w=W + 2)
    cap = load_capture(root)
    with pytest.raises(CaptureError, match="frame_001.png.*34x24.*32x24"):
        cap.load_image(1)
    with pytest.raises(CaptureError, match="frame_001.png.*34x24.*32x24"):
        validate_capture(cap)


def test_no_poses_tells_to_run_poses(tmp_path) -> None:
    write_image(tmp_path / "cap" / "images" / "a.png")
    with pytest.raises(CaptureError, match="labelsynth poses"):
        load_capture(tmp_path / "cap")


def test_classes_json_and_override(tmp_path) -> None:
    root = make_capture(tmp_path / "cap", n=2)
    (root / "classes.json").write_text(json.dumps(
        {"classes": [{"id": 0, "name": "background", "color": [0, 0, 0]},
                     {"id": 7, "name": "object", "color": [255, 255, 255]}]}))
    cap = load_capture(root)
    assert cap.classes.names == ["background", "object"]
    assert cap.color_table[(255, 255, 255)] == 7
    override = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "wound", (9, 9, 9))))
    cap = load_capture(root, classes=override)
    assert cap.classes is override
    validate_capture(cap)  # no masks: nothing to complain about


def test_nerfstudio_point_cloud_used_for_roi(tmp_path) -> None:
    import trimesh

    root = make_capture(tmp_path / "cap", n=4, extra={"ply_file_path": "sparse_pc.ply"})
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.05, (200, 3)) + [0.1, 0.0, 0.0]
    trimesh.PointCloud(pts).export(root / "sparse_pc.ply")
    before = snapshot(root)
    cap = load_capture(root)
    assert snapshot(root) == before
    np.testing.assert_allclose(cap.points, pts, atol=1e-6)
    np.testing.assert_allclose(cap.normalization.center, np.median(pts, axis=0), atol=1e-6)
