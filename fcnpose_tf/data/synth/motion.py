"""Motion sequences: a workcell's arm moving smoothly from pose to pose, sampled at a frame rate.

The arm dwells at a pose (0.2-0.8 s, as at a pick), then moves to the next pose of its task in joint space
along a minimum-jerk profile (s = 10 u^3 - 15 u^4 + 6 u^5: zero speed and acceleration at both ends),
the joint that moves furthest at up to MAX_JOINT_SPEED. Waypoints are poses the cell's camera sees whole
(`scene.pose_in_view`); poses between them are not checked and may leave the picture or the task's
sector for a moment. The same (seed, scene seed, look family, frame rate) gives the same joint angles.
"""

from __future__ import annotations

import math

import numpy as np

from fcnpose_tf.data.synth.scene import pose_in_view, workcell

MAX_JOINT_SPEED = math.radians(60.0)
"""Speed (rad/s) of the joint that moves furthest in a move; a UR5's joints go up to 180 deg/s."""
DWELL_S = (0.2, 0.8)
"""Pause at each waypoint (s)."""


def _min_jerk(u: np.ndarray) -> np.ndarray:
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u)


def motion_joints(seed: int, n: int, fps: float, scene_seed: int = 0, width: int = 640, height: int = 480,
                  looks: str = "classic") -> np.ndarray:
    """Joint angles (n x 6, rad) of n consecutive frames at `fps` of the workcell `scene_seed`."""
    cell = workcell(scene_seed, width, height, looks)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x3071]))
    q = pose_in_view(rng, cell, 0.0)
    frames: list[np.ndarray] = []
    while len(frames) < n:
        frames += [q] * max(1, int(round(rng.uniform(*DWELL_S) * fps)))
        target = pose_in_view(rng, cell, 0.0)
        delta = (target - q + math.pi) % (2 * math.pi) - math.pi  # the shorter way round every joint
        steps = max(2, int(round(max(0.4, float(np.abs(delta).max()) / MAX_JOINT_SPEED) * fps)))
        frames += [q + s * delta for s in _min_jerk(np.arange(1, steps + 1) / steps)]
        q = q + delta
    return np.array(frames[:n])
