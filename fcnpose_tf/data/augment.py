"""Offline keypoint-aware augmentation (the paper's rotation and padding), with Albumentations.

Each augmented copy of a frame is, at random, a rotation about the image
centre, a padding, or both. Padding adds borders of random widths on each side
and scales the result back to the frame size, so the image centre moves in any
direction while the whole frame stays visible. Both are one affine warp
(Albumentations `Affine`), applied to the image and, exactly, to the
keypoints; the target maps are then drawn from the new keypoints. A copy in
which any visible keypoint leaves the frame is rejected and drawn again.
Frame size is kept. Same seed, same copies.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from fcnpose_tf.errors import UserError

KINDS = ("rotation", "padding", "rotation+padding")
"""The three kinds of augmented copy, drawn with equal probability."""


@dataclass(frozen=True)
class AugmentConfig:
    """Ranges of the random augmentation.

    max_rotation_deg: rotation angle drawn uniformly in [-max, +max] degrees.
    max_pad_fraction: total padding per axis drawn uniformly in [0, max] times the
        frame side (0.3: the frame shrinks to 1/1.3 = 77% at most), split between the
        two sides at random.
    max_tries: draws before giving up on a frame whose keypoints keep leaving the
        frame; then a padding-only copy is used (padding never moves a point out).
    fill: grey level of the new border pixels.
    """

    max_rotation_deg: float = 30.0
    max_pad_fraction: float = 0.3
    max_tries: int = 50
    fill: int = 0

    def __post_init__(self):
        if not 0 <= self.max_rotation_deg <= 180:
            raise UserError(f"max rotation must be between 0 and 180 degrees, got {self.max_rotation_deg}")
        if not 0 <= self.max_pad_fraction <= 10:
            raise UserError(f"max padding fraction must be between 0 and 10, got {self.max_pad_fraction}")
        if self.max_tries < 1:
            raise UserError(f"max tries must be at least 1, got {self.max_tries}")


@dataclass
class AugmentedFrame:
    """One accepted augmented copy: image (H x W x 3 uint8), K x 2 keypoints (NaN missing) and what was done."""

    image: np.ndarray
    keypoints: np.ndarray
    kind: str
    rotation_deg: float
    scale_xy: tuple[float, float]
    shift_px: tuple[int, int]
    tries: int


def inside_frame(keypoints: np.ndarray, width: int, height: int) -> bool:
    """True if every visible (finite) keypoint lies on the frame (-0.5 .. W-0.5, pixel-centre convention)."""
    kps = np.asarray(keypoints, np.float64)
    vis = np.isfinite(kps).all(axis=1)
    x, y = kps[vis, 0], kps[vis, 1]
    return bool(np.all((x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)))


def _albumentations():
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")  # no network check at import
    try:
        import albumentations as A
    except ImportError as exc:  # the Pi-only install (the pi extra) has no augmentation
        raise UserError(f"augmenting frames needs Albumentations ({exc}); install the training extra: "
                        "pip install 'fcnpose-tf[train]'") from None
    return A


def _draw(rng: np.random.Generator, kind: str, width: int, height: int, config: AugmentConfig):
    angle = float(rng.uniform(-config.max_rotation_deg, config.max_rotation_deg)) if "rotation" in kind else 0.0
    scale, shift = [1.0, 1.0], [0, 0]
    if "padding" in kind:
        for axis, side in enumerate((width, height)):
            s = 1.0 / (1.0 + float(rng.uniform(0.0, config.max_pad_fraction)))
            free = (1.0 - s) * side / 2.0  # the shrunk frame may move this far from the centre and stay whole
            scale[axis] = s
            shift[axis] = int(np.trunc(rng.uniform(-free, free)))
    return angle, (scale[0], scale[1]), (shift[0], shift[1])


def _warp(image: np.ndarray, points: np.ndarray, angle: float, scale: tuple[float, float],
          shift: tuple[int, int], fill: int) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    A = _albumentations()
    transform = A.Compose(
        [A.Affine(rotate=(angle, angle), scale={"x": (scale[0], scale[0]), "y": (scale[1], scale[1])},
                  translate_px={"x": (shift[0], shift[0]), "y": (shift[1], shift[1])}, keep_ratio=False,
                  interpolation=cv2.INTER_LINEAR, border_mode=cv2.BORDER_CONSTANT, fill=fill, p=1.0)],
        keypoint_params=A.KeypointParams(format="xy", remove_invisible=False, check_each_transform=False),
        seed=0)
    out = transform(image=np.ascontiguousarray(image), keypoints=points.reshape(-1, 2).astype(np.float32))
    return out["image"], np.asarray(out["keypoints"], np.float64).reshape(-1, 2)[:, :2]


def augment_frame(image: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator,
                  config: AugmentConfig = AugmentConfig()) -> AugmentedFrame:
    """One random augmented copy of a frame whose visible keypoints all stay inside the frame.

    Args:
        image: H x W x C uint8 frame.
        keypoints: K x 2 (x, y) frame pixels, NaN rows missing (they stay NaN).
        rng: numpy Generator; the copy depends only on its state.
        config: rotation and padding ranges.

    Raises:
        UserError: if a visible keypoint is already outside the frame.
    """
    h, w = image.shape[:2]
    kps = np.asarray(keypoints, np.float64).reshape(-1, 2)
    if not inside_frame(kps, w, h):
        raise UserError(f"cannot augment: a keypoint lies outside the {w}x{h} frame")
    visible = np.isfinite(kps).all(axis=1)
    for tries in range(1, config.max_tries + 2):
        kind = KINDS[int(rng.integers(len(KINDS)))] if tries <= config.max_tries else "padding"
        angle, scale, shift = _draw(rng, kind, w, h, config)
        out_image, moved = _warp(image, kps[visible], angle, scale, shift, config.fill)
        new = np.full_like(kps, np.nan)
        new[visible] = moved
        if inside_frame(new, w, h):
            return AugmentedFrame(out_image, new, kind, angle, scale, shift, tries)
    raise AssertionError("unreachable: a padding-only copy keeps in-frame keypoints inside")  # pragma: no cover


def augment_copies(image: np.ndarray, keypoints: np.ndarray, copies: int = 2, seed: int | np.random.Generator = 0,
                   config: AugmentConfig = AugmentConfig()) -> list[AugmentedFrame]:
    """`copies` augmented copies of one frame (the paper: 2 per training frame); same seed, same copies."""
    if copies < 0:
        raise UserError(f"augmentation copies must be >= 0, got {copies}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return [augment_frame(image, keypoints, rng, config) for _ in range(copies)]
