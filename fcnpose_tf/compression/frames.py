"""The frames an export is verified and calibrated on: real frames from a dataset (never the measured ones for
calibration), or seeded random inputs in the model's range when it is not a keypoint model.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from fcnpose_tf import settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.preprocess import ViewLike
from fcnpose_tf.settings import TFLITE_FORMATS


def check_enough_frames(quantize: Sequence[str], check_count: int, train_count: int, source: Any) -> None:
    """Refuse, before any work, the formats whose gate needs more real frames than `export_frames` can gather.

    Args:
        quantize: the formats to write (`settings.TFLITE_FORMATS` keys).
        check_count, train_count: the frames the file is verified on, and the training frames that top them up.
        source: what holds the frames, for the message (the VIA project's path).
    Raises:
        UserError: one line naming the formats, the frames they need and the frames there are.
    """
    available = check_count + train_count
    short = [q for q in quantize if TFLITE_FORMATS[q].min_frames > available]
    if short:
        raise UserError(f"{', '.join(short)} export is verified on keypoints of at least "
                        f"{max(TFLITE_FORMATS[q].min_frames for q in short)} real frames; {source} has {available} "
                        f"(add frames, or leave {', '.join(short)} out of --quantize)")


def export_frames(quantize: str, input_size: ViewLike, train_dataset: Any, train_indices: Sequence[int],
                  check_dataset: Any, check_indices: Sequence[int], calibration_count: int,
                  seed: int = settings.CALIBRATION_SEED.default) -> tuple[np.ndarray, np.ndarray | None]:
    """Real frames for `export_tflite`.

    The file is verified on the first `settings.TFLITE_FORMATS`' min_frames frames of `check_indices` (16, topped
    up with training frames when there are fewer); an int8 file is calibrated on up to
    `calibration_count` frames drawn (seeded) from `train_indices`, which should hold no frame a
    result is measured on.

    Args:
        quantize: the format (`settings.TFLITE_FORMATS`).
        input_size: the model's view (S, (H, W) or a `preprocess.FrameView`).
        train_dataset, train_indices: the training frames int8 is calibrated on.
        check_dataset, check_indices: the frames the file is verified on.
        calibration_count: calibration frames at most.
        seed: seed of the calibration frames' choice.
    Returns:
        (sample_frames, calibration_frames or None for a format without calibration).
    Raises:
        UserError: as `calibration_frames`.
    """
    from fcnpose_tf.preprocess import preprocess_frame

    count = max(f.min_frames for f in TFLITE_FORMATS.values())
    chosen = [(check_dataset, int(i)) for i in list(check_indices)[:count]]
    chosen += [(train_dataset, int(i)) for i in list(train_indices)[:count - len(chosen)]]
    samples = np.stack([preprocess_frame(dataset.load_image(i), input_size) for dataset, i in chosen])
    calibration = None
    if TFLITE_FORMATS[quantize].calibrated:
        calibration = calibration_frames(train_dataset, train_indices, min(calibration_count, len(train_indices)),
                                         input_size, seed)
    return samples, calibration


def describe_check_frames(samples: int, check_count: int, check_name: str = "validation split") -> str:
    """Which frames `export_frames` verified a file on, in words: "the first 16 frames of the validation split", or
    with fewer than `samples` there "the 5 frames of the validation split and the first 11 of the training split".

    Args:
        samples: the frames verified on.
        check_count: the frames the check part had (`check_indices`).
        check_name: what the check part is.
    Returns:
        The phrase.
    """
    if check_count >= samples:
        return f"the first {samples} frames of the {check_name}"
    return (f"the {check_count} frame{'s' if check_count != 1 else ''} of the {check_name} and the first "
            f"{samples - check_count} of the training split")


def calibration_frames(dataset: Any, indices: Sequence[int], count: int, input_size: ViewLike,
                       seed: int = settings.CALIBRATION_SEED.default) -> np.ndarray:
    """`count` frames drawn (seeded, without replacement) from `indices` of `dataset`, preprocessed as
    the runtime does: the representative data of a full-integer export.

    Draw them from training frames, never from the frames a result is measured on.

    Args:
        dataset: a loaded dataset.
        indices: the frames to draw from.
        count: how many.
        input_size: the model's view (S, (H, W) or a `preprocess.FrameView`).
        seed: seed of the choice.
    Returns:
        count x H x W x 3 float32 frames.
    Raises:
        UserError: if `count` is not a positive number or `indices` holds fewer frames.
    """
    from fcnpose_tf.preprocess import preprocess_frame

    indices = np.asarray(list(indices), dtype=np.int64)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise UserError(f"calibration frames must be a positive number, got {count!r}")
    if count > len(indices):
        raise UserError(f"{count} calibration frames asked for, but only {len(indices)} training frames are there")
    chosen = np.sort(np.random.default_rng(seed).choice(indices, size=count, replace=False))
    return np.stack([preprocess_frame(dataset.load_image(int(i)), input_size) for i in chosen])


GENERIC_SAMPLES = 16
"""Random inputs a model that is not a keypoint model is verified on, when no inputs are given."""


def random_inputs(input_shape: tuple[int, ...], count: int, input_range: tuple[float, float],
                  seed: int) -> np.ndarray:
    """`count` seeded inputs uniform in `input_range`.

    Args:
        input_shape: the model's input shape (batch first).
        count: how many.
        input_range: (low, high): the range the model takes, e.g. (-1, 1) for Keras' MobileNetV2, (0, 1) for
            FCN-Pose's frames.
        seed: seed of the values.
    Returns:
        count x the model's input, float32.
    Raises:
        UserError: a range that is not two finite numbers low < high.
    """
    low, high = (float(v) for v in input_range)
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise UserError(f"input range must be two finite numbers LOW < HIGH, got {input_range!r}")
    return np.random.default_rng(seed).uniform(low, high, (count, *input_shape[1:])).astype(np.float32)


def checked_frames(frames: np.ndarray | None, input_shape: tuple[int, ...], num_samples: int,
                   seed: int, what: str = "sample frames") -> np.ndarray:
    """Frames to verify a file on, checked against the model's input.

    Args:
        frames: N x the model's input (None: `num_samples` seeded random frames in [0, 1)).
        input_shape: the model's input shape (batch first).
        num_samples: random frames without `frames`.
        seed: seed of the random frames.
        what: what the frames are, for the error.
    Returns:
        The frames, float32.
    Raises:
        UserError: frames of another shape, empty or not finite; `num_samples` not a positive integer.
    """
    if frames is None:
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
            raise UserError(f"num_samples must be a positive integer, got {num_samples!r}")
        return np.random.default_rng(seed).random((num_samples, *input_shape[1:]), dtype=np.float32)
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[1:] != tuple(input_shape[1:]) or len(frames) == 0:
        raise UserError(f"{what} must be N x {' x '.join(map(str, input_shape[1:]))} (the model's input), "
                        f"got shape {np.shape(frames)}")
    if not np.isfinite(frames).all():
        raise UserError(f"{what} contain NaN or infinite values")
    return frames
