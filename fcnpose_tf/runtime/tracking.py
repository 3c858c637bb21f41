"""A crop that follows the arm on video: each frame read over the box of the previous frame's keypoints.

Where views vary there is no workspace to crop to, and a model reads the whole frame; but on video the arm of one
frame is near where it was in the frame before. `TrackingCrop` wraps any predictor (LiteRT or Keras) and reads each
frame over a box about the previous frame's keypoints (`follow_box`: their bounding box grown by `TRACK_MARGIN` on
each side, at the model's input aspect), so the arm gets the input's pixels instead of the whole frame's share of
them: the same file at a smaller input then reads it as well as at a larger one over the whole frame
(docs/runtime.md, "A crop that follows the arm"). The model's own view (the whole frame, or its workspace crop)
reads the first frame, any frame whose predecessor had fewer than `TRACK_MIN_FOUND` keypoints found, and any frame
of another size; `whole_view_frames` counts them.

The crop depends on the frame before, so a tracked run is sequential (no pipelining). numpy and OpenCV only: the Pi
runtime runs it.
"""

from __future__ import annotations

import math

import numpy as np

from fcnpose_tf.preprocess import Box, FrameView
from fcnpose_tf.runtime.estimator import KeypointPredictor, Prediction

TRACK_MARGIN = 0.25
"""Added to the keypoint box on each side, as a share of its side: a margin for the arm's motion in one frame and for
the parts past the outer keypoints (the tool, the base's housing). The per-frame crop experiment's value (docs/results.md,
"A crop that follows the arm")."""

TRACK_MIN_FOUND = 4
"""Fewer keypoints found in a frame: the next frame is read over the model's own view again (the arm is lost, or
mostly hidden)."""

CROP_SIDE_STEP = 4
"""Crop sides are multiples of this: an image reduced by whole blocks of 2 (or 4) takes OpenCV's exact integer
area path (`preprocess.block_factor`), fast and the same on every platform."""


def follow_box(keypoints: np.ndarray, frame_shape: tuple[int, ...], input_hw: tuple[int, int],
               margin: float = TRACK_MARGIN, min_found: int = TRACK_MIN_FOUND) -> Box | None:
    """The crop that holds a frame's keypoints for the next frame, or None when there is none to follow.

    Args:
        keypoints: K x 2 keypoints in frame pixels (NaN: not found).
        frame_shape: (height, width[, channels]) of the frames.
        input_hw: (height, width) of the model's input: the crop has its aspect, and is never smaller (the model
            reads no upsampled crop).
        margin: added on each side, as a share of the keypoint box's side.
        min_found: fewer keypoints found give None.
    Returns:
        (x, y, width, height) inside the frame, the box's centre kept where the frame allows; a box with its margin
        larger than the frame gives the largest crop of the input's aspect that fits (part of the margin lost).
        None with fewer than `min_found` keypoints, or when even the keypoints' own box would not fit in that crop.
    """
    points = np.asarray(keypoints, np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < max(1, min_found):
        return None
    frame_h, frame_w = int(frame_shape[0]), int(frame_shape[1])
    in_h, in_w = input_hw
    aspect = in_w / in_h
    low, high = points.min(axis=0), points.max(axis=0)
    need_w, need_h = (high - low + 1) * (1 + 2 * margin)
    width = max(need_w, need_h * aspect, in_w)
    height = width / aspect
    fit = min(1.0, frame_w / width, frame_h / height)  # larger than the frame: the largest crop that fits
    if fit < 1 and (width * fit < high[0] - low[0] + 1 or height * fit < high[1] - low[1] + 1):
        return None  # even the keypoints' own box would be cut: the model's own view reads the frame
    width = CROP_SIDE_STEP * math.ceil(width * fit / CROP_SIDE_STEP)
    height = CROP_SIDE_STEP * math.ceil(height * fit / CROP_SIDE_STEP)
    width, height = min(width, frame_w // CROP_SIDE_STEP * CROP_SIDE_STEP), \
        min(height, frame_h // CROP_SIDE_STEP * CROP_SIDE_STEP)
    if width < CROP_SIDE_STEP or height < CROP_SIDE_STEP:  # a frame a few pixels across: nothing to crop
        return None
    centre = (low + high) / 2  # pixel centres: a crop of columns x..x+w-1 is centred on x + (w - 1) / 2
    x = int(np.clip(round(centre[0] - (width - 1) / 2), 0, frame_w - width))
    y = int(np.clip(round(centre[1] - (height - 1) / 2), 0, frame_h - height))
    return x, y, int(width), int(height)


def predict_over(model: KeypointPredictor, frame_bgr: np.ndarray, box: Box | None) -> Prediction:
    """The model's prediction for a frame read over `box` instead of its own view (None: its own view), keypoints in
    frame pixels; the model keeps its own view afterwards.

    Args:
        model: any predictor.
        frame_bgr: the BGR uint8 frame.
        box: (x, y, width, height) inside the frame, resized to the model's input; None for its own view.
    Returns:
        The prediction; its `crop` is the box.
    """
    if box is None:
        return model.predict(frame_bgr)
    own = model.view
    model.view = FrameView(own.height, own.width, box, (frame_bgr.shape[1], frame_bgr.shape[0]))
    try:
        return model.predict(frame_bgr)
    finally:
        model.view = own


class TrackingCrop(KeypointPredictor):
    """A predictor that reads each frame over the box of the previous frame's keypoints (`follow_box`).

    Args:
        model: the predictor to run (`KeypointModel` or Keras); its own view reads the frames nothing is followed in.
        margin: `follow_box`'s margin.
        min_found: `follow_box`'s minimum of keypoints found.
    Example:
        >>> tracked = TrackingCrop(KeypointModel("arm_p70_int8.tflite"))  # doctest: +SKIP
        >>> with open_source("clip.mp4") as frames:  # doctest: +SKIP
        ...     for frame in frames:
        ...         prediction = tracked.predict(frame.image)  # prediction.crop: the box it read
    """

    pipelinable = False

    def __init__(self, model: KeypointPredictor, margin: float = TRACK_MARGIN, min_found: int = TRACK_MIN_FOUND):
        if not 0 <= margin <= 2:
            raise ValueError(f"margin must be in [0, 2], got {margin}")
        self.model = model
        self.margin = float(margin)
        self.min_found = int(min_found)
        self.own_view: FrameView = model.view
        self.view = model.view
        self.num_maps = model.num_maps
        self.decoding = model.decoding
        self.num_threads = model.num_threads
        self.schema = model.schema
        self.path = getattr(model, "path", None)
        self._next: tuple[tuple[int, int], Box] | None = None
        self.frames = 0
        """Frames predicted."""
        self.whole_view_frames = 0
        """Frames read over the model's own view: the first, and those after a frame that lost the arm."""

    @property
    def backend_label(self) -> str:
        return self.model.backend_label

    def describe(self) -> str:
        """The model's line, with the tracking crop's rule.

        Returns:
            The line.
        """
        return (f"{self.model.describe()}; a crop following the arm (margin {self.margin:g}, the model's own view "
                f"after a frame with fewer than {self.min_found} keypoints)")

    def run_note(self) -> str | None:
        """How many frames were read over the model's own view.

        Returns:
            The summary's line.
        """
        return (f"Tracking: {self.frames - self.whole_view_frames} of {self.frames} frames read over the previous "
                f"frame's keypoint box, {self.whole_view_frames} over the model's own view "
                f"({self.own_view.describe()}: the first frame, or the arm lost in the frame before)")

    def reset(self) -> None:
        """Forget the previous frame: the next one is read over the model's own view."""
        self._next = None

    def set_input(self, frame_bgr: np.ndarray) -> None:
        """The wrapped model's (its argument: `KeypointPredictor.set_input`'s)."""
        self.model.set_input(frame_bgr)

    def invoke(self) -> None:
        self.model.invoke()

    def read_maps(self, copy: bool = True) -> np.ndarray:
        """The wrapped model's (its argument and result: `KeypointPredictor.read_maps`'s)."""
        return self.model.read_maps(copy)

    def predict(self, frame_bgr: np.ndarray) -> Prediction:
        """Keypoints of one frame, read over the box the previous frame's keypoints give (or the model's own view); its
        argument and result are `KeypointPredictor.predict`'s."""
        size = tuple(frame_bgr.shape[:2]) if frame_bgr is not None and frame_bgr.ndim >= 2 else None
        box = self._next[1] if self._next is not None and self._next[0] == size else None
        prediction = predict_over(self.model, frame_bgr, box)
        self.frames += 1
        self.whole_view_frames += box is None
        following = follow_box(prediction.keypoints, frame_bgr.shape, self.own_view.shape, self.margin,
                               self.min_found)
        self._next = (size, following) if following is not None else None
        return prediction

    def warmup(self, frame_shape: tuple[int, int, int] = (480, 640, 3), runs: int = 1) -> None:
        """The model's warm-up (over its own view); the tracking starts afresh. Its arguments: `KeypointPredictor.warmup`'s."""
        self.model.warmup(frame_shape, runs)
        self.reset()
