"""The rendered arm: paint, model and tool of one robot (`RobotStyle`) and its shapes at given joint angles."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fcnpose_tf.data.synth.kinematics import forward_kinematics
from fcnpose_tf.data.synth.looks import ARMS, UR5_ARM, ArmModel, LookFamily, paint_colours
from fcnpose_tf.data.synth.primitives import LABEL_ROBOT, Box, Material, Part, Tube


UR5_SILVER = np.array([0.80, 0.81, 0.82])
UR5_CAP_BLUE = np.array([0.47, 0.60, 0.73])
UR5_BAND_DARK = np.array([0.11, 0.115, 0.125])


@dataclass
class RobotStyle:
    """Colours, model and tool of one rendered arm (varied a little per frame, like real paint and light).

    silver: the links' paint; housing: the joint housings' (None: the links'). opening: a gripper's
    opening between the fingertips (m; None: the classic gripper's fixed fingers).
    """

    silver: Material
    cap: Material
    band: Material
    tool: str
    tool_length: float
    tool_material: Material
    finger_material: Material
    arm: ArmModel = UR5_ARM
    housing: Material | None = None
    opening: float | None = None

    @property
    def housing_material(self) -> Material:
        return self.silver if self.housing is None else self.housing


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


TOOL_LENGTHS = {"gripper": (0.12, 0.17), "gripper3": (0.13, 0.19), "vacuum": (0.07, 0.12), "spindle": (0.10, 0.15),
                "suction": (0.09, 0.13), "none": (0.015, 0.03), "adaptive2f": (0.14, 0.17)}
"""Flange to tool point (m) per end effector; `none` is a bare tool-changer plate."""


def robot_style_for(rng: np.random.Generator, family: LookFamily) -> RobotStyle:
    """A robot of a look family: `classic` draws exactly as `robot_style`; other families draw the arm
    model, the paint scheme (per-link colours, gloss, caps) and the end effector from the family."""
    if family.name == "classic":
        return robot_style(rng)
    arm = ARMS[str(rng.choice(family.arms))]
    link, housing, cap, band = paint_colours(rng, str(rng.choice(family.paints)))
    gloss = rng.uniform(0.05, 0.6)
    silver = Material(link, specular=gloss, shininess=rng.uniform(4, 60))
    housing_m = Material(housing, specular=gloss * rng.uniform(0.6, 1.2), shininess=rng.uniform(4, 60))
    cap_m = Material(cap, specular=rng.uniform(0.05, 0.5), shininess=rng.uniform(8, 50))
    band_m = Material(band, specular=0.15, shininess=20)
    tool = str(rng.choice(family.tools))
    length = float(rng.uniform(*TOOL_LENGTHS[tool])) * (0.85 + 0.15 * arm.scale)
    if tool == "adaptive2f":  # a black adaptive gripper with aluminium fingers
        body, fingers = np.array([0.07, 0.07, 0.08]), np.array([0.62, 0.63, 0.66])
    else:
        body = rng.uniform(0.05, 0.9, 3) if rng.random() < 0.4 else np.full(3, rng.uniform(0.06, 0.8))
        fingers = rng.uniform(0.05, 0.9, 3) if rng.random() < 0.3 else np.full(3, rng.uniform(0.1, 0.75))
    opening = float(rng.uniform(0.0, 0.085)) if tool in ("gripper", "gripper3", "adaptive2f") else None
    return RobotStyle(silver, cap_m, band_m, tool, length, Material(body, rng.uniform(0.1, 0.5), 24),
                      Material(fingers, 0.3, 24), arm, housing_m, opening)


def _housing_parts(centre_o, axis, span, radius, style: RobotStyle, ends=("cap", "cap")) -> list[Part]:
    """A UR joint housing: a body whose ends are each a dark band plus a cap ("cap"), a plain face
    ("plain") or hidden inside the neighbouring housing ("buried", no face)."""
    lo, hi = span
    s = style.arm.scale
    band, cap = 0.010 * s, 0.014 * s
    p = lambda s: centre_o + s * axis  # noqa: E731
    body_lo = lo + (band + cap if ends[0] == "cap" else 0.0)
    body_hi = hi - (band + cap if ends[1] == "cap" else 0.0)
    parts: list[Part] = [Tube(p(body_lo), p(body_hi), (radius, radius), (radius, radius), style.housing_material,
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
    """The arm's shapes (world coordinates) at joint angles q, mounted with its base face at height base_z."""
    arm = style.arm
    s = arm.scale
    frames = forward_kinematics(q, arm)
    o = frames[:, :3, 3] + (0.0, 0.0, base_z)
    z = frames[:, :3, 2]
    x = frames[:, :3, 0]
    up = np.array([0.0, 0.0, 1.0])
    silver = style.silver
    parts: list[Part] = []
    # base: dark mounting ring and the vertical joint-1 housing
    parts.append(Tube(o[0], o[0] + 0.012 * s * up, (0.09 * s, 0.09 * s), (0.088 * s, 0.088 * s), style.band,
                      LABEL_ROBOT, caps=(False, True), segments=28))
    parts.append(Tube(o[0] + arm.base_span[0] * up, o[0] + 0.022 * s * up, (arm.base_radius,) * 2,
                      (arm.base_radius,) * 2, style.band, LABEL_ROBOT, caps=(False, False), segments=24))
    parts.append(Tube(o[0] + 0.022 * s * up, o[0] + arm.base_span[1] * up, (arm.base_radius,) * 2,
                      (arm.base_radius,) * 2, style.housing_material, LABEL_ROBOT, caps=(False, True), segments=24))
    for name in ("shoulder", "elbow", "wrist1", "wrist2", "wrist3"):
        i, span, radius, ends = arm.housings[name]
        parts += _housing_parts(o[i], z[i], span, radius, style, ends)
    # upper arm and forearm tubes, thicker where they meet the housings
    ua0, ua1 = o[1] + arm.shoulder_offset * z[1], o[2] + arm.shoulder_offset * z[1]
    fa0, fa1 = o[2] + arm.forearm_offset * z[2], o[3] + arm.forearm_offset * z[3]
    for a, b, r in ((ua0, ua1, 0.044 * s), (fa0, fa1, 0.037 * s)):
        d = (b - a) / np.linalg.norm(b - a)
        parts.append(Tube(a + 0.04 * s * d, b - 0.04 * s * d, (r, r), (r, r), silver, LABEL_ROBOT,
                          caps=(False, False)))
        parts.append(Tube(a, a + 0.07 * s * d, (r * 1.12, r * 1.12), (r, r), silver, LABEL_ROBOT, caps=(False, False)))
        parts.append(Tube(b - 0.07 * s * d, b, (r, r), (r * 1.12, r * 1.12), silver, LABEL_ROBOT, caps=(False, False)))
    # tool flange and tool
    parts.append(Tube(o[5] + arm.flange_span[0] * z[5], o[6], (arm.flange_radius,) * 2, (arm.flange_radius,) * 2,
                      Material(silver.rgb * 0.8, 0.4, 30), LABEL_ROBOT, caps=(False, True), segments=20))
    parts += _tool_parts(o[6], z[6], x[6], style)
    return parts


def _tool_parts(flange: np.ndarray, n: np.ndarray, side: np.ndarray, style: RobotStyle) -> list[Part]:
    L = style.tool_length
    m = style.tool_material
    if style.tool == "adaptive2f":
        return _adaptive_gripper(flange, n, side, style)
    if style.tool == "gripper3":
        return _three_finger_gripper(flange, n, side, style)
    if style.tool == "vacuum":
        return _vacuum_plate(flange, n, side, style)
    if style.tool == "none":
        return [Tube(flange, flange + L * n, (0.034,) * 2, (0.034,) * 2, style.band, LABEL_ROBOT, caps=(False, True),
                     segments=18)]
    if style.tool == "gripper":
        body = 0.55 * L
        parts: list[Part] = [Tube(flange, flange + 0.012 * n, (0.036,) * 2, (0.036,) * 2, style.band, LABEL_ROBOT,
                                  caps=(False, True)),
                             Tube(flange + 0.012 * n, flange + body * n, (0.037, 0.030), (0.037, 0.030), m,
                                  LABEL_ROBOT, caps=(False, True), u=side, segments=16)]
        half_open = None if style.opening is None else 0.5 * style.opening
        for sgn in (-1.0, 1.0):
            if half_open is None:  # the classic gripper's fixed fingers
                a = flange + body * n + sgn * 0.018 * side
                b = flange + L * n + sgn * 0.009 * side
            else:
                a = flange + body * n + sgn * (half_open + 0.012) * side
                b = flange + L * n + sgn * (half_open + 0.006) * side
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


def _finger(a: np.ndarray, b: np.ndarray, side: np.ndarray, n: np.ndarray, width: float, thickness: float,
            material: Material) -> Box:
    """A flat finger from a to b, `thickness` across `side`, `width` across the other direction."""
    across = np.cross(n, side)
    return Box(0.5 * (a + b), np.stack([0.5 * thickness * side, 0.5 * width * across, 0.5 * (b - a)], 1), material,
               LABEL_ROBOT)


def _adaptive_gripper(flange: np.ndarray, n: np.ndarray, side: np.ndarray, style: RobotStyle) -> list[Part]:
    """An adaptive two-finger gripper (Robotiq 2F-like): a wide flat body, two-link fingers with pads; the
    tool point lies in free space between the fingertips."""
    L = style.tool_length
    half_open = 0.5 * (style.opening or 0.0)
    across = np.cross(n, side)
    body_len = 0.5 * L
    centre = flange + (0.012 + 0.5 * body_len) * n
    parts: list[Part] = [Tube(flange, flange + 0.012 * n, (0.038,) * 2, (0.038,) * 2, style.band, LABEL_ROBOT,
                              caps=(False, True)),
                         Box(centre, np.stack([0.045 * side, 0.020 * across, 0.5 * body_len * n], 1),
                             style.tool_material, LABEL_ROBOT)]
    for sgn in (-1.0, 1.0):
        knuckle = flange + (0.012 + body_len) * n + sgn * 0.030 * side
        joint = flange + (0.012 + body_len + 0.45 * (L - body_len)) * n + sgn * (half_open + 0.014) * side
        tip = flange + L * n + sgn * (half_open + 0.007) * side
        parts.append(_finger(knuckle, joint, side, n, 0.026, 0.010, style.finger_material))
        parts.append(_finger(joint, tip, side, n, 0.022, 0.012, style.tool_material))
    return parts


def _three_finger_gripper(flange: np.ndarray, n: np.ndarray, side: np.ndarray, style: RobotStyle) -> list[Part]:
    """A round body with three fingers 120 degrees apart, closing toward the tool point."""
    L = style.tool_length
    r_open = 0.5 * (style.opening or 0.0)
    across = np.cross(n, side)
    body = 0.5 * L
    parts: list[Part] = [Tube(flange, flange + body * n, (0.042,) * 2, (0.036,) * 2, style.tool_material, LABEL_ROBOT,
                              caps=(False, True), segments=18)]
    for k in range(3):
        ang = 2.0 * np.pi * k / 3.0
        radial = np.cos(ang) * side + np.sin(ang) * across
        a = flange + body * n + 0.028 * radial
        b = flange + L * n + (r_open + 0.006) * radial
        parts.append(_finger(a, b, radial, n, 0.014, 0.008, style.finger_material))
    return parts


def _vacuum_plate(flange: np.ndarray, n: np.ndarray, side: np.ndarray, style: RobotStyle) -> list[Part]:
    """A bar with four suction cups: the tool point is the centre of the cups' faces."""
    L = style.tool_length
    across = np.cross(n, side)
    stem = 0.45 * L
    parts: list[Part] = [Tube(flange, flange + stem * n, (0.022,) * 2, (0.022,) * 2, style.tool_material, LABEL_ROBOT,
                              segments=14),
                         Box(flange + (stem + 0.008) * n, np.stack([0.09 * side, 0.03 * across, 0.008 * n], 1),
                             style.tool_material, LABEL_ROBOT)]
    cup = Material(np.array([0.06, 0.06, 0.07]), 0.2, 16)
    for a in (-0.065, -0.022, 0.022, 0.065):
        top = flange + (stem + 0.016) * n + a * side
        parts.append(Tube(top, flange + L * n + a * side, (0.008,) * 2, (0.016,) * 2, cup, LABEL_ROBOT, segments=12))
    return parts
