"""Metrics: keypoint accuracy (PCK, PCK-AUC, EPE) and model cost (MACs). numpy only.

Keypoints are N x K x 2 arrays of (x, y) pixel coordinates -- N frames, K keypoints -- in the
original frame's pixels (map keypoints back with :func:`fcnpose_tf.postprocess.decode` first).
NaN marks a missing keypoint: a missing *prediction* is a keypoint the network did not find, a
missing *ground truth* one that is not annotated (not visible).

Definitions (docs/training.md, evaluation; the JSON keys of :func:`keypoint_report` carry their names):

- **PCK@alpha (bbox)**, MMPose's PCKAccuracy convention: a prediction is correct when its
  Euclidean distance to the ground truth divided by max(w, h) of the bounding box of that frame's
  visible ground-truth keypoints is *below* alpha (strictly). Missing predictions are wrong;
  missing ground truth is excluded. Frames whose box has no size (fewer than two distinct visible
  ground-truth keypoints, so max(w, h) = 0) are excluded: the normalisation is undefined there
  (MMPose skips them the same way); the report counts them. The overall PCK is the mean over
  keypoints of the per-keypoint PCK (each keypoint weighs the same, as in MMPose).
- **PCK-AUC 0-20 px**, NVlabs DREAM's convention: PCK at pixel thresholds t in [0, 20] (correct
  when the error is below t), area under that curve divided by 20, pooled over every visible
  ground-truth keypoint, missing predictions wrong. Computed exactly: the integral equals the mean
  of max(0, 1 - error / 20) with missing predictions contributing 0. DREAM's code integrates on a
  0.01 px grid with the trapezoidal rule and differs from the exact value by less than 0.001.
- **EPE (px)**: mean Euclidean pixel error over the keypoints that were predicted and have ground
  truth (DREAM's "L2 error"); missing predictions have no error and are reported separately as
  ``missing_fraction`` (missing predictions / visible ground-truth keypoints), so EPE must always be
  read next to it.
- **MACs**: multiply-accumulates of all convolutions for one frame; FLOPs = 2 x MACs.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.measurements import DEFAULT_MAX_PX, KeypointMetrics, KeypointScores, auc_key, pck_key

__all__ = [
    "DEFAULT_ALPHAS", "DEFAULT_MAX_PX", "conv_macs", "bbox_sizes", "errors_px", "normalized_errors",
    "pck", "pck_per_keypoint", "pck_curve_px", "pck_auc_px", "epe", "epe_per_keypoint",
    "missing_fraction", "pck_key", "auc_key", "keypoint_report", "format_report", "mean_pck", "frame_errors",
    "worst_frames",
]

DEFAULT_ALPHAS: tuple[float, ...] = (0.5, 0.2, 0.05)
"""The PCK thresholds reported: 0.5 (the paper's figure), 0.2 and 0.05."""


def conv_macs(out_h: int, out_w: int, k_h: int, k_w: int, c_in: int, c_out: int) -> int:
    """Multiply-accumulates of one 'same'/'valid' Conv2D for one frame: H*W*k*k*Cin*Cout (FLOPs = 2 x MACs)."""
    return int(out_h) * int(out_w) * int(k_h) * int(k_w) * int(c_in) * int(c_out)


FCN_POSE_WIDTHS: tuple[int, ...] = (128, 64, 32, 16, 8, 8, 16, 32, 64)
"""conv1..conv9 of the paper's FCN-Pose (training.model.DEFAULT_WIDTHS)."""
FCN_POSE_P70_WIDTHS: tuple[int, ...] = (15, 15, 15, 15, 8, 8, 15, 15, 15)
"""conv1..conv9 after `compress --rate 0.7` on its defaults (no layer under 15 filters): the bundled 70 % files."""
_FCN_POSE_SCALES = (1, 2, 4, 8, 16, 32, 16, 8, 4, 1)
"""The resolution divisor of conv1..conv10 (five 2x poolings, then upsampling by 2, 2, 2 and 4)."""


def fcn_pose_macs(input_shape: tuple[int, int], widths: Sequence[int] = FCN_POSE_WIDTHS, num_maps: int = 9) -> int:
    """Multiply-accumulates of FCN-Pose for one frame at an H x W input, from its layer shapes alone (no model).

    Example:
        >>> fcn_pose_macs((224, 224))
        1481675328
    """
    h, w = int(input_shape[0]), int(input_shape[1])
    channels = (3, *widths, num_maps)
    return sum(conv_macs(h // d, w // d, 3, 3, channels[i], channels[i + 1]) for i, d in enumerate(_FCN_POSE_SCALES))


# ---------------------------------------------------------------------------- inputs

def _pair(pred: Any, gt: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate and promote pred/gt to float64 N x K x 2 (a single K x 2 frame becomes N = 1)."""
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if p.ndim == 2:
        p = p[None]
    if g.ndim == 2:
        g = g[None]
    for name, a, given in (("predictions", p, pred), ("ground truth", g, gt)):
        if a.ndim != 3 or a.shape[-1] != 2:
            raise UserError(f"expected {name} of shape N x K x 2 (x, y), got {np.shape(given)}")
    if p.shape != g.shape:
        raise UserError(f"predictions {p.shape} and ground truth {g.shape} must have the same N x K x 2 shape")
    return p, g


def _valid(p: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(gt_visible, pred_found) boolean N x K masks; a keypoint is missing if either coordinate is NaN."""
    return ~np.isnan(g).any(axis=-1), ~np.isnan(p).any(axis=-1)


def _nan_mean(values: np.ndarray) -> float:
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else math.nan


# ---------------------------------------------------------------------------- building blocks

def bbox_sizes(gt: Any) -> np.ndarray:
    """max(w, h) of the bounding box of each frame's visible ground-truth keypoints.

    Args:
        gt: N x K x 2 (or K x 2) ground truth, NaN where not visible.

    Returns:
        (N,) float64; NaN for a frame without visible keypoints, 0.0 for one whose visible
        keypoints all coincide (e.g. a single one).

    Example:
        >>> bbox_sizes([[[0, 0], [30, 10], [np.nan, np.nan]]]).tolist()
        [30.0]
    """
    g = _pair(gt, gt)[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice": a frame without visible GT
        span = np.nanmax(g, axis=1) - np.nanmin(g, axis=1)  # N x 2: (w, h)
    return np.max(span, axis=1)


def errors_px(pred: Any, gt: Any) -> np.ndarray:
    """Euclidean pixel error per keypoint.

    Returns:
        N x K float64: the distance where both exist, +inf where the ground truth is visible but
        the prediction missing, NaN where the ground truth is missing.
    """
    p, g = _pair(pred, gt)
    visible, found = _valid(p, g)
    err = np.hypot(p[..., 0] - g[..., 0], p[..., 1] - g[..., 1])
    err[visible & ~found] = np.inf
    err[~visible] = np.nan
    return err


def normalized_errors(pred: Any, gt: Any) -> np.ndarray:
    """Pixel errors divided by each frame's ground-truth bbox size, max(w, h).

    Returns:
        N x K float64: +inf for a missing prediction, NaN where excluded (ground truth missing,
        or a frame whose bbox has zero size).
    """
    err = errors_px(pred, gt)
    size = bbox_sizes(gt)
    out = np.full_like(err, np.nan)
    ok = size > 0  # NaN compares False: frames without visible GT stay NaN
    out[ok] = err[ok] / size[ok, None]
    return out


def frame_errors(pred: Any, gt: Any) -> np.ndarray:
    """How wrong each frame is, for ranking frames: the mean over its annotated keypoints of the error as a share of
    its ground-truth bbox size, max(w, h), each capped at 0.5 (PCK@0.5's threshold: a keypoint on the wrong part
    of the arm), a missing prediction counted at the cap. N floats; NaN for a frame with nothing to score."""
    err = np.minimum(normalized_errors(pred, gt), 0.5)  # +inf (missing) becomes the cap; NaN (excluded) stays
    scored = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        return np.where(scored.any(axis=1), np.nansum(np.where(scored, err, 0.0), axis=1) /
                        np.maximum(scored.sum(axis=1), 1), np.nan)


def worst_frames(scores: np.ndarray, count: int) -> list[int]:
    """Positions of the `count` frames with the largest `frame_errors` scores, worst first (ties: the earlier
    frame; a frame with nothing scored, NaN, never)."""
    order = sorted((i for i in range(len(scores)) if np.isfinite(scores[i])), key=lambda i: (-scores[i], i))
    return order[:max(int(count), 0)]


# ---------------------------------------------------------------------------- PCK

def pck_per_keypoint(pred: Any, gt: Any, alpha: float) -> np.ndarray:
    """PCK@alpha (bbox) of each keypoint over the frames.

    Args:
        pred, gt: N x K x 2 keypoints in pixels, NaN where missing.
        alpha: fraction of max(w, h) of the frame's ground-truth bbox; correct when below it.

    Returns:
        (K,) float64 in [0, 1]; NaN for a keypoint with no usable ground truth.

    Example:
        >>> gt = [[[0, 0], [10, 0]]]
        >>> pck_per_keypoint([[[1, 0], [np.nan, np.nan]]], gt, 0.5).tolist()
        [1.0, 0.0]
    """
    alpha = _check_positive(alpha, "alpha")
    d = normalized_errors(pred, gt)
    used = ~np.isnan(d)
    correct = np.where(used, d < alpha, False).sum(axis=0)
    total = used.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, correct / np.maximum(total, 1), np.nan)


def pck(pred: Any, gt: Any, alpha: float) -> float:
    """PCK@alpha (bbox): the mean over keypoints of :func:`pck_per_keypoint`.

    Args:
        pred: N x K x 2 predicted (x, y) in pixels, NaN where the network found nothing (wrong).
        gt: N x K x 2 ground truth in the same pixels, NaN where not annotated (excluded).
        alpha: correct when distance / max(w, h) of the frame's GT bbox is below alpha.

    Returns:
        The fraction of correct keypoints, each keypoint weighing the same; NaN if no ground
        truth is usable.

    Example:
        >>> gt = np.array([[[0.0, 0.0], [100.0, 50.0]]])           # bbox 100 x 50 -> size 100
        >>> pred = np.array([[[4.0, 3.0], [100.0, 110.0]]])        # errors 5 px and 60 px
        >>> pck(pred, gt, 0.5), pck(pred, gt, 0.05)
        (0.5, 0.0)
    """
    return _nan_mean(pck_per_keypoint(pred, gt, alpha))


def pck_curve_px(pred: Any, gt: Any, thresholds_px: Sequence[float]) -> np.ndarray:
    """PCK at pixel thresholds (correct when the pixel error is below t), pooled over keypoints.

    Returns:
        float64 array like ``thresholds_px``; NaN if no ground truth is visible.
    """
    err = errors_px(pred, gt)
    err = err[~np.isnan(err)]
    t = np.asarray(thresholds_px, np.float64)
    if err.size == 0:
        return np.full(t.shape, np.nan)
    return (err[:, None] < t.ravel()[None, :]).mean(axis=0).reshape(t.shape)


def pck_auc_px(pred: Any, gt: Any, max_px: float = DEFAULT_MAX_PX) -> float:
    """Area under the PCK-vs-pixel-threshold curve on [0, max_px], divided by max_px (DREAM).

    Exact: equals the mean over visible ground-truth keypoints of max(0, 1 - error / max_px),
    missing predictions counting 0. 1.0 means every keypoint exact.

    Example:
        >>> gt = [[[0, 0], [0, 0]]]
        >>> pck_auc_px([[[0, 5], [np.nan, np.nan]]], gt, max_px=20)    # (0.75 + 0) / 2
        0.375
    """
    max_px = _check_positive(max_px, "max_px")
    err = errors_px(pred, gt)
    err = err[~np.isnan(err)]
    if err.size == 0:
        return math.nan
    return float(np.clip(1.0 - err / max_px, 0.0, 1.0).mean())


# ---------------------------------------------------------------------------- EPE, missing

def epe_per_keypoint(pred: Any, gt: Any) -> np.ndarray:
    """Mean pixel error of each keypoint over the frames where it was predicted and annotated.

    Returns:
        (K,) float64; NaN for a keypoint never predicted (or never annotated).
    """
    err = errors_px(pred, gt)
    err = np.where(np.isfinite(err), err, np.nan)
    count = (~np.isnan(err)).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.nansum(err, axis=0) / np.maximum(count, 1), np.nan)


def epe(pred: Any, gt: Any) -> float:
    """Mean Euclidean pixel error (EPE) over keypoints both predicted and annotated.

    Missing predictions are not in this mean; read it with :func:`missing_fraction`.

    Returns:
        The mean error in pixels of the input's coordinates; NaN if nothing was predicted.

    Example:
        >>> epe([[[3, 4], [np.nan, np.nan]]], [[[0, 0], [1, 1]]])
        5.0
    """
    err = errors_px(pred, gt)
    err = err[np.isfinite(err)]
    return float(err.mean()) if err.size else math.nan


def missing_fraction(pred: Any, gt: Any) -> float:
    """Fraction of visible ground-truth keypoints without a prediction (NaN if none is visible).

    Example:
        >>> missing_fraction([[[3, 4], [np.nan, np.nan]]], [[[0, 0], [1, 1]]])
        0.5
    """
    p, g = _pair(pred, gt)
    visible, found = _valid(p, g)
    n = int(visible.sum())
    return float((visible & ~found).sum() / n) if n else math.nan


def _check_positive(value: float, name: str) -> float:
    v = float(value)
    if not v > 0 or not math.isfinite(v):
        raise UserError(f"{name} must be a positive number, got {value!r}")
    return v


# ---------------------------------------------------------------------------- report

def mean_pck(report: KeypointMetrics, alphas: Sequence[float] = DEFAULT_ALPHAS) -> float:
    """One score of a `keypoint_report`: the mean of its PCK@alpha over `alphas` (missing keypoints count as wrong).

    With the reported thresholds a keypoint off by a whole link (PCK@0.5, PCK@0.2) weighs as much as fine
    localisation (PCK@0.05); a pixel AUC up to 20 px would ignore every error beyond 20 px. Used to choose between
    models measured on the same frames at different input sizes, where validation losses do not compare.
    """
    values = [report.pck.get(float(a)) for a in alphas]
    return float(np.mean([0.0 if v is None else v for v in values]))


def _json(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def keypoint_report(pred: Any, gt: Any, names: Sequence[str], alphas: Sequence[float] = DEFAULT_ALPHAS,
                    max_px: float = DEFAULT_MAX_PX) -> KeypointMetrics:
    """All keypoint metrics, overall and per keypoint (`KeypointMetrics`; its `to_json()` has stable keys naming
    their normalisation).

    Args:
        pred, gt: N x K x 2 keypoints in frame pixels, NaN where missing.
        names: the K keypoint names (e.g. ``fcnpose_tf.keypoints.UR5.keypoints``).
        alphas: PCK thresholds (bbox normalisation).
        max_px: upper pixel threshold of the PCK-AUC.

    Returns:
        The metrics (undefined values are None, never NaN, so they serialise as strict JSON); `to_json()`::

            {"pck@0.5_bbox": ..., "pck@0.2_bbox": ..., "pck@0.05_bbox": ...,   # mean over keypoints
             "pck_auc_0-20px": ..., "epe_px": ..., "epe_median_px": ..., "missing_fraction": ...,
             "num_frames": N, "num_keypoints": K, "num_gt_visible": ..., "num_missing": ...,
             "num_frames_excluded_bbox": ...,
             "per_keypoint": {name: {"pck@0.5_bbox": ..., ..., "pck_auc_0-20px": ..., "epe_px": ...,
                                     "missing_fraction": ..., "num_gt_visible": ...}, ...}}

    Example:
        >>> r = keypoint_report([[[1, 0], [10, 0]]], [[[0, 0], [10, 0]]], ["a", "b"], alphas=(0.5,))
        >>> r.pck[0.5], r.epe_px, r.per_keypoint["a"].epe_px
        (1.0, 0.5, 1.0)
    """
    p, g = _pair(pred, gt)
    names = [str(n) for n in names]
    if len(names) != p.shape[1]:
        raise UserError(f"got {len(names)} keypoint names for {p.shape[1]} keypoints")
    alphas = [_check_positive(a, "alpha") for a in alphas]
    max_px = float(max_px)
    visible, found = _valid(p, g)
    err = errors_px(p, g)
    finite = err[np.isfinite(err)]
    per_kp_pck = {a: pck_per_keypoint(p, g, a) for a in alphas}
    per_kp_epe = epe_per_keypoint(p, g)
    sizes = bbox_sizes(g)
    per: dict[str, KeypointScores] = {}
    for k, name in enumerate(names):
        vis_k = int(visible[:, k].sum())
        per[name] = KeypointScores(
            pck={a: _json(per_kp_pck[a][k]) for a in alphas}, max_px=max_px,
            pck_auc=_json(pck_auc_px(p[:, k:k + 1], g[:, k:k + 1], max_px)), epe_px=_json(per_kp_epe[k]),
            missing_fraction=_json((visible[:, k] & ~found[:, k]).sum() / vis_k if vis_k else math.nan),
            num_gt_visible=vis_k)
    return KeypointMetrics(
        pck={a: _json(_nan_mean(per_kp_pck[a])) for a in alphas}, max_px=max_px,
        pck_auc=_json(pck_auc_px(p, g, max_px)),
        epe_px=_json(float(finite.mean()) if finite.size else math.nan),
        epe_median_px=_json(float(np.median(finite)) if finite.size else math.nan),
        missing_fraction=_json(missing_fraction(p, g)), num_frames=int(p.shape[0]), num_keypoints=int(p.shape[1]),
        num_gt_visible=int(visible.sum()), num_missing=int((visible & ~found).sum()),
        # Frames with visible ground truth but a zero-size box: left out of the bbox PCK.
        num_frames_excluded_bbox=int(((sizes == 0) & visible.any(axis=1)).sum()), per_keypoint=per)


def format_report(report: KeypointMetrics, markdown: bool = False) -> str:
    """A table of :func:`keypoint_report`: one row per keypoint and a final ``all`` row.

    Columns are the report's metric keys, so every PCK shows its normalisation in the header. The
    ``all`` row holds the report's overall values: PCK (bbox) is the mean over keypoints, the
    others are pooled over every keypoint (see the module docstring).
    """
    from fcnpose_tf.tables import format_table  # plain Python, no dependencies

    overall = report.to_json()
    per = overall["per_keypoint"]
    cols = [k for k in next(iter(per.values()), {}) if k != "num_gt_visible"] if per else []
    rows = [[name] + [_round(v.get(c)) for c in cols] for name, v in per.items()]
    rows.append(["all"] + [_round(overall.get(c)) for c in cols])
    return format_table(["keypoint"] + cols, rows, markdown=markdown)


def _round(value: Any) -> Any:
    return round(value, 4) if isinstance(value, float) else value


# ----------------------------------------------------------------------------------------- sequences

SEQUENCE_DEFINITIONS = (
    "jitter: RMS over keypoints and consecutive frame pairs of the change of the error vector (prediction - "
    "ground truth) from one frame to the next, px; lag: the shift (frames) that best aligns the predicted "
    "track's frame-to-frame motion with the ground truth's (normalised cross-correlation pooled over keypoints, "
    "parabolic sub-frame peak; positive: the prediction trails)")
"""How `jitter_px` and `lag_frames` are defined (printed next to the figures)."""


def jitter_px(pred: Any, gt: Any) -> float:
    """RMS of the frame-to-frame change of the error vector (px) over N consecutive frames (N x K x 2).

    A steady offset adds nothing; a prediction that shakes around the truth does. Pairs where either
    frame misses the prediction or the ground truth are left out; NaN if none is left.
    """
    p, g = _pair(pred, gt)
    err = p - g
    step = err[1:] - err[:-1]
    ok = np.isfinite(step).all(-1)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.mean(np.sum(step[ok] ** 2, axis=-1))))


def lag_frames(pred: Any, gt: Any, max_lag: int = 8) -> float:
    """Frames by which the predicted tracks trail the ground truth (negative: lead), within +-max_lag.

    The frame-to-frame motion of prediction and ground truth is cross-correlated (normalised, pooled
    over keypoints and both axes) at every integer shift; the peak is refined by a parabola through
    it and its neighbours. NaN when nothing moves or too few frames are valid.
    """
    p, g = _pair(pred, gt)
    vp, vg = p[1:] - p[:-1], g[1:] - g[:-1]
    n = len(vp)
    shifts = np.arange(-max_lag, max_lag + 1)
    score = np.full(len(shifts), np.nan)
    for i, s in enumerate(shifts):
        if abs(s) >= n - 1:
            continue
        a = vp[s:] if s >= 0 else vp[:s]  # prediction at t
        b = vg[:n - s] if s >= 0 else vg[-s:]  # ground truth at t - s
        ok = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
        if ok.sum() < 3:
            continue
        den = math.sqrt(float(np.sum(a[ok] ** 2)) * float(np.sum(b[ok] ** 2)))
        if den > 0:
            score[i] = float(np.sum(a[ok] * b[ok])) / den
    if not np.isfinite(score).any():
        return float("nan")
    best = int(np.nanargmax(score))
    if 0 < best < len(shifts) - 1 and np.isfinite(score[best - 1]) and np.isfinite(score[best + 1]):
        y0, y1, y2 = score[best - 1], score[best], score[best + 1]
        den = y0 - 2 * y1 + y2
        offset = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        return float(shifts[best] + np.clip(offset, -0.5, 0.5))
    return float(shifts[best])
