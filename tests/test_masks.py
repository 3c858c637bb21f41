"""Target maps: sub-pixel disc centres, the paper's sizes at 224 and their scaling, missing keypoints."""

import numpy as np
import pytest

from fcnpose_tf.data.masks import default_radius, default_thickness, make_target_maps
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema


def chain_keypoints(size=224):
    """UR5 keypoints along a zig-zag well inside a size x size map, at sub-pixel positions."""
    t = np.linspace(0.2, 0.8, 8)
    return np.c_[t * size + 0.37, (0.3 + 0.4 * (np.arange(8) % 2)) * size - 0.21]


def centroid(mask):
    ys, xs = np.nonzero(mask)
    return xs.mean(), ys.mean()


def test_maps_layout_and_values():
    maps = make_target_maps(chain_keypoints(), 224, UR5)
    assert maps.shape == (224, 224, 9) and maps.dtype == np.uint8 and maps.flags.c_contiguous
    assert set(np.unique(maps)) == {0, 1}
    floats = make_target_maps(chain_keypoints(), 224, UR5, dtype=np.float32)
    assert floats.dtype == np.float32
    np.testing.assert_array_equal(floats, maps)


def test_discs_are_centred_on_sub_pixel_keypoints_with_the_paper_radius():
    kps = chain_keypoints()
    maps = make_target_maps(kps, 224, UR5)
    for k in range(8):
        cx, cy = centroid(maps[..., k])
        assert abs(cx - kps[k, 0]) < 0.25 and abs(cy - kps[k, 1]) < 0.25  # rounding would allow 0.5
        area = maps[..., k].sum()
        assert abs(area - np.pi * 6 ** 2) < 0.06 * np.pi * 6 ** 2  # radius 6 px at 224
        assert maps[int(round(kps[k, 1])), int(round(kps[k, 0])), 8] == 1  # the skeleton passes each keypoint


@pytest.mark.parametrize("radius", [0, 1, 2, 6, 9])
def test_discs_at_whole_pixels_equal_opencv_filled_circles(radius):
    import cv2

    kps = np.array([[20.0, 30.0], [0.0, 5.0], [63.0, 63.0], [40.0, 2.0]])
    schema = KeypointSchema("four", ("a", "b", "c", "d"), ())
    maps = make_target_maps(kps, 64, schema, radius=radius)
    for k, (x, y) in enumerate(kps.astype(int)):
        expected = np.zeros((64, 64), np.uint8)
        cv2.circle(expected, (int(x), int(y)), radius, 1, -1)
        np.testing.assert_array_equal(maps[..., k], expected)


def test_skeleton_is_30_px_thick_at_224():
    kps = np.full((8, 2), np.nan)
    kps[0], kps[1] = (40.0, 112.0), (180.0, 112.0)  # one horizontal segment
    skeleton = make_target_maps(kps, 224, UR5)[..., 8]
    assert skeleton[:, 110].sum() in (30, 31)
    assert skeleton[112, 20] == 0 and skeleton[112, 200] == 0


@pytest.mark.parametrize("size", [64, 128, 224, 448])
def test_defaults_scale_with_the_input_size(size):
    assert default_radius(size) == pytest.approx(6 * size / 224)
    assert default_thickness(size) == pytest.approx(30 * size / 224)
    kps = chain_keypoints(size)
    maps = make_target_maps(kps, size, UR5)
    # the share of the map covered by each target stays about the same at every size
    reference = make_target_maps(chain_keypoints(224), 224, UR5)
    assert maps[..., 8].mean() == pytest.approx(reference[..., 8].mean(), rel=0.12)
    if size >= 128:
        assert maps[..., 0].mean() == pytest.approx(reference[..., 0].mean(), rel=0.15)


def test_a_missing_keypoint_empties_its_map_and_breaks_only_its_segments():
    kps = chain_keypoints()
    kps[3] = np.nan
    maps = make_target_maps(kps, 224, UR5, thickness=3)
    assert maps[..., 3].sum() == 0
    skeleton = maps[..., 8]

    def on_segment(a, b):
        mid = (kps[a] + kps[b]) / 2
        return skeleton[int(round(mid[1])), int(round(mid[0]))]

    assert on_segment(2, 4) == 0  # no shortcut across the missing keypoint
    full = chain_keypoints()
    for a, b in UR5.edges:
        mid = (full[a] + full[b]) / 2
        expected = 0 if 3 in (a, b) else 1
        assert skeleton[int(round(mid[1])), int(round(mid[0]))] == expected, (a, b)


def test_explicit_radius_and_thickness():
    kps = chain_keypoints(64) / 1.0
    thin = make_target_maps(kps, 64, UR5, radius=1, thickness=1)
    thick = make_target_maps(kps, 64, UR5, radius=5, thickness=12)
    assert thin[..., :8].sum() < thick[..., :8].sum() and thin[..., 8].sum() < thick[..., 8].sum()


def test_keypoints_outside_the_map_draw_only_their_visible_part():
    schema = KeypointSchema.chain("two", ("a", "b"))
    maps = make_target_maps(np.array([[-1e9, 32.0], [32.0, 32.0]]), 64, schema)
    assert maps[..., 0].sum() == 0 and maps[..., 1].sum() > 0
    assert maps[32, 0, 2] == 1  # the segment still reaches the map edge


def test_bad_arguments():
    with pytest.raises(UserError, match="expected 8 x 2 keypoints"):
        make_target_maps(np.zeros((7, 2)), 64, UR5)
    with pytest.raises(UserError, match="thickness"):
        make_target_maps(np.zeros((8, 2)), 64, UR5, thickness=0)
