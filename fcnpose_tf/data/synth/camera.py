"""The camera that frames every synthetic scene: a pinhole with optional radial (barrel) distortion."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Camera:
    """Camera: K (3 x 3), R (world -> camera rotation, rows = right, down, forward), eye (m), and k1, the
    radial distortion of OpenCV's model (x_d = x_u (1 + k1 r^2), k2 = p1 = p2 = 0; 0: a pinhole).

    Pixel coordinates follow the pixel-centre convention (pixel i's centre is at i), as OpenCV and VIA;
    `project` equals `cv2.projectPoints` with distortion coefficients (k1, 0, 0, 0).
    """

    K: np.ndarray
    R: np.ndarray
    eye: np.ndarray
    width: int
    height: int
    k1: float = 0.0

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (N x 3) in camera coordinates (x right, y down, z forward)."""
        return (np.asarray(points, np.float64) - self.eye) @ self.R.T

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N x 2 pixel coordinates, N depths) of world points; depth <= 0 means behind the camera."""
        pc = self.to_camera(points)
        z = pc[:, 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        if not self.k1:
            uv = np.stack([self.K[0, 0] * pc[:, 0] / zs + self.K[0, 2], self.K[1, 1] * pc[:, 1] / zs + self.K[1, 2]], 1)
            return uv, z
        x, y = pc[:, 0] / zs, pc[:, 1] / zs
        radial = 1.0 + self.k1 * (x * x + y * y)
        uv = np.stack([self.K[0, 0] * x * radial + self.K[0, 2], self.K[1, 1] * y * radial + self.K[1, 2]], 1)
        return uv, z

    def undistort_scale(self) -> float:
        """How much wider a pinhole must see to cover this camera's picture (1 without distortion)."""
        if not self.k1:
            return 1.0
        corner = np.hypot(max(self.K[0, 2], self.width - 1 - self.K[0, 2]) / self.K[0, 0],
                          max(self.K[1, 2], self.height - 1 - self.K[1, 2]) / self.K[1, 1])
        return float(_undistort_radius(np.array([corner]), self.k1)[0] / corner)

    def render_camera(self) -> "Camera":
        """The pinhole (same pose and resolution, focal divided by `undistort_scale`) whose picture,
        resampled by `distortion_maps`, gives this camera's."""
        if not self.k1:
            return self
        K = self.K.copy()
        scale = self.undistort_scale()
        K[0, 0] /= scale
        K[1, 1] /= scale
        return Camera(K, self.R, self.eye, self.width, self.height)

    def distortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """`cv2.remap` maps (float32, H x W) from this camera's pixels to `render_camera`'s."""
        render = self.render_camera()
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xd, yd = (u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1]
        rd = np.hypot(xd, yd)
        ratio = np.where(rd > 1e-12, _undistort_radius(rd, self.k1) / np.maximum(rd, 1e-12), 1.0)
        map_x = render.K[0, 0] * xd * ratio + render.K[0, 2]
        map_y = render.K[1, 1] * yd * ratio + render.K[1, 2]
        return map_x.astype(np.float32), map_y.astype(np.float32)

    def scaled(self, factor: float) -> "Camera":
        """The same camera imaging at `factor` times the resolution (pixel centres stay consistent)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Camera(K, self.R, self.eye, int(round(self.width * factor)), int(round(self.height * factor)), self.k1)

    @staticmethod
    def look_at(eye, target, focal: float, width: int, height: int, roll: float = 0.0,
                principal: tuple[float, float] | None = None) -> "Camera":
        """A level camera at `eye` looking at `target` (world z up), rolled by `roll` rad."""
        eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        fwd = target - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, (0.0, 0.0, 1.0))
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        c, s = math.cos(roll), math.sin(roll)
        right, down = c * right + s * down, -s * right + c * down
        cx, cy = principal if principal is not None else ((width - 1) / 2, (height - 1) / 2)
        K = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
        return Camera(K, np.stack([right, down, fwd]), eye, width, height)


def _undistort_radius(rd: np.ndarray, k1: float, iterations: int = 20) -> np.ndarray:
    """The undistorted radius r_u with r_u (1 + k1 r_u^2) = rd (fixed-point iteration, as cv2.undistortPoints)."""
    ru = rd.copy()
    for _ in range(iterations):
        ru = rd / (1.0 + k1 * ru * ru)
    return ru
