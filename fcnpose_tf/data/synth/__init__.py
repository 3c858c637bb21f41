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

The modules, from the bottom up: `kinematics` (DH model, keypoints, poses), `camera`,
`primitives` (materials, light, tubes, spheres, boxes), `robot` and `person` (their shapes),
`textures` (floor, walls), `rendering` (shading, painter's algorithm, room, shadows), `scene`
(mounts, clutter, camera placement, workcells), `frame` (one rendered frame), `datasets`
(folders of frames plus a VIA file) and `preview` (grids to look at; the drawing itself is
`fcnpose_tf.draw`). See docs/synthetic.md.
"""

from fcnpose_tf.data.synth.camera import Camera
from fcnpose_tf.data.synth.datasets import (IMAGE_DIR, VIA_FILENAME, FrameRecord, SynthReport, default_workers,
                                            generate, generate_dataset)
from fcnpose_tf.data.synth.frame import SynthSample, render_frame, render_sample
from fcnpose_tf.data.synth.kinematics import (WorkTask, dh_transform, forward_kinematics, pose_is_plausible,
                                              sample_joints, ur5_keypoints_3d)
from fcnpose_tf.data.synth.preview import preview_grid, write_preview
from fcnpose_tf.data.synth.primitives import LABEL_CLUTTER, LABEL_MOUNT, LABEL_PERSON, LABEL_ROBOT
from fcnpose_tf.data.synth.scene import DEFAULT_SCENE, DEFAULT_TIGHT_FRAMING, SCENES, Scene, workcell

__all__ = [
    "Camera", "IMAGE_DIR", "VIA_FILENAME", "FrameRecord", "SynthReport", "default_workers", "generate",
    "generate_dataset", "SynthSample", "render_frame", "render_sample", "WorkTask", "dh_transform",
    "forward_kinematics", "pose_is_plausible", "sample_joints", "ur5_keypoints_3d", "preview_grid",
    "write_preview", "LABEL_CLUTTER", "LABEL_MOUNT", "LABEL_PERSON", "LABEL_ROBOT", "DEFAULT_SCENE",
    "DEFAULT_TIGHT_FRAMING", "SCENES", "Scene", "workcell",
]
