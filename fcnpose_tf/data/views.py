"""Does the camera move between a dataset's frames? `train --augment auto` chooses its augmentation by it.

A fixed camera (the paper's use case: one camera watching one cell) films the same background in every
frame: once each frame is reduced to a small grey thumbnail and standardised (its own mean and spread
removed, so exposure and light changes do not count), most pixels stay near the median thumbnail of
the set. Frames from moving or different cameras share no background and sit far from it. The score
is the median absolute deviation from the median thumbnail, in standard deviations of a frame.

Measured on this package's proxies (docs/training.md, "Training on your own frames"): a fixed-camera
cell 0.11-0.13 (another arm pose, person and light in every frame), domain-randomised views 0.53-0.57.
"""

from __future__ import annotations

import os
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.preprocess import read_image

THUMBNAIL_SIZE = (32, 24)
"""Width x height of the grey thumbnails compared: the background's layout, not its detail or noise."""
SAMPLE_FRAMES = 40
"""Frames looked at, evenly spaced over the set (a fraction of a second to read)."""
FIXED_CAMERA_MAX_VARIATION = 0.3
"""Above this the views vary: between the fixed cell (0.11-0.13) and random views (0.53-0.57)."""


def view_variation(image_paths: Sequence[str | os.PathLike], sample: int = SAMPLE_FRAMES) -> float:
    """Median absolute deviation of standardised grey thumbnails from their median thumbnail.

    Args:
        image_paths: the dataset's frames; up to `sample` of them, evenly spaced, are read.
        sample: how many frames to read.
    Returns:
        About 0.1 for one fixed camera, above 0.5 for a new view in every frame; 0.0 for one frame.
    Raises:
        UserError: an image that cannot be read.
    """
    paths = list(image_paths)
    if len(paths) < 2:
        return 0.0
    picks = np.unique(np.linspace(0, len(paths) - 1, min(sample, len(paths))).round().astype(int))
    thumbs = []
    for i in picks:
        image = read_image(paths[i], cv2.IMREAD_REDUCED_GRAYSCALE_4)
        if image is None:
            raise UserError(f"{paths[i]}: cannot be read as an image")
        thumb = cv2.resize(image, THUMBNAIL_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)
        thumbs.append((thumb - thumb.mean()) / (thumb.std() + 1e-6))
    stack = np.stack(thumbs)
    return float(np.median(np.abs(stack - np.median(stack, axis=0))))


def choose_augment(variation: float) -> str:
    """`paper` (the fixed copies) for one fixed camera, `online` (fresh transforms) when the views vary."""
    return "paper" if variation <= FIXED_CAMERA_MAX_VARIATION else "online"
