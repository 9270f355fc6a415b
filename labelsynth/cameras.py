"""Camera conventions, in one place.

- Extrinsics are camera-to-world 4x4 matrices with OpenGL axes (x right, y up, the camera
  looks down -z), as in nerfstudio's ``transforms.json``.
- Pixel (u, v): u to the right, v down; the centre of the top-left pixel is (0.5, 0.5).
- Intrinsics follow OpenCV (fx, fy, cx, cy, optional k1 k2 p1 p2). Distortion is handled by
  *distorting rays*, not by resampling images: a ray for pixel (u, v) goes through the
  undistorted normalised coordinate of (u, v), so images and masks stay untouched and the
  output masks align with the original frames pixel for pixel.
- COLMAP stores world-to-camera with OpenCV axes (y down, looking down +z);
  ``colmap_to_opengl_c2w`` converts.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

# OpenCV camera axes -> OpenGL camera axes (flip y and z).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with optional OPENCV radial-tangential distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: np.ndarray  # (4, 4) camera-to-world, OpenGL axes
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise ValueError("camera-to-world must be a finite 4x4 (or 3x4) matrix")
        object.__setattr__(self, "c2w", c2w)
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError("camera width, height and focal lengths must be positive")

    # --- basic properties ----------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2], dtype=np.float64)

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.dist_coeffs != 0.0))

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    @property
    def w2c(self) -> np.ndarray:
        return np.linalg.inv(self.c2w)

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing direction in world coordinates (the camera's -z axis)."""
        f = -self.c2w[:3, 2]
        return f / np.linalg.norm(f)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.25 for a quarter)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy)

    def with_c2w(self, c2w: np.ndarray) -> "Camera":
        return replace(self, c2w=np.asarray(c2w, dtype=np.float64))

    # --- pixels <-> normalised coordinates ----------------------------------------------
    def pixel_grid(self) -> np.ndarray:
        """(H*W, 2) pixel-centre coordinates in row-major order."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.stack([u.ravel(), v.ravel()], axis=-1)

    def undistort_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (N,2) -> undistorted normalised image coordinates (N,2) (OpenCV: y down)."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted:
            return np.stack([(pixels[:, 0] - self.cx) / self.fx, (pixels[:, 1] - self.cy) / self.fy], -1)
        # OpenCV's pixel convention puts the centre of the top-left pixel at (0, 0); ours at
        # (0.5, 0.5). cx, cy are in our convention (as in nerfstudio/COLMAP), so no shift.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        src = pixels.reshape(-1, 1, 2)
        # OpenCV 4 takes the stopping criteria only in undistortPointsIter; OpenCV 5 folded them
        # into undistortPoints (and a dev install pins OpenCV < 5 through Datumaro): either works.
        if hasattr(cv2, "undistortPointsIter"):
            out = cv2.undistortPointsIter(src, self.K, self.dist_coeffs, None, None, criteria)
        else:
            out = cv2.undistortPoints(src, self.K, self.dist_coeffs, None, None, None, criteria)
        return out.reshape(-1, 2)

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N,2) -> pixels (N,2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        if self.is_distorted:
            r2 = x * x + y * y
            radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
            xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
            yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
            x, y = xd, yd
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], -1)

    # --- rays and projection -------------------------------------------------------------
    def rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World-space ray origins and unit directions (N,3) through pixel coordinates.

        ``pixels`` defaults to every pixel centre (row-major). Directions are unit length,
        so distances along a ray are metric in world units.
        """
        if pixels is None:
            pixels = self.pixel_grid()
        xy = self.undistort_normalized(pixels)
        d_cam = np.stack([xy[:, 0], -xy[:, 1], -np.ones(len(xy))], axis=-1)  # OpenGL axes
        d_world = d_cam @ self.c2w[:3, :3].T
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.c2w[:3, 3], d_world.shape).copy()
        return origins, d_world

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) -> pixel coordinates (N,2) and depth along the view axis (N,).

        Depth is positive in front of the camera; points behind it get depth <= 0 and
        their pixel coordinates are meaningless.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p_cam = points @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        depth = -p_cam[:, 2]
        safe = np.where(np.abs(depth) < 1e-12, 1e-12, depth)
        xy = np.stack([p_cam[:, 0] / safe, -p_cam[:, 1] / safe], -1)
        return self.distort_normalized(xy), depth


def colmap_to_opengl_c2w(qvec_wxyz: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP world-to-camera (quaternion w,x,y,z + translation, OpenCV axes) -> OpenGL c2w."""
    w, x, y, z = np.asarray(qvec_wxyz, dtype=np.float64) / np.linalg.norm(qvec_wxyz)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return w2c_cv_to_c2w_gl(R, tvec)


def w2c_cv_to_c2w_gl(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera (R, t) -> OpenGL camera-to-world 4x4."""
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return np.linalg.inv(w2c) @ CV_TO_GL


def c2w_gl_to_w2c_cv(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world -> OpenCV world-to-camera 4x4 (inverse of the above)."""
    return np.linalg.inv(np.asarray(c2w, dtype=np.float64) @ CV_TO_GL)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world for a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w
