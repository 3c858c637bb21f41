"""Frame preprocessing shared by training and the Pi runtime (numpy + OpenCV only).

A frame (H x W x 3, uint8, BGR as OpenCV reads it) is resized to the model's
square input (no letterbox: the paper resizes the whole frame), converted to
RGB and scaled to [0, 1] float32. Keypoints scale with the same factors, so a
keypoint found in map pixels maps back to frame pixels exactly.
"""

from __future__ import annotations

import cv2
import numpy as np

from fcnpose_tf.errors import UserError


def preprocess_frame(frame_bgr: np.ndarray, input_size: int, out: np.ndarray | None = None) -> np.ndarray:
    """Resize a BGR uint8 frame to input_size x input_size RGB float32 in [0, 1].

    `out` (input_size x input_size x 3 float32) may be given to reuse a buffer.
    """
    if frame_bgr is None or frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
        shape = None if frame_bgr is None else frame_bgr.shape
        raise UserError(f"expected a colour frame of shape H x W x 3, got {shape}")
    interp = cv2.INTER_AREA if frame_bgr.shape[0] > input_size else cv2.INTER_LINEAR
    small = cv2.resize(frame_bgr, (input_size, input_size), interpolation=interp)
    rgb = cv2.cvtColor(small, cv2.COLOR_BGR2RGB)
    if out is None:
        out = np.empty((input_size, input_size, 3), np.float32)
    np.multiply(rgb, np.float32(1.0 / 255.0), out=out, casting="unsafe")
    return out


def frame_to_input_scale(frame_shape: tuple[int, ...], input_size: int) -> np.ndarray:
    """(sx, sy) multiplying frame pixel coordinates into model-input pixel coordinates."""
    h, w = frame_shape[:2]
    return np.array([input_size / w, input_size / h], np.float64)


def keypoints_to_input(keypoints: np.ndarray, frame_shape: tuple[int, ...], input_size: int) -> np.ndarray:
    """Scale K x 2 (x, y) frame-pixel keypoints to model-input pixels (NaN stays NaN).

    Coordinates follow the pixel-centre convention of OpenCV and VIA (pixel i's
    centre is at i), so scaling goes through the pixel edges: (x + 0.5) * s - 0.5,
    which is how cv2.resize places pixel centres.
    """
    return (np.asarray(keypoints, np.float64) + 0.5) * frame_to_input_scale(frame_shape, input_size) - 0.5


def keypoints_to_frame(keypoints: np.ndarray, frame_shape: tuple[int, ...], map_size: int) -> np.ndarray:
    """Scale K x 2 keypoints from map/model-input pixels back to frame pixels (NaN stays NaN)."""
    return (np.asarray(keypoints, np.float64) + 0.5) / frame_to_input_scale(frame_shape, map_size) - 0.5
