"""Target maps: one filled disc per keypoint plus one skeleton map, at the model's input size.

The paper draws discs of radius 6 px and skeleton lines 30 px thick on 224 x 224
maps. Those defaults are defined at 224 px and scale with the input's shorter side S:
radius = 6 * S / 224 and thickness = 30 * S / 224 (at 64 px: 1.71 px and 8.57 px; at
224 x 288: the paper's 6 and 30 px).

Shapes are rasterised exactly, in the pixel-centre convention (pixel i's centre
is at coordinate i): a pixel is in a disc when its centre lies within the radius
of the keypoint, and on the skeleton when its centre lies within thickness / 2 of
a segment (round ends). For whole-pixel centres and radii a disc is exactly
cv2.circle's filled disc; for sub-pixel keypoints it stays centred on the
keypoint, while OpenCV's fixed-point drawing (`shift`) makes discs about 0.3 px
wider. numpy only.
"""

from __future__ import annotations

import math

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.preprocess import FrameView, ViewLike

REFERENCE_INPUT_SIZE = 224
"""Input side at which the paper's disc radius and line thickness are given."""
PAPER_RADIUS_PX = 6.0
PAPER_THICKNESS_PX = 30.0

def default_radius(input_size: int) -> float:
    """The paper's disc radius (6 px at 224) scaled to `input_size`."""
    return PAPER_RADIUS_PX * input_size / REFERENCE_INPUT_SIZE


def default_thickness(input_size: int) -> float:
    """The paper's skeleton line thickness (30 px at 224) scaled to `input_size`."""
    return PAPER_THICKNESS_PX * input_size / REFERENCE_INPUT_SIZE


def _box(lo_x: float, hi_x: float, lo_y: float, hi_y: float, shape: tuple[int, ...]):
    """Integer pixel ranges [x0, x1) x [y0, y1) covering the given coordinates, clipped to a map of `shape` (H, W)."""
    x0, x1 = max(0, math.floor(lo_x)), min(shape[1], math.ceil(hi_x) + 1)
    y0, y1 = max(0, math.floor(lo_y)), min(shape[0], math.ceil(hi_y) + 1)
    return x0, x1, y0, y1


def draw_disc(plane: np.ndarray, x: float, y: float, radius: float) -> None:
    """Set to 1 the pixels of `plane` whose centres lie within `radius` of (x, y)."""
    x0, x1, y0, y1 = _box(x - radius, x + radius, y - radius, y + radius, plane.shape)
    if x0 >= x1 or y0 >= y1:
        return
    dx = np.arange(x0, x1) - x
    dy = np.arange(y0, y1)[:, None] - y
    plane[y0:y1, x0:x1] |= (dx * dx + dy * dy <= radius * radius).astype(np.uint8)


def draw_segment(plane: np.ndarray, a: np.ndarray, b: np.ndarray, thickness: float) -> None:
    """Set to 1 the pixels of `plane` whose centres lie within thickness/2 of the segment a-b (round ends)."""
    h = thickness / 2.0
    x0, x1, y0, y1 = _box(min(a[0], b[0]) - h, max(a[0], b[0]) + h, min(a[1], b[1]) - h, max(a[1], b[1]) + h,
                          plane.shape)
    if x0 >= x1 or y0 >= y1:
        return
    px = np.arange(x0, x1) - a[0]
    py = np.arange(y0, y1)[:, None] - a[1]
    d = b - a
    length2 = float(d @ d)
    t = np.clip((px * d[0] + py * d[1]) / length2, 0.0, 1.0) if length2 > 0 else np.zeros_like(px * py)
    ex, ey = px - t * d[0], py - t * d[1]
    plane[y0:y1, x0:x1] |= (ex * ex + ey * ey <= h * h).astype(np.uint8)


def make_target_maps(keypoints: np.ndarray, input_size: ViewLike, schema: KeypointSchema,
                     radius: float | None = None, thickness: float | None = None, dtype: type = np.uint8) -> np.ndarray:
    """H x W x (K+1) binary target maps (1 inside, 0 outside) for K keypoints in input pixels.

    Args:
        keypoints: K x 2 (x, y) in model-input pixels (see preprocess.keypoints_to_input);
            NaN rows are missing keypoints.
        input_size: the maps' size: S (S x S), (H, W) or the model's `FrameView`.
        schema: keypoint names and skeleton edges; maps are ordered keypoints first, skeleton last.
        radius: disc radius in input pixels; default the paper's 6 px at 224, scaled to the shorter side.
        thickness: skeleton line thickness in input pixels; default the paper's 30 px at 224,
            scaled to the shorter side.
        dtype: uint8 (compact, for storage) or a float type (a training target).

    A missing keypoint leaves its own map empty and removes only the skeleton
    segments that end at it; keypoints outside the map draw only their in-map part.
    """
    kps = np.asarray(keypoints, np.float64)
    if kps.shape != (schema.num_keypoints, 2):
        raise UserError(f"expected {schema.num_keypoints} x 2 keypoints for schema {schema.name!r}, got {kps.shape}")
    height, width = FrameView.of(input_size).shape
    radius = default_radius(min(height, width)) if radius is None else float(radius)
    thickness = default_thickness(min(height, width)) if thickness is None else float(thickness)
    if radius < 0 or thickness <= 0:
        raise UserError(f"disc radius must be >= 0 and line thickness > 0, got {radius} and {thickness}")
    planes = np.zeros((schema.num_maps, height, width), np.uint8)
    visible = np.isfinite(kps).all(axis=1)
    for k in np.flatnonzero(visible):
        draw_disc(planes[k], kps[k, 0], kps[k, 1], radius)
    skeleton = planes[schema.num_keypoints]
    for a, b in schema.edges:
        if visible[a] and visible[b]:
            draw_segment(skeleton, kps[a], kps[b], thickness)
    maps = np.ascontiguousarray(planes.transpose(1, 2, 0))
    return maps if dtype == np.uint8 else maps.astype(dtype)
