"""How large is the arm in a dataset's frames? `train --input-size auto` chooses the model's input side by it.

The model sees the whole frame resized to a square (no letterbox), so an arm whose keypoints span a
fraction `s` of the frame (the larger of width and height, each against the frame's own) spans `s * N`
pixels of an N x N input. Fine localisation is judged against the arm's size (PCK@0.05: within 5 % of the
keypoint box), and the network cannot place a keypoint much finer than a few of its input pixels: where
the arm is small in the frame, that radius shrinks to a few input pixels at 224 and fine localisation
falls, whatever the training. `choose_input_size` takes the smallest input side (a multiple of 32, from
224) at which the median frame's arm spans MIN_ARM_INPUT_PX input pixels, up to AUTO_MAX_INPUT_SIZE.

Measured (docs/training.md, "Someone else's arm"): on a wide-angle fixed camera whose arm spans 0.39 of the
frame, PCK@0.05 0.673 at 224 (an 87-px arm), 0.733 at 320 (125 px) and 0.773 at 384 (149 px); on a
fixed cell whose arm spans 0.53, 0.879 at 224 (118 px) and 0.929 at 320.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from fcnpose_tf.settings import INPUT_SIZE, INPUT_SIZE_MULTIPLE

MIN_ARM_INPUT_PX = 140
"""The arm's keypoint box should span at least this many input pixels: PCK@0.05's radius is then 7 of them."""
AUTO_MAX_INPUT_SIZE = 384
"""The largest side `auto` chooses: 2.94x the multiply-adds of 224 per frame (and a third of its frame rate)."""
AUTO_MIN_INPUT_SIZE = INPUT_SIZE.default
"""The smallest side `auto` chooses: the paper's 224, the size every bundled model was trained at."""


def arm_span(frames: Iterable[tuple[np.ndarray, int, int]]) -> float:
    """Median over frames of the arm's size in the frame: max(box width / frame width, box height / frame height).

    Args:
        frames: (keypoints K x 2 with NaN for missing, frame width, frame height) per frame; frames with fewer
            than two visible keypoints have no box and are skipped.
    Returns:
        The median fraction (0-1], or 0.0 when no frame has a box.
    """
    spans = []
    for keypoints, width, height in frames:
        points = np.asarray(keypoints, np.float64).reshape(-1, 2)
        points = points[np.isfinite(points).all(axis=1)]
        if len(points) < 2 or width <= 0 or height <= 0:
            continue
        extent = points.max(axis=0) - points.min(axis=0)
        spans.append(max(extent[0] / width, extent[1] / height))
    return float(np.median(spans)) if spans else 0.0


def choose_input_size(span: float, start_size: int | None = None) -> int:
    """The smallest multiple of 32 from AUTO_MIN_INPUT_SIZE at which an arm spanning `span` of the frame covers
    MIN_ARM_INPUT_PX input pixels; AUTO_MAX_INPUT_SIZE when none up to it does, AUTO_MIN_INPUT_SIZE when the
    span is unknown (0: no frame with two keypoints).

    `start_size`, the input size the starting model was trained at, is kept instead when it is a size `auto`
    can choose and the arm already spans MIN_ARM_INPUT_PX input pixels there: a model continued on more frames of
    the same camera (the correction loop's next round) stays at the scale it learnt, and its rounds compare, even
    when the merged frames' median arm moves a little. The bundled models (224) never change the choice: 224
    qualifies only when it is the smallest size that does.
    """
    if span <= 0:
        return AUTO_MIN_INPUT_SIZE
    if (start_size is not None and AUTO_MIN_INPUT_SIZE <= start_size <= AUTO_MAX_INPUT_SIZE
            and start_size % INPUT_SIZE_MULTIPLE == 0 and span * start_size >= MIN_ARM_INPUT_PX):
        return start_size
    for size in range(AUTO_MIN_INPUT_SIZE, AUTO_MAX_INPUT_SIZE + 1, INPUT_SIZE_MULTIPLE):
        if span * size >= MIN_ARM_INPUT_PX:
            return size
    return AUTO_MAX_INPUT_SIZE
