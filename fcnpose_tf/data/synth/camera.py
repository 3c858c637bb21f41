"""The pinhole camera that frames every synthetic scene (projection, look-at, resolution scaling)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Camera:
    """Pinhole camera: K (3 x 3), R (world -> camera rotation, rows = right, down, forward), eye (m).

    Pixel coordinates follow the pixel-centre convention (pixel i's centre is at i), as OpenCV and VIA.
    """

    K: np.ndarray
    R: np.ndarray
    eye: np.ndarray
    width: int
    height: int

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (N x 3) in camera coordinates (x right, y down, z forward)."""
        return (np.asarray(points, np.float64) - self.eye) @ self.R.T

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N x 2 pixel coordinates, N depths) of world points; depth <= 0 means behind the camera."""
        pc = self.to_camera(points)
        z = pc[:, 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = np.stack([self.K[0, 0] * pc[:, 0] / zs + self.K[0, 2], self.K[1, 1] * pc[:, 1] / zs + self.K[1, 2]], 1)
        return uv, z

    def scaled(self, factor: float) -> "Camera":
        """The same camera imaging at `factor` times the resolution (pixel centres stay consistent)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Camera(K, self.R, self.eye, int(round(self.width * factor)), int(round(self.height * factor)))

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
