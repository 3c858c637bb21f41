"""UR kinematics: DH forward kinematics, the 8 keypoints in 3-D, plausible working poses.

The UR5 is the default arm; every function takes another of the family (`looks.ARMS`). By default
the keypoint of a joint is the centre of its housing on the joint axis, where an annotator clicks
(the housings' spans are shared with the robot's shapes, `robot.ur5_parts`); the `kinematic`
convention puts it at the URDF link frame instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fcnpose_tf.data.synth.looks import DEFAULT_LABELS, UR5_ARM, ArmModel

PI = math.pi


UR5_DH_D = np.array(UR5_ARM.d)
"""DH link offsets d1..d6 (m), Universal Robots' published UR5 parameters."""
UR5_DH_A = np.array(UR5_ARM.a)
"""DH link lengths a1..a6 (m)."""
UR5_DH_ALPHA = np.array(UR5_ARM.alpha)
"""DH link twists alpha1..alpha6 (rad)."""

SHOULDER_OFFSET = UR5_ARM.shoulder_offset
"""Upper-arm centreline offset along the shoulder/elbow axes from the DH plane (UR5 URDF)."""
FOREARM_OFFSET = UR5_ARM.forearm_offset
"""Forearm centreline offset along the same axes (the elbow steps back 0.1197 m)."""

# Joint housings: (axis frame index i -> axis z_i through DH origin O_i, span (lo, hi) along that axis, radius,
# what each end shows: a blue-grey "cap", a "plain" face, or nothing when "buried" in the previous housing).
# The keypoint of a joint is the centre of its housing on the joint axis, where an annotator clicks.
# Other arms of the UR family: `looks.ARMS`.
HOUSINGS = UR5_ARM.housings
BASE_SPAN, BASE_RADIUS = UR5_ARM.base_span, UR5_ARM.base_radius
FLANGE_SPAN, FLANGE_RADIUS = UR5_ARM.flange_span, UR5_ARM.flange_radius


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Standard (distal) DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha) as a 4 x 4 matrix."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct],
                     [st, ct * ca, -ct * sa, a * st],
                     [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


def forward_kinematics(q: Sequence[float], arm: ArmModel = UR5_ARM) -> np.ndarray:
    """The 7 DH frames (base, after joints 1..6) of an arm (default a UR5) at joint angles q (rad), 7 x 4 x 4.

    Frame i's origin O_i lies on joint i+1's axis z_i; frame 6 is the tool flange.
    With all joints at zero the arm is stretched along -x: O_6 = (-0.81725, -0.19145, -0.005491).
    """
    q = np.asarray(q, np.float64).reshape(6)
    frames = np.empty((7, 4, 4))
    frames[0] = np.eye(4)
    for i in range(6):
        frames[i + 1] = frames[i] @ dh_transform(q[i], arm.d[i], arm.a[i], arm.alpha[i])
    return frames


def ur5_keypoints_3d(q: Sequence[float], tool_length: float = 0.12, base_z: float = 0.0, arm: ArmModel = UR5_ARM,
                     labels: str = DEFAULT_LABELS) -> np.ndarray:
    """World positions (8 x 3, m) of the arm's keypoints in `UR5` order for joint angles q.

    base: centre of the robot's mounting face (z = base_z); flange: tool-flange centre (DH O_6);
    tool: tip of the tool, tool_length along the flange normal. shoulder .. wrist3 by `labels`:
    "housing", the centre of each joint housing on its axis (where an annotator clicks); "kinematic",
    the URDF link frames (shoulder_link at O_1, forearm_link and wrist_1_link on the elbow and wrist 1
    axes at the forearm's centreline, wrist_2_link and wrist_3_link at O_4 and O_5).
    """
    frames = forward_kinematics(q, arm)
    origin = frames[:, :3, 3] + (0.0, 0.0, base_z)
    axis = frames[:, :3, 2]
    points = [origin[0]]
    if labels == "kinematic":
        points += [origin[1], origin[2] + arm.forearm_offset * axis[2], origin[3] + arm.forearm_offset * axis[3],
                   origin[4], origin[5]]
    else:
        for name in ("shoulder", "elbow", "wrist1", "wrist2", "wrist3"):
            i, (lo, hi), _, _ = arm.housings[name]
            points.append(origin[i] + 0.5 * (lo + hi) * axis[i])
    points.append(origin[6])
    points.append(origin[6] + tool_length * axis[6])
    return np.array(points)


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point (N x 3) to the segment a-b."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def pose_is_plausible(q: Sequence[float], tool_length: float = 0.12, arm: ArmModel = UR5_ARM) -> bool:
    """True when the arm stays above its mounting plane and clear of its own base and upper arm.

    Checks the obvious self-collisions only (wrist and tool against the base column and
    the upper arm, forearm against the base column); the elbow is kept below +-2.7 rad.
    Clearances scale with the arm's size (`ArmModel.scale`).
    """
    q = np.asarray(q, np.float64)
    if abs(q[2]) > 2.7:
        return False
    s = arm.scale
    frames = forward_kinematics(q, arm)
    o, z = frames[:, :3, 3], frames[:, :3, 2]
    kp = ur5_keypoints_3d(q, tool_length, arm=arm)
    if kp[1:7, 2].min() < 0.075 * s or kp[7, 2] < 0.03 * s:
        return False
    elbow_arm = o[2] + arm.forearm_offset * z[2]
    wrist_arm = o[3] + arm.forearm_offset * z[3]
    forearm = elbow_arm + np.linspace(0.25, 1.0, 6)[:, None] * (wrist_arm - elbow_arm)
    distal = np.vstack([kp[3:8], o[4], o[5], forearm])
    base_a, base_b = np.zeros(3), np.array([0.0, 0.0, arm.d[0] + 0.08 * s])
    if segment_distance(distal, base_a, base_b).min() < 0.17 * s:
        return False
    upper_a, upper_b = o[1] + arm.shoulder_offset * z[1], o[2] + arm.shoulder_offset * z[1]
    if segment_distance(np.vstack([kp[4:8], o[5]]), upper_a, upper_b).min() < 0.12 * s:
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


def sample_joints(rng: np.random.Generator, tool_length: float = 0.12, task: WorkTask | None = None,
                  arm: ArmModel = UR5_ARM) -> np.ndarray:
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
            if pose_is_plausible(q, tool_length, arm):
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
        if pose_is_plausible(q, tool_length, arm):
            return q
    raise RuntimeError("no plausible UR5 pose found in 1000 draws")  # pragma: no cover - never seen
