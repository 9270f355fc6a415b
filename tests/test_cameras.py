"""Camera conventions: projection vs OpenCV, rays back through projections, COLMAP -> OpenGL."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from labelsynth.cameras import Camera, c2w_gl_to_w2c_cv, colmap_to_opengl_c2w, look_at


def _camera(dist: bool) -> Camera:
    c2w = look_at([0.5, -3.0, 1.0], [0.1, 0.2, -0.1])
    kw = dict(k1=-0.12, k2=0.03, p1=0.002, p2=-0.0015) if dist else {}
    return Camera(width=640, height=480, fx=500.0, fy=510.0, cx=321.5, cy=238.0, c2w=c2w, **kw)


def _points() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform(-0.6, 0.6, size=(50, 3))


@pytest.mark.parametrize("dist", [False, True])
def test_project_matches_cv2(dist: bool) -> None:
    cam, pts = _camera(dist), _points()
    uv, depth = cam.project(pts)
    w2c = c2w_gl_to_w2c_cv(cam.c2w)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    ref, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], cam.K, cam.dist_coeffs)
    assert np.all(depth > 0)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)


@pytest.mark.parametrize("dist", [False, True])
def test_ray_through_projection_hits_point(dist: bool) -> None:
    cam, pts = _camera(dist), _points()
    uv, depth = cam.project(pts)
    origins, dirs = cam.rays(uv)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    to_pt = pts - origins
    along = np.einsum("ij,ij->i", to_pt, dirs)
    assert np.all(along > 0)
    miss = np.linalg.norm(to_pt - along[:, None] * dirs, axis=1)
    assert miss.max() < 1e-6


def test_colmap_identity_rotation() -> None:
    t = np.array([1.0, 2.0, 3.0])
    c2w = colmap_to_opengl_c2w([1.0, 0.0, 0.0, 0.0], t)
    np.testing.assert_allclose(c2w[:3, 3], -t)
    np.testing.assert_allclose(c2w[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    cam = Camera(width=10, height=10, fx=10, fy=10, cx=5, cy=5, c2w=c2w)
    np.testing.assert_allclose(cam.forward, [0.0, 0.0, 1.0], atol=1e-12)  # COLMAP looks down +z


def test_colmap_rotation_about_y() -> None:
    # 90 degrees about y: R = [[0,0,1],[0,1,0],[-1,0,0]]; with t = (0,0,4) the centre is
    # -R^T t = (4,0,0), and the camera's +z (its viewing direction) is R^T e_z = (-1,0,0).
    q = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]
    c2w = colmap_to_opengl_c2w(q, [0.0, 0.0, 4.0])
    np.testing.assert_allclose(c2w[:3, 3], [4.0, 0.0, 0.0], atol=1e-12)
    cam = Camera(width=10, height=10, fx=10, fy=10, cx=5, cy=5, c2w=c2w)
    np.testing.assert_allclose(cam.forward, [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [0.0, -1.0, 0.0], atol=1e-12)  # OpenGL up = -(COLMAP y)
    uv, depth = cam.project([[0.0, 0.0, 0.0]])
    np.testing.assert_allclose(uv, [[5.0, 5.0]])
    assert depth[0] == pytest.approx(4.0)


def test_look_at_sanity() -> None:
    c2w = look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    cam = Camera(width=100, height=80, fx=90, fy=90, cx=50, cy=40, c2w=c2w)
    np.testing.assert_allclose(cam.forward, [0.0, 1.0, 0.0], atol=1e-12)
    uv, depth = cam.project([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.5, 0.0, 0.0]])
    np.testing.assert_allclose(uv[0], [50.0, 40.0])
    assert depth[0] == pytest.approx(3.0)
    assert uv[1, 1] < 40.0  # world up appears up in the image (v grows downwards)
    assert uv[2, 0] > 50.0  # world +x is to the right when looking along +y with z up
