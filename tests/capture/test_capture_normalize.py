"""Region of interest for object-centric and wound (one-sided, phone) captures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labelsynth.cameras import Camera, look_at
from labelsynth.capture import load_capture, region_of_interest

from .test_capture_support import make_capture


def _cam(eye, target, w=800, h=600, f=700.0) -> Camera:
    return Camera(width=w, height=h, fx=f, fy=f, cx=w / 2, cy=h / 2, c2w=look_at(eye, target))


def _sphere_cameras(n=30, radius=4.0311) -> list[Camera]:
    rng = np.random.default_rng(0)
    cams = []
    f = 0.5 * 800 / math.tan(0.5 * 0.6911)
    for _ in range(n):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.1  # upper hemisphere, as in NeRF-synthetic
        cams.append(_cam(radius * d / np.linalg.norm(d), [0, 0, 0], w=800, h=800, f=f))
    return cams


def _wound_cameras(n=25, wound=(0.3, -0.2, 0.0), seed=0) -> list[Camera]:
    """A phone 20-30 cm above a skin plane (z = 0), moving around the wound and aiming at it."""
    rng = np.random.default_rng(seed)
    wound = np.asarray(wound)
    cams = []
    for _ in range(n):
        eye = wound + np.array([*rng.uniform(-0.12, 0.12, 2), rng.uniform(0.2, 0.3)])
        cams.append(_cam(eye, wound + np.array([*rng.uniform(-0.01, 0.01, 2), 0.0]), w=480, h=640, f=520))
    return cams


def _close_up_cameras(n=30, seed=0) -> list[Camera]:
    """Cameras a unit above a large flat object (z = 0), each aimed at a different part of it:
    a DTU scan whose building fills every view, where the axes do not meet at one point."""
    rng = np.random.default_rng(seed)
    cams = []
    for _ in range(n):
        target = np.array([*rng.uniform(-1, 1, 2), 0.0])
        angle, tilt = rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 0.6)
        cams.append(_cam(target + [tilt * math.cos(angle), tilt * math.sin(angle), 1.0], target))
    return cams


def _seen_inside(cam: Camera, roi) -> float:
    """The share of what the camera sees of the plane z = 0 (a 9 x 9 grid of its pixels, corners
    included) that lies inside the cube."""
    u, v = np.meshgrid(np.linspace(0, cam.width, 9), np.linspace(0, cam.height, 9))
    o, d = cam.rays(np.stack([u.ravel(), v.ravel()], 1))
    on_plane = o + d * (-o[:, 2] / d[:, 2])[:, None]
    return float(np.mean(np.abs(roi.to_unit(on_plane)).max(1) <= 1.0))


def test_close_up_views_of_a_large_object_stay_inside_the_cube() -> None:
    # One image's footprint (the rule before) kept 56% of what these cameras see inside the
    # cube (12% of the worst view): the rest could only be called background.
    cams = _close_up_cameras()
    roi = region_of_interest(cams)
    seen = [_seen_inside(c, roi) for c in cams]
    assert np.mean(seen) >= 0.95 and min(seen) >= 0.9, (roi, np.mean(seen), min(seen))


def test_converging_cameras_keep_one_footprint() -> None:
    # a phone aimed at the wound: its axes miss the wound by less than the footprint's margin,
    # so the cube stays one footprint x 1.2
    cams = _wound_cameras()
    roi = region_of_interest(cams)
    d_med = float(np.median([np.linalg.norm(c.center - roi.center) for c in cams]))
    assert roi.scale == pytest.approx(d_med * max(240 / 520, 320 / 520) * 1.2, rel=1e-9)


def test_object_centric_sphere() -> None:
    cams = _sphere_cameras()
    roi = region_of_interest(cams)
    np.testing.assert_allclose(roi.center, 0.0, atol=1e-6)
    expected = 4.0311 * math.tan(0.5 * 0.6911) * 1.2
    assert roi.scale == pytest.approx(expected, rel=1e-3)
    assert roi.scale > 1.3  # NeRF-synthetic objects lie within about [-1.3, 1.3]^3
    assert all(np.abs(roi.to_unit(c.center)).max() > 1 for c in cams)  # cameras outside: fine


def test_wound_capture_without_points() -> None:
    roi = region_of_interest(_wound_cameras())
    np.testing.assert_allclose(roi.center, [0.3, -0.2, 0.0], atol=0.02)
    assert 0.1 < roi.scale < 0.5
    assert np.all(np.abs(roi.to_unit([[0.35, -0.15, 0.0], [0.25, -0.25, 0.0]])) <= 1)


def test_wound_capture_with_points_and_outliers() -> None:
    rng = np.random.default_rng(1)
    skin = np.c_[rng.uniform(0.15, 0.45, (400, 1)), rng.uniform(-0.35, -0.05, (400, 1)), rng.normal(0, 0.003, (400, 1))]
    outliers = rng.normal(0, 1, (20, 3)) * 50  # SfM junk far away
    behind = np.c_[rng.uniform(-1, 1, (30, 2)), np.full(30, 5.0)]  # above the phone: never seen
    cams = _wound_cameras()
    roi = region_of_interest(cams, np.vstack([skin, outliers, behind]))
    np.testing.assert_allclose(roi.center[:2], [0.3, -0.2], atol=0.02)
    assert abs(roi.center[2]) < 0.01  # on the surface, from the points
    r = np.linalg.norm(skin - roi.center, axis=1)
    assert roi.scale >= np.percentile(r, 95) * 0.9
    assert roi.scale < 1.0  # the outliers did not blow it up


def test_parallel_axes_fall_back_in_front_of_the_cameras() -> None:
    cams = [Camera(width=64, height=48, fx=50, fy=50, cx=32, cy=24,
                   c2w=look_at([x, 0.0, 1.0], [x, 0.001, 0.0]))  # all looking straight down
            for x in np.linspace(-0.2, 0.2, 5)]
    roi = region_of_interest(cams)
    assert np.all(np.isfinite(roi.center)) and roi.scale > 0
    assert roi.center[2] < 1.0  # in front of (below) the cameras
    assert roi.center[2] - roi.scale <= 1.0 - 2 * (1.0 - roi.center[2]) + 1e-9  # reaches 2x the guess
    np.testing.assert_allclose(roi.center[:2], [0.0, 0.0], atol=1e-3)


def test_single_camera() -> None:
    roi = region_of_interest([_cam([0, 0, 2], [0, 0, 0])])
    np.testing.assert_allclose(roi.center, [0, 0, 1], atol=1e-9)
    assert roi.scale > 0


def test_load_capture_sets_normalization(tmp_path) -> None:
    cap = load_capture(make_capture(tmp_path / "cap", n=4))
    assert cap.normalization is not None
    np.testing.assert_allclose(cap.normalization.center, 0.0, atol=1e-6)  # ring cameras aim at 0
    unit = cap.unit_cameras()
    np.testing.assert_allclose(unit[0].center * cap.normalization.scale, cap.frames[0].camera.center, atol=1e-12)
