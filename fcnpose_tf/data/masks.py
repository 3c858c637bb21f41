"""Target maps: one filled disc per keypoint plus one skeleton map, at the model's input size.

The paper draws discs of radius 6 px and skeleton lines 30 px thick on 224 x 224
maps. Those defaults are defined at 224 px and scale with the input side S:
radius = 6 * S / 224 and thickness = 30 * S / 224 (at 64 px: 1.71 px and 8.6 px,
the thickness rounded to 9 as OpenCV draws whole-pixel line widths). Centres are
drawn with sub-pixel precision (OpenCV `shift`), in the pixel-centre convention
(pixel i's centre is at coordinate i), so a disc's centroid is its keypoint.
"""

from __future__ import annotations

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema

REFERENCE_INPUT_SIZE = 224
"""Input side at which the paper's disc radius and line thickness are given."""
PAPER_RADIUS_PX = 6.0
PAPER_THICKNESS_PX = 30.0

_SHIFT = 8  # fractional bits for cv2 sub-pixel coordinates (1/256 px)


def default_radius(input_size: int) -> float:
    """The paper's disc radius (6 px at 224) scaled to `input_size`."""
    return PAPER_RADIUS_PX * input_size / REFERENCE_INPUT_SIZE


def default_thickness(input_size: int) -> float:
    """The paper's skeleton line thickness (30 px at 224) scaled to `input_size`."""
    return PAPER_THICKNESS_PX * input_size / REFERENCE_INPUT_SIZE


def _fixed(value: float) -> int:
    return int(round(float(value) * (1 << _SHIFT)))


def make_target_maps(keypoints: np.ndarray, input_size: int, schema: KeypointSchema, radius: float | None = None,
                     thickness: float | None = None, dtype: type = np.uint8) -> np.ndarray:
    """S x S x (K+1) binary target maps (1 inside, 0 outside) for K keypoints in input pixels.

    Args:
        keypoints: K x 2 (x, y) in model-input pixels (see preprocess.keypoints_to_input);
            NaN rows are missing keypoints.
        input_size: side S of the square maps.
        schema: keypoint names and skeleton edges; maps are ordered keypoints first, skeleton last.
        radius: disc radius in input pixels; default the paper's 6 px at 224, scaled to S.
        thickness: skeleton line thickness in input pixels; default the paper's 30 px at 224,
            scaled to S (rounded to whole pixels, at least 1).
        dtype: uint8 (compact, for storage) or a float type (a training target).

    A missing keypoint leaves its own map empty and removes only the skeleton
    segments that end at it; keypoints outside the map draw only their in-map part.
    """
    import cv2

    kps = np.asarray(keypoints, np.float64)
    if kps.shape != (schema.num_keypoints, 2):
        raise UserError(f"expected {schema.num_keypoints} x 2 keypoints for schema {schema.name!r}, got {kps.shape}")
    if input_size < 1:
        raise UserError(f"input size must be positive, got {input_size}")
    radius = default_radius(input_size) if radius is None else float(radius)
    thickness = default_thickness(input_size) if thickness is None else float(thickness)
    if radius < 0 or thickness <= 0:
        raise UserError(f"disc radius must be >= 0 and line thickness > 0, got {radius} and {thickness}")
    line_px = max(1, int(round(thickness)))
    planes = np.zeros((schema.num_maps, input_size, input_size), np.uint8)  # each plane C-contiguous for OpenCV
    visible = np.isfinite(kps).all(axis=1)
    # far-away coordinates would overflow OpenCV's fixed-point ints; they draw nothing in the map anyway
    limit = 4.0 * input_size + radius + line_px
    clipped = np.clip(np.nan_to_num(kps), -limit, limit)
    for k in range(schema.num_keypoints):
        if visible[k]:
            x, y = clipped[k]
            cv2.circle(planes[k], (_fixed(x), _fixed(y)), _fixed(radius), 1, thickness=-1,
                       lineType=cv2.LINE_8, shift=_SHIFT)
    skeleton = planes[schema.num_keypoints]
    for a, b in schema.edges:
        if visible[a] and visible[b]:
            pa = (_fixed(clipped[a, 0]), _fixed(clipped[a, 1]))
            pb = (_fixed(clipped[b, 0]), _fixed(clipped[b, 1]))
            cv2.line(skeleton, pa, pb, 1, thickness=line_px, lineType=cv2.LINE_8, shift=_SHIFT)
    maps = np.ascontiguousarray(planes.transpose(1, 2, 0))
    return maps if dtype == np.uint8 else maps.astype(dtype)
