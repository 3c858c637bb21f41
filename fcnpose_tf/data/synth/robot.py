"""The rendered UR5: paint and tool of one robot (`RobotStyle`) and its shapes at given joint angles."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fcnpose_tf.data.synth.kinematics import (BASE_RADIUS, BASE_SPAN, FLANGE_RADIUS, FLANGE_SPAN, FOREARM_OFFSET,
                                              HOUSINGS, SHOULDER_OFFSET, forward_kinematics)
from fcnpose_tf.data.synth.primitives import LABEL_ROBOT, Box, Material, Part, Tube


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


def robot_style(rng: np.random.Generator) -> RobotStyle:
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
    parts.append(Tube(o[0] + BASE_SPAN[0] * up, o[0] + 0.022 * up, (BASE_RADIUS,) * 2, (BASE_RADIUS,) * 2,
                      style.band, LABEL_ROBOT, caps=(False, False), segments=24))
    parts.append(Tube(o[0] + 0.022 * up, o[0] + BASE_SPAN[1] * up, (BASE_RADIUS,) * 2, (BASE_RADIUS,) * 2,
                      silver, LABEL_ROBOT, caps=(False, True), segments=24))
    for name in ("shoulder", "elbow", "wrist1", "wrist2", "wrist3"):
        i, span, radius, ends = HOUSINGS[name]
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
    parts.append(Tube(o[5] + FLANGE_SPAN[0] * z[5], o[6], (FLANGE_RADIUS,) * 2, (FLANGE_RADIUS,) * 2,
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
