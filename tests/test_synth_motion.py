"""Motion sequences of the synthetic generator (`synth --motion`): smooth, reproducible, a video beside the frames."""

import math

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.synth import generate_dataset
from fcnpose_tf.data.synth.datasets import MOTION_VIDEO
from fcnpose_tf.data.synth.motion import MAX_JOINT_SPEED, motion_joints
from fcnpose_tf.data.via import read_via
from fcnpose_tf.errors import UserError


def test_motion_is_smooth_and_seed_reproducible():
    q = motion_joints(3, 240, 30.0)
    np.testing.assert_array_equal(q, motion_joints(3, 240, 30.0))
    assert not np.array_equal(q, motion_joints(4, 240, 30.0))
    step = np.abs(np.diff(q, axis=0)).max(1)
    assert step.max() <= 1.9 * MAX_JOINT_SPEED / 30.0  # minimum jerk peaks at 1.875x the mean speed
    assert (step == 0).mean() > 0.05  # it dwells at its waypoints
    assert step.max() > math.radians(0.5)  # and moves between them


def test_a_motion_set_has_ground_truth_for_every_frame_and_a_video(tmp_path):
    report = generate_dataset(tmp_path / "seq", n=6, seed=1, width=96, height=72, workers=1, progress=False,
                              motion_fps=30.0)
    assert report.motion_fps == 30.0 and all(r.person == "none" for r in report.frames)
    ann = read_via(report.via_path)
    assert len(ann.frames) == 6
    video = cv2.VideoCapture(str(tmp_path / "seq" / MOTION_VIDEO))
    count = 0
    while video.read()[0]:
        count += 1
    assert count == 6
    assert video.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)


@pytest.mark.parametrize("kwargs", [{"motion_fps": 0.0}, {"motion_fps": 30.0, "scene": "random"}])
def test_bad_motion_options_are_user_errors(tmp_path, kwargs):
    with pytest.raises(UserError, match="--motion"):
        generate_dataset(tmp_path / "x", n=2, width=64, height=48, workers=1, progress=False, **kwargs)
    assert not (tmp_path / "x").exists()
