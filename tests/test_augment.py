"""Rotation/padding augmentation: keypoints follow the pixels, stay in the frame, and seeds reproduce."""

import numpy as np
import pytest

from fcnpose_tf.data.augment import KINDS, AugmentConfig, augment_copies, augment_frame, inside_frame
from fcnpose_tf.errors import UserError

W, H = 80, 60


def dot_image(keypoints):
    """A black frame with one small bright blob per keypoint, each keypoint in its own channel."""
    image = np.zeros((H, W, 3), np.uint8)
    yy, xx = np.mgrid[0:H, 0:W]
    for c, (x, y) in enumerate(keypoints):
        blob = np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2 ** 2))
        image[..., c] = np.round(255 * blob).astype(np.uint8)
    return image


def blob_centre(channel):
    weights = channel.astype(np.float64)
    weights[weights < 10] = 0  # ignore interpolation fringe
    yy, xx = np.mgrid[0:channel.shape[0], 0:channel.shape[1]]
    return np.array([(xx * weights).sum() / weights.sum(), (yy * weights).sum() / weights.sum()])


def test_dots_drawn_at_keypoints_end_up_at_the_transformed_keypoints():
    kps = np.array([[20.0, 15.0], [55.5, 40.25], [40.0, 30.0]])
    image = dot_image(kps)
    rng = np.random.default_rng(0)
    kinds = set()
    for _ in range(24):
        aug = augment_frame(image, kps, rng)
        kinds.add(aug.kind)
        assert aug.image.shape == image.shape and aug.image.dtype == np.uint8
        for c in range(3):
            error = np.hypot(*(blob_centre(aug.image[..., c]) - aug.keypoints[c]))
            # keypoints follow the pixels (docs/data.md, augmentation): the warp is exact
            assert error < 0.25, (aug.kind, c, error)
    assert kinds == set(KINDS)


def test_each_kind_does_what_it_says():
    kps = np.array([[20.0, 15.0], [60.0, 45.0]])
    rng = np.random.default_rng(3)
    seen = {}
    for _ in range(30):
        aug = augment_frame(dot_image(kps), kps, rng)
        seen.setdefault(aug.kind, aug)
    rot, pad, both = seen["rotation"], seen["padding"], seen["rotation+padding"]
    assert rot.scale_xy == (1.0, 1.0) and rot.shift_px == (0, 0) and rot.rotation_deg != 0
    assert pad.rotation_deg == 0 and max(pad.scale_xy) < 1
    # padding shrinks the frame into itself: the whole original frame stays visible
    assert (pad.image[..., 0] > 0).sum() > 0.5 * (dot_image(kps)[..., 0] > 0).sum()
    assert both.rotation_deg != 0 and max(both.scale_xy) < 1


def test_no_accepted_copy_has_a_keypoint_outside_the_frame():
    # keypoints near the corners: most rotations push one out, so copies are often redrawn
    kps = np.array([[1.0, 1.0], [W - 2.0, 2.0], [3.0, H - 1.5], [W - 1.0, H - 1.0], [np.nan, np.nan]])
    image = np.full((H, W, 3), 128, np.uint8)
    copies = augment_copies(image, kps, copies=40, seed=1, config=AugmentConfig(max_rotation_deg=45))
    assert all(inside_frame(c.keypoints, W, H) for c in copies)
    assert any(c.tries > 1 for c in copies)  # rejection happened and was redrawn
    assert all(np.isnan(c.keypoints[4]).all() for c in copies)  # missing stays missing
    assert all(np.isfinite(c.keypoints[:4]).all() for c in copies)


def test_gives_up_on_rotation_with_a_padding_copy_when_nothing_else_fits():
    kps = np.array([[0.0, 0.0], [W - 1.0, H - 1.0]])  # any rotation moves a corner out
    copies = augment_copies(np.zeros((H, W, 3), np.uint8), kps, copies=5, seed=0,
                            config=AugmentConfig(max_rotation_deg=90, max_tries=2))
    assert all(inside_frame(c.keypoints, W, H) for c in copies)
    assert all(c.kind == "padding" or abs(c.rotation_deg) < 1 for c in copies)


def test_same_seed_same_copies_other_seed_other_copies():
    kps = np.array([[20.0, 15.0], [55.0, 40.0]])
    image = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    a = augment_copies(image, kps, 3, seed=7)
    b = augment_copies(image, kps, 3, seed=7)
    c = augment_copies(image, kps, 3, seed=8)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.keypoints, y.keypoints)
        assert x.kind == y.kind
    assert any(not np.array_equal(x.keypoints, z.keypoints) for x, z in zip(a, c))


def test_bad_input():
    image = np.zeros((H, W, 3), np.uint8)
    with pytest.raises(UserError, match="outside the 80x60 frame"):
        augment_frame(image, np.array([[90.0, 5.0]]), np.random.default_rng(0))
    with pytest.raises(UserError, match="copies"):
        augment_copies(image, np.array([[9.0, 5.0]]), copies=-1)
    with pytest.raises(UserError, match="rotation"):
        AugmentConfig(max_rotation_deg=200)


def test_without_albumentations_augmenting_is_one_line_naming_the_extra(monkeypatch):
    """The Pi-only install (`pip install 'fcnpose-tf[pi]'`) has no Albumentations: `data inspect --out` there says
    which extra augments frames instead of a traceback."""
    import sys

    monkeypatch.setitem(sys.modules, "albumentations", None)  # import albumentations raises ImportError
    image = np.zeros((48, 64, 3), np.uint8)
    keypoints = np.full((8, 2), 20.0)
    with pytest.raises(UserError, match=r"needs Albumentations .*pip install 'fcnpose-tf\[train\]'"):
        augment_frame(image, keypoints, np.random.default_rng(0), AugmentConfig())
