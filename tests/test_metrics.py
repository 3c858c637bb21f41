"""Keypoint metrics against hand-computed values, edge cases and a plain loop reference."""

from __future__ import annotations

import doctest
import json
import math

import numpy as np
import pytest

import fcnpose_tf.metrics as metrics
from fcnpose_tf.errors import UserError
from fcnpose_tf.measurements import KeypointMetrics
from fcnpose_tf.metrics import (auc_key, bbox_sizes, conv_macs, epe, epe_per_keypoint, errors_px, format_report,
                                keypoint_report, missing_fraction, normalized_errors, pck, pck_auc_px, pck_curve_px,
                                pck_key, pck_per_keypoint)

NAN = math.nan

# Two frames, three keypoints, worked by hand:
#   frame 0: GT (0,0) (100,0) (100,50) -> bbox 100 x 50, size 100
#            pred errors 5 px (0.05), 30 px (0.3), missing
#   frame 1: GT (10,10) (10,30) not-visible -> bbox 0 x 20, size 20
#            pred errors 10 px (0.5), 1 px (0.05), a prediction for the invisible one (ignored)
GT = np.array([[[0, 0], [100, 0], [100, 50]],
               [[10, 10], [10, 30], [NAN, NAN]]], float)
PRED = np.array([[[3, 4], [100, 30], [NAN, NAN]],
                 [[10, 20], [10, 31], [5, 5]]], float)


def test_conv_macs():
    assert conv_macs(224, 224, 3, 3, 3, 32) == 224 * 224 * 9 * 3 * 32


def test_bbox_sizes_and_errors():
    assert bbox_sizes(GT).tolist() == [100.0, 20.0]
    err = errors_px(PRED, GT)
    assert err[0].tolist() == [5.0, 30.0, math.inf]
    assert err[1, :2].tolist() == [10.0, 1.0] and math.isnan(err[1, 2])
    d = normalized_errors(PRED, GT)
    assert d[0].tolist() == [0.05, 0.3, math.inf] and d[1, :2].tolist() == [0.5, 0.05]


def test_pck_hand_computed_including_strict_threshold():
    # distance exactly alpha * size is not "below": 0.5 at alpha 0.5, 0.05 at alpha 0.05 are wrong
    np.testing.assert_array_equal(pck_per_keypoint(PRED, GT, 0.5), [0.5, 1.0, 0.0])
    np.testing.assert_array_equal(pck_per_keypoint(PRED, GT, 0.2), [0.5, 0.5, 0.0])
    np.testing.assert_array_equal(pck_per_keypoint(PRED, GT, 0.05), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(pck_per_keypoint(PRED, GT, 0.06), [0.5, 0.5, 0.0])
    assert pck(PRED, GT, 0.5) == pytest.approx(0.5)
    assert pck(PRED, GT, 0.2) == pytest.approx(1 / 3)
    assert pck(PRED, GT, 0.05) == 0.0


def test_pck_is_the_mean_over_keypoints_not_over_all_pairs():
    gt = np.array([[[0, 0], [10, 0]], [[0, 0], [NAN, NAN]], [[0, 0], [NAN, NAN]]], float)
    gt[1, 1] = [0, 10]
    gt[2, 1] = [10, 10]
    pred = gt.copy()
    pred[:, 0] += 100                     # keypoint 0 always wrong (3 frames)
    pred[2, 1] = NAN                      # keypoint 1: right, right, missing -> 2/3
    assert pck_per_keypoint(pred, gt, 0.5).tolist() == [0.0, pytest.approx(2 / 3)]
    assert pck(pred, gt, 0.5) == pytest.approx(1 / 3)         # pooled would be 2/6 as well...
    pred[0, 0] = gt[0, 0]                                      # ...now per-keypoint 1/3 and 2/3
    assert pck(pred, gt, 0.5) == pytest.approx(0.5)


def test_zero_size_bbox_frames_are_excluded():
    gt = np.array([[[5, 5], [NAN, NAN]],          # single visible keypoint: size 0
                   [[5, 5], [5, 5]],              # two coincident keypoints: size 0
                   [[0, 0], [10, 0]]], float)     # size 10
    pred = np.array([[[5, 5], [1, 1]],
                     [[5, 5], [5, 5]],
                     [[0, 0], [NAN, NAN]]], float)
    assert bbox_sizes(gt).tolist() == [0.0, 0.0, 10.0]
    assert np.isnan(normalized_errors(pred, gt)[:2]).all()
    np.testing.assert_array_equal(pck_per_keypoint(pred, gt, 0.5), [1.0, 0.0])
    report = keypoint_report(pred, gt, ["a", "b"])
    assert report.num_frames_excluded_bbox == 2
    # Only the bbox PCK excludes them: pixel metrics still use every visible keypoint.
    assert report.epe_px == 0.0 and report.num_gt_visible == 5 and report.num_missing == 1
    only_single = gt[:1], pred[:1]
    assert math.isnan(pck(only_single[1], only_single[0], 0.5))
    assert np.isnan(pck_per_keypoint(only_single[1], only_single[0], 0.5)).all()


def test_epe_missing_fraction_hand_computed():
    assert epe(PRED, GT) == pytest.approx((5 + 30 + 10 + 1) / 4)
    assert missing_fraction(PRED, GT) == pytest.approx(1 / 5)
    per = epe_per_keypoint(PRED, GT)
    assert per[:2].tolist() == [7.5, 15.5] and math.isnan(per[2])


def test_pck_auc_px_exact_and_close_to_dream_discretisation():
    # errors 5, 30, 10, 1 and one missing: (0.75 + 0 + 0.5 + 0.95 + 0) / 5
    assert pck_auc_px(PRED, GT) == pytest.approx(2.2 / 5)
    assert pck_auc_px(PRED, GT, max_px=40) == pytest.approx((0.875 + 0.25 + 0.75 + 0.975) / 5)
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 200, (50, 8, 2))
    pred = gt + rng.normal(0, 6, gt.shape)
    pred[rng.random((50, 8)) < 0.1] = NAN
    err = errors_px(pred, gt).ravel()
    # NVlabs DREAM's keypoint_metrics: trapezoid on a 0.01 px grid over [0, 20), / 20 / num_gt.
    grid = np.arange(0, 20, 0.01)
    found = err[np.isfinite(err)]
    y = [(found < t).sum() for t in grid]
    dream = np.sum((np.array(y[1:]) + np.array(y[:-1])) / 2 * 0.01) / 20 / err.size
    assert abs(pck_auc_px(pred, gt) - dream) < 1e-3


def test_pck_curve_px():
    curve = pck_curve_px(PRED, GT, [0, 1, 1.5, 10, 31])
    np.testing.assert_allclose(curve, [0, 0, 1 / 5, 2 / 5, 4 / 5])
    assert np.isnan(pck_curve_px(GT * NAN, GT * NAN, [1, 2])).all()


def test_perfect_predictions():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0, 500, (10, 8, 2))
    report = keypoint_report(gt, gt, [f"k{i}" for i in range(8)])
    assert report.pck[0.05] == 1.0 and report.pck_auc == 1.0
    assert report.epe_px == 0.0 and report.missing_fraction == 0.0


def test_all_missing_predictions_and_no_ground_truth():
    nothing = np.full((2, 3, 2), NAN)
    assert pck(nothing, GT[:, :3], 0.5) == 0.0
    assert math.isnan(epe(nothing, GT)) and missing_fraction(nothing, GT) == 1.0
    assert pck_auc_px(nothing, GT) == 0.0
    for f in (lambda: pck(GT, nothing, 0.5), lambda: epe(GT, nothing), lambda: pck_auc_px(GT, nothing),
              lambda: missing_fraction(GT, nothing)):
        assert math.isnan(f())
    report = keypoint_report(nothing, nothing, ["a", "b", "c"])
    assert report.pck[0.5] is None and report.epe_px is None
    json.dumps(report.to_json(), allow_nan=False)


def _loop_pck_per_keypoint(pred, gt, alpha):
    """A plain, loop-per-frame PCK (bbox) to check the vectorised one against."""
    n, k, _ = gt.shape
    correct, total = np.zeros(k), np.zeros(k)
    for i in range(n):
        vis = [j for j in range(k) if not np.isnan(gt[i, j]).any()]
        if not vis:
            continue
        xs, ys = [gt[i, j, 0] for j in vis], [gt[i, j, 1] for j in vis]
        size = max(max(xs) - min(xs), max(ys) - min(ys))
        if size <= 0:
            continue
        for j in vis:
            total[j] += 1
            if not np.isnan(pred[i, j]).any() and math.dist(pred[i, j], gt[i, j]) / size < alpha:
                correct[j] += 1
    return np.where(total > 0, correct / np.maximum(total, 1), np.nan)


def test_vectorised_pck_matches_loop_on_random_data_with_gaps():
    rng = np.random.default_rng(42)
    gt = rng.uniform(0, 300, (40, 6, 2))
    pred = gt + rng.normal(0, 20, gt.shape)
    gt[rng.random((40, 6)) < 0.2] = NAN
    pred[rng.random((40, 6)) < 0.15] = NAN
    gt[3, 1:] = NAN                                         # a frame with one visible keypoint
    gt[4] = NAN                                             # a frame with none
    for alpha in (0.5, 0.2, 0.05):
        np.testing.assert_allclose(pck_per_keypoint(pred, gt, alpha), _loop_pck_per_keypoint(pred, gt, alpha))


def test_half_nan_keypoint_counts_as_missing():
    gt = np.array([[[0, 0], [10, 10]]], float)
    pred = np.array([[[0, NAN], [10, 10]]], float)
    assert missing_fraction(pred, gt) == 0.5 and pck(pred, gt, 0.5) == 0.5


def test_single_frame_k_by_2_is_accepted():
    assert pck(PRED[0], GT[0], 0.5) == pck(PRED[:1], GT[:1], 0.5)


@pytest.mark.parametrize("pred, gt, match", [
    (np.zeros((2, 3, 2)), np.zeros((2, 4, 2)), "same N x K x 2"),
    (np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), "N x K x 2"),
    (np.zeros(5), np.zeros(5), "N x K x 2"),
])
def test_shape_errors(pred, gt, match):
    with pytest.raises(UserError, match=match):
        pck(pred, gt, 0.5)


@pytest.mark.parametrize("bad", [0, -0.1, math.nan, math.inf])
def test_bad_alpha_and_max_px(bad):
    with pytest.raises(UserError, match="alpha"):
        pck(PRED, GT, bad)
    with pytest.raises(UserError, match="max_px"):
        pck_auc_px(PRED, GT, bad)


def test_report_keys_values_and_json():
    names = ["base", "shoulder", "elbow"]
    typed = keypoint_report(PRED, GT, names)
    report = typed.to_json()
    assert list(report) == ["pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox", "pck_auc_0-20px", "epe_px",
                            "epe_median_px", "missing_fraction", "num_frames", "num_keypoints", "num_gt_visible",
                            "num_missing", "num_frames_excluded_bbox", "per_keypoint"]
    assert report["pck@0.5_bbox"] == pytest.approx(0.5) and report["pck_auc_0-20px"] == pytest.approx(0.44)
    assert report["epe_px"] == pytest.approx(11.5) and report["epe_median_px"] == pytest.approx(7.5)
    assert report["missing_fraction"] == pytest.approx(0.2)
    assert (report["num_frames"], report["num_keypoints"], report["num_gt_visible"], report["num_missing"],
            report["num_frames_excluded_bbox"]) == (2, 3, 5, 1, 0)
    assert list(report["per_keypoint"]) == names
    elbow = report["per_keypoint"]["elbow"]
    assert elbow == {"pck@0.5_bbox": 0.0, "pck@0.2_bbox": 0.0, "pck@0.05_bbox": 0.0, "pck_auc_0-20px": 0.0,
                     "epe_px": None, "missing_fraction": 1.0, "num_gt_visible": 1}
    base = report["per_keypoint"]["base"]
    assert base["epe_px"] == 7.5 and base["pck_auc_0-20px"] == pytest.approx((0.75 + 0.5) / 2)
    text = json.dumps(report, allow_nan=False)
    assert json.loads(text) == report
    assert all(type(v) in (float, int, type(None), dict) for v in report.values())
    assert KeypointMetrics.from_json(json.loads(text)) == typed and typed.per_keypoint["base"].epe_px == 7.5


def test_report_key_helpers_and_custom_alphas():
    assert pck_key(0.5) == "pck@0.5_bbox" and pck_key(0.05) == "pck@0.05_bbox" and auc_key() == "pck_auc_0-20px"
    report = keypoint_report(PRED, GT, ["a", "b", "c"], alphas=(0.1,), max_px=10)
    assert list(report.pck) == [0.1] and report.max_px == 10
    assert "pck@0.1_bbox" in report.to_json() and "pck_auc_0-10px" in report.to_json()
    assert KeypointMetrics.from_json(report.to_json()) == report


def test_report_names_must_match():
    with pytest.raises(UserError, match="3 keypoints"):
        keypoint_report(PRED, GT, ["a", "b"])


def test_format_report_table():
    text = format_report(keypoint_report(PRED, GT, ["base", "shoulder", "elbow"]))
    lines = text.splitlines()
    assert "pck@0.5_bbox" in lines[0] and "epe_px" in lines[0] and "pck_auc_0-20px" in lines[0]
    assert [line.split()[0] for line in lines[2:]] == ["base", "shoulder", "elbow", "all"]
    assert "-" in lines[4].split()            # elbow's EPE is undefined
    md = format_report(keypoint_report(PRED, GT, ["base", "shoulder", "elbow"]), markdown=True)
    assert md.startswith("| keypoint")


def test_docstring_examples():
    assert doctest.testmod(metrics).failed == 0


def test_frame_errors_rank_frames_by_their_share_of_the_box_with_a_miss_at_the_cap():
    from fcnpose_tf.metrics import frame_errors, worst_frames

    gt = np.array([[[0.0, 0.0], [100.0, 0.0]]] * 4)  # box side 100
    pred = gt.copy()
    pred[0, 0] += (10, 0)  # 0.1 and 0: mean 0.05
    pred[1, 1] = np.nan  # a miss counts 0.5: mean 0.25
    pred[2, 0] += (300, 0)  # 3.0 capped at 0.5: mean 0.25 (ties keep the earlier frame first)
    gt[3] = np.nan  # nothing to score
    pred[3] = np.nan
    np.testing.assert_allclose(frame_errors(pred, gt)[:3], [0.05, 0.25, 0.25])
    assert np.isnan(frame_errors(pred, gt)[3])
    scores = frame_errors(pred, gt)
    assert worst_frames(scores, 2) == [1, 2] and worst_frames(scores, 10) == [1, 2, 0]
