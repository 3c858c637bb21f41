"""One-Euro smoothing of keypoint tracks and the sequence metrics (jitter, lag): numpy references, no TF."""

import math

import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.metrics import jitter_px, lag_frames
from fcnpose_tf.smoothing import KeypointSmoother, OneEuroParams, smooth_track

FPS = 30.0


def test_a_constant_signal_stays_constant():
    track = np.tile([[100.0, 50.0], [10.0, 20.0]], (60, 1, 1))
    np.testing.assert_array_equal(smooth_track(track, FPS), track)


def test_a_step_is_followed_within_a_few_frames():
    track = np.zeros((60, 1, 2))
    track[30:] = [40.0, 0.0]
    out = smooth_track(track, FPS)
    np.testing.assert_array_equal(out[:30], 0.0)
    assert 0 < out[30, 0, 0] < 40.0  # smoothed, not jumping
    within = np.argmax(np.abs(out[30:, 0, 0] - 40.0) < 2.0)  # 5 % of the step
    assert 1 <= within <= 4
    assert np.all(np.diff(out[29:, 0, 0]) >= 0)  # no overshoot on the way


def test_noise_at_rest_is_cut_and_a_moving_point_is_not_dragged():
    rng = np.random.default_rng(0)
    t = np.arange(300) / FPS
    truth = np.stack([200 + 120 * np.sin(2 * math.pi * 0.4 * t), 150 + 60 * np.cos(2 * math.pi * 0.3 * t)], -1)
    truth = truth[:, None, :]
    noisy = truth + rng.normal(0, 2.0, truth.shape)
    out = smooth_track(noisy, FPS)
    assert jitter_px(out, truth) < 0.6 * jitter_px(noisy, truth)  # 2 px of noise on a point moving up to 300 px/s
    assert abs(lag_frames(out, truth)) <= 1.0
    still = np.full((100, 1, 2), 100.0)
    assert jitter_px(smooth_track(still + rng.normal(0, 2.0, still.shape), FPS), still) < 0.25 * 4.0  # raw: 2 px per axis, sqrt(2 * 2 * 2^2) = 4 px


def test_missing_frames_coast_then_reset():
    smoother = KeypointSmoother(1, OneEuroParams(max_coast=2))
    for i in range(5):
        smoother(np.array([[10.0, 10.0]]), i / FPS)
    held = [smoother(np.array([[np.nan, np.nan]]), (5 + i) / FPS) for i in range(3)]
    np.testing.assert_array_equal(held[0], [[10.0, 10.0]])
    np.testing.assert_array_equal(held[1], [[10.0, 10.0]])
    assert np.isnan(held[2]).all()  # the third missing frame: reported missing
    again = smoother(np.array([[300.0, 40.0]]), 8 / FPS)
    np.testing.assert_array_equal(again, [[300.0, 40.0]])  # a fresh track, not dragged from (10, 10)


def test_bad_parameters_are_user_errors():
    with pytest.raises(UserError):
        KeypointSmoother(8, OneEuroParams(min_cutoff_hz=0))
    with pytest.raises(UserError):
        KeypointSmoother(8, OneEuroParams(beta=-1))


def test_jitter_is_zero_for_a_constant_offset_and_grows_with_shake():
    truth = np.cumsum(np.ones((50, 2, 2)), axis=0)
    assert jitter_px(truth + 5.0, truth) == 0.0
    shake = truth.copy()
    shake[::2] += [3.0, 4.0]  # +-5 px every other frame
    assert jitter_px(shake, truth) == pytest.approx(5.0)
    missing = truth.copy()
    missing[:] = np.nan
    assert math.isnan(jitter_px(missing, truth))


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_lag_finds_a_known_delay(delay):
    t = np.arange(200) / FPS
    truth = np.stack([100 * np.sin(2 * math.pi * 0.5 * t), 50 * np.sin(2 * math.pi * 0.7 * t + 1)], -1)[:, None]
    pred = np.roll(truth, delay, axis=0)
    pred[:delay] = np.nan
    assert lag_frames(pred, truth) == pytest.approx(delay, abs=0.15)


@pytest.mark.usefixtures("few_timed_frames")
def test_evaluate_sequence_reports_jitter_and_lag(cli_here, tmp_path):
    from fcnpose_tf.data.synth import generate_dataset
    from fcnpose_tf.bundled import baseline_model

    generate_dataset(tmp_path / "seq", n=6, seed=2, width=160, height=120, workers=1, progress=False, motion_fps=30)
    out = tmp_path / "e.json"
    status, stdout, err = cli_here("evaluate", baseline_model(), "--data", tmp_path / "seq", "--sequence", 30,
                                   "--smooth", "--threads", 1, "--json", out)
    assert status == 0, err
    assert "jitter" in stdout and "lag" in stdout and "smoothed" in stdout
    import json

    seq = json.loads(out.read_text())["sequence"]
    assert seq["fps"] == 30 and set(seq) >= {"raw", "smoothed", "smoothing", "definitions"}
    assert seq["raw"]["jitter_px"] is None or seq["raw"]["jitter_px"] >= 0
    status, _, err = cli_here("evaluate", baseline_model(), "--data", tmp_path / "seq", "--smooth")
    assert status == 2 and "--sequence" in err


def test_a_camera_of_another_resolution_is_smoothed_alike():
    rng = np.random.default_rng(1)
    t = np.arange(120) / FPS
    track = np.stack([300 + 150 * np.sin(2 * math.pi * 0.4 * t), 200 + 80 * np.cos(2 * math.pi * 0.3 * t)], -1)
    noisy = (track + rng.normal(0, 2.0, track.shape))[:, None, :]
    at_640 = smooth_track(noisy, FPS, frame_shape=(480, 640, 3))
    np.testing.assert_array_equal(at_640, smooth_track(noisy, FPS))  # the frames the defaults were tuned on
    # the same motion filmed at 1920 x 1440: 3x the pixels, 3x the speeds; smoothed as at 640 x 480, scaled
    at_1920 = smooth_track((noisy + 0.5) * 3 - 0.5, FPS, frame_shape=(1440, 1920))
    np.testing.assert_allclose(at_1920, (at_640 + 0.5) * 3 - 0.5, atol=1e-9)
