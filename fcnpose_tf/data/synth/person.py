"""The co-worker: a standing person built from tubes, spheres and boxes, in random clothes."""

from __future__ import annotations

import math

import numpy as np

from fcnpose_tf.data.synth.primitives import LABEL_PERSON, Material, Part, Sphere, Tube, box_part


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
        parts.append(box_part(foot + 0.05 * fwd - 0.035 * up, (0.27, 0.1, 0.08), facing, shoes, lab))
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
