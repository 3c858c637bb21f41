"""Scene sampling: what a frame's robot stands on, the clutter, the light, the room and the camera.

A workcell (`workcell`) is one fixed cell and camera per scene seed whose arm works at one task; a
random scene (`random_scene`) is a new cell and camera per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fcnpose_tf.data.synth.camera import Camera
from fcnpose_tf.data.synth.kinematics import PI, WorkTask, sample_joints, ur5_keypoints_3d
from fcnpose_tf.data.synth.looks import DEFAULT_LOOKS, LookFamily, look_family
from fcnpose_tf.data.synth.primitives import (LABEL_CLUTTER, LABEL_MOUNT, Light, Material, Part, Tube, box_part,
                                              part_points)
from fcnpose_tf.data.synth.rendering import Room
from fcnpose_tf.data.synth.robot import RobotStyle, robot_style_for, ur5_parts


def _keypoint_bbox_fraction(uv: np.ndarray, width: int, height: int) -> float:
    span = uv.max(0) - uv.min(0)
    return float(max(span[0] / width, span[1] / height))


DEFAULT_TIGHT_FRAMING = 0.0
"""Default share of frames framed so tightly that one or two keypoints fall outside (left
unannotated); `--tight-framing 0.04` gives 1 frame in 25, to exercise partly annotated frames."""


def _place_camera(rng: np.random.Generator, kp3d: np.ndarray, robot_pts: np.ndarray, width: int, height: int,
                  min_eye_z: float, tight_framing: float = DEFAULT_TIGHT_FRAMING,
                  frac_range: tuple[float, float] = (0.38, 0.72), fov_deg: tuple[float, float] = (55.0, 78.0),
                  roll_deg: float = 2.5) -> Camera:
    """A camera around the robot framing the arm at a random size and image position.

    `fov_deg`: range of the diagonal field of view (default: common webcams); `roll_deg`: standard
    deviation of the roll. In `tight_framing` of the frames the framing is tight and one or two
    keypoints fall outside the image. The draw is made whatever the rate, so other frames do not depend on it.
    """
    diag = math.hypot(width, height)
    centre = 0.5 * (kp3d.min(0) + kp3d.max(0))
    size = np.array([width, height]) - 1.0
    if rng.random() < tight_framing:
        for _ in range(100):
            focal = 0.5 * diag / math.tan(math.radians(rng.uniform(*fov_deg)) / 2)
            yaw, elev = rng.uniform(-PI, PI), math.radians(rng.uniform(0.0, 35.0))
            direction = np.array([math.cos(yaw) * math.cos(elev), math.sin(yaw) * math.cos(elev), math.sin(elev)])
            eye = centre + rng.uniform(1.4, 2.2) * direction
            if not (0.3 <= eye[2] <= 2.5) or eye[2] < min_eye_z:
                continue
            target = centre + rng.normal(0.0, 0.25, 3)
            cam = Camera.look_at(eye, target, focal, width, height, roll=math.radians(rng.normal(0.0, roll_deg)))
            uv, z = cam.project(kp3d)
            inside = (z > 0.2) & (uv >= 0).all(1) & (uv <= size).all(1)
            if 6 <= inside.sum() <= 7 and cam.project(robot_pts)[1].min() > 0.2:
                return cam
    for _ in range(100):
        fov = math.radians(rng.uniform(*fov_deg))  # diagonal field of view
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
        roll = math.radians(rng.normal(0.0, roll_deg))
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
        parts: list[Part] = [box_part(pos + up * sz / 2, dims, yaw, Material(col, 0.03), lab, edges=True)]
        if rng.random() < 0.4:
            d2 = (sx * 0.8, sy * 0.8, sz * 0.8)
            parts.append(box_part(pos + up * (sz + d2[2] / 2), d2, yaw + rng.normal(0, 0.2), Material(col * 0.95, 0.03),
                              lab, edges=True))
        return parts
    if kind == "cabinet":
        col = [np.array([0.7, 0.1, 0.1]), np.array([0.15, 0.25, 0.55]), np.array([0.35, 0.36, 0.38]),
               np.array([0.12, 0.4, 0.2]), np.array([0.1, 0.1, 0.1])][rng.integers(5)]
        return [box_part(pos + up * sz / 2, dims, yaw, Material(col, 0.3, 20), lab, edges=True)]
    if kind == "bench":
        top = Material([np.array([0.65, 0.48, 0.3]), np.array([0.5, 0.5, 0.5]), np.array([0.85, 0.85, 0.82])][
            rng.integers(3)] * rng.uniform(0.85, 1.1), 0.1)
        frame = Material(np.array([0.25, 0.35, 0.55]) if rng.random() < 0.5 else np.array([0.3, 0.3, 0.3]), 0.3)
        parts = [box_part(pos + up * (sz - 0.02), (sx, sy, 0.04), yaw, top, lab)]
        for a in (-1, 1):
            for b in (-1, 1):
                leg = pos + a * ex * (sx / 2 - 0.05) + b * ey * (sy / 2 - 0.05) + up * (sz - 0.04) / 2
                parts.append(box_part(leg, (0.05, 0.05, sz - 0.04), yaw, frame, lab))
        if rng.random() < 0.7:
            item = pos + ex * rng.uniform(-sx / 3, sx / 3) + up * (sz + 0.08)
            parts.append(box_part(item, (0.25, 0.2, 0.16), yaw + rng.normal(0, 0.3),
                                  Material(rng.uniform(0.1, 0.9, 3), 0.2), lab))
        return parts
    if kind == "shelving":
        frame = Material(np.array([0.2, 0.35, 0.6]) if rng.random() < 0.5 else np.array([0.55, 0.55, 0.56]), 0.3)
        parts = []
        for a in (-1, 1):
            for b in (-1, 1):
                post = pos + a * ex * (sx / 2 - 0.03) + b * ey * (sy / 2 - 0.03) + up * sz / 2
                parts.append(box_part(post, (0.04, 0.04, sz), yaw, frame, lab))
        for level in np.linspace(0.15, sz - 0.05, int(rng.integers(3, 5))):
            parts.append(box_part(pos + up * level, (sx, sy, 0.03), yaw, Material(np.array([0.6, 0.6, 0.6]), 0.2), lab))
            if level < sz - 0.3:
                for _ in range(int(rng.integers(0, 3))):
                    w = rng.uniform(0.2, 0.4)
                    off = rng.uniform(-sx / 2 + w / 2, sx / 2 - w / 2)
                    h = rng.uniform(0.12, 0.28)
                    parts.append(box_part(pos + ex * off + up * (level + 0.015 + h / 2), (w, sy * 0.8, h), yaw,
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
                box_part(pos + up * 0.015, (0.36, 0.36, 0.03), yaw, Material(np.array([0.9, 0.3, 0.05]), 0.2), lab)]
    # machine: a big enclosure with a dark window
    col = np.array([0.75, 0.76, 0.74]) * rng.uniform(0.8, 1.05)
    parts = [box_part(pos + up * sz / 2, dims, yaw, Material(col, 0.2, 16), lab, edges=True)]
    parts.append(box_part(pos + up * sz * 0.6 + ey * (sy / 2 + 0.005), (sx * 0.6, 0.01, sz * 0.35), yaw,
                      Material(np.array([0.12, 0.14, 0.16]), 0.6, 40), lab))
    parts.append(box_part(pos + up * sz * 0.6 - ey * (sy / 2 + 0.005), (sx * 0.6, 0.01, sz * 0.35), yaw,
                      Material(np.array([0.12, 0.14, 0.16]), 0.6, 40), lab))
    return parts


def _mount_parts(rng: np.random.Generator) -> tuple[str, float, list[Part], float]:
    """What the robot stands on: (kind, base height, parts, keep-out radius)."""
    kind = rng.choice(["floor", "floor", "pedestal", "table"])
    lab = LABEL_MOUNT
    if kind == "floor":
        plate = Material(np.full(3, rng.uniform(0.25, 0.7)), 0.3, 20)
        return "floor", 0.012, [box_part((0, 0, 0.006), (0.3, 0.3, 0.012), rng.uniform(0, PI), plate, lab)], 0.3
    if kind == "pedestal":
        h = rng.uniform(0.35, 0.85)
        w = rng.uniform(0.22, 0.4)
        col = [np.array([0.3, 0.3, 0.32]), np.array([0.7, 0.7, 0.72]), np.array([0.85, 0.7, 0.1]),
               np.array([0.15, 0.3, 0.55])][rng.integers(4)]
        yaw = rng.uniform(0, PI)
        rim = Material(col * 0.9, 0.3, 20)
        parts: list[Part] = [box_part((0, 0, h / 2), (w, w, h), yaw, Material(col, 0.3, 20), lab, edges=True),
                             box_part((0, 0, h - 0.01), (w + 0.08, w + 0.08, 0.02), yaw, rim, lab),
                             box_part((0, 0, 0.01), (w + 0.15, w + 0.15, 0.02), yaw, rim, lab)]
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
    parts = [box_part(centre + (0, 0, h - 0.02), (sx, sy, 0.04), yaw, top, lab)]
    for a in (-1, 1):
        for b in (-1, 1):
            leg = centre + a * ex * (sx / 2 - 0.04) + b * ey * (sy / 2 - 0.04) + np.array([0, 0, (h - 0.04) / 2])
            parts.append(box_part(leg, (0.045, 0.045, h - 0.04), yaw, frame, lab))
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


def _direction(azimuth: float, elevation_deg: float) -> np.ndarray:
    el = math.radians(elevation_deg)
    return np.array([math.cos(azimuth) * math.cos(el), math.sin(azimuth) * math.cos(el), math.sin(el)])


def _tint(rng: np.random.Generator, spread: float) -> np.ndarray:
    warmth = rng.uniform(-spread, spread)
    return np.array([1 + 0.07 * warmth, 1.0, 1 - 0.09 * warmth])


def light_for(rng: np.random.Generator, family: LookFamily) -> Light:
    """The light of a look family. `classic`: one key light 35-78 degrees high plus ambient (as always).
    `key`: the same with a wider colour range and 25-80 degrees; `key+fill`: plus a coloured fill light
    from another side; `overcast`: soft (weak key, strong ambient). `overhead` (held out): a key light
    82-90 degrees high, cool, with a warm fill from low on one side."""
    model = family.lights[0] if len(family.lights) == 1 else str(rng.choice(family.lights))
    if model == "classic":
        return _light(rng)
    if model == "overhead":
        key = Light(_direction(rng.uniform(-PI, PI), rng.uniform(82, 90)), _tint(rng, 0.3) * (0.95, 1.0, 1.08),
                    rng.uniform(0.6, 0.85), rng.uniform(0.3, 0.45))
        key.fill_direction = _direction(rng.uniform(-PI, PI), rng.uniform(5, 20))
        key.fill_color = np.array([1.15, 0.95, 0.75])
        key.fill = float(rng.uniform(0.25, 0.4))
        return key
    if model == "overcast":
        return Light(_direction(rng.uniform(-PI, PI), rng.uniform(40, 80)), _tint(rng, 1.2), rng.uniform(0.12, 0.3),
                     rng.uniform(0.65, 0.9))
    key = Light(_direction(rng.uniform(-PI, PI), rng.uniform(25, 80)), _tint(rng, 2.0), rng.uniform(0.4, 0.85),
                rng.uniform(0.3, 0.6))
    if model == "key+fill":
        key.fill_direction = _direction(rng.uniform(-PI, PI), rng.uniform(10, 60))
        key.fill_color = 0.75 + 0.5 * rng.random(3)
        key.fill = float(rng.uniform(0.12, 0.35))
    return key


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
        pts = np.vstack([part_points(p) for p in obj])
        lo, hi, z = _image_box(cam, pts)
        if z.min() < 0.3:
            continue
        if _overlap(lo, hi, arm_lo, arm_hi) and z.min() < robot_far + 0.05:
            continue
        clutter.append(obj)
    return [p for obj in clutter for p in obj]


def _scene_rng(scene_seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(scene_seed) & 0xFFFFFFFF, 0xCE11]))


_WORKCELLS: dict[tuple[int, int, int, str], Scene] = {}


WORKCELL_FRAMING = (0.85, 0.95)
"""Share of the image side a workcell's camera gives its task's workspace (the keypoints of
WORKSPACE_POSES sampled poses)."""


def workcell(scene_seed: int = 0, width: int = 640, height: int = 480, looks: str = DEFAULT_LOOKS) -> Scene:
    """The fixed cell of `scene_seed` in look family `looks`: an arm at one task (`WorkTask`: a 90-degree
    sector, elbow on one side, tool down) and a camera framing that task's workspace (many sampled poses)."""
    key = (int(scene_seed), int(width), int(height), looks)
    if key not in _WORKCELLS:
        family = look_family(looks)
        rng = _scene_rng(scene_seed) if looks == DEFAULT_LOOKS else np.random.default_rng(
            np.random.SeedSequence([int(scene_seed) & 0xFFFFFFFF, 0xCE11, sum(map(ord, looks))]))
        task = WorkTask(yaw=float(rng.uniform(-PI, PI)), elbow=1.0 if rng.random() < 0.5 else -1.0)
        style = robot_style_for(rng, family)
        mount, base_z, mount_parts, mount_radius = _mount_parts(rng)
        reach = np.vstack([ur5_keypoints_3d(sample_joints(rng, style.tool_length, task, style.arm), style.tool_length,
                                            base_z, style.arm) for _ in range(WORKSPACE_POSES)])
        cam = _place_camera(rng, reach, reach, width, height, min_eye_z=base_z + 0.15, frac_range=WORKCELL_FRAMING,
                            fov_deg=family.fov_deg, roll_deg=family.roll_deg)
        cam = _lens(rng, cam, family)
        light = light_for(rng, family)
        room, lamp = _room(rng, cam)
        keepout = [(np.zeros(2), mount_radius + 1.0), (cam.eye[:2], 0.7)]
        far = float(cam.to_camera(reach)[:, 2].max())
        objects = _clutter_in_view(rng, cam, room, keepout, reach, far)
        _WORKCELLS[key] = Scene(style, mount, base_z, mount_parts, mount_radius, cam, light, room, lamp, objects,
                                keepout, room_seed=int(rng.integers(0, 2 ** 63)), task=task)
    return _WORKCELLS[key]


def _lens(rng: np.random.Generator, cam: Camera, family: LookFamily) -> Camera:
    """The camera with the family's lens distortion (classic: a pinhole, no draw)."""
    if family.distorted_share <= 0.0:
        return cam
    if rng.random() >= family.distorted_share:
        return cam
    pull = float(rng.uniform(*family.corner_distortion))  # 1 - r_d / r_u at the picture's corner
    r_d = math.hypot(cam.width - 1, cam.height - 1) / 2 / cam.K[0, 0]
    r_u = r_d / (1.0 - pull)
    return Camera(cam.K, cam.R, cam.eye, cam.width, cam.height, -pull / (r_u * r_u))


def pose_in_view(rng: np.random.Generator, scene: Scene, tight_framing: float) -> np.ndarray:
    """Joint angles of a plausible pose whose 8 keypoints the scene's camera sees (6-7 when tightly framed)."""
    cam, style = scene.camera, scene.style
    size = np.array([cam.width, cam.height]) - 1.0
    tight = rng.random() < tight_framing
    q = None
    for _ in range(400):
        q = sample_joints(rng, style.tool_length, scene.task, style.arm)
        kp3d = ur5_keypoints_3d(q, style.tool_length, scene.base_z, style.arm)
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


def random_scene(rng: np.random.Generator, width: int, height: int,
                 tight_framing: float, looks: str = DEFAULT_LOOKS) -> tuple[Scene, np.ndarray]:
    """A new cell and camera of look family `looks` framing the arm in a random pose: (scene, joint angles)."""
    family = look_family(looks)
    style = robot_style_for(rng, family)
    mount, base_z, mount_parts, mount_radius = _mount_parts(rng)
    q = sample_joints(rng, style.tool_length, arm=style.arm)
    kp3d = ur5_keypoints_3d(q, style.tool_length, base_z, style.arm)
    robot_pts = np.vstack([part_points(p) for p in ur5_parts(q, style, base_z)])
    cam = _place_camera(rng, kp3d, robot_pts, width, height, min_eye_z=base_z + 0.15, tight_framing=tight_framing,
                        frac_range=family.framing, fov_deg=family.fov_deg, roll_deg=family.roll_deg)
    cam = _lens(rng, cam, family)
    light = light_for(rng, family)
    room, lamp = _room(rng, cam)
    keepout = [(np.zeros(2), mount_radius + 1.0), (cam.eye[:2], 0.7)]
    far = float(cam.to_camera(np.vstack([robot_pts] + [part_points(p) for p in mount_parts]))[:, 2].max())
    objects = _clutter_in_view(rng, cam, room, keepout, kp3d, far)
    return Scene(style, mount, base_z, mount_parts, mount_radius, cam, light, room, lamp, objects, keepout), q
