"""COLMAP sparse models, text (written by hand) and binary (written by pycolmap)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from labelsynth.cameras import colmap_to_opengl_c2w
from labelsynth.capture import CaptureError, load_capture

from .test_capture_support import H, W, snapshot, write_image

Q_Y90 = (float(np.cos(np.pi / 4)), 0.0, float(np.sin(np.pi / 4)), 0.0)

CAMERAS = {
    "OPENCV": ("30 31 16 12 -0.1 0.02 0.001 -0.002", dict(fx=30, fy=31, cx=16, cy=12, k1=-0.1, k2=0.02, p1=0.001, p2=-0.002)),
    "PINHOLE": ("30 31 16 12", dict(fx=30, fy=31, cx=16, cy=12)),
    "SIMPLE_PINHOLE": ("30 16 12", dict(fx=30, fy=30, cx=16, cy=12)),
    "SIMPLE_RADIAL": ("30 16 12 -0.05", dict(fx=30, fy=30, cx=16, cy=12, k1=-0.05)),
    "RADIAL": ("30 16 12 -0.05 0.01", dict(fx=30, fy=30, cx=16, cy=12, k1=-0.05, k2=0.01)),
}


def write_text_model(model: Path, camera_model: str = "OPENCV", params: str | None = None) -> None:
    """Two images: identity rotation with t=(1,2,3), and 90 degrees about y with t=(0,0,4)."""
    model.mkdir(parents=True, exist_ok=True)
    params = CAMERAS[camera_model][0] if params is None else params
    (model / "cameras.txt").write_text(f"# Camera list\n1 {camera_model} {W} {H} {params}\n")
    (model / "images.txt").write_text(
        "# Image list\n"
        "1 1 0 0 0 1 2 3 1 a.png\n"
        "10 20 1 11 12 2\n"
        f"2 {Q_Y90[0]!r} 0 {Q_Y90[2]!r} 0 0 0 4 1 b.png\n"
        "14 13 2\n"
    )
    (model / "points3D.txt").write_text(
        "# 3D point list\n"
        "1 -1 -2 -3 255 0 0 0.5 1 0\n"
        "2 0.5 0.25 0.125 0 255 0 0.5 1 1 2 0\n"
    )


def make_colmap_capture(root: Path, camera_model: str = "OPENCV", binary: bool = False) -> Path:
    write_image(root / "images" / "a.png", seed=1)
    write_image(root / "images" / "b.png", seed=2)
    model = root / "sparse" / "0"
    if binary:
        text_dir = root.parent / (root.name + "_text")
        write_text_model(text_dir, camera_model)
        model.mkdir(parents=True)
        pycolmap.Reconstruction(str(text_dir)).write_binary(str(model))
        assert (model / "cameras.bin").is_file()
    else:
        write_text_model(model, camera_model)
    return root


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_model_gives_hand_computed_cameras(tmp_path, binary) -> None:
    root = make_colmap_capture(tmp_path / "cap", binary=binary)
    before = snapshot(root)
    cap = load_capture(root)
    assert snapshot(root) == before
    assert cap.names == ["a", "b"] and cap.source.startswith("colmap:")
    a, b = (f.camera for f in cap.frames)
    assert (a.width, a.height, a.fx, a.fy, a.cx, a.cy) == (W, H, 30, 31, 16, 12)
    assert (a.k1, a.k2, a.p1, a.p2) == pytest.approx((-0.1, 0.02, 0.001, -0.002))
    # identity rotation, t = (1,2,3): centre -t, OpenGL axes = COLMAP axes with y, z flipped
    np.testing.assert_allclose(a.c2w[:3, 3], [-1, -2, -3], atol=1e-9)
    np.testing.assert_allclose(a.c2w[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-9)
    # 90 degrees about y, t = (0,0,4): centre (4,0,0), looking at the origin along -x
    np.testing.assert_allclose(b.c2w[:3, 3], [4, 0, 0], atol=1e-9)
    np.testing.assert_allclose(b.forward, [-1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(b.c2w, colmap_to_opengl_c2w(Q_Y90, [0, 0, 4]), atol=1e-9)
    np.testing.assert_allclose(cap.points, [[-1, -2, -3], [0.5, 0.25, 0.125]], atol=1e-9)


def test_text_and_binary_agree(tmp_path) -> None:
    t = load_capture(make_colmap_capture(tmp_path / "t", binary=False))
    b = load_capture(make_colmap_capture(tmp_path / "b", binary=True))
    for ft, fb in zip(t.frames, b.frames):
        assert ft.name == fb.name
        np.testing.assert_allclose(ft.camera.c2w, fb.camera.c2w, atol=1e-12)
        assert ft.camera.K.tolist() == fb.camera.K.tolist()


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"])
def test_camera_models(tmp_path, model) -> None:
    cap = load_capture(make_colmap_capture(tmp_path / "cap", camera_model=model))
    cam = cap.frames[0].camera
    expected = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, **CAMERAS[model][1]}
    assert {k: getattr(cam, k) for k in expected} == pytest.approx(expected)


@pytest.mark.parametrize("model", ["PINHOLE", "OPENCV", "RADIAL"])
def test_projection_matches_pycolmap(tmp_path, model) -> None:
    """Our camera projects SfM points where COLMAP's own camera model does (both images),
    and the ray through that pixel passes through the point (distortion included)."""
    root = make_colmap_capture(tmp_path / "cap", camera_model=model)
    cap = load_capture(root)
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    point = rec.points3D[2].xyz
    for frame, image_id in zip(cap.frames, (1, 2)):
        image = rec.images[image_id]
        colmap_uv = rec.cameras[1].img_from_cam(image.cam_from_world() * point)
        uv, depth = frame.camera.project(cap.points[1:2])
        assert depth[0] > 0
        np.testing.assert_allclose(uv[0], np.asarray(colmap_uv).reshape(-1)[:2], atol=1e-9)
        origin, direction = frame.camera.rays(uv)
        to_pt = point - origin[0]
        miss = to_pt - (to_pt @ direction[0]) * direction[0]
        assert np.linalg.norm(miss) < 1e-7


def test_unsupported_colmap_model(tmp_path) -> None:
    root = tmp_path / "cap"
    write_image(root / "images" / "a.png")
    write_image(root / "images" / "b.png")
    write_text_model(root / "sparse" / "0", "OPENCV_FISHEYE", "30 31 16 12 0.1 0 0 0")
    with pytest.raises(CaptureError, match="OPENCV_FISHEYE") as err:
        load_capture(root)
    assert "sparse" in str(err.value)


def test_colmap_missing_image_skipped(tmp_path) -> None:
    root = make_colmap_capture(tmp_path / "cap")
    (root / "images" / "b.png").unlink()
    with pytest.warns(UserWarning, match="1 frame"):
        cap = load_capture(root)
    assert cap.names == ["a"]


def test_broken_colmap_model(tmp_path) -> None:
    root = make_colmap_capture(tmp_path / "cap")
    (root / "sparse" / "0" / "images.txt").write_text("1 1 0 0 0 1 2 3 99 a.png\n\n")  # unknown camera
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(CaptureError, match="COLMAP") as err:
            load_capture(root)
    assert "sparse" in str(err.value) and "\n" not in str(err.value)
