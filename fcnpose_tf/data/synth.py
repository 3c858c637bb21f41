"""Synthetic UR5 scenes: rendered frames with exact keypoints, standing in for the paper's webcam data.

Every frame is built from scratch by a small numpy/OpenCV renderer (no TensorFlow,
no 3-D engine): a UR5 posed by forward kinematics from its published DH
parameters, seen by a pinhole camera on a "tripod" next to the robot, in a
randomised room (floor, walls, clutter, a person) under randomised light and
sensor effects. The keypoints are the projections of known 3-D points, so the
labels are exact; what a human annotator would click (joint centres, flange
centre, tool tip) is defined in `ur5_keypoints_3d`.

Each frame's randomness comes from its own generator seeded with (seed, index),
so a frame does not depend on which worker renders it or on the other frames:
the same seed gives byte-identical files for any number of workers.

Public API: `forward_kinematics`, `ur5_keypoints_3d`, `sample_joints`, `Camera`,
`render_sample` / `render_frame` (one frame in memory), `generate` /
`generate_dataset` (a dataset folder: images/*.png plus one VIA project file),
`draw_keypoints` / `preview_grid` / `write_preview` (pictures to look at).
See docs/synthetic.md.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.system import available_cores
from fcnpose_tf.keypoints import UR5

PI = math.pi

# ================================================================================ kinematics

UR5_DH_D = np.array([0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823])
"""DH link offsets d1..d6 (m), Universal Robots' published UR5 parameters."""
UR5_DH_A = np.array([0.0, -0.425, -0.39225, 0.0, 0.0, 0.0])
"""DH link lengths a1..a6 (m)."""
UR5_DH_ALPHA = np.array([PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0])
"""DH link twists alpha1..alpha6 (rad)."""
UR5_JOINT_LIMITS = np.array([[-2 * PI, 2 * PI]] * 6)
"""Joint limits (rad): every UR5 joint turns +-360 degrees."""

SHOULDER_OFFSET = 0.13585
"""Upper-arm centreline offset along the shoulder/elbow axes from the DH plane (UR5 URDF)."""
FOREARM_OFFSET = 0.13585 - 0.1197
"""Forearm centreline offset along the same axes (the elbow steps back 0.1197 m)."""

# Joint housings: (axis frame index i -> axis z_i through DH origin O_i, span (lo, hi) along that axis, radius,
# what each end shows: a blue-grey "cap", a "plain" face, or nothing when "buried" in the previous housing).
# The keypoint of a joint is the centre of its housing on the joint axis, where an annotator clicks.
_HOUSINGS = {
    "shoulder": (1, (-0.070, 0.205), 0.0625, ("cap", "cap")),
    "elbow": (2, (-0.045, 0.205), 0.0500, ("cap", "cap")),
    "wrist1": (3, (-0.045, 0.160), 0.0450, ("cap", "cap")),
    "wrist2": (4, (-0.010, 0.150), 0.0450, ("buried", "cap")),
    "wrist3": (5, (-0.010, 0.070), 0.0450, ("buried", "plain")),
}
_BASE_SPAN, _BASE_RADIUS = (0.012, 0.075), 0.0640
_FLANGE_SPAN, _FLANGE_RADIUS = (0.070, 0.0823), 0.0315


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Standard (distal) DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha) as a 4 x 4 matrix."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct],
                     [st, ct * ca, -ct * sa, a * st],
                     [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


def forward_kinematics(q: Sequence[float]) -> np.ndarray:
    """The 7 DH frames (base, after joints 1..6) of a UR5 at joint angles q (rad), 7 x 4 x 4, base frame.

    Frame i's origin O_i lies on joint i+1's axis z_i; frame 6 is the tool flange.
    With all joints at zero the arm is stretched along -x: O_6 = (-0.81725, -0.19145, -0.005491).
    """
    q = np.asarray(q, np.float64).reshape(6)
    frames = np.empty((7, 4, 4))
    frames[0] = np.eye(4)
    for i in range(6):
        frames[i + 1] = frames[i] @ dh_transform(q[i], UR5_DH_D[i], UR5_DH_A[i], UR5_DH_ALPHA[i])
    return frames


def ur5_keypoints_3d(q: Sequence[float], tool_length: float = 0.12, base_z: float = 0.0) -> np.ndarray:
    """World positions (8 x 3, m) of the UR5 keypoints in `UR5` order for joint angles q.

    base: centre of the robot's mounting face (z = base_z); shoulder .. wrist3:
    centre of each joint housing on its axis; flange: tool-flange centre (DH O_6);
    tool: tip of the tool, tool_length along the flange normal.
    """
    frames = forward_kinematics(q)
    origin = frames[:, :3, 3] + (0.0, 0.0, base_z)
    axis = frames[:, :3, 2]
    points = [origin[0]]
    for name in ("shoulder", "elbow", "wrist1", "wrist2", "wrist3"):
        i, (lo, hi), _, _ = _HOUSINGS[name]
        points.append(origin[i] + 0.5 * (lo + hi) * axis[i])
    points.append(origin[6])
    points.append(origin[6] + tool_length * axis[6])
    return np.array(points)


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point (N x 3) to the segment a-b."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def pose_is_plausible(q: Sequence[float], tool_length: float = 0.12) -> bool:
    """True when the arm stays above its mounting plane and clear of its own base and upper arm.

    Checks the obvious self-collisions only (wrist and tool against the base column and
    the upper arm, forearm against the base column); the elbow is kept below +-2.7 rad.
    """
    q = np.asarray(q, np.float64)
    if abs(q[2]) > 2.7:
        return False
    frames = forward_kinematics(q)
    o, z = frames[:, :3, 3], frames[:, :3, 2]
    kp = ur5_keypoints_3d(q, tool_length)
    if kp[1:7, 2].min() < 0.075 or kp[7, 2] < 0.03:
        return False
    elbow_arm = o[2] + FOREARM_OFFSET * z[2]
    wrist_arm = o[3] + FOREARM_OFFSET * z[3]
    forearm = elbow_arm + np.linspace(0.25, 1.0, 6)[:, None] * (wrist_arm - elbow_arm)
    distal = np.vstack([kp[3:8], o[4], o[5], forearm])
    base_a, base_b = np.zeros(3), np.array([0.0, 0.0, UR5_DH_D[0] + 0.08])
    if _segment_distance(distal, base_a, base_b).min() < 0.17:
        return False
    upper_a, upper_b = o[1] + SHOULDER_OFFSET * z[1], o[2] + SHOULDER_OFFSET * z[1]
    if _segment_distance(np.vstack([kp[4:8], o[5]]), upper_a, upper_b).min() < 0.12:
        return False
    return True


def _wrap(angle: float) -> float:
    return (angle + PI) % (2 * PI) - PI


@dataclass(frozen=True)
class WorkTask:
    """The poses a workcell's arm takes: its base turns within `half_width` of `yaw` (rad), the elbow
    stays on one side (`elbow` = +1 or -1), the tool points roughly down (pick and place)."""

    yaw: float
    half_width: float = math.radians(45.0)
    elbow: float = 1.0


def sample_joints(rng: np.random.Generator, tool_length: float = 0.12, task: WorkTask | None = None) -> np.ndarray:
    """Random plausible joint angles (rad), biased toward poses a working UR5 takes.

    Without a task: any base angle; four in five draws raise the upper arm and bend the elbow
    (either way); three in five point the tool roughly down (wrist 1 compensating shoulder +
    elbow). With a `task`: the base within the task's sector, the upper arm raised, the elbow on
    the task's side, the tool down. Draws that hit the floor or the robot itself
    (`pose_is_plausible`) are redrawn.
    """
    for _ in range(1000):
        q = np.empty(6)
        if task is not None:
            q[0] = task.yaw + rng.uniform(-task.half_width, task.half_width)
            q[1] = rng.uniform(-2.4, -0.7)
            q[2] = rng.uniform(0.5, 2.4) * task.elbow
            q[3] = _wrap(-PI / 2 - q[1] - q[2] + rng.normal(0.0, 0.35))
            q[4] = -PI / 2 + rng.normal(0.0, 0.35)
            q[5] = rng.uniform(-PI, PI)
            if pose_is_plausible(q, tool_length):
                return q
            continue
        q[0] = rng.uniform(-PI, PI)
        if rng.random() < 0.8:
            q[1] = rng.uniform(-2.55, -0.55)
            q[2] = rng.uniform(0.35, 2.5) * (1.0 if rng.random() < 0.5 else -1.0)
        else:
            q[1] = rng.uniform(-PI, 0.0)
            q[2] = rng.uniform(-2.7, 2.7)
        if rng.random() < 0.6:
            q[3] = _wrap(-PI / 2 - q[1] - q[2] + rng.normal(0.0, 0.35))
            q[4] = (-PI / 2 if rng.random() < 0.7 else PI / 2) + rng.normal(0.0, 0.35)
        else:
            q[3] = rng.uniform(-PI, PI)
            q[4] = rng.uniform(-PI, PI)
        q[5] = rng.uniform(-PI, PI)
        if pose_is_plausible(q, tool_length):
            return q
    raise RuntimeError("no plausible UR5 pose found in 1000 draws")  # pragma: no cover - never seen


# ================================================================================ camera


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


# ================================================================================ scene primitives


@dataclass
class Material:
    """Surface colour (RGB, 0..1) with a Blinn-Phong highlight."""

    rgb: np.ndarray
    specular: float = 0.1
    shininess: float = 16.0


@dataclass
class Light:
    """A directional key light (unit vector toward the light) plus hemispheric ambient light."""

    direction: np.ndarray
    color: np.ndarray
    diffuse: float
    ambient: float


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


def _box(centre, size, yaw: float, material: Material, label: int, **kw) -> Box:
    c, s = math.cos(yaw), math.sin(yaw)
    axes = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) * (np.asarray(size, np.float64) / 2)
    return Box(np.asarray(centre, np.float64), axes, material, label, **kw)


_RING_COS, _RING_SIN = np.cos(np.arange(8) * PI / 4), np.sin(np.arange(8) * PI / 4)
_SPHERE_DIRS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if x or y or z], float)
_SPHERE_DIRS /= np.linalg.norm(_SPHERE_DIRS, axis=1, keepdims=True)


def _part_points(part: Part) -> np.ndarray:
    """A few points on a part's outline (for framing, shadows and overlap tests)."""
    if isinstance(part, Box):
        return part.corners()
    if isinstance(part, Sphere):
        return part.centre + part.radius * _SPHERE_DIRS
    a = part.p1 - part.p0
    a = a / max(np.linalg.norm(a), 1e-9)
    u = _perpendicular(a, part.u)
    v = _cross(a, u)
    ring = _RING_COS[:, None] * u + _RING_SIN[:, None] * v
    r0, r1 = max(part.r0), max(part.r1)
    return np.vstack([part.p0 + r0 * ring, part.p1 + r1 * ring])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross is ~20x slower on single vectors)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _perpendicular(a: np.ndarray, hint: np.ndarray | None) -> np.ndarray:
    """A unit vector perpendicular to unit vector `a`, as close to `hint` as possible."""
    if hint is None:
        hint = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = hint - float(hint @ a) * a
    n = math.sqrt(float(u @ u))
    if n < 1e-6:
        return _perpendicular(a, None)
    return u / n


# ================================================================================ the robot


UR5_SILVER = np.array([0.80, 0.81, 0.82])
UR5_CAP_BLUE = np.array([0.47, 0.60, 0.73])
UR5_BAND_DARK = np.array([0.11, 0.115, 0.125])


@dataclass
class RobotStyle:
    """Colours and tool of one rendered UR5 (varied a little per frame, like real paint and light)."""

    silver: Material
    cap: Material
    band: Material
    tool: str
    tool_length: float
    tool_material: Material
    finger_material: Material


def _robot_style(rng: np.random.Generator) -> RobotStyle:
    jitter = lambda c, s: np.clip(c + rng.normal(0.0, s, 3), 0, 1)  # noqa: E731
    silver = Material(jitter(UR5_SILVER * rng.uniform(0.9, 1.05), 0.015), specular=rng.uniform(0.25, 0.45),
                      shininess=rng.uniform(12, 30))
    cap = Material(jitter(UR5_CAP_BLUE * rng.uniform(0.85, 1.1), 0.03), specular=0.25, shininess=30)
    band = Material(jitter(UR5_BAND_DARK, 0.01), specular=0.15, shininess=20)
    tool = str(rng.choice(["gripper", "gripper", "gripper", "spindle", "suction"]))
    length = {"gripper": rng.uniform(0.12, 0.17), "spindle": rng.uniform(0.10, 0.15),
              "suction": rng.uniform(0.09, 0.13)}[tool]
    body = [np.array([0.08, 0.08, 0.09]), np.array([0.2, 0.2, 0.22]), np.array([0.62, 0.63, 0.65]),
            np.array([0.75, 0.35, 0.08])][rng.integers(4)]
    fingers = [np.array([0.12, 0.12, 0.13]), np.array([0.55, 0.56, 0.58])][rng.integers(2)]
    return RobotStyle(silver, cap, band, tool, float(length), Material(jitter(body, 0.02), 0.3, 24),
                      Material(fingers, 0.3, 24))


def _housing_parts(centre_o, axis, span, radius, style: RobotStyle, ends=("cap", "cap")) -> list[Part]:
    """A UR joint housing: a silver body whose ends are each a dark band plus blue-grey cap ("cap"),
    a plain silver face ("plain") or hidden inside the neighbouring housing ("buried", no face)."""
    lo, hi = span
    band, cap = 0.010, 0.014
    p = lambda s: centre_o + s * axis  # noqa: E731
    body_lo = lo + (band + cap if ends[0] == "cap" else 0.0)
    body_hi = hi - (band + cap if ends[1] == "cap" else 0.0)
    parts: list[Part] = [Tube(p(body_lo), p(body_hi), (radius, radius), (radius, radius), style.silver,
                              LABEL_ROBOT, caps=(ends[0] == "plain", ends[1] == "plain"), segments=24)]
    for end, kind in enumerate(ends):
        if kind != "cap":
            continue
        sign = -1.0 if end == 0 else 1.0
        edge = lo if end == 0 else hi
        b0, b1 = edge - sign * (band + cap), edge - sign * cap
        parts.append(Tube(p(b0), p(b1), (radius * 0.985,) * 2, (radius * 0.985,) * 2, style.band, LABEL_ROBOT,
                          caps=(False, False), segments=24))
        r_out = radius * 0.97
        parts.append(Tube(p(b1), p(edge), (r_out, r_out), (r_out * 0.92, r_out * 0.92), style.cap, LABEL_ROBOT,
                          caps=(False, True), segments=24, cap_in_front=True))  # p1 is the outer end
    return parts


def ur5_parts(q: Sequence[float], style: RobotStyle, base_z: float = 0.0) -> list[Part]:
    """The UR5's shapes (world coordinates) at joint angles q, mounted with its base face at height base_z."""
    frames = forward_kinematics(q)
    o = frames[:, :3, 3] + (0.0, 0.0, base_z)
    z = frames[:, :3, 2]
    x = frames[:, :3, 0]
    up = np.array([0.0, 0.0, 1.0])
    silver = style.silver
    parts: list[Part] = []
    # base: dark mounting ring and the vertical joint-1 housing
    parts.append(Tube(o[0], o[0] + 0.012 * up, (0.09, 0.09), (0.088, 0.088), style.band, LABEL_ROBOT,
                      caps=(False, True), segments=28))
    parts.append(Tube(o[0] + _BASE_SPAN[0] * up, o[0] + 0.022 * up, (_BASE_RADIUS,) * 2, (_BASE_RADIUS,) * 2,
                      style.band, LABEL_ROBOT, caps=(False, False), segments=24))
    parts.append(Tube(o[0] + 0.022 * up, o[0] + _BASE_SPAN[1] * up, (_BASE_RADIUS,) * 2, (_BASE_RADIUS,) * 2,
                      silver, LABEL_ROBOT, caps=(False, True), segments=24))
    for name in ("shoulder", "elbow", "wrist1", "wrist2", "wrist3"):
        i, span, radius, ends = _HOUSINGS[name]
        parts += _housing_parts(o[i], z[i], span, radius, style, ends)
    # upper arm and forearm tubes, thicker where they meet the housings
    ua0, ua1 = o[1] + SHOULDER_OFFSET * z[1], o[2] + SHOULDER_OFFSET * z[1]
    fa0, fa1 = o[2] + FOREARM_OFFSET * z[2], o[3] + FOREARM_OFFSET * z[3]
    for a, b, r in ((ua0, ua1, 0.044), (fa0, fa1, 0.037)):
        d = (b - a) / np.linalg.norm(b - a)
        parts.append(Tube(a + 0.04 * d, b - 0.04 * d, (r, r), (r, r), silver, LABEL_ROBOT, caps=(False, False)))
        parts.append(Tube(a, a + 0.07 * d, (r * 1.12, r * 1.12), (r, r), silver, LABEL_ROBOT, caps=(False, False)))
        parts.append(Tube(b - 0.07 * d, b, (r, r), (r * 1.12, r * 1.12), silver, LABEL_ROBOT, caps=(False, False)))
    # tool flange and tool
    parts.append(Tube(o[5] + _FLANGE_SPAN[0] * z[5], o[6], (_FLANGE_RADIUS,) * 2, (_FLANGE_RADIUS,) * 2,
                      Material(silver.rgb * 0.8, 0.4, 30), LABEL_ROBOT, caps=(False, True), segments=20))
    parts += _tool_parts(o[6], z[6], x[6], style)
    return parts


def _tool_parts(flange: np.ndarray, n: np.ndarray, side: np.ndarray, style: RobotStyle) -> list[Part]:
    L = style.tool_length
    m = style.tool_material
    if style.tool == "gripper":
        body = 0.55 * L
        parts: list[Part] = [Tube(flange, flange + 0.012 * n, (0.036,) * 2, (0.036,) * 2, style.band, LABEL_ROBOT,
                                  caps=(False, True)),
                             Tube(flange + 0.012 * n, flange + body * n, (0.037, 0.030), (0.037, 0.030), m,
                                  LABEL_ROBOT, caps=(False, True), u=side, segments=16)]
        for sgn in (-1.0, 1.0):
            a = flange + body * n + sgn * 0.018 * side
            b = flange + L * n + sgn * 0.009 * side
            parts.append(Box(0.5 * (a + b), np.stack([0.006 * side, 0.011 * np.cross(n, side), 0.5 * (b - a)], 1),
                             style.finger_material, LABEL_ROBOT))
        return parts
    if style.tool == "spindle":
        return [Tube(flange, flange + 0.45 * L * n, (0.034,) * 2, (0.030,) * 2, m, LABEL_ROBOT, segments=16),
                Tube(flange + 0.45 * L * n, flange + L * n, (0.014,) * 2, (0.004,) * 2, style.finger_material,
                     LABEL_ROBOT, segments=12)]
    return [Tube(flange, flange + 0.35 * L * n, (0.032,) * 2, (0.026,) * 2, m, LABEL_ROBOT, segments=16),
            Tube(flange + 0.35 * L * n, flange + 0.8 * L * n, (0.009,) * 2, (0.009,) * 2, style.finger_material,
                 LABEL_ROBOT, segments=10),
            Tube(flange + 0.8 * L * n, flange + L * n, (0.010,) * 2, (0.024,) * 2,
                 Material(np.array([0.06, 0.06, 0.07]), 0.2, 16), LABEL_ROBOT, segments=14)]


# ================================================================================ the person


_SKIN = np.array([[0.95, 0.80, 0.69], [0.88, 0.68, 0.55], [0.76, 0.57, 0.42], [0.55, 0.38, 0.26],
                  [0.38, 0.25, 0.17]])
_HAIR = np.array([[0.05, 0.04, 0.04], [0.18, 0.11, 0.06], [0.35, 0.22, 0.12], [0.75, 0.62, 0.38],
                  [0.45, 0.18, 0.08]])
_SHIRT = np.array([[0.70, 0.12, 0.12], [0.10, 0.14, 0.36], [0.14, 0.45, 0.20], [0.07, 0.07, 0.08],
                   [0.92, 0.45, 0.10], [0.85, 0.75, 0.15], [0.42, 0.20, 0.50], [0.45, 0.08, 0.12],
                   [0.08, 0.45, 0.45], [0.45, 0.30, 0.18], [0.85, 0.93, 0.15], [0.78, 0.68, 0.48]])
_TROUSERS = np.array([[0.17, 0.24, 0.40], [0.07, 0.07, 0.08], [0.58, 0.52, 0.38], [0.22, 0.22, 0.23],
                      [0.12, 0.14, 0.24]])
_HELMET = np.array([[0.95, 0.8, 0.1], [0.85, 0.15, 0.1], [0.95, 0.45, 0.1], [0.1, 0.3, 0.8]])


def person_parts(rng: np.random.Generator, feet: np.ndarray, facing: float, height: float,
                 reach: np.ndarray | None = None) -> list[Part]:
    """A standing person (legs, torso, arms, head) of `height` m at floor point `feet`, facing yaw `facing`.

    With `reach` (a world point), the arm on that side reaches toward it, as a co-worker handing
    something to the robot; otherwise both arms take random relaxed or working poses.
    """
    pick = lambda table: table[rng.integers(len(table))] * rng.uniform(0.9, 1.08)  # noqa: E731
    skin = Material(np.clip(pick(_SKIN), 0, 1), 0.08, 10)
    shirt = Material(np.clip(pick(_SHIRT), 0, 1), 0.05, 8)
    trousers = Material(np.clip(pick(_TROUSERS), 0, 1), 0.04, 8)
    shoes = Material(np.array([0.06, 0.05, 0.05]) + rng.uniform(0, 0.15), 0.1, 10)
    helmet = rng.random() < 0.2
    hair = Material(pick(_HELMET) if helmet else np.clip(pick(_HAIR), 0, 1), 0.3 if helmet else 0.05, 20)
    long_sleeves = rng.random() < 0.5
    fwd = np.array([math.cos(facing), math.sin(facing), 0.0])
    lat = np.array([-math.sin(facing), math.cos(facing), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    h = height
    base = np.array([feet[0], feet[1], 0.0])
    hip_z, sh_z = 0.52 * h, 0.815 * h
    parts: list[Part] = []
    lab = LABEL_PERSON
    for side in (-1.0, 1.0):
        hip = base + up * hip_z + side * 0.085 * lat
        foot = base + up * 0.07 + side * 0.11 * lat + rng.uniform(-0.15, 0.15) * fwd
        knee = 0.5 * (hip + foot) + rng.uniform(0.0, 0.06) * fwd
        parts.append(Tube(hip, knee, (0.08,) * 2, (0.06,) * 2, trousers, lab, caps=(False, False), segments=14))
        parts.append(Sphere(knee, 0.06, trousers, lab))
        parts.append(Tube(knee, foot, (0.06,) * 2, (0.05,) * 2, trousers, lab, caps=(False, False), segments=14))
        parts.append(_box(foot + 0.05 * fwd - 0.035 * up, (0.27, 0.1, 0.08), facing, shoes, lab))
        shoulder = base + up * (sh_z - 0.035) + side * 0.2 * lat
        if reach is not None and side * ((reach - base) @ lat) >= 0:  # the arm on the target's side
            to_target = (reach - shoulder) / max(np.linalg.norm(reach - shoulder), 1e-6)
            upper_dir = to_target - 0.3 * up
            upper_dir /= np.linalg.norm(upper_dir)
            elbow = shoulder + 0.17 * h * upper_dir
            fore_dir = (reach - elbow) / max(np.linalg.norm(reach - elbow), 1e-6)
        else:
            flex, abduct = rng.uniform(-0.4, 1.4), rng.uniform(0.05, 0.45)
            upper_dir = -up * math.cos(flex) + fwd * math.sin(flex)
            upper_dir = upper_dir * math.cos(abduct) + side * lat * math.sin(abduct)
            elbow = shoulder + 0.17 * h * upper_dir
            bend = rng.uniform(0.0, 1.9)  # elbow flexion: the forearm swings forward about the lateral axis
            ahead = np.cross(upper_dir, lat)
            ahead /= max(np.linalg.norm(ahead), 1e-6)
            fore_dir = upper_dir * math.cos(bend) + ahead * math.sin(bend)
        wrist = elbow + 0.145 * h * fore_dir
        sleeve = shirt if long_sleeves else skin
        parts.append(Sphere(shoulder, 0.052, shirt, lab))
        parts.append(Tube(shoulder, elbow, (0.056,) * 2, (0.045,) * 2, shirt, lab, caps=(False, False), segments=12))
        parts.append(Sphere(elbow, 0.044, sleeve, lab))
        parts.append(Tube(elbow, wrist, (0.044,) * 2, (0.032,) * 2, sleeve, lab, caps=(False, False), segments=12))
        parts.append(Sphere(wrist + 0.045 * fore_dir, 0.04, skin, lab))
    parts.append(Tube(base + up * (hip_z - 0.1), base + up * (hip_z + 0.04), (0.17, 0.115), (0.17, 0.115),
                      trousers, lab, caps=(True, False), u=lat, segments=16))
    parts.append(Tube(base + up * (hip_z + 0.02), base + up * (sh_z + 0.01), (0.165, 0.11), (0.205, 0.12), shirt,
                      lab, caps=(False, True), u=lat, segments=18))
    yoke = base + up * (sh_z - 0.035)
    parts.append(Tube(yoke - 0.2 * lat, yoke + 0.2 * lat, (0.055, 0.05), (0.055, 0.05), shirt, lab, u=up,
                      caps=(False, False), segments=14))
    parts.append(Tube(base + up * (sh_z - 0.02), base + up * 0.875 * h, (0.06,) * 2, (0.052,) * 2, skin, lab,
                      caps=(False, False), segments=12))
    head = base + up * 0.925 * h + 0.01 * fwd
    parts.append(Sphere(head, 0.057 * h, skin, lab))
    if helmet:
        parts.append(Sphere(head + up * 0.035 - 0.01 * fwd, 0.062 * h, hair, lab))
    else:
        parts.append(Sphere(head + up * 0.018 - 0.022 * fwd, 0.059 * h, hair, lab))
    return parts


# ================================================================================ textures


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth value noise (~N(0, 1)) with features about `cell` texels across."""
    h, w = shape
    gh, gw = max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def _fractal(rng, shape, cells=(64, 16, 4), weights=(1.0, 0.5, 0.25)) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for c, wt in zip(cells, weights):
        out += wt * _noise(rng, shape, c)
    return out


def _floor_texture(rng: np.random.Generator, size: int, ppm: float) -> np.ndarray:
    """A size x size RGB texture covering size/ppm metres of floor (tiles seamlessly every few metres)."""
    kind = rng.choice(["concrete", "concrete", "concrete", "epoxy", "epoxy", "tiles", "tiles", "wood", "wood", "vinyl",
                       "checker"])
    shape = (size, size)
    if kind == "concrete":
        base = np.full(3, rng.uniform(0.42, 0.68)) * (1 + rng.normal(0, 0.03, 3))
        tex = base * (1 + 0.07 * _fractal(rng, shape)[..., None])
        tex *= 1 - 0.12 * np.clip(_noise(rng, shape, 90), 0, None)[..., None]
        step = int(ppm * rng.choice([1.0, 2.0, 4.0])) or size
        tex[::step, :] *= 0.6
        tex[:, ::step] *= 0.6
    elif kind == "epoxy":
        base = [np.array([0.45, 0.52, 0.45]), np.array([0.42, 0.47, 0.55]), np.array([0.58, 0.58, 0.56]),
                np.array([0.55, 0.33, 0.28]), np.array([0.35, 0.42, 0.35])][rng.integers(5)]
        tex = base * (1 + 0.04 * _fractal(rng, shape, (48, 8, 2))[..., None])
        tex += 0.05 * (rng.random(shape, dtype=np.float32) > 0.97)[..., None]
    elif kind == "tiles":
        n_tiles = int(rng.choice([5, 8, 10, 16]))
        cell = (np.arange(size) * n_tiles) // size
        base = np.full(3, rng.uniform(0.5, 0.85)) * (1 + rng.normal(0, 0.05, 3))
        tone = 1 + rng.normal(0, 0.04, (n_tiles, n_tiles)).astype(np.float32)
        tex = base * tone[cell[:, None], cell[None, :]][..., None]
        tex *= 1 + 0.025 * _fractal(rng, shape, (32, 6))[..., None]
        edge = np.flatnonzero(np.diff(cell, prepend=-1))
        g = max(1, size // n_tiles // 40)
        grout = rng.uniform(0.3, 0.9) * base
        for i in edge:
            tex[i:i + g, :] = grout
            tex[:, i:i + g] = grout
    elif kind == "wood":
        n_planks = int(rng.choice([20, 25, 32, 40]))
        cell = (np.arange(size) * n_planks) // size
        base = np.array([0.62, 0.45, 0.28]) * rng.uniform(0.6, 1.15)
        grain = cv2.resize(rng.standard_normal((size // 2, 12), dtype=np.float32), (size, size),
                           interpolation=cv2.INTER_CUBIC)
        tone = (1 + rng.normal(0, 0.08, n_planks).astype(np.float32))[cell]
        tex = base * (tone[:, None] * (1 + 0.06 * grain))[..., None]
        edge = np.flatnonzero(np.diff(cell, prepend=-1))
        tex[edge, :] *= 0.55
        for lo, hi in zip(edge, list(edge[1:]) + [size]):
            cut = int(rng.integers(0, size))
            tex[lo:hi, cut:cut + 2] *= 0.6
        if rng.random() < 0.5:
            tex = np.ascontiguousarray(tex.transpose(1, 0, 2))
    elif kind == "vinyl":
        base = np.clip(np.array([0.75, 0.74, 0.70]) * (1 + rng.normal(0, 0.06, 3)), 0, 1)
        tex = base * (1 + 0.05 * _fractal(rng, shape, (24, 6, 2))[..., None])
        tex += 0.08 * (rng.random(shape, dtype=np.float32) > 0.985)[..., None] * (rng.random(3) - 0.5)
    else:  # checker lab floor
        n = int(rng.choice([8, 10, 16]))
        cell = (np.arange(size) * n) // size
        a, b = np.full(3, rng.uniform(0.06, 0.2)), np.full(3, rng.uniform(0.65, 0.85))
        ii = cell[:, None] + cell[None, :]
        tex = np.where((ii % 2 == 0)[..., None], a, b) * (1 + 0.03 * _fractal(rng, shape, (32, 4))[..., None])
    return np.clip(tex, 0, 1).astype(np.float32)


_WALL_PAINT = np.array([[0.92, 0.91, 0.88], [0.88, 0.86, 0.78], [0.78, 0.80, 0.80], [0.70, 0.78, 0.85],
                        [0.74, 0.84, 0.74], [0.90, 0.84, 0.62], [0.62, 0.64, 0.66], [0.85, 0.75, 0.72],
                        [0.55, 0.62, 0.72], [0.95, 0.95, 0.95]])


def _wall_texture(rng: np.random.Generator, length: float, height: float, ppm: float) -> np.ndarray:
    """RGB texture of one wall (length x height m): paint, brick or block, plus doors, windows, boards, shelves."""
    w, h = max(8, int(length * ppm)), max(8, int(height * ppm))
    kind = rng.choice(["paint", "paint", "paint", "brick", "block", "panel"])
    if kind == "brick":
        base = [np.array([0.62, 0.30, 0.22]), np.array([0.80, 0.78, 0.74]), np.array([0.55, 0.42, 0.35])][
            rng.integers(3)]
        bw, bh = int(0.23 * ppm), int(0.075 * ppm)
        rows = h // bh + 1
        cols = w // bw + 2
        tone = 1 + rng.normal(0, 0.07, (rows, cols)).astype(np.float32)
        tex = np.empty((h, w, 3), np.float32)
        for r in range(rows):
            off = (bw // 2) * (r % 2)
            line = np.repeat(tone[r], bw)[off:off + w]
            tex[r * bh:(r + 1) * bh] = base * line[None, :, None]
        mortar = np.array([0.75, 0.74, 0.70]) * rng.uniform(0.6, 1.0)
        tex[::bh] = mortar
        for r in range(rows):
            off = (bw // 2) * (r % 2)
            tex[r * bh:(r + 1) * bh, (bw - off) % bw::bw] = mortar
    elif kind == "block":
        base = np.full(3, rng.uniform(0.55, 0.8)) * (1 + rng.normal(0, 0.03, 3))
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        bw, bh = int(0.4 * ppm), int(0.2 * ppm)
        tex[::bh] *= 0.75
        for r in range(h // bh + 1):
            off = (bw // 2) * (r % 2)
            tex[r * bh:(r + 1) * bh, off::bw] *= 0.75
    elif kind == "panel":
        base = [np.array([0.80, 0.80, 0.78]), np.array([0.65, 0.50, 0.35]), np.array([0.55, 0.60, 0.62])][
            rng.integers(3)]
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        step = int(rng.uniform(0.6, 1.25) * ppm)
        tex[:, ::step] *= 0.6
    else:
        base = _WALL_PAINT[rng.integers(len(_WALL_PAINT))] * (1 + rng.normal(0, 0.03, 3))
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        if rng.random() < 0.35:  # two-tone wall
            band = int(rng.uniform(0.9, 1.3) * ppm)
            tex[h - band:] = _WALL_PAINT[rng.integers(len(_WALL_PAINT))] * 0.85
    tex *= 1 + 0.03 * _fractal(rng, (h, w), (48, 12))[..., None]

    def rect(x0, y0, x1, y1, color, edge=None):
        """A rectangle in metres from the wall's left end and from the floor."""
        p0 = (int(x0 * ppm), int(h - y1 * ppm))
        p1 = (int(x1 * ppm), int(h - y0 * ppm))
        cv2.rectangle(tex, p0, p1, tuple(float(c) for c in color), -1)
        if edge is not None:
            cv2.rectangle(tex, p0, p1, tuple(float(c) for c in edge), max(1, int(0.02 * ppm)))

    x = rng.uniform(0.0, 1.0)
    while x < length - 0.5:
        kind = rng.choice(["door", "window", "board", "poster", "shelf", "pegboard", "cabinet", "gap", "gap"])
        if kind == "door" and height > 2.3:
            wd = rng.uniform(0.85, 1.6)
            col = rng.uniform(0.2, 0.9, 3)
            rect(x, 0.0, x + wd, 2.1, col, col * 0.6)
            cv2.circle(tex, (int((x + wd - 0.1) * ppm), int(h - 1.0 * ppm)), max(1, int(0.03 * ppm)),
                       (0.7, 0.7, 0.7), -1)
            x += wd
        elif kind == "window" and height > 2.2:
            wd = rng.uniform(0.8, 2.5)
            y0 = rng.uniform(0.9, 1.2)
            y1 = min(height - 0.2, y0 + rng.uniform(0.8, 1.4))
            sky = np.array([0.85, 0.9, 0.97]) * rng.uniform(0.9, 1.1)
            rect(x, y0, x + wd, y1, sky, (0.3, 0.3, 0.32) if rng.random() < 0.5 else (0.9, 0.9, 0.9))
            xm = int((x + wd / 2) * ppm)
            cv2.line(tex, (xm, int(h - y1 * ppm)), (xm, int(h - y0 * ppm)), (0.5, 0.5, 0.5), max(1, int(0.03 * ppm)))
            x += wd
        elif kind in ("board", "poster"):
            wd = rng.uniform(0.4, 1.8) if kind == "board" else rng.uniform(0.3, 0.7)
            ht = rng.uniform(0.4, 1.1)
            y0 = rng.uniform(0.9, 1.4)
            col = np.array([0.93, 0.93, 0.92]) if kind == "board" else rng.uniform(0.1, 0.95, 3)
            rect(x, y0, x + wd, y0 + ht, col, (0.4, 0.4, 0.42))
            for k in range(int(rng.integers(0, 7))):  # writing / print lines
                yy = y0 + ht * (0.85 - 0.12 * k)
                if yy <= y0 + 0.05:
                    break
                rect(x + 0.05, yy, x + 0.05 + rng.uniform(0.1, wd - 0.1), yy + 0.015, rng.uniform(0, 0.6, 3))
            x += wd
        elif kind == "shelf":
            wd = rng.uniform(0.8, 2.0)
            for level in np.arange(rng.uniform(0.4, 0.8), min(height - 0.3, 2.2), rng.uniform(0.35, 0.5)):
                xx = x
                while xx < x + wd - 0.15:
                    bw = rng.uniform(0.1, 0.4)
                    rect(xx, level, min(xx + bw, x + wd), level + rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.9, 3))
                    xx += bw + rng.uniform(0.0, 0.15)
                rect(x, level - 0.03, x + wd, level, (0.3, 0.3, 0.32))
            x += wd
        elif kind == "pegboard":
            wd, y0, ht = rng.uniform(0.8, 1.6), rng.uniform(0.9, 1.1), rng.uniform(0.6, 1.0)
            rect(x, y0, x + wd, y0 + ht, np.array([0.75, 0.6, 0.42]) * rng.uniform(0.8, 1.1))
            for k in range(int(rng.integers(3, 9))):
                tx = x + rng.uniform(0.05, wd - 0.05)
                ty = y0 + rng.uniform(0.1, ht - 0.1)
                rect(tx, ty - rng.uniform(0.05, 0.25), tx + rng.uniform(0.02, 0.05), ty, rng.uniform(0, 0.9, 3))
            x += wd
        elif kind == "cabinet":
            wd = rng.uniform(0.4, 0.8)
            ht = rng.uniform(0.5, 0.9)
            y0 = rng.uniform(1.2, 1.6)
            rect(x, y0, x + wd, y0 + ht, np.array([0.78, 0.78, 0.76]) * rng.uniform(0.8, 1.05), (0.3, 0.3, 0.3))
            x += wd
        x += rng.uniform(0.2, 1.5)
    skirting = rng.uniform(0.0, 0.12)
    if skirting > 0.03:
        rect(0, 0, length, skirting, np.full(3, rng.uniform(0.1, 0.6)))
    return np.clip(tex, 0, 1).astype(np.float32)


# ================================================================================ rendering


def _shade(material: Material, normals: np.ndarray, points: np.ndarray, light: Light, eye: np.ndarray) -> np.ndarray:
    """Blinn-Phong colour (N x 3) of surface points with unit normals under the key + hemispheric light."""
    view = eye - points
    view /= np.linalg.norm(view, axis=-1, keepdims=True) + 1e-12
    ndl = np.clip(normals @ light.direction, 0.0, None)
    half = light.direction + view
    half /= np.linalg.norm(half, axis=-1, keepdims=True) + 1e-12
    spec = np.clip((normals * half).sum(-1), 0.0, None) ** material.shininess
    hemi = 0.55 + 0.45 * normals[..., 2]  # sky above, darker floor bounce below
    rim = np.clip(1.0 - (normals * view).sum(-1), 0.0, 1.0) ** 3  # a faint environment reflection at grazing
    col = material.rgb * (light.ambient * hemi + light.diffuse * ndl)[..., None] * light.color
    col = col + (material.specular * spec * light.diffuse)[..., None] * light.color + 0.08 * material.specular * rim[..., None]
    return np.clip(col, 0.0, 1.5)


class _Painter:
    """Painter's algorithm over facets: parts are cut into small planar facets (cylinder strips, caps, box
    faces, whole spheres), which are sorted by depth and drawn back to front onto a float RGB canvas and
    an integer label map. Sorting facets rather than whole parts keeps long links, joints that touch and
    a person next to the robot in the right order."""

    SEGMENT_LENGTH = 0.08  # m; longer cylinders are cut along their length too

    def __init__(self, canvas: np.ndarray, labels: np.ndarray, cam: Camera, light: Light, shift: int = 3,
                 depth: np.ndarray | None = None):
        self.canvas, self.labels, self.cam, self.light = canvas, labels, cam, light
        self.depth = depth  # optional float32 map of each pixel's facet depth (m), for occlusion tests
        self.shift = shift
        self.one = 1 << shift
        self.items: list[tuple[float, int, object, object, int]] = []

    def add(self, part: Part, min_depth: float = 0.0) -> None:
        """Queue a part's visible facets; `min_depth` pushes them back (drawn before nearer facets)."""
        if isinstance(part, Tube):
            self._tube(part, min_depth)
        elif isinstance(part, Sphere):
            self._sphere(part, min_depth)
        else:
            self._box(part, min_depth)

    def _fixed(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates as OpenCV's fixed-point integers (`shift` fractional bits)."""
        return np.round(uv * self.one).astype(np.int32)

    def _queue(self, depth: float, shape, color, label: int) -> None:
        """Queue a polygon (fixed-point int32 points) or a Sphere."""
        self.items.append((depth, len(self.items), shape, color, label))

    def flush(self) -> None:
        """Draw everything queued, farthest first."""
        self.items.sort(key=lambda it: (-it[0], it[1]))
        canvas, labels, depth, shift = self.canvas, self.labels, self.depth, self.shift
        for z, _, shape, color, label in self.items:
            if isinstance(shape, Sphere):
                self._draw_sphere(shape, label, z)
            else:
                cv2.fillConvexPoly(canvas, shape, color, cv2.LINE_8, shift)
                cv2.fillConvexPoly(labels, shape, label, cv2.LINE_8, shift)
                if depth is not None:
                    cv2.fillConvexPoly(depth, shape, z, cv2.LINE_8, shift)
        self.items.clear()

    def _tube(self, t: Tube, min_depth: float) -> None:
        axis = t.p1 - t.p0
        length = float(np.linalg.norm(axis))
        if length < 1e-6:
            return
        a = axis / length
        u = _perpendicular(a, t.u)
        v = _cross(a, u)
        n = t.segments
        m = max(1, int(math.ceil(length / self.SEGMENT_LENGTH)))
        th = np.arange(n) * (2 * PI / n)
        s = np.linspace(0.0, 1.0, m + 1)
        rx = t.r0[0] + (t.r1[0] - t.r0[0]) * s
        ry = t.r0[1] + (t.r1[1] - t.r0[1]) * s
        rings = (t.p0 + s[:, None] * axis)[:, None, :] + (rx[:, None, None] * np.cos(th)[None, :, None] * u
                                                          + ry[:, None, None] * np.sin(th)[None, :, None] * v)
        uv, z = self.cam.project(rings.reshape(-1, 3))
        if z.min() < 0.05:
            return
        uv = uv.reshape(m + 1, n, 2)
        thm = th + PI / n
        rxm, rym = 0.5 * (t.r0[0] + t.r1[0]), 0.5 * (t.r0[1] + t.r1[1])
        radial = (np.cos(thm) / rxm)[:, None] * u + (np.sin(thm) / rym)[:, None] * v
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        normals = radial + ((max(t.r0) - max(t.r1)) / length) * a
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        nxt = np.roll(np.arange(n), -1)
        centres = 0.25 * (rings[:-1] + rings[:-1, nxt] + rings[1:] + rings[1:, nxt])  # m x n x 3
        visible = ((self.cam.eye - centres) * normals).sum(-1) > 0
        if visible.any():
            colors = _shade(t.material, np.broadcast_to(normals, centres.shape), centres, self.light, self.cam.eye)
            depth = np.maximum(self.cam.to_camera(centres.reshape(-1, 3))[:, 2].reshape(m, n), min_depth)
            label = int(t.label)
            quads = self._fixed(np.stack([uv[:-1], uv[:-1, nxt], uv[1:, nxt], uv[1:]], axis=2))  # m x n x 4 x 2
            colors = colors.tolist()
            depth = depth.tolist()
            for j, i in zip(*np.nonzero(visible)):
                self._queue(depth[j][i], quads[j, i], tuple(colors[j][i]), label)
        cap_mat = t.cap_material or t.material
        z = z.reshape(m + 1, n)
        for capped, centre, normal, end in ((t.caps[0], t.p0, -a, 0), (t.caps[1], t.p1, a, -1)):
            if capped and (self.cam.eye - centre) @ normal > 0:
                col = _shade(cap_mat, normal[None], centre[None], self.light, self.cam.eye)[0]
                # a joint's end cap hides whatever is attached behind its plane (the link leaving the
                # housing's side), so it sorts by its nearest rim point rather than its centre
                depth = float(z[end].min()) if t.cap_in_front else float(self.cam.to_camera(centre[None])[0, 2])
                depth = max(depth, min_depth)
                self._queue(depth, self._fixed(uv[end]), tuple(col.tolist()), int(t.label))

    def _sphere(self, sp: Sphere, min_depth: float) -> None:
        depth = float(self.cam.to_camera(sp.centre[None])[0, 2])
        if depth > sp.radius + 0.05:
            self._queue(max(depth, min_depth), sp, None, int(sp.label))

    def _draw_sphere(self, sp: Sphere, label: int, z: float) -> None:
        pc = self.cam.to_camera(sp.centre[None])[0]
        K = self.cam.K
        cu, cv_ = K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2]
        rad = K[0, 0] * sp.radius / math.sqrt(max(pc @ pc - sp.radius ** 2, 1e-9))
        H, W = self.labels.shape
        x0, x1 = max(0, int(cu - rad - 1)), min(W, int(cu + rad + 2))
        y0, y1 = max(0, int(cv_ - rad - 1)), min(H, int(cv_ + rad + 2))
        if x0 >= x1 or y0 >= y1:
            return
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        dx, dy = (xx - cu) / rad, (yy - cv_) / rad
        r2 = dx * dx + dy * dy
        inside = r2 <= 1.0
        if not inside.any():
            return
        nz = -np.sqrt(np.clip(1.0 - r2[inside], 0.0, 1.0))
        n_world = np.stack([dx[inside], dy[inside], nz], 1) @ self.cam.R
        points = sp.centre + sp.radius * n_world
        self.canvas[y0:y1, x0:x1][inside] = _shade(sp.material, n_world, points, self.light, self.cam.eye)
        self.labels[y0:y1, x0:x1][inside] = label
        if self.depth is not None:
            self.depth[y0:y1, x0:x1][inside] = z

    _FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
    _FACE_AXIS = ((0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1))

    def _box(self, b: Box, min_depth: float) -> None:
        corners = b.corners()
        uv, z = self.cam.project(corners)
        if z.min() < 0.05:
            return
        for face, (ax, sign) in zip(self._FACES, self._FACE_AXIS):
            normal = sign * b.axes[:, ax] / np.linalg.norm(b.axes[:, ax])
            centre = b.centre + sign * b.axes[:, ax]
            if (self.cam.eye - centre) @ normal <= 0:
                continue
            mat = b.top_material if (b.top_material is not None and normal[2] > 0.9) else b.material
            col = _shade(mat, normal[None], centre[None], self.light, self.cam.eye)[0]
            depth = max(float(self.cam.to_camera(centre[None])[0, 2]), min_depth)
            if b.edges:  # a darker rim, as real edges and seams catch less light
                self._queue(depth, self._fixed(uv[list(face)]), tuple((col * 0.7).tolist()), int(b.label))
                inner = (corners[list(face)] - centre) * 0.97 + centre
                self._queue(depth - 1e-4, self._fixed(self.cam.project(inner)[0]), tuple(col.tolist()), int(b.label))
            else:
                self._queue(depth, self._fixed(uv[list(face)]), tuple(col.tolist()), int(b.label))


@dataclass
class Room:
    """An axis-aligned room: floor z = 0, walls at x/y limits, ceiling at `height`."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    height: float


def _render_background(rng: np.random.Generator, cam: Camera, room: Room, light: Light,
                       lamp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast floor, walls and ceiling: (H x W x 3 float32 RGB, H x W float32 floor mask)."""
    W, H = cam.width, cam.height
    K, R = cam.K, cam.R.astype(np.float32)
    a = ((np.arange(W, dtype=np.float32) - K[0, 2]) / K[0, 0])[None, :]
    b = ((np.arange(H, dtype=np.float32) - K[1, 2]) / K[1, 1])[:, None]
    d = [R[0, i] * a + R[1, i] * b + R[2, i] for i in range(3)]  # world ray directions, per pixel
    e = cam.eye.astype(np.float32)
    big = np.float32(1e6)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ts = []
        for i, (lo, hi) in enumerate(((room.xmin, room.xmax), (room.ymin, room.ymax), (0.0, room.height))):
            t = np.where(d[i] > 0, (hi - e[i]) / d[i], (lo - e[i]) / d[i])
            ts.append(np.where(np.isfinite(t) & (t > 0), t, big).astype(np.float32))
    # surface id: 0 floor, 1 ceiling, 2 wall x=xmin, 3 wall x=xmax, 4 wall y=ymin, 5 wall y=ymax
    hit_z = ts[2] <= np.minimum(ts[0], ts[1])
    wall_x = ~hit_z & (ts[0] <= ts[1])
    t = np.minimum(np.minimum(ts[0], ts[1]), ts[2])
    p = [e[i] + t * d[i] for i in range(3)]
    surf = np.where(hit_z, np.where(d[2] < 0, 0, 1),
                    np.where(wall_x, np.where(d[0] < 0, 2, 3), np.where(d[1] < 0, 4, 5))).astype(np.uint8)
    present = np.bincount(surf.ravel(), minlength=6) > 0
    wall_seeds = rng.integers(0, 2 ** 63, size=4)
    out = np.zeros((H, W, 3), np.float32)

    ppm_floor, size = 64.0, 256  # 4 m of floor, tiled
    floor_tex = _floor_texture(rng, size, ppm_floor)
    floor = (surf == 0).astype(np.uint8)
    if present[0]:
        mx = np.mod(p[0] * ppm_floor, size).astype(np.float32)
        my = np.mod(p[1] * ppm_floor, size).astype(np.float32)
        cv2.copyTo(cv2.remap(floor_tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP), floor, out)
    ceiling_rgb = np.array([0.85, 0.85, 0.83], np.float32) * rng.uniform(0.8, 1.0)
    if present[1]:
        panel = (np.mod(p[0], 1.2) < 0.6) & (np.mod(p[1], 2.4) < 1.2)
        ceil = np.where(panel[..., None], np.float32(1.3), ceiling_rgb).astype(np.float32)
        cv2.copyTo(ceil, (surf == 1).astype(np.uint8), out)
    ppm_wall = 64.0
    for k, (coord, lo, hi) in enumerate(((1, room.ymin, room.ymax), (1, room.ymin, room.ymax),
                                         (0, room.xmin, room.xmax), (0, room.xmin, room.xmax))):
        if not present[2 + k]:
            continue
        tex = _wall_texture(np.random.default_rng(int(wall_seeds[k])), hi - lo, room.height, ppm_wall)
        mx = ((p[coord] - lo) * ppm_wall).astype(np.float32)
        my = (tex.shape[0] - p[2] * ppm_wall).astype(np.float32)
        cv2.copyTo(cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                   (surf == 2 + k).astype(np.uint8), out)
    # light: key light (constant per surface) + a ceiling lamp's falloff + darker corners
    normals = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float32)
    per_surface = light.ambient * (0.75 + 0.25 * normals[:, 2]) + light.diffuse * 0.8 * np.clip(
        normals @ light.direction.astype(np.float32), 0, None)
    lx, ly, lz = lamp.astype(np.float32)
    lamp_term = 1.0 / (1.0 + ((p[0] - lx) ** 2 + (p[1] - ly) ** 2 + (p[2] - lz) ** 2) / 9.0)
    corner = np.minimum(np.minimum(p[0] - room.xmin, room.xmax - p[0]), np.minimum(p[1] - room.ymin, room.ymax - p[1]))
    corner = np.minimum(corner, np.where(floor > 0, big, p[2]))
    ao = 1.0 - 0.3 * np.exp(-np.clip(corner, 0, None) / 0.3)
    shade = per_surface.astype(np.float32)[surf] * (0.55 + 0.8 * lamp_term) * ao
    out *= shade[..., None]
    out *= light.color.astype(np.float32)
    return out, floor.astype(np.float32)


def _shadow_mask(parts: Sequence[Part], light: Light, cam: Camera, shape: tuple[int, int]) -> np.ndarray:
    """Soft shadows (0..1, H x W float32) that `parts` cast on the floor plane along the key light."""
    mask = np.zeros(shape, np.uint8)
    l = light.direction
    for part in parts:
        pts = _part_points(part)
        ground = pts - (pts[:, 2] / max(l[2], 0.2))[:, None] * l
        uv, z = cam.project(ground)
        if z.min() < 0.05:
            continue
        hull = cv2.convexHull(np.round(uv * 8).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 255, cv2.LINE_8, 3)
    sigma = max(1.0, 0.006 * shape[1])
    return cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (0, 0), sigma)


# ================================================================================ scene sampling


@dataclass
class SynthSample:
    """One rendered frame and what produced it.

    keypoints: K x 2 pixel coordinates (pixel-centre convention), NaN where outside the frame.
    occluded: per keypoint, True when the person is in front of it (it is still annotated).
    labels: H x W uint8 map of what each pixel shows (0 room, 1 robot, 2 person, 3 clutter, 4 mount).
    person: "none" (nobody in the scene), "beside" (a person who hides no keypoint) or "occluding"
    (hides 1 to MAX_HIDDEN_BY_PERSON keypoints).
    """

    image: np.ndarray
    keypoints: np.ndarray
    keypoints_3d: np.ndarray
    joints: np.ndarray
    camera: Camera
    occluded: np.ndarray
    labels: np.ndarray
    person: str
    mount: str
    tool: str
    tool_length: float


def _frame_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index), 0x5EED]))


def _keypoint_bbox_fraction(uv: np.ndarray, width: int, height: int) -> float:
    span = uv.max(0) - uv.min(0)
    return float(max(span[0] / width, span[1] / height))


DEFAULT_TIGHT_FRAMING = 0.0
"""Default share of frames framed so tightly that one or two keypoints fall outside (left
unannotated); `--tight-framing 0.04` gives 1 frame in 25, to exercise partly annotated frames."""


def _place_camera(rng: np.random.Generator, kp3d: np.ndarray, robot_pts: np.ndarray, width: int, height: int,
                  min_eye_z: float, tight_framing: float = DEFAULT_TIGHT_FRAMING,
                  frac_range: tuple[float, float] = (0.38, 0.72)) -> Camera:
    """A webcam-like camera around the robot framing the arm at a random size and image position.

    In `tight_framing` of the frames the framing is tight and one or two keypoints fall outside
    the image. The draw is made whatever the rate, so other frames do not depend on it.
    """
    diag = math.hypot(width, height)
    centre = 0.5 * (kp3d.min(0) + kp3d.max(0))
    size = np.array([width, height]) - 1.0
    if rng.random() < tight_framing:
        for _ in range(100):
            focal = 0.5 * diag / math.tan(math.radians(rng.uniform(55.0, 78.0)) / 2)
            yaw, elev = rng.uniform(-PI, PI), math.radians(rng.uniform(0.0, 35.0))
            direction = np.array([math.cos(yaw) * math.cos(elev), math.sin(yaw) * math.cos(elev), math.sin(elev)])
            eye = centre + rng.uniform(1.4, 2.2) * direction
            if not (0.3 <= eye[2] <= 2.5) or eye[2] < min_eye_z:
                continue
            target = centre + rng.normal(0.0, 0.25, 3)
            cam = Camera.look_at(eye, target, focal, width, height, roll=math.radians(rng.normal(0.0, 2.5)))
            uv, z = cam.project(kp3d)
            inside = (z > 0.2) & (uv >= 0).all(1) & (uv <= size).all(1)
            if 6 <= inside.sum() <= 7 and cam.project(robot_pts)[1].min() > 0.2:
                return cam
    for _ in range(100):
        fov = math.radians(rng.uniform(55.0, 78.0))  # diagonal field of view of common webcams
        focal = 0.5 * diag / math.tan(fov / 2)
        yaw = rng.uniform(-PI, PI)
        elev = math.radians(rng.uniform(-8.0, 42.0))
        frac = rng.uniform(*frac_range)
        direction = np.array([math.cos(yaw) * math.cos(elev), math.sin(yaw) * math.cos(elev), math.sin(elev)])
        target = centre + rng.normal(0.0, 0.03, 3)
        dist = 2.5
        for _ in range(4):
            cam = Camera.look_at(target + dist * direction, target, focal, width, height)
            uv, z = cam.project(kp3d)
            if z.min() < 0.2:
                dist *= 1.5
                continue
            dist = float(np.clip(dist * _keypoint_bbox_fraction(uv, width, height) / frac, 0.9, 5.0))
        eye = target + dist * direction
        if not (0.3 <= eye[2] <= 2.5) or eye[2] < min_eye_z:
            continue
        cam = Camera.look_at(eye, target, focal, width, height)
        uv, z = cam.project(kp3d)
        if z.min() < 0.3:
            continue
        # shift the arm away from the image centre: pan/tilt so the keypoint box lands at a random place
        margin = np.array([0.05 * width, 0.05 * height])
        lo, hi = uv.min(0), uv.max(0)
        slack_lo, slack_hi = margin - lo, size - margin - hi
        if (slack_lo > slack_hi).any():
            continue
        shift = rng.uniform(np.minimum(slack_lo, 0) * 0.9, np.maximum(slack_hi, 0) * 0.9)
        roll = math.radians(rng.normal(0.0, 2.5))
        for _ in range(4):
            ct = cam.to_camera(target[None])[0]
            moved = target - (shift[0] * ct[2] / focal) * cam.R[0] - (shift[1] * ct[2] / focal) * cam.R[1]
            cam2 = Camera.look_at(eye, moved, focal, width, height, roll=roll)
            uv2, _ = cam2.project(kp3d)
            _, rz = cam2.project(robot_pts)
            ok = (uv2.min(0) >= 0.02 * size).all() and (uv2.max(0) <= 0.98 * size).all() and rz.min() > 0.2
            if ok:
                return cam2
            shift *= 0.5
            roll *= 0.5
        return cam
    raise RuntimeError("could not place the camera")  # pragma: no cover - never seen


def _overlap(a_lo, a_hi, b_lo, b_hi) -> bool:
    return bool((a_lo < b_hi).all() and (b_lo < a_hi).all())


def _image_box(cam: Camera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv, z = cam.project(pts)
    return uv.min(0), uv.max(0), z


def _clutter(rng: np.random.Generator, room: Room, keepout: list[tuple[np.ndarray, float]]) -> list[list[Part]]:
    """Random workshop objects (boxes, cabinets, benches, shelving, bins) standing on the floor."""
    objects: list[list[Part]] = []
    for _ in range(int(rng.integers(3, 10))):
        kind = rng.choice(["carton", "carton", "cabinet", "bench", "shelving", "bin", "machine", "cone"])
        dims = {"carton": (rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.6)),
                "cabinet": (rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.6), rng.uniform(0.8, 1.3)),
                "bench": (rng.uniform(1.2, 2.0), rng.uniform(0.6, 0.8), rng.uniform(0.75, 0.92)),
                "shelving": (rng.uniform(0.9, 1.8), rng.uniform(0.35, 0.5), rng.uniform(1.5, 2.1)),
                "bin": (rng.uniform(0.4, 0.6),) * 2 + (rng.uniform(0.5, 0.9),),
                "machine": (rng.uniform(1.0, 1.8), rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.0)),
                "cone": (0.35, 0.35, 0.5)}[kind]
        sx, sy, _ = dims
        if rng.random() < 0.6:  # against a wall
            wall = rng.integers(4)
            if wall < 2:
                y = rng.uniform(room.ymin + sx / 2, room.ymax - sx / 2)
                x = room.xmin + sy / 2 + 0.02 if wall == 0 else room.xmax - sy / 2 - 0.02
                yaw = PI / 2
            else:
                x = rng.uniform(room.xmin + sx / 2, room.xmax - sx / 2)
                y = room.ymin + sy / 2 + 0.02 if wall == 2 else room.ymax - sy / 2 - 0.02
                yaw = 0.0
        else:
            x, y = rng.uniform(room.xmin + 0.5, room.xmax - 0.5), rng.uniform(room.ymin + 0.5, room.ymax - 0.5)
            yaw = rng.uniform(-PI, PI)
        radius = 0.5 * math.hypot(sx, sy)
        pos = np.array([x, y])
        if any(np.linalg.norm(pos - c) < r + radius for c, r in keepout):
            continue
        keepout.append((pos, radius))
        objects.append(_clutter_parts(rng, kind, np.array([x, y, 0.0]), dims, yaw))
    return objects


def _clutter_parts(rng, kind: str, pos: np.ndarray, dims, yaw: float) -> list[Part]:
    sx, sy, sz = dims
    lab = LABEL_CLUTTER
    c, s = math.cos(yaw), math.sin(yaw)
    ex, ey = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    if kind == "carton":
        col = np.array([0.62, 0.47, 0.30]) * rng.uniform(0.75, 1.1)
        parts: list[Part] = [_box(pos + up * sz / 2, dims, yaw, Material(col, 0.03), lab, edges=True)]
        if rng.random() < 0.4:
            d2 = (sx * 0.8, sy * 0.8, sz * 0.8)
            parts.append(_box(pos + up * (sz + d2[2] / 2), d2, yaw + rng.normal(0, 0.2), Material(col * 0.95, 0.03),
                              lab, edges=True))
        return parts
    if kind == "cabinet":
        col = [np.array([0.7, 0.1, 0.1]), np.array([0.15, 0.25, 0.55]), np.array([0.35, 0.36, 0.38]),
               np.array([0.12, 0.4, 0.2]), np.array([0.1, 0.1, 0.1])][rng.integers(5)]
        return [_box(pos + up * sz / 2, dims, yaw, Material(col, 0.3, 20), lab, edges=True)]
    if kind == "bench":
        top = Material([np.array([0.65, 0.48, 0.3]), np.array([0.5, 0.5, 0.5]), np.array([0.85, 0.85, 0.82])][
            rng.integers(3)] * rng.uniform(0.85, 1.1), 0.1)
        frame = Material(np.array([0.25, 0.35, 0.55]) if rng.random() < 0.5 else np.array([0.3, 0.3, 0.3]), 0.3)
        parts = [_box(pos + up * (sz - 0.02), (sx, sy, 0.04), yaw, top, lab)]
        for a in (-1, 1):
            for b in (-1, 1):
                leg = pos + a * ex * (sx / 2 - 0.05) + b * ey * (sy / 2 - 0.05) + up * (sz - 0.04) / 2
                parts.append(_box(leg, (0.05, 0.05, sz - 0.04), yaw, frame, lab))
        if rng.random() < 0.7:
            item = pos + ex * rng.uniform(-sx / 3, sx / 3) + up * (sz + 0.08)
            parts.append(_box(item, (0.25, 0.2, 0.16), yaw + rng.normal(0, 0.3), Material(rng.uniform(0.1, 0.9, 3), 0.2),
                              lab))
        return parts
    if kind == "shelving":
        frame = Material(np.array([0.2, 0.35, 0.6]) if rng.random() < 0.5 else np.array([0.55, 0.55, 0.56]), 0.3)
        parts = []
        for a in (-1, 1):
            for b in (-1, 1):
                post = pos + a * ex * (sx / 2 - 0.03) + b * ey * (sy / 2 - 0.03) + up * sz / 2
                parts.append(_box(post, (0.04, 0.04, sz), yaw, frame, lab))
        for level in np.linspace(0.15, sz - 0.05, int(rng.integers(3, 5))):
            parts.append(_box(pos + up * level, (sx, sy, 0.03), yaw, Material(np.array([0.6, 0.6, 0.6]), 0.2), lab))
            if level < sz - 0.3:
                for _ in range(int(rng.integers(0, 3))):
                    w = rng.uniform(0.2, 0.4)
                    off = rng.uniform(-sx / 2 + w / 2, sx / 2 - w / 2)
                    h = rng.uniform(0.12, 0.28)
                    parts.append(_box(pos + ex * off + up * (level + 0.015 + h / 2), (w, sy * 0.8, h), yaw,
                                      Material(rng.uniform(0.1, 0.9, 3), 0.15), lab, edges=True))
        return parts
    if kind == "bin":
        col = [np.array([0.1, 0.3, 0.7]), np.array([0.9, 0.7, 0.1]), np.array([0.2, 0.5, 0.2]),
               np.array([0.3, 0.3, 0.3])][rng.integers(4)]
        return [Tube(pos, pos + up * sz, (sx / 2,) * 2, (sx / 2 * 1.05,) * 2, Material(col, 0.2, 16), lab,
                     caps=(False, True), segments=20)]
    if kind == "cone":
        return [Tube(pos, pos + up * sz, (0.15,) * 2, (0.02,) * 2, Material(np.array([0.95, 0.35, 0.05]), 0.2),
                     lab, segments=16),
                _box(pos + up * 0.015, (0.36, 0.36, 0.03), yaw, Material(np.array([0.9, 0.3, 0.05]), 0.2), lab)]
    # machine: a big enclosure with a dark window
    col = np.array([0.75, 0.76, 0.74]) * rng.uniform(0.8, 1.05)
    parts = [_box(pos + up * sz / 2, dims, yaw, Material(col, 0.2, 16), lab, edges=True)]
    parts.append(_box(pos + up * sz * 0.6 + ey * (sy / 2 + 0.005), (sx * 0.6, 0.01, sz * 0.35), yaw,
                      Material(np.array([0.12, 0.14, 0.16]), 0.6, 40), lab))
    parts.append(_box(pos + up * sz * 0.6 - ey * (sy / 2 + 0.005), (sx * 0.6, 0.01, sz * 0.35), yaw,
                      Material(np.array([0.12, 0.14, 0.16]), 0.6, 40), lab))
    return parts


def _mount_parts(rng: np.random.Generator) -> tuple[str, float, list[Part], float]:
    """What the robot stands on: (kind, base height, parts, keep-out radius)."""
    kind = rng.choice(["floor", "floor", "pedestal", "table"])
    lab = LABEL_MOUNT
    if kind == "floor":
        plate = Material(np.full(3, rng.uniform(0.25, 0.7)), 0.3, 20)
        return "floor", 0.012, [_box((0, 0, 0.006), (0.3, 0.3, 0.012), rng.uniform(0, PI), plate, lab)], 0.3
    if kind == "pedestal":
        h = rng.uniform(0.35, 0.85)
        w = rng.uniform(0.22, 0.4)
        col = [np.array([0.3, 0.3, 0.32]), np.array([0.7, 0.7, 0.72]), np.array([0.85, 0.7, 0.1]),
               np.array([0.15, 0.3, 0.55])][rng.integers(4)]
        yaw = rng.uniform(0, PI)
        parts: list[Part] = [_box((0, 0, h / 2), (w, w, h), yaw, Material(col, 0.3, 20), lab, edges=True),
                             _box((0, 0, h - 0.01), (w + 0.08, w + 0.08, 0.02), yaw, Material(col * 0.9, 0.3, 20), lab),
                             _box((0, 0, 0.01), (w + 0.15, w + 0.15, 0.02), yaw, Material(col * 0.9, 0.3, 20), lab)]
        return "pedestal", h, parts, w
    h = rng.uniform(0.72, 0.9)
    sx, sy = rng.uniform(0.7, 1.1), rng.uniform(0.6, 0.9)
    yaw = rng.uniform(-PI, PI)
    off = rng.uniform(-0.15, 0.15, 2)
    top = Material([np.array([0.65, 0.48, 0.3]), np.array([0.45, 0.46, 0.48]), np.array([0.88, 0.88, 0.85]),
                    np.array([0.2, 0.2, 0.22])][rng.integers(4)] * rng.uniform(0.85, 1.1), 0.15, 12)
    frame = Material(np.array([0.55, 0.56, 0.58]) * rng.uniform(0.5, 1.2), 0.3, 20)
    c, s = math.cos(yaw), math.sin(yaw)
    ex, ey = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    centre = np.array([off[0], off[1], 0.0])
    parts = [_box(centre + (0, 0, h - 0.02), (sx, sy, 0.04), yaw, top, lab)]
    for a in (-1, 1):
        for b in (-1, 1):
            leg = centre + a * ex * (sx / 2 - 0.04) + b * ey * (sy / 2 - 0.04) + np.array([0, 0, (h - 0.04) / 2])
            parts.append(_box(leg, (0.045, 0.045, h - 0.04), yaw, frame, lab))
    return "table", h, parts, 0.5 * math.hypot(sx, sy) + 0.2


SCENES = ("workcell", "random")
DEFAULT_SCENE = "workcell"
"""`workcell`: one robot cell filmed by one fixed camera, as in the paper (a webcam on a tripod
watching its arm). The robot's paint and tool, its mount, the room, the clutter, the light and the
camera come from `scene_seed`; each frame draws the arm's pose, the co-worker and the camera's
exposure, blur, noise and compression. `random`: every frame is a new cell seen from a new camera
(domain randomisation; a much harder task for a small network)."""

PERSON_ODDS = {"workcell": (0.15, 0.45), "random": (0.65, 0.2)}
"""Chances that the co-worker stands in front of the arm (hiding 1-3 keypoints) or beside it; else
nobody is there. A workcell is mostly the robot at work; random scenes stress occlusion."""

WORKSPACE_POSES = 64
"""Poses sampled to frame a workcell's camera on the arm's workspace."""


@dataclass
class Scene:
    """What stays put while the arm moves: robot look, mount, camera, light, room and clutter."""

    style: RobotStyle
    mount: str
    base_z: float
    mount_parts: list
    mount_radius: float
    camera: Camera
    light: Light
    room: Room
    lamp: np.ndarray
    objects: list
    keepout: list
    room_seed: int | None = None
    """Seed of the room's textures (fixed in a workcell); None: drawn from the frame's generator."""
    task: WorkTask | None = None
    """The poses a workcell's arm takes (None: any plausible pose, a random scene)."""


def _light(rng: np.random.Generator) -> Light:
    az, el = rng.uniform(-PI, PI), math.radians(rng.uniform(35, 78))
    light_dir = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    warmth = rng.uniform(-1, 1)
    return Light(light_dir, np.array([1 + 0.07 * warmth, 1.0, 1 - 0.09 * warmth]), rng.uniform(0.45, 0.8),
                 rng.uniform(0.35, 0.6))


def _room(rng: np.random.Generator, cam: Camera) -> tuple[Room, np.ndarray]:
    """A room around the robot (at the origin) and the camera, and its ceiling lamp."""
    ex, ey = cam.eye[0], cam.eye[1]
    room = Room(xmin=min(-rng.uniform(1.8, 6.0), ex - rng.uniform(0.6, 3.0)),
                xmax=max(rng.uniform(1.8, 6.0), ex + rng.uniform(0.6, 3.0)),
                ymin=min(-rng.uniform(1.8, 6.0), ey - rng.uniform(0.6, 3.0)),
                ymax=max(rng.uniform(1.8, 6.0), ey + rng.uniform(0.6, 3.0)),
                height=rng.uniform(2.6, 4.5))
    lamp = np.array([rng.uniform(room.xmin, room.xmax), rng.uniform(room.ymin, room.ymax), room.height - 0.1])
    return room, lamp


def _clutter_in_view(rng: np.random.Generator, cam: Camera, room: Room, keepout: list, arm_pts: np.ndarray,
                     robot_far: float) -> list[Part]:
    """Clutter parts that neither stand in `keepout` nor hide the arm's image box (`arm_pts` projected)."""
    uv, _ = cam.project(arm_pts)
    pad = 0.08 * max(cam.width, cam.height)
    arm_lo, arm_hi = uv.min(0) - pad, uv.max(0) + pad
    clutter = []
    for obj in _clutter(rng, room, keepout):
        pts = np.vstack([_part_points(p) for p in obj])
        lo, hi, z = _image_box(cam, pts)
        if z.min() < 0.3:
            continue
        if _overlap(lo, hi, arm_lo, arm_hi) and z.min() < robot_far + 0.05:
            continue
        clutter.append(obj)
    return [p for obj in clutter for p in obj]


def _scene_rng(scene_seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(scene_seed) & 0xFFFFFFFF, 0xCE11]))


_WORKCELLS: dict[tuple[int, int, int], Scene] = {}


WORKCELL_FRAMING = (0.85, 0.95)
"""Share of the image side a workcell's camera gives its task's workspace (the keypoints of
WORKSPACE_POSES sampled poses)."""


def workcell(scene_seed: int = 0, width: int = 640, height: int = 480) -> Scene:
    """The fixed cell of `scene_seed`: an arm at one task (`WorkTask`: a 90-degree sector, elbow on
    one side, tool down) and a camera framing that task's workspace (many sampled poses)."""
    key = (int(scene_seed), int(width), int(height))
    if key not in _WORKCELLS:
        rng = _scene_rng(scene_seed)
        task = WorkTask(yaw=float(rng.uniform(-PI, PI)), elbow=1.0 if rng.random() < 0.5 else -1.0)
        style = _robot_style(rng)
        mount, base_z, mount_parts, mount_radius = _mount_parts(rng)
        reach = np.vstack([ur5_keypoints_3d(sample_joints(rng, style.tool_length, task), style.tool_length, base_z)
                           for _ in range(WORKSPACE_POSES)])
        cam = _place_camera(rng, reach, reach, width, height, min_eye_z=base_z + 0.15, frac_range=WORKCELL_FRAMING)
        light = _light(rng)
        room, lamp = _room(rng, cam)
        keepout = [(np.zeros(2), mount_radius + 1.0), (cam.eye[:2], 0.7)]
        far = float(cam.to_camera(reach)[:, 2].max())
        objects = _clutter_in_view(rng, cam, room, keepout, reach, far)
        _WORKCELLS[key] = Scene(style, mount, base_z, mount_parts, mount_radius, cam, light, room, lamp, objects,
                                keepout, room_seed=int(rng.integers(0, 2 ** 63)), task=task)
    return _WORKCELLS[key]


def _pose_in_view(rng: np.random.Generator, scene: Scene, tight_framing: float) -> np.ndarray:
    """Joint angles of a plausible pose whose 8 keypoints the scene's camera sees (6-7 when tightly framed)."""
    cam, style = scene.camera, scene.style
    size = np.array([cam.width, cam.height]) - 1.0
    tight = rng.random() < tight_framing
    q = None
    for _ in range(400):
        q = sample_joints(rng, style.tool_length, scene.task)
        kp3d = ur5_keypoints_3d(q, style.tool_length, scene.base_z)
        uv, z = cam.project(kp3d)
        if z.min() < 0.3:
            continue
        if tight:
            inside = (uv >= 0).all(1) & (uv <= size).all(1)
            if 6 <= inside.sum() <= 7:
                return q
        elif (uv >= 0.02 * size).all() and (uv <= 0.98 * size).all():
            return q
    return q  # pragma: no cover - a workspace-framed camera sees most poses


def _random_scene(rng: np.random.Generator, width: int, height: int,
                  tight_framing: float) -> tuple[Scene, np.ndarray]:
    """A new cell and camera framing the arm in a random pose: (scene, joint angles)."""
    style = _robot_style(rng)
    mount, base_z, mount_parts, mount_radius = _mount_parts(rng)
    q = sample_joints(rng, style.tool_length)
    kp3d = ur5_keypoints_3d(q, style.tool_length, base_z)
    robot_pts = np.vstack([_part_points(p) for p in ur5_parts(q, style, base_z)])
    cam = _place_camera(rng, kp3d, robot_pts, width, height, min_eye_z=base_z + 0.15, tight_framing=tight_framing)
    light = _light(rng)
    room, lamp = _room(rng, cam)
    keepout = [(np.zeros(2), mount_radius + 1.0), (cam.eye[:2], 0.7)]
    far = float(cam.to_camera(np.vstack([robot_pts] + [_part_points(p) for p in mount_parts]))[:, 2].max())
    objects = _clutter_in_view(rng, cam, room, keepout, kp3d, far)
    return Scene(style, mount, base_z, mount_parts, mount_radius, cam, light, room, lamp, objects, keepout), q


def render_sample(seed: int | np.random.Generator = 0, index: int = 0, width: int = 640,
                  height: int = 480, tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                  scene_seed: int = 0) -> SynthSample:
    """Render frame `index` of the synthetic set `seed` (or draw from a given Generator) at width x height.

    `scene` is "workcell" (the fixed cell of `scene_seed`) or "random" (see DEFAULT_SCENE).
    """
    if width < 32 or height < 32:
        raise UserError(f"frame size {width}x{height} is too small; expected at least 32x32")
    if scene not in SCENES:
        raise UserError(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}")
    rng = seed if isinstance(seed, np.random.Generator) else _frame_rng(seed, index)
    if scene == "workcell":
        cell = workcell(scene_seed, width, height)
        q = _pose_in_view(rng, cell, tight_framing)
    else:
        cell, q = _random_scene(rng, width, height, tight_framing)
    style, cam, base_z = cell.style, cell.camera, cell.base_z
    kp3d = ur5_keypoints_3d(q, style.tool_length, base_z)
    robot = ur5_parts(q, style, base_z)
    robot_pts = np.vstack([_part_points(p) for p in robot])
    kp_uv, kp_z = cam.project(kp3d)
    person, _ = _place_person(rng, cam, kp3d, kp_uv, kp_z, cell.mount_radius, cell.keepout[2:],
                              PERSON_ODDS[scene])

    keypoints = kp_uv.copy()
    inside = (kp_z > 0) & (kp_uv[:, 0] >= 0) & (kp_uv[:, 0] <= width - 1) & (kp_uv[:, 1] >= 0) & \
             (kp_uv[:, 1] <= height - 1)
    keypoints[~inside] = np.nan
    state = rng.bit_generator.state
    ss = 2
    while True:
        room_rng = None if cell.room_seed is None else np.random.default_rng(cell.room_seed)
        canvas, labels, depth = _paint(rng, cam, ss, cell.room, cell.light, cell.lamp, robot, cell.mount_parts,
                                       person, cell.objects, robot_depth_far=float(cam.to_camera(robot_pts)[:, 2].max()),
                                       room_rng=room_rng)
        occluded = _person_in_front(labels, depth, (keypoints + 0.5) * ss - 0.5, kp_z)
        if occluded.sum() <= MAX_HIDDEN_BY_PERSON or not person:
            break
        rng.bit_generator.state = state  # the person would hide most of the arm: the same frame without them
        person = []
    person_mode = "none" if not person else "occluding" if occluded.any() else "beside"
    img = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA)
    labels_1x = cv2.resize(labels, (width, height), interpolation=cv2.INTER_NEAREST)
    img = _camera_effects(rng, img)
    return SynthSample(img, keypoints, kp3d, q, cam, occluded, labels_1x, person_mode, cell.mount, style.tool,
                       style.tool_length)


MAX_HIDDEN_BY_PERSON = 3
"""A frame where the person would hide more keypoints than this is rendered without the person."""


def _paint(rng: np.random.Generator, cam: Camera, ss: int, room: Room, light: Light, lamp: np.ndarray,
           robot: list[Part], mount_parts: list[Part], person: list[Part], objects: list[Part],
           robot_depth_far: float, room_rng: np.random.Generator | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(RGB canvas, label map, depth map) at `ss` times the camera's resolution.

    The room is rendered at half resolution (it is out of focus anyway) with the objects' shadows,
    upsampled, and everything else painted over it back to front. The room's textures are drawn
    from `room_rng` when given (a workcell's fixed room), else from `rng`.
    """
    bg_cam = cam.scaled(0.5)
    bg, floor_mask = _render_background(rng if room_rng is None else room_rng, bg_cam, room, light, lamp)
    shadow = _shadow_mask(robot + mount_parts + person + objects, light, bg_cam, bg.shape[:2]) * floor_mask
    bg *= (1.0 - rng.uniform(0.3, 0.55) * shadow)[..., None]
    cam2 = cam.scaled(ss)
    canvas = cv2.resize(bg, (cam2.width, cam2.height), interpolation=cv2.INTER_LINEAR)
    labels = np.zeros((cam2.height, cam2.width), np.uint8)
    depth = np.full((cam2.height, cam2.width), np.inf, np.float32)
    painter = _Painter(canvas, labels, cam2, light, depth=depth)
    for part in robot + person + objects:
        painter.add(part)
    for part in mount_parts:  # the mount is under the robot: drawn before any robot facet
        painter.add(part, min_depth=robot_depth_far + 1e-3)
    painter.flush()
    return canvas, labels, depth


def _robot_clearance(parts: Sequence[Part], kp3d: np.ndarray) -> float:
    """Smallest distance (m) from the parts' outline points to the arm's skeleton, minus the arm's radius."""
    pts = np.vstack([_part_points(p) for p in parts])
    chain = np.vstack([kp3d[:1], kp3d[:1] + (0, 0, 0.1), kp3d[1:]])
    return min(float(_segment_distance(pts, a, b).min()) for a, b in zip(chain[:-1], chain[1:])) - 0.08


def _place_person(rng: np.random.Generator, cam: Camera, kp3d: np.ndarray, kp_uv: np.ndarray, kp_z: np.ndarray,
                  mount_radius: float, keepout: Sequence[tuple[np.ndarray, float]] = (),
                  odds: tuple[float, float] = (0.65, 0.2)) -> tuple[list[Part], str]:
    """A person standing clear of the robot and of `keepout` circles ((centre xy, radius) of furniture):
    in front hiding 1-3 keypoints, beside it (chances `odds`), or ([], "none")."""
    r = rng.random()
    p_front, p_beside = odds
    cam_xy = cam.eye[:2]
    arm_xy = kp3d[:, :2].mean(0)
    away = max(0.55, mount_radius + 0.3)  # feet at least this far from the base axis

    def blocked(feet):
        return any(np.linalg.norm(feet - c) < r + 0.3 for c, r in keepout)

    def make(feet, facing, reach=None):
        return person_parts(rng, feet, facing, rng.uniform(1.58, 1.92), reach)

    if r < p_front:
        line = arm_xy - cam_xy
        lateral = np.array([-line[1], line[0]]) / max(np.linalg.norm(line), 1e-6)
        unit = line / max(np.linalg.norm(line), 1e-6)
        for _ in range(40):  # next to the robot on the camera's side, as a co-worker would stand
            feet = arm_xy - rng.uniform(0.35, 1.2) * unit + rng.uniform(-0.8, 0.8) * lateral
            if np.linalg.norm(feet - cam_xy) < 0.6 or np.linalg.norm(feet) < away or blocked(feet):
                continue
            chest_uv, chest_z = cam.project(np.array([[feet[0], feet[1], 1.0]]))
            if chest_z[0] < 0.5 or chest_uv[0, 1] < 0 or not 0 <= chest_uv[0, 0] <= cam.width - 1:
                continue  # keep the torso in the picture: a person, not two posts or a lone arm
            reach = None
            if rng.random() < 0.6:  # hand something to the robot: reach toward a point near a joint
                kp = kp3d[rng.integers(2, 8)]
                away_from_kp = np.array([feet[0], feet[1], kp[2]]) - kp
                reach = kp + 0.25 * away_from_kp / max(np.linalg.norm(away_from_kp), 1e-6)
                facing = math.atan2(reach[1] - feet[1], reach[0] - feet[0]) + rng.normal(0, 0.3)
            else:
                facing = math.atan2(-feet[1], -feet[0]) + rng.normal(0, 0.9)
            cand = make(feet, facing, reach)
            if 1 <= int(_covered(cand, cam, kp_uv, kp_z).sum()) <= 3 and _robot_clearance(cand, kp3d) > 0.1:
                return cand, "occluding"
    if r < p_front + p_beside:
        to_cam = math.atan2(cam_xy[1], cam_xy[0])
        in_view = rng.random() < 0.8  # most of the time the person is (at least partly) in the picture
        for _ in range(30):
            ang = to_cam + rng.choice([-1, 1]) * rng.uniform(0.5, 2.8)
            feet = rng.uniform(away, away + 1.3) * np.array([math.cos(ang), math.sin(ang)])
            if np.linalg.norm(feet - cam_xy) < 0.8 or blocked(feet):
                continue
            if in_view:
                uv, z = cam.project(np.array([[feet[0], feet[1], 1.2]]))
                if z[0] < 0.5 or not 0.0 <= uv[0, 0] <= cam.width - 1:
                    continue
            facing = math.atan2(-feet[1], -feet[0]) + rng.normal(0, 1.0)
            cand = make(feet, facing)
            if not _covered(cand, cam, kp_uv, kp_z).any() and _robot_clearance(cand, kp3d) > 0.1:
                return cand, "beside"
    return [], "none"


def _person_in_front(labels: np.ndarray, depth: np.ndarray, kp_uv: np.ndarray, kp_z: np.ndarray) -> np.ndarray:
    """Keypoints whose pixel shows the person at a smaller depth than the keypoint's own."""
    px = np.round(np.nan_to_num(kp_uv, nan=-1.0)).astype(int)
    inside = (px >= 0).all(1) & (px[:, 0] < labels.shape[1]) & (px[:, 1] < labels.shape[0])
    hidden = np.zeros(len(kp_uv), bool)
    y, x = px[inside, 1], px[inside, 0]
    hidden[inside] = (labels[y, x] == LABEL_PERSON) & (depth[y, x] < kp_z[inside])
    return hidden


def _covered(parts: Sequence[Part], cam: Camera, kp_uv: np.ndarray, kp_z: np.ndarray) -> np.ndarray:
    """Which keypoints the given (person) parts would hide: drawn into a small mask, depth-tested per part."""
    hidden = np.zeros(len(kp_uv), bool)
    for part in parts:
        pts = _part_points(part)
        uv, z = cam.project(pts)
        if z.min() < 0.05:
            continue
        hull = cv2.convexHull(uv.astype(np.float32))
        for k in range(len(kp_uv)):
            if not hidden[k] and z.mean() < kp_z[k] and cv2.pointPolygonTest(hull, tuple(map(float, kp_uv[k])),
                                                                            False) >= 0:
                hidden[k] = True
    return hidden


def _camera_effects(rng: np.random.Generator, img: np.ndarray) -> np.ndarray:
    """Exposure, white balance, vignetting, blur, sensor noise, gamma and (sometimes) JPEG: float RGB -> uint8 BGR."""
    h, w = img.shape[:2]
    scale = w / 640.0
    # auto-exposure as a webcam does it: bring the mean level to a target, within the sensor's gain range
    exposure = float(np.clip(rng.uniform(0.36, 0.55) / max(float(img.mean()), 1e-3), 0.6, 2.6))
    gain = np.float32(exposure) * (1 + rng.normal(0, 0.04, 3)).astype(np.float32)
    vignette = np.float32(rng.uniform(0.0, 0.25) / 2)
    vx = ((np.arange(w, dtype=np.float32) - w / 2) / (w / 2)) ** 2
    vy = ((np.arange(h, dtype=np.float32) - h / 2) / (h / 2)) ** 2
    img *= (1.0 - vignette * (vx[None, :] + vy[:, None]))[..., None]
    img *= gain
    if rng.random() < 0.12:  # camera shake
        n = int(rng.integers(3, 8) * scale) | 1
        kernel = np.zeros((n, n), np.float32)
        kernel[n // 2, :] = 1.0 / n
        rot = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), rng.uniform(0, 180), 1.0)
        kernel = cv2.warpAffine(kernel, rot, (n, n))
        img = cv2.filter2D(img, -1, kernel / max(float(kernel.sum()), 1e-6))
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.25, 1.1) * scale)
    # sensor noise after the camera's processing: mostly luminance, shot-noise-like (grows with sqrt of the
    # level), plus coarser colour noise
    sigma = np.float32(1.6 * rng.uniform(0.004, 0.022))
    lum = rng.standard_normal((h, w), dtype=np.float32)
    lum *= np.sqrt(np.clip(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), 0.02, 1.0))
    lum *= sigma
    img += lum[..., None]
    chroma = rng.standard_normal(((h + 1) // 2, (w + 1) // 2, 3), dtype=np.float32)
    chroma *= sigma * np.float32(0.35)
    img += cv2.resize(chroma, (w, h), interpolation=cv2.INTER_LINEAR)
    np.clip(img, 0.0, 1.0, out=img)
    out = cv2.cvtColor(cv2.convertScaleAbs(img, alpha=255.0), cv2.COLOR_RGB2BGR)
    gamma = rng.uniform(0.85, 1.15)
    lut = np.clip(255.0 * (np.arange(256) / 255.0) ** gamma + 0.5, 0, 255).astype(np.uint8)
    out = cv2.LUT(out, lut)
    if rng.random() < 0.5:  # webcam MJPEG compression
        _, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(60, 96))])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return out


def render_frame(seed: int | np.random.Generator = 0, index: int = 0, width: int = 640,
                 height: int = 480, tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                 scene_seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(H x W x 3 uint8 BGR image, 8 x 2 keypoints in UR5 order, NaN outside the frame) of one frame."""
    sample = render_sample(seed, index, width, height, tight_framing, scene, scene_seed)
    return sample.image, sample.keypoints


# ================================================================================ previews


_KEYPOINT_COLORS_BGR = ((60, 60, 230), (40, 160, 250), (40, 220, 230), (60, 200, 60), (220, 200, 40),
                        (230, 110, 40), (200, 60, 200), (250, 250, 250))


def draw_keypoints(image_bgr: np.ndarray, keypoints: np.ndarray, schema=UR5, labels: bool = True,
                   occluded: np.ndarray | None = None) -> np.ndarray:
    """A copy of a BGR frame with the skeleton, keypoint dots and (optionally) their names drawn on it.

    Names are placed greedily where they overlap neither each other nor the dots, with a thin leader
    line when pushed away; occluded keypoints (if given) are drawn as rings.
    """
    out = np.ascontiguousarray(image_bgr.copy())
    h, w = out.shape[:2]
    scale = max(0.6, h / 480)
    kp = np.asarray(keypoints, np.float64)
    shift = 4
    fx = lambda p: (int(round(p[0] * 16)), int(round(p[1] * 16)))  # noqa: E731
    for a, b in schema.edges:
        if np.isfinite(kp[[a, b]]).all():
            cv2.line(out, fx(kp[a]), fx(kp[b]), (255, 255, 255), max(1, int(3 * scale)), cv2.LINE_AA, shift)
            cv2.line(out, fx(kp[a]), fx(kp[b]), (40, 40, 40), max(1, int(1 * scale)), cv2.LINE_AA, shift)
    r = max(2, int(4 * scale))
    visible = [k for k in range(schema.num_keypoints) if np.isfinite(kp[k]).all()]
    for k in visible:
        color = _KEYPOINT_COLORS_BGR[k % len(_KEYPOINT_COLORS_BGR)]
        hollow = occluded is not None and bool(occluded[k])
        cv2.circle(out, fx(kp[k]), r * 16, color, max(1, int(2 * scale)) if hollow else -1, cv2.LINE_AA, shift)
        cv2.circle(out, fx(kp[k]), (r + 1) * 16, (0, 0, 0), 1, cv2.LINE_AA, shift)
    if not labels:
        return out
    fs = max(0.4, 0.45 * scale)
    taken = [(kp[k, 0] - r, kp[k, 1] - r, kp[k, 0] + r, kp[k, 1] + r) for k in visible]
    for k in visible:
        name = schema.keypoints[k]
        color = _KEYPOINT_COLORS_BGR[k % len(_KEYPOINT_COLORS_BGR)]
        (tw, th), base = cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)
        x, y = kp[k]
        best = None
        for dist in (r + 3, 3 * r + 8, 6 * r + 14, 10 * r + 22):
            for dx, dy in ((1, 0), (-1, 0), (0, -1), (0, 1), (1, -1), (-1, -1), (1, 1), (-1, 1)):
                x0 = x + dx * dist - (tw if dx < 0 else 0 if dx > 0 else tw / 2)
                y0 = y + dy * dist + (th / 2 if dy == 0 else 0 if dy > 0 else -th) - th / 2
                box = (x0 - 1, y0 - 1, x0 + tw + 1, y0 + th + base)
                if box[0] < 0 or box[1] < 0 or box[2] >= w or box[3] >= h:
                    continue
                if all(box[2] < t[0] or box[0] > t[2] or box[3] < t[1] or box[1] > t[3] for t in taken):
                    best = (box, dist)
                    break
            if best:
                break
        if best is None:
            continue  # no free spot: leave this name out rather than cover another
        box, dist = best
        taken.append(box)
        org = (int(box[0] + 1), int(box[1] + 1 + th))
        if dist > r + 3:
            anchor = (min(max(x, box[0]), box[2]), min(max(y, box[1]), box[3]))
            cv2.line(out, fx(kp[k]), fx(anchor), color, 1, cv2.LINE_AA, shift)
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, fs, color, 1, cv2.LINE_AA)
    return out


def preview_grid(frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]], columns: int = 3,
                 tile_width: int = 480, labels: bool = True) -> np.ndarray:
    """One BGR image tiling (image, keypoints, occluded-or-None) frames with skeleton, dots and names drawn."""
    if not frames:
        raise UserError("no frames to preview")
    tiles = []
    for image, keypoints, occluded in frames:
        f = tile_width / image.shape[1]
        tile = cv2.resize(image, (tile_width, int(round(image.shape[0] * f))),
                          interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
        tiles.append(draw_keypoints(tile, (np.asarray(keypoints) + 0.5) * f - 0.5, labels=labels, occluded=occluded))
    th = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, th - t.shape[0], 0, 0, cv2.BORDER_CONSTANT, value=(0, 0, 0)) for t in tiles]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.hstack([cv2.copyMakeBorder(t, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
                       for t in tiles[i:i + columns]]) for i in range(0, len(tiles), columns)]
    return np.ascontiguousarray(np.vstack(rows))


# ================================================================================ datasets


VIA_FILENAME = "ur5_synth.json"
"""Name of the VIA project file `generate` writes in the output folder."""
IMAGE_DIR = "images"
IMAGE_NAME = "synth_{index:05d}.png"
PNG_COMPRESSION = 1  # fast; level 3 saves only ~4 % on noisy frames


@dataclass
class FrameRecord:
    """What a worker reports about one written frame."""

    index: int
    filename: str
    size: int
    keypoints: np.ndarray
    occluded: np.ndarray
    person: str
    mount: str
    tool: str


@dataclass
class SynthReport:
    """Result of `generate_dataset`: where the VIA file is, one record per frame, and the wall time."""

    via_path: Path
    frames: list[FrameRecord]
    seconds: float
    workers: int
    width: int
    height: int

    def summary_rows(self) -> list[tuple[str, object]]:
        """(quantity, value) rows for the CLI's closing table."""
        n = len(self.frames)
        kp = np.stack([f.keypoints for f in self.frames])
        visible = np.isfinite(kp).all(-1)
        occluded = np.stack([f.occluded for f in self.frames])
        span = []
        for k in kp:
            k = k[np.isfinite(k).all(1)]
            if len(k):
                span.append((k[:, 1].max() - k[:, 1].min()) / self.height)
        count = lambda attr, value: sum(getattr(f, attr) == value for f in self.frames)  # noqa: E731
        return [
            ("frames", n),
            ("frame size (px)", f"{self.width}x{self.height}"),
            ("keypoints annotated (in frame)", f"{int(visible.sum())} of {visible.size}"),
            ("frames with all 8 keypoints", int(visible.all(1).sum())),
            ("frames with the person hiding part of the arm", int(occluded.any(1).sum())),
            ("keypoints hidden by the person (still annotated)", int(occluded.sum())),
            ("frames with a person in the scene", n - count("person", "none")),
            ("mounts floor / pedestal / table", f"{count('mount', 'floor')} / {count('mount', 'pedestal')} / "
                                                f"{count('mount', 'table')}"),
            ("keypoint box height / frame height, median", round(float(np.median(span)), 3) if span else None),
            ("wall time (s)", round(self.seconds, 1)),
            ("frames per second", round(n / max(self.seconds, 1e-9), 1)),
            ("workers", self.workers),
        ]


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one process per core; OpenCV's own threads would only compete


def _render_and_write(task: tuple[int, int, int, int, str, float, str, int]) -> FrameRecord:
    """Worker: render frame `index`, write it as PNG atomically, return its record."""
    from fcnpose_tf import fileio

    seed, index, width, height, image_dir, tight_framing, scene, scene_seed = task
    sample = render_sample(seed, index, width, height, tight_framing, scene, scene_seed)
    ok, buf = cv2.imencode(".png", sample.image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 BGR image
        raise RuntimeError("PNG encoding failed")
    name = IMAGE_NAME.format(index=index)
    data = buf.tobytes()
    fileio.write_bytes(Path(image_dir) / name, data, force=True)
    return FrameRecord(index, name, len(data), sample.keypoints, sample.occluded, sample.person, sample.mount,
                       sample.tool)


def default_workers() -> int:
    """Cores this process may run on."""
    return available_cores()


def _prepare_output(out_dir: Path, force: bool) -> Path:
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise UserError(f"{out_dir}: folder is not empty; pass --force to write into it (replacing earlier "
                        "synthetic frames)")
    try:
        (out_dir / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out_dir}: cannot create output folder ({exc.strerror})") from None
    for folder in (out_dir, out_dir / IMAGE_DIR):
        if not os.access(folder, os.W_OK | os.X_OK):
            raise UserError(f"{folder}: output folder is not writable")
    return out_dir / IMAGE_DIR


def generate_dataset(out_dir: str | os.PathLike, n: int = 500, seed: int = 0, width: int = 640, height: int = 480,
                     workers: int | None = None, force: bool = False, progress: bool = True,
                     tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                     scene_seed: int = 0) -> SynthReport:
    """Render n frames into out_dir/images/*.png and write out_dir/ur5_synth.json (VIA 2.x project).

    Frames are rendered by a pool of `workers` processes (default: one per core);
    the files are the same for any number of workers. `scene` and `scene_seed` choose one fixed
    workcell or a new random cell per frame (see DEFAULT_SCENE). A non-empty out_dir is refused
    unless force, which also removes what belonged to the set being replaced: synth_*.png
    frames beyond n and the stored folds (ur5_synth.splits.json).

    Raises:
        UserError: n < 1, a frame size below 32x32, workers < 1, an unknown scene, or an output folder that
            is not empty (without force), not a folder, or not writable.
    """
    from fcnpose_tf.data.via import ViaFrame, write_via_project

    if int(n) != n or n < 1:
        raise UserError(f"--n must be at least 1, got {n}")
    if width < 32 or height < 32:
        raise UserError(f"frame size {width}x{height} is too small; expected at least 32x32")
    if scene not in SCENES:
        raise UserError(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}")
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    out_dir = Path(out_dir)
    image_dir = _prepare_output(out_dir, force)
    keep = {IMAGE_NAME.format(index=i) for i in range(n)}
    for stale in image_dir.glob("synth_*.png"):
        if stale.name not in keep:
            stale.unlink()
    from fcnpose_tf.data.splits import splits_path

    splits_path(out_dir / VIA_FILENAME).unlink(missing_ok=True)  # folds of the set being replaced
    (out_dir / VIA_FILENAME).unlink(missing_ok=True)  # written again last: no VIA file while frames change

    from tqdm import tqdm

    start = time.perf_counter()
    if not 0.0 <= tight_framing <= 1.0:
        raise UserError(f"--tight-framing must be between 0 and 1, got {tight_framing}")
    tasks = [(int(seed), i, int(width), int(height), str(image_dir), float(tight_framing), scene, int(scene_seed))
             for i in range(n)]
    workers = min(workers, n)
    records: list[FrameRecord] = []
    with tqdm(total=n, unit="frame", desc="synth", disable=not progress, dynamic_ncols=True) as bar:
        if workers == 1:
            for task in tasks:
                records.append(_render_and_write(task))
                bar.update()
        else:
            import multiprocessing

            ctx = multiprocessing.get_context("spawn")  # safe even when the caller has threads (TF, OpenCV)
            with ctx.Pool(workers, initializer=_init_worker) as pool:
                for record in pool.imap_unordered(_render_and_write, tasks, chunksize=4):
                    records.append(record)
                    bar.update()
    records.sort(key=lambda r: r.index)
    frames = [ViaFrame(r.filename, width, height, r.keypoints, size=r.size) for r in records]
    via_path = write_via_project(out_dir / VIA_FILENAME, frames, UR5, attribute="keypoint", force=True)
    return SynthReport(Path(via_path), records, time.perf_counter() - start, workers, int(width), int(height))


def generate(out_dir: str | os.PathLike, n: int = 500, seed: int = 0, width: int = 640, height: int = 480,
             workers: int | None = None, force: bool = False, progress: bool = True,
             tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE, scene_seed: int = 0) -> Path:
    """Render a synthetic UR5 dataset into out_dir (see `generate_dataset`); returns the VIA file's path.

    Example:
        >>> via = generate("data/synth", n=500, seed=0)   # data/synth/images/*.png + ur5_synth.json
    """
    return generate_dataset(out_dir, n, seed, width, height, workers, force, progress, tight_framing, scene,
                            scene_seed).via_path


def write_preview(report: SynthReport, path: str | os.PathLike, count: int = 6, force: bool = False) -> Path:
    """Write a PNG grid of the report's first `count` frames (read back from disk) with keypoints drawn."""
    from fcnpose_tf import fileio

    image_dir = report.via_path.parent / IMAGE_DIR
    frames = []
    for record in report.frames[:count]:
        image = cv2.imread(str(image_dir / record.filename), cv2.IMREAD_COLOR)
        if image is None:
            raise UserError(f"{image_dir / record.filename}: cannot read the frame back")
        frames.append((image, record.keypoints, record.occluded))
    grid = preview_grid(frames, columns=3 if len(frames) > 4 else 2, tile_width=400)
    _, buf = cv2.imencode(".png", grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return fileio.write_bytes(path, buf.tobytes(), force=force)
