"""Scene primitives: materials, the key light, tubes, spheres and boxes, and what each pixel shows (labels)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fcnpose_tf.data.synth.kinematics import PI


@dataclass
class Material:
    """Surface colour (RGB, 0..1) with a Blinn-Phong highlight."""

    rgb: np.ndarray
    specular: float = 0.1
    shininess: float = 16.0


@dataclass
class Light:
    """A directional key light (unit vector toward the light) plus hemispheric ambient light, and an
    optional second directional light (`fill` > 0) of another colour that casts no shadow."""

    direction: np.ndarray
    color: np.ndarray
    diffuse: float
    ambient: float
    fill_direction: np.ndarray | None = None
    fill_color: np.ndarray | None = None
    fill: float = 0.0


@dataclass
class Tube:
    """A (possibly tapered, elliptic) cylinder from p0 to p1; radii (along u, across u) at each end."""

    p0: np.ndarray
    p1: np.ndarray
    r0: tuple[float, float]
    r1: tuple[float, float]
    material: Material
    label: int
    caps: tuple[bool, bool] = (True, True)
    cap_material: Material | None = None
    u: np.ndarray | None = None
    segments: int = 20
    cap_in_front: bool = False  # nothing sticks out of the end discs: sort them by their nearest rim point

    def centroid(self) -> np.ndarray:
        return 0.5 * (self.p0 + self.p1)


@dataclass
class Sphere:
    centre: np.ndarray
    radius: float
    material: Material
    label: int

    def centroid(self) -> np.ndarray:
        return self.centre


@dataclass
class Box:
    """An oriented box: centre and three half-extent vectors (columns of `axes`)."""

    centre: np.ndarray
    axes: np.ndarray
    material: Material
    label: int
    top_material: Material | None = None
    edges: bool = False

    def centroid(self) -> np.ndarray:
        return self.centre

    def corners(self) -> np.ndarray:
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
        return self.centre + signs @ self.axes.T


Part = Tube | Sphere | Box

LABEL_ROBOT, LABEL_PERSON, LABEL_CLUTTER, LABEL_MOUNT = 1, 2, 3, 4


def box_part(centre, size, yaw: float, material: Material, label: int, **kw) -> Box:
    c, s = math.cos(yaw), math.sin(yaw)
    axes = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) * (np.asarray(size, np.float64) / 2)
    return Box(np.asarray(centre, np.float64), axes, material, label, **kw)


_RING_COS, _RING_SIN = np.cos(np.arange(8) * PI / 4), np.sin(np.arange(8) * PI / 4)
_SPHERE_DIRS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if x or y or z], float)
_SPHERE_DIRS /= np.linalg.norm(_SPHERE_DIRS, axis=1, keepdims=True)


def part_points(part: Part) -> np.ndarray:
    """A few points on a part's outline (for framing, shadows and overlap tests)."""
    if isinstance(part, Box):
        return part.corners()
    if isinstance(part, Sphere):
        return part.centre + part.radius * _SPHERE_DIRS
    a = part.p1 - part.p0
    a = a / max(np.linalg.norm(a), 1e-9)
    u = perpendicular(a, part.u)
    v = cross3(a, u)
    ring = _RING_COS[:, None] * u + _RING_SIN[:, None] * v
    r0, r1 = max(part.r0), max(part.r1)
    return np.vstack([part.p0 + r0 * ring, part.p1 + r1 * ring])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross is ~20x slower on single vectors)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def perpendicular(a: np.ndarray, hint: np.ndarray | None) -> np.ndarray:
    """A unit vector perpendicular to unit vector `a`, as close to `hint` as possible."""
    if hint is None:
        hint = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = hint - float(hint @ a) * a
    n = math.sqrt(float(u @ u))
    if n < 1e-6:
        return perpendicular(a, None)
    return u / n
