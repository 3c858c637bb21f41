"""One synthetic frame: the arm's pose, the co-worker, painting, occlusion tests and the webcam's effects.

Each frame's randomness comes from its own generator seeded with (seed, index), so a frame does
not depend on which worker renders it or on the other frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.data.synth.camera import Camera
from fcnpose_tf.data.synth.kinematics import segment_distance, ur5_keypoints_3d
from fcnpose_tf.data.synth.looks import DEFAULT_LABELS, DEFAULT_LOOKS, check_labels, look_family
from fcnpose_tf.data.synth.person import person_parts
from fcnpose_tf.data.synth.primitives import LABEL_PERSON, Light, Part, part_points
from fcnpose_tf.data.synth.rendering import Painter, Room, render_background, shadow_mask
from fcnpose_tf.data.synth.robot import ur5_parts
from fcnpose_tf.data.synth.scene import (DEFAULT_SCENE, DEFAULT_TIGHT_FRAMING, PERSON_ODDS, SCENES, pose_in_view,
                                         random_scene, workcell)
from fcnpose_tf.errors import UserError


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
    arm: str = "ur5"
    looks: str = DEFAULT_LOOKS
    label_convention: str = DEFAULT_LABELS


def _frame_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index), 0x5EED]))


def render_sample(seed: int | np.random.Generator = 0, index: int = 0, width: int = 640,
                  height: int = 480, tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                  scene_seed: int = 0, looks: str = DEFAULT_LOOKS, labels: str = DEFAULT_LABELS,
                  joints: np.ndarray | None = None, person: bool = True) -> SynthSample:
    """Render frame `index` of the synthetic set `seed` (or draw from a given Generator) at width x height.

    `scene` is "workcell" (the fixed cell of `scene_seed`) or "random" (see DEFAULT_SCENE); `looks` the
    look family (`looks.FAMILIES`); `labels` the keypoint convention (`looks.LABEL_CONVENTIONS`).
    `joints` poses a workcell's arm (a motion sequence, `motion.motion_joints`) instead of drawing a pose;
    `person=False` leaves the co-worker out.
    """
    if width < 32 or height < 32:
        raise UserError(f"frame size {width}x{height} is too small; expected at least 32x32")
    if scene not in SCENES:
        raise UserError(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}")
    family = look_family(looks)
    check_labels(labels)
    rng = seed if isinstance(seed, np.random.Generator) else _frame_rng(seed, index)
    if scene == "workcell":
        cell = workcell(scene_seed, width, height, looks)
        q = pose_in_view(rng, cell, tight_framing) if joints is None else np.asarray(joints, np.float64)
    else:
        cell, q = random_scene(rng, width, height, tight_framing, looks)
    style, lens_cam, base_z = cell.style, cell.camera, cell.base_z
    cam = lens_cam.render_camera()  # painted as a pinhole; a distorting lens resamples the picture at the end
    kp3d = ur5_keypoints_3d(q, style.tool_length, base_z, style.arm, labels)
    robot = ur5_parts(q, style, base_z)
    robot_pts = np.vstack([part_points(p) for p in robot])
    kp_uv, kp_z = cam.project(kp3d)
    person, _ = _place_person(rng, cam, kp3d, kp_uv, kp_z, cell.mount_radius, cell.keepout[2:],
                              PERSON_ODDS[scene]) if person else ([], "none")

    keypoints = lens_cam.project(kp3d)[0] if lens_cam.k1 else kp_uv.copy()
    inside = (kp_z > 0) & (keypoints[:, 0] >= 0) & (keypoints[:, 0] <= width - 1) & (keypoints[:, 1] >= 0) & \
             (keypoints[:, 1] <= height - 1)
    keypoints[~inside] = np.nan
    painted_uv = np.where(inside[:, None], kp_uv, np.nan)  # where the keypoints are on the painted canvas
    state = rng.bit_generator.state
    ss = 2
    while True:
        room_rng = None if cell.room_seed is None else np.random.default_rng(cell.room_seed)
        canvas, label_map, depth = _paint(rng, cam, ss, cell.room, cell.light, cell.lamp, robot, cell.mount_parts,
                                       person, cell.objects, robot_depth_far=float(cam.to_camera(robot_pts)[:, 2].max()),
                                       room_rng=room_rng)
        occluded = _person_in_front(label_map, depth, (painted_uv + 0.5) * ss - 0.5, kp_z)
        if occluded.sum() <= MAX_HIDDEN_BY_PERSON or not person:
            break
        rng.bit_generator.state = state  # the person would hide most of the arm: the same frame without them
        person = []
    person_mode = "none" if not person else "occluding" if occluded.any() else "beside"
    img = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA)
    labels_1x = cv2.resize(label_map, (width, height), interpolation=cv2.INTER_NEAREST)
    if lens_cam.k1:
        map_x, map_y = lens_cam.distortion_maps()
        img = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        labels_1x = cv2.remap(labels_1x, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    img = _camera_effects(rng, img, SENSORS[family.sensor])
    return SynthSample(img, keypoints, kp3d, q, lens_cam, occluded, labels_1x, person_mode, cell.mount, style.tool,
                       style.tool_length, style.arm.name, looks, labels)


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
    bg, floor_mask = render_background(rng if room_rng is None else room_rng, bg_cam, room, light, lamp)
    shadow = shadow_mask(robot + mount_parts + person + objects, light, bg_cam, bg.shape[:2]) * floor_mask
    bg *= (1.0 - rng.uniform(0.3, 0.55) * shadow)[..., None]
    cam2 = cam.scaled(ss)
    canvas = cv2.resize(bg, (cam2.width, cam2.height), interpolation=cv2.INTER_LINEAR)
    labels = np.zeros((cam2.height, cam2.width), np.uint8)
    depth = np.full((cam2.height, cam2.width), np.inf, np.float32)
    painter = Painter(canvas, labels, cam2, light, depth=depth)
    for part in robot + person + objects:
        painter.add(part)
    for part in mount_parts:  # the mount is under the robot: drawn before any robot facet
        painter.add(part, min_depth=robot_depth_far + 1e-3)
    painter.flush()
    return canvas, labels, depth


def _robot_clearance(parts: Sequence[Part], kp3d: np.ndarray) -> float:
    """Smallest distance (m) from the parts' outline points to the arm's skeleton, minus the arm's radius."""
    pts = np.vstack([part_points(p) for p in parts])
    chain = np.vstack([kp3d[:1], kp3d[:1] + (0, 0, 0.1), kp3d[1:]])
    return min(float(segment_distance(pts, a, b).min()) for a, b in zip(chain[:-1], chain[1:])) - 0.08


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
        pts = part_points(part)
        uv, z = cam.project(pts)
        if z.min() < 0.05:
            continue
        hull = cv2.convexHull(uv.astype(np.float32))
        for k in range(len(kp_uv)):
            if not hidden[k] and z.mean() < kp_z[k] and cv2.pointPolygonTest(hull, tuple(map(float, kp_uv[k])),
                                                                            False) >= 0:
                hidden[k] = True
    return hidden


@dataclass(frozen=True)
class Sensor:
    """Ranges of a camera's processing (`_camera_effects`); `clean` skips noise, shake, gamma and JPEG."""

    exposure: tuple[float, float] = (0.36, 0.55)
    white_balance: float = 0.04
    vignette: float = 0.25
    shake: float = 0.12
    blur: tuple[float, float] = (0.25, 1.1)
    noise: tuple[float, float] = (0.004, 0.022)
    gamma: tuple[float, float] = (0.85, 1.15)
    jpeg: float = 0.5
    jpeg_quality: tuple[int, int] = (60, 96)
    clean: bool = False


SENSORS = {
    "webcam": Sensor(),
    "varied": Sensor(exposure=(0.3, 0.6), white_balance=0.12, vignette=0.4, shake=0.12, blur=(0.2, 1.6),
                     noise=(0.0, 0.03), gamma=(0.8, 1.25), jpeg=0.6, jpeg_quality=(35, 96)),
    "clean": Sensor(exposure=(0.42, 0.5), white_balance=0.0, vignette=0.0, shake=0.0, blur=(0.35, 0.35), clean=True),
}
"""`webcam`: the classic look (a USB webcam); `varied`: wider white balance, noise, blur and JPEG for
pretraining; `clean` (held out): a render engine's output, sharp and noiseless."""


def _camera_effects(rng: np.random.Generator, img: np.ndarray, sensor: Sensor = SENSORS["webcam"]) -> np.ndarray:
    """Exposure, white balance, vignetting, blur, sensor noise, gamma and (sometimes) JPEG: float RGB -> uint8 BGR."""
    h, w = img.shape[:2]
    scale = w / 640.0
    if sensor.clean:  # a renderer's output: exposure, a little anti-aliasing blur, nothing else
        img *= np.float32(rng.uniform(*sensor.exposure) / max(float(img.mean()), 1e-3))
        img = cv2.GaussianBlur(img, (0, 0), sensor.blur[0] * scale)
        np.clip(img, 0.0, 1.0, out=img)
        return cv2.cvtColor(cv2.convertScaleAbs(img, alpha=255.0), cv2.COLOR_RGB2BGR)
    # auto-exposure as a webcam does it: bring the mean level to a target, within the sensor's gain range
    exposure = float(np.clip(rng.uniform(*sensor.exposure) / max(float(img.mean()), 1e-3), 0.6, 2.6))
    gain = np.float32(exposure) * (1 + rng.normal(0, sensor.white_balance, 3)).astype(np.float32)
    vignette = np.float32(rng.uniform(0.0, sensor.vignette) / 2)
    vx = ((np.arange(w, dtype=np.float32) - w / 2) / (w / 2)) ** 2
    vy = ((np.arange(h, dtype=np.float32) - h / 2) / (h / 2)) ** 2
    img *= (1.0 - vignette * (vx[None, :] + vy[:, None]))[..., None]
    img *= gain
    if rng.random() < sensor.shake:  # camera shake
        n = int(rng.integers(3, 8) * scale) | 1
        kernel = np.zeros((n, n), np.float32)
        kernel[n // 2, :] = 1.0 / n
        rot = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), rng.uniform(0, 180), 1.0)
        kernel = cv2.warpAffine(kernel, rot, (n, n))
        img = cv2.filter2D(img, -1, kernel / max(float(kernel.sum()), 1e-6))
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(*sensor.blur) * scale)
    # sensor noise after the camera's processing: mostly luminance, shot-noise-like (grows with sqrt of the
    # level), plus coarser colour noise
    sigma = np.float32(1.6 * rng.uniform(*sensor.noise))
    lum = rng.standard_normal((h, w), dtype=np.float32)
    lum *= np.sqrt(np.clip(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), 0.02, 1.0))
    lum *= sigma
    img += lum[..., None]
    chroma = rng.standard_normal(((h + 1) // 2, (w + 1) // 2, 3), dtype=np.float32)
    chroma *= sigma * np.float32(0.35)
    img += cv2.resize(chroma, (w, h), interpolation=cv2.INTER_LINEAR)
    np.clip(img, 0.0, 1.0, out=img)
    out = cv2.cvtColor(cv2.convertScaleAbs(img, alpha=255.0), cv2.COLOR_RGB2BGR)
    gamma = rng.uniform(*sensor.gamma)
    lut = np.clip(255.0 * (np.arange(256) / 255.0) ** gamma + 0.5, 0, 255).astype(np.uint8)
    out = cv2.LUT(out, lut)
    if rng.random() < sensor.jpeg:  # webcam MJPEG compression
        _, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(*sensor.jpeg_quality))])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return out


def render_frame(seed: int | np.random.Generator = 0, index: int = 0, width: int = 640,
                 height: int = 480, tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                 scene_seed: int = 0, looks: str = DEFAULT_LOOKS,
                 labels: str = DEFAULT_LABELS) -> tuple[np.ndarray, np.ndarray]:
    """(H x W x 3 uint8 BGR image, 8 x 2 keypoints in UR5 order, NaN outside the frame) of one frame."""
    sample = render_sample(seed, index, width, height, tight_framing, scene, scene_seed, looks, labels)
    return sample.image, sample.keypoints
