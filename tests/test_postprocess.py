"""Post-processing: the fast path must return exactly what the paper's Algorithm 1 returns."""

from __future__ import annotations

import doctest
import math

import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT

import fcnpose_tf.postprocess as pp
from fcnpose_tf.errors import UserError
from fcnpose_tf.postprocess import decode, largest_cluster, maps_to_keypoints, probability_to_logit
from fcnpose_tf.preprocess import keypoints_to_frame


# --------------------------------------------------------------------------------------------
# The reference: Algorithm 1 (Expansion Clustering) transcribed line by line, deliberately slow.
# --------------------------------------------------------------------------------------------

def expansion_clustering(points: list[tuple[int, int]], m: float = 1.0) -> list[list[tuple[int, int]]]:
    """Algorithm 1 of the paper, literally. `points` is S, in the order the scan visits it.

    Two readings the pseudo-code leaves open, taken from the paper's text: the seed p is removed
    from S when it starts a cluster ("Those points are removed from the initial set of points";
    otherwise a lone point would loop forever and every seed would be counted twice), and
    "for each point p in S" skips points an earlier cluster of the same pass has taken.
    """
    S = list(points)                                   # S = set of points (x, y)
    clusters: list[list[tuple[int, int]]] = []         # Clusters = set of clusters
    M = m                                              # M = minimum distance
    while S:                                           # while S is not empty
        for p in list(S):                              # for each point p in S
            if p not in S:
                continue
            C = [p]                                    # create a new cluster C; add p to C
            S.remove(p)
            new_point_added = True
            while new_point_added:                     # while a new point is added on C
                new_point_added = False
                for p_i in C:                          # for each point p_i in C (C grows meanwhile)
                    for p_j in list(S):                # for each point p_j in S
                        if p_i != p_j and math.dist(p_i, p_j) <= M:
                            C.append(p_j)              # add p_j to C
                            S.remove(p_j)              # remove p_j from S
                            new_point_added = True
            clusters.append(C)                         # add C into Clusters
    return clusters


def reference_keypoint(mask: np.ndarray) -> tuple[float, float, int]:
    """The paper's keypoint: the centroid of the cluster with most points (the first one on ties)."""
    points = [(int(c), int(r)) for r, c in np.argwhere(mask)]   # (x, y), row-major order
    clusters = expansion_clustering(points)
    if not clusters:
        return math.nan, math.nan, 0
    best = max(clusters, key=len)                                # first maximal cluster
    n = len(best)
    return sum(p[0] for p in best) / n, sum(p[1] for p in best) / n, n


def reference_maps_to_keypoints(maps: np.ndarray, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    k = maps.shape[-1] - 1
    kp = np.full((k, 2), np.nan)
    conf = np.zeros(k, np.int64)
    for i in range(k):
        x, y, n = reference_keypoint(maps[..., i] > threshold)
        kp[i] = x, y
        conf[i] = n
    return kp, conf


def count_ties(mask: np.ndarray) -> int:
    """How many other clusters share the largest size (0 = no tie)."""
    sizes = [len(c) for c in expansion_clustering([(int(c), int(r)) for r, c in np.argwhere(mask)])]
    return sizes.count(max(sizes)) - 1 if sizes else 0


def assert_same(fast, ref):
    kp, conf = fast
    rkp, rconf = ref
    np.testing.assert_array_equal(conf, rconf)
    # Exact equality (NaN == NaN): the fast path must not even differ in the last bit.
    np.testing.assert_array_equal(kp, rkp)


def test_reference_on_hand_made_mask():
    """The transcription itself on a case worked by hand, so the reference cannot be wrong silently."""
    mask = np.zeros((5, 6), bool)
    mask[0, 0] = True                    # lone pixel, first in row-major order
    mask[1, 2:5] = True                  # a bar of three
    mask[2, 2] = True                    # below the bar's left end: joins it (distance 1)
    mask[3, 5] = True                    # diagonal to nothing: distance sqrt(2) > 1
    mask[4, 4] = True                    # diagonal to (3, 5): its own cluster
    clusters = expansion_clustering([(int(c), int(r)) for r, c in np.argwhere(mask)])
    assert [sorted(c) for c in clusters] == [[(0, 0)], [(2, 1), (2, 2), (3, 1), (4, 1)], [(5, 3)], [(4, 4)]]
    assert reference_keypoint(mask) == (11 / 4, 5 / 4, 4)
    assert largest_cluster(mask) == (11 / 4, 5 / 4, 4)


# --------------------------------------------------------------------------------------------
# Equivalence on random masks
# --------------------------------------------------------------------------------------------

SHAPES = [(1, 1), (1, 9), (9, 1), (2, 2), (5, 5), (7, 13), (12, 12), (16, 10)]
DENSITIES = [0.0, 0.03, 0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9, 1.0]


def test_largest_cluster_equals_algorithm_1_on_random_masks():
    rng = np.random.default_rng(1234)
    ties = checked = 0
    for shape in SHAPES:
        for density in DENSITIES:
            for _ in range(6):
                mask = rng.random(shape) < density
                expected = reference_keypoint(mask)
                got = largest_cluster(mask)
                assert got[2] == expected[2], (shape, density, mask.astype(int))
                np.testing.assert_array_equal(got[:2], expected[:2], err_msg=str(mask.astype(int)))
                ties += count_ties(mask) > 0
                checked += 1
    # The sample must exercise the tie rule, or this test proves less than it claims.
    assert ties >= 40, ties
    assert checked == len(SHAPES) * len(DENSITIES) * 6


def test_sparse_speckles_with_ties_equal_algorithm_1():
    """Few active pixels in a wide window (the path that labels only the active pixels), where
    the largest clusters are tied speckles of one or two pixels."""
    rng = np.random.default_rng(77)
    ties = 0
    for _ in range(40):
        shape = tuple(rng.integers(20, 48, size=2))
        mask = rng.random(shape) < rng.uniform(0.005, 0.05)
        mask[:, 1:] |= mask[:, :-1] & (rng.random((shape[0], shape[1] - 1)) < 0.3)   # some 2-pixel speckles
        mask[rng.integers(shape[0]), rng.integers(shape[1])] = True                   # never empty
        assert 8 * mask.sum() <= shape[0] * shape[1]
        expected = reference_keypoint(mask)
        assert largest_cluster(mask) == expected, mask.astype(int)
        ties += count_ties(mask) > 0
    assert ties >= 20, ties


def test_blobs_and_speckles_in_wide_windows_equal_algorithm_1():
    """Large, mostly empty windows (the path that squeezes out empty rows and columns): blobs,
    speckles next to and one line apart from each other, clusters touching the squeezed gaps."""
    rng = np.random.default_rng(2024)
    ties = 0
    for trial in range(40):
        size = int(rng.integers(40, 90))
        mask = np.zeros((size, size), bool)
        for _ in range(int(rng.integers(1, 4))):
            r, c, a, b = rng.integers(0, size - 4), rng.integers(0, size - 4), rng.integers(1, 4), rng.integers(1, 4)
            mask[r:r + a, c:c + b] = True                          # rectangles, often tied in size
        ys, xs = rng.integers(0, size, (2, int(rng.integers(0, 25))))
        mask[ys, xs] = True                                        # speckles
        if trial % 4 == 0:                                         # two bars one empty line apart
            mask[5, 2:8] = mask[7, 2:8] = True
        expected = reference_keypoint(mask)
        assert largest_cluster(mask) == expected, np.argwhere(mask).tolist()
        ties += count_ties(mask) > 0
    assert ties >= 8, ties


def test_lone_pixels_in_sparse_windows_equal_algorithm_1():
    """Sparse windows over 1024 px drop their lone pixels before labelling: windows of lone pixels only
    (diagonal neighbours among them: still lone), of lone pixels and tied 2-4 px clusters, and lone pixels
    ahead of the largest cluster in raster order."""
    rng = np.random.default_rng(77)
    lone_only = 0
    for trial in range(60):
        size = int(rng.integers(36, 80))
        mask = np.zeros((size, size), bool)
        ys, xs = rng.integers(0, size, (2, int(rng.integers(1, size * size // 40))))
        mask[ys, xs] = True                                        # speckles, some touching
        if trial % 3 == 0:                                         # a diagonal chain: lone pixels, each its own cluster
            r, c = rng.integers(0, size - 6, 2)
            mask[r + np.arange(5), c + np.arange(5)] = True
        if trial % 2 == 0:
            lone = np.zeros_like(mask)                             # keep only pixels with no kept edge neighbour
            for r, c in np.argwhere(mask):
                if not ((r and lone[r - 1, c]) or (c and lone[r, c - 1])):
                    lone[r, c] = True
            mask = lone
        mask[0, 0] = mask[-1, -1] = True                           # the window is the whole mask
        assert np.count_nonzero(mask) * pp._LONE_MAX_DENSITY <= mask.size
        expected = reference_keypoint(mask)
        assert largest_cluster(mask) == expected, np.argwhere(mask).tolist()
        lone_only += expected[2] == 1
    assert lone_only >= 20, lone_only


def test_large_windows_more_than_half_active_equal_algorithm_1():
    """Windows over 1024 px that are more than half active skip the search for empty lines (it could
    never squeeze them): labelled as they are, many clusters and ties included."""
    rng = np.random.default_rng(31)
    for density in (0.55, 0.7, 0.85):
        for _ in range(3):
            mask = rng.random((36, 37)) < density
            mask[0, 0] = mask[-1, -1] = True                       # the window is the whole mask
            assert 2 * np.count_nonzero(mask) > mask.size > 1024
            assert largest_cluster(mask) == reference_keypoint(mask), density


def test_squeezing_keeps_one_separator_line():
    mask = np.zeros((60, 60), bool)
    mask[10, 10:13] = True
    mask[12, 10:14] = True                                         # 4 px, one empty row below the 3 px bar
    mask[50, 50] = True                                            # makes the window large
    assert largest_cluster(mask) == (11.5, 12.0, 4)
    mask[11, 11] = True                                            # now all joined: 3 + 1 + 4
    assert largest_cluster(mask) == reference_keypoint(mask)
    assert largest_cluster(mask)[2] == 8


def test_maps_to_keypoints_equals_algorithm_1_on_random_maps():
    """Whole maps, values drawn from a grid that hits the threshold exactly (strict '>')."""
    rng = np.random.default_rng(99)
    levels = np.array([0.0, 0.25, 0.5, 0.5, 0.75, 1.0], np.float32)
    for trial in range(40):
        h, w = rng.integers(1, 15, size=2)
        c = int(rng.integers(2, 6))
        maps = rng.choice(levels, size=(h, w, c))
        # Vary how much of each map is active: scale some maps towards "off".
        maps[..., : c - 1] *= (rng.random(c - 1) < 0.8).astype(np.float32)[None, None] * 0.5 + 0.5
        assert_same(maps_to_keypoints(maps, centroid="plain"), reference_maps_to_keypoints(maps))


def test_realistic_224_maps_equal_algorithm_1():
    """Blobs of radius 6 plus speckles at the model's real size, including touching blobs."""
    rng = np.random.default_rng(7)
    maps = realistic_maps(rng, size=224, num_maps=9, speckles=6)
    assert_same(maps_to_keypoints(maps, centroid="plain"), reference_maps_to_keypoints(maps))


def realistic_maps(rng: np.random.Generator, size: int, num_maps: int, speckles: int) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    maps = np.zeros((size, size, num_maps), np.float32)
    for k in range(num_maps - 1):
        for _ in range(1 + (k % 3 == 0)):                      # some maps get a second blob
            cx, cy = rng.uniform(0, size - 1, 2)
            maps[..., k] = np.maximum(maps[..., k], 1.0 / (1.0 + np.exp(np.hypot(xx - cx, yy - cy) - 6.0)))
        ys, xs = rng.integers(0, size, (2, speckles))
        maps[ys, xs, k] = rng.uniform(0.5, 1.0, speckles)
    maps[..., -1] = rng.random((size, size))                   # skeleton map: ignored
    return maps


# --------------------------------------------------------------------------------------------
# Tie rule, thresholds, edge cases
# --------------------------------------------------------------------------------------------

def test_tie_goes_to_cluster_with_earliest_pixel_in_row_major_order():
    mask = np.zeros((6, 8), bool)
    mask[3:5, 0:2] = True        # square of 4, top-left pixel at row 3
    mask[1, 4:8] = True          # bar of 4, first pixel at row 1: earlier in row-major order
    assert largest_cluster(mask) == (5.5, 1.0, 4)
    mask[1, 4] = False           # now the bar has 3: the square wins
    assert largest_cluster(mask) == (0.5, 3.5, 4)


def test_tie_on_same_top_row_goes_to_the_left_one():
    mask = np.zeros((5, 9), bool)
    mask[0:3, 6] = True          # vertical bar of 3, first pixel (row 0, col 6)
    mask[0, 1:4] = True          # horizontal bar of 3, first pixel (row 0, col 1)
    assert largest_cluster(mask) == (2.0, 0.0, 3)


def test_tie_rule_is_first_pixel_not_bounding_box():
    """Two 11-pixel clusters on the same top row: the L-shaped one reaches further left (bbox
    left 0) but starts later in row-major order, so the block wins."""
    mask = np.zeros((7, 6), bool)
    mask[1:7, 5] = True
    mask[6, 0:5] = True          # L shape: 11 pixels, first pixel (row 1, col 5), bbox left 0
    mask[1:5, 1:4] = True
    mask[4, 1] = False           # block: 11 pixels, first pixel (row 1, col 1), bbox left 1
    assert count_ties(mask) == 1
    assert reference_keypoint(mask) == (23 / 11, 26 / 11, 11)
    assert largest_cluster(mask) == (23 / 11, 26 / 11, 11)


def test_diagonal_neighbours_are_separate_clusters():
    mask = np.eye(5, dtype=bool)            # five pixels touching only by corners
    assert largest_cluster(mask) == (0.0, 0.0, 1)


def test_threshold_is_strict_and_nan_is_inactive():
    maps = np.zeros((4, 4, 2), np.float32)
    maps[1, 1, 0] = 0.5                     # exactly at the threshold: inactive
    maps[2, 2, 0] = np.nan                  # NaN: inactive
    kp, conf = maps_to_keypoints(maps, 0.5, centroid="plain")
    assert np.isnan(kp).all() and conf.tolist() == [0]
    maps[1, 1, 0] = np.nextafter(np.float32(0.5), np.float32(1))
    kp, conf = maps_to_keypoints(maps, 0.5, centroid="plain")
    assert kp.tolist() == [[1.0, 1.0]] and conf.tolist() == [1]


def test_empty_full_and_single_pixel_maps():
    h, w = 7, 5
    maps = np.zeros((h, w, 4), np.float32)
    maps[..., 1] = 1.0                      # full map: one cluster of every pixel
    maps[6, 4, 2] = 1.0                     # single pixel in the last corner
    kp, conf = maps_to_keypoints(maps, centroid="plain")
    assert np.isnan(kp[0]).all() and conf[0] == 0
    assert kp[1].tolist() == [(w - 1) / 2, (h - 1) / 2] and conf[1] == h * w
    assert kp[2].tolist() == [4.0, 6.0] and conf[2] == 1
    assert kp.dtype == np.float64 and conf.dtype == np.int64 and kp.shape == (3, 2) and conf.shape == (3,)


def test_skeleton_map_is_ignored():
    maps = np.zeros((6, 6, 3), np.float32)
    maps[..., 2] = 1.0
    kp, conf = maps_to_keypoints(maps, centroid="plain")
    assert kp.shape == (2, 2) and np.isnan(kp).all() and conf.tolist() == [0, 0]


def test_one_by_one_and_thin_maps():
    assert_same(maps_to_keypoints(np.ones((1, 1, 2)), centroid="plain"), (np.array([[0.0, 0.0]]), np.array([1])))
    row = np.zeros((1, 9, 2)); row[0, [0, 2, 3, 4, 7, 8], 0] = 1
    assert_same(maps_to_keypoints(row, centroid="plain"), (np.array([[3.0, 0.0]]), np.array([3])))
    col = np.transpose(row, (1, 0, 2))
    assert_same(maps_to_keypoints(col, centroid="plain"), (np.array([[0.0, 3.0]]), np.array([3])))


def test_any_dtype_and_layout_gives_the_same_result():
    rng = np.random.default_rng(3)
    maps = realistic_maps(rng, size=32, num_maps=5, speckles=4)
    expected = maps_to_keypoints(maps, centroid="plain")
    assert_same(maps_to_keypoints(maps.astype(np.float64), centroid="plain"), expected)
    assert_same(maps_to_keypoints(maps.astype(np.float16), centroid="plain"), expected)
    fortran = np.asfortranarray(maps)
    assert not fortran.flags.c_contiguous
    assert_same(maps_to_keypoints(fortran, centroid="plain"), expected)
    chw = np.ascontiguousarray(maps.transpose(2, 0, 1))
    assert_same(maps_to_keypoints(chw.transpose(1, 2, 0), centroid="plain"), expected)      # a strided view
    assert_same(maps_to_keypoints(maps > 0.5, threshold=0.5, centroid="plain"), expected)   # bool masks work too


def test_batch_equals_frame_by_frame():
    rng = np.random.default_rng(5)
    batch = np.stack([realistic_maps(rng, 40, 4, 3) for _ in range(3)])
    batch[1, ..., 0] = 0.0                  # a missing keypoint inside the batch
    kp, conf = maps_to_keypoints(batch, centroid="plain")
    assert kp.shape == (3, 3, 2) and conf.shape == (3, 3)
    for j in range(3):
        assert_same((kp[j], conf[j]), maps_to_keypoints(batch[j], centroid="plain"))
    assert np.isnan(kp[1, 0]).all() and conf[1, 0] == 0


def test_logits_threshold_equals_sigmoid_threshold():
    rng = np.random.default_rng(11)
    z = rng.choice(np.array([-6.0, -1.0, -1e-3, 0.0, 1e-3, 1.0, 6.0]), size=(20, 20, 4))
    p = 1.0 / (1.0 + np.exp(-z))
    for t in (0.5, 0.3, 0.9):
        assert_same(maps_to_keypoints(z, t, logits=True, centroid="plain"), maps_to_keypoints(p, t, centroid="plain"))
    assert probability_to_logit(0.5) == 0.0
    assert probability_to_logit(0.9) == pytest.approx(math.log(9))


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.1, 2.0, float("nan")])
def test_logits_need_a_probability_threshold(bad):
    with pytest.raises(UserError, match="strictly between 0 and 1"):
        maps_to_keypoints(np.zeros((4, 4, 2)), bad, logits=True, centroid="plain")


def test_min_size_rejects_small_clusters():
    maps = np.zeros((8, 8, 3))
    maps[0:2, 0:2, 0] = 1                   # 4 pixels
    maps[5, 5, 1] = 1                       # 1 pixel
    kp, conf = maps_to_keypoints(maps, min_size=2, centroid="plain")
    assert kp[0].tolist() == [0.5, 0.5] and conf.tolist() == [4, 0] and np.isnan(kp[1]).all()
    with pytest.raises(UserError, match="min_size"):
        maps_to_keypoints(maps, min_size=0, centroid="plain")


@pytest.mark.parametrize("shape, match", [
    ((4, 4), "H x W x C"),
    ((2, 2, 2, 2, 2), "H x W x C"),
    ((4, 4, 1), "at least 2 maps"),
    ((0, 4, 3), "empty dimension"),
])
def test_bad_shapes_are_user_errors(shape, match):
    with pytest.raises(UserError, match=match):
        maps_to_keypoints(np.zeros(shape), centroid="plain")


def test_bad_dtype_and_mask_shape_are_user_errors():
    with pytest.raises(UserError, match="numeric"):
        maps_to_keypoints(np.zeros((3, 3, 2), complex), centroid="plain")
    with pytest.raises(UserError, match="2-D mask"):
        largest_cluster(np.zeros((3, 3, 3)))


# --------------------------------------------------------------------------------------------
# decode: map pixels -> frame pixels
# --------------------------------------------------------------------------------------------

def test_decode_maps_keypoints_to_frame_pixels():
    rng = np.random.default_rng(2)
    maps = realistic_maps(rng, size=32, num_maps=4, speckles=0)
    frame_shape = (480, 640, 3)
    kp_map, conf = maps_to_keypoints(maps, centroid="plain")
    kp_frame, conf_frame = decode(maps, frame_shape, centroid="plain")
    np.testing.assert_array_equal(kp_frame, keypoints_to_frame(kp_map, frame_shape, 32))
    np.testing.assert_array_equal(conf_frame, conf)
    # Pixel-centre convention: map pixel 0 spans frame pixels 0..19 (640 / 32), centre 9.5.
    one = np.zeros((32, 32, 2)); one[0, 0, 0] = 1
    assert decode(one, frame_shape, centroid="plain")[0].tolist() == [[9.5, 7.0]]
    assert decode(one[None].repeat(2, 0), frame_shape, centroid="plain")[0].shape == (2, 1, 2)


def test_decode_keeps_missing_and_maps_h_by_w_maps_through_their_view():
    from fcnpose_tf.preprocess import FrameView

    kp, conf = decode(np.zeros((16, 16, 3)), (100, 100), centroid="plain")
    assert np.isnan(kp).all() and conf.tolist() == [0, 0]
    maps = np.zeros((16, 8, 2), np.float32)
    maps[3, 5, 0] = 1.0  # row 3, column 5 of a 16 x 8 (H x W) map
    kp, _ = decode(maps, (160, 40), centroid="plain")  # whole frame: 40 wide (5x), 160 high (10x)
    np.testing.assert_allclose(kp[0], [(5 + 0.5) * 5 - 0.5, (3 + 0.5) * 10 - 0.5])
    view = FrameView(16, 8, crop=(10, 20, 16, 32), frame_size=(40, 160))  # a 16 x 32 crop at (10, 20): 2x
    kp, _ = decode(maps, (160, 40), centroid="plain", view=view)
    np.testing.assert_allclose(kp[0], [10 + (5 + 0.5) * 2 - 0.5, 20 + (3 + 0.5) * 2 - 0.5])
    with pytest.raises(UserError, match="do not match"):
        decode(np.zeros((16, 16, 3)), (100, 100), centroid="plain", view=view)
    with pytest.raises(UserError, match="frame shape"):
        decode(np.zeros((16, 16, 3)), (100,), centroid="plain")


def test_docstring_examples():
    assert doctest.testmod(pp, optionflags=doctest.ELLIPSIS).failed == 0


def test_postprocess_imports_no_tensorflow():
    import subprocess
    import sys
    code = ("import sys; import fcnpose_tf.postprocess, fcnpose_tf.metrics; "
            "bad = [m for m in ('tensorflow', 'tf_keras', 'keras') if m in sys.modules]; "
            "sys.exit(1 if bad else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_result_does_not_depend_on_opencv_threads():
    """OpenCV may label in parallel stripes with several threads; the tie rule must not care."""
    import cv2
    rng = np.random.default_rng(13)
    maps = realistic_maps(rng, size=224, num_maps=9, speckles=40)
    maps[..., 3] = rng.random((224, 224)) < 0.5                     # thousands of clusters, ties
    old = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        single = maps_to_keypoints(maps, centroid="plain")
        cv2.setNumThreads(4)
        assert_same(maps_to_keypoints(maps, centroid="plain"), single)
    finally:
        cv2.setNumThreads(old)


def test_benchmark_tool_runs_and_checks_its_variants(tmp_path):
    """Smoke test of tools/bench_postprocess.py on tiny maps (no timing is asserted)."""
    import json
    import subprocess
    import sys
    from pathlib import Path
    tool = Path(__file__).resolve().parents[1] / "tools" / "bench_postprocess.py"
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, str(tool), "--size", "48", "--rounds", "3", "--warmup", "1",
                           "--json", str(out)], capture_output=True, text=True,
                           timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 0, proc.stderr
    assert "library (bbox window)" in proc.stdout and "median µs" in proc.stdout
    report = json.loads(out.read_text())
    assert {r["scenario"] for r in report["results"]} == {"clean", "speckled", "noisy", "empty", "full", "random50"}
    assert report["threads"] == 1 and all(r["median_us"] > 0 for r in report["results"])


# --------------------------------------------------------------------------------------------
# Quantized maps (the int8 export's output) thresholded as integers
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype,scale,zero_point", [
    (np.int8, 1 / 256, -128),     # the int8 export's sigmoid output
    (np.uint8, 1 / 256, 0),
    (np.int8, 0.0047, -3),
    (np.uint8, 1 / 255, 7),
])
@pytest.mark.parametrize("threshold", [0.5, 0.3, 0.5 + 1 / 512, 0.9])
def test_quantized_thresholding_finds_the_keypoints_of_the_dequantized_maps(dtype, scale, zero_point, threshold):
    info = np.iinfo(dtype)
    rng = np.random.default_rng(3)
    raw = rng.integers(info.min, info.max + 1, size=(3, 40, 40, 9)).astype(dtype)
    # blobs and pixels exactly at and one level around the cut, where rounding could differ
    cut = pp.quantized_cut(threshold, scale, zero_point, dtype)
    for level in (cut - 1, cut, cut + 1):
        if info.min <= level <= info.max:
            raw[:, rng.integers(0, 40, 200), rng.integers(0, 40, 200), :] = level
    raw[:, 10:16, 20:25, :] = info.max
    maps = pp.dequantize(raw, scale, zero_point)
    expected = maps_to_keypoints(maps, threshold, centroid="plain")
    got = maps_to_keypoints(raw, threshold, quantization=(scale, zero_point), centroid="plain")
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    frame_kp, frame_conf = decode(raw[0], (480, 640, 3), threshold, quantization=(scale, zero_point), centroid="plain")
    np.testing.assert_array_equal(frame_kp, decode(maps[0], (480, 640, 3), threshold, centroid="plain")[0])


def test_quantized_cut_is_the_last_level_at_or_below_the_threshold():
    assert pp.quantized_cut(0.5, 1 / 256, -128, np.int8) == 0          # (0 + 128) / 256 = 0.5 is not above it
    levels = np.arange(-128, 128).astype(np.int8)
    values = pp.dequantize(levels, 0.01, 5)
    for t in (-5.0, 0.0, 0.333, 1.2, 9.0):
        cut = pp.quantized_cut(t, 0.01, 5, np.int8)
        assert np.array_equal(levels > cut, values > np.float32(t))
    assert pp.quantized_cut(-10.0, 0.01, 5, np.int8) == -129          # every level active
    assert pp.quantized_cut(10.0, 0.01, 5, np.int8) == 127            # none


def test_quantized_maps_must_be_integers():
    with pytest.raises(UserError, match="quantized maps are integers"):
        maps_to_keypoints(np.zeros((4, 4, 2), np.float32), quantization=(1 / 256, -128), centroid="plain")
    with pytest.raises(UserError, match="with logits=True"):
        maps_to_keypoints(np.zeros((4, 4, 2), np.int8), logits=True, quantization=(1 / 256, -128), centroid="plain")


# --------------------------------------------------------------------------------------------
# --fallback: a map with nothing above the threshold is read above a lower one
# --------------------------------------------------------------------------------------------

def reference_with_fallback(maps: np.ndarray, threshold: float, fallback: float) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1 at `threshold`; keypoints it misses, Algorithm 1 at `fallback` (the reference above)."""
    kp, conf = reference_maps_to_keypoints(maps, threshold)
    low_kp, low_conf = reference_maps_to_keypoints(maps, fallback)
    missing = conf == 0
    kp[missing], conf[missing] = low_kp[missing], low_conf[missing]
    return kp, conf


def test_fallback_reads_only_maps_empty_at_the_threshold():
    maps = np.zeros((12, 12, 4), np.float32)
    maps[2:4, 2:4, 0] = 0.9           # found at 0.5; a larger faint cluster must not replace it
    maps[6:11, 6:11, 0] = 0.3
    maps[5:8, 1:3, 1] = 0.3           # nothing above 0.5: the fallback reads this cluster
    maps[0, 11, 1] = 0.25
    maps[..., 2] = 0.1                # below both: still missing
    plain = maps_to_keypoints(maps, centroid="plain")
    kp, conf = maps_to_keypoints(maps, fallback=0.2, centroid="plain")
    assert_same((kp, conf), reference_with_fallback(maps, 0.5, 0.2))
    np.testing.assert_array_equal(kp[0], plain[0][0])
    assert conf[0] == plain[1][0] == 4
    assert np.isnan(plain[0][1]).all() and kp[1].tolist() == [1.5, 6.0] and conf[1] == 6
    assert np.isnan(kp[2]).all() and conf[2] == 0


def test_fallback_equals_the_reference_on_random_maps():
    rng = np.random.default_rng(11)
    for _ in range(20):
        maps = (rng.random((16, 16, 5)) * rng.choice([0.55, 0.8, 1.0], size=5)).astype(np.float32)
        assert_same(maps_to_keypoints(maps, 0.5, fallback=0.3, centroid="plain"),
                    reference_with_fallback(maps, 0.5, 0.3))


def test_fallback_is_the_same_on_logits_and_quantized_maps():
    rng = np.random.default_rng(5)
    raw = rng.integers(-128, 128, size=(2, 24, 24, 6)).astype(np.int8)
    raw[..., :3] //= 4                  # maps that never reach 0.5 (q <= 31 -> at most 0.62; most below)
    raw[0, :, :, 1] = np.minimum(raw[0, :, :, 1], -1)  # strictly below 0.5 everywhere
    probs = pp.dequantize(raw, 1 / 256, -128)
    expected = maps_to_keypoints(probs, 0.5, fallback=0.4, centroid="plain")
    got = maps_to_keypoints(raw, 0.5, quantization=(1 / 256, -128), fallback=0.4, centroid="plain")
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert not np.isnan(expected[0][0, 1]).any()     # found by the fallback only
    with np.errstate(divide="ignore"):  # q = -128 is probability 0: logit -inf, below every cut
        logits = np.log(probs.astype(np.float64)) - np.log1p(-probs.astype(np.float64))
    by_logits = maps_to_keypoints(logits, 0.5, logits=True, fallback=0.4, centroid="plain")
    np.testing.assert_array_equal(by_logits[1], expected[1])


@pytest.mark.parametrize("fallback", [0.5, 0.7, 0.0, -0.1, float("nan")])
def test_fallback_must_be_between_zero_and_the_threshold(fallback):
    with pytest.raises(UserError, match="fallback threshold must be above 0 and below the threshold 0.5"):
        maps_to_keypoints(np.zeros((4, 4, 2), np.float32), 0.5, fallback=fallback, centroid="plain")


# --------------------------------------------------------------------------------------------
# --centroid weighted: Algorithm 1's cluster, its pixels weighted by (p - threshold)^2
# --------------------------------------------------------------------------------------------

def reference_weighted(maps: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Algorithm 1's cluster (the reference above: its size and plain centroid identify it), read as the
    (p - threshold)^2-weighted mean of its pixel indices, by brute force."""
    kp, conf = reference_maps_to_keypoints(maps, threshold)
    out = np.full_like(kp, np.nan)
    for k in range(maps.shape[-1] - 1):
        if conf[k] == 0:
            continue
        import cv2

        n, labels = cv2.connectedComponents((maps[..., k] > threshold).astype(np.uint8), connectivity=4)
        for label in range(1, n):
            rows, cols = np.nonzero(labels == label)
            if len(rows) == conf[k] and np.allclose([cols.mean(), rows.mean()], kp[k]):
                w = (maps[rows, cols, k].astype(np.float64) - threshold) ** 2
                out[k] = [cols @ w / w.sum(), rows @ w / w.sum()]
                break
    return out


def test_weighted_centroid_leans_to_the_sure_pixels_of_the_same_cluster():
    maps = np.zeros((6, 8, 3), np.float32)
    maps[2, 1:4, 0] = [0.6, 0.6, 1.0]        # weights 0.01, 0.01, 0.25
    maps[4, 6, 0] = 0.99                     # a smaller, surer cluster: not chosen
    maps[1:3, 5:7, 1] = 0.8                  # even values: the plain centroid
    kp, conf = maps_to_keypoints(maps, centroid="weighted")
    plain, plain_conf = maps_to_keypoints(maps, centroid="plain")
    np.testing.assert_array_equal(conf, plain_conf)
    assert kp[0].tolist() == pytest.approx([(1 * 0.01 + 2 * 0.01 + 3 * 0.25) / 0.27, 2.0])
    assert plain[0].tolist() == [2.0, 2.0]
    np.testing.assert_array_equal(kp[1], plain[1])
    assert maps_to_keypoints(maps[..., 1:], centroid="weighted")[1][0] == 4  # a missing map stays missing
    assert np.isnan(maps_to_keypoints(np.zeros((4, 4, 2), np.float32), centroid="weighted")[0]).all()


def test_weighted_centroid_equals_the_reference_on_random_maps():
    rng = np.random.default_rng(3)
    for _ in range(20):
        maps = (rng.random((16, 16, 5)) * rng.choice([0.55, 0.8, 1.0], size=5)).astype(np.float32)
        kp, _ = maps_to_keypoints(maps, centroid="weighted")
        np.testing.assert_allclose(kp, reference_weighted(maps), atol=1e-9)
    # far-apart blobs in a large window (its empty lines squeezed out before labelling), uneven values
    for _ in range(10):
        maps = np.zeros((64, 64, 4), np.float32)
        for k in range(3):
            for _ in range(rng.integers(1, 4)):
                y, x, size = rng.integers(0, 58), rng.integers(0, 58), rng.integers(1, 6)
                maps[y:y + size, x:x + size, k] = rng.uniform(0.51, 1.0, (size, size))
        kp, _ = maps_to_keypoints(maps, centroid="weighted")
        np.testing.assert_allclose(kp, reference_weighted(maps), atol=1e-9)
    # a cluster that fills the window around a map's active pixels (read from the window's slices)
    maps = np.zeros((40, 48, 3), np.float32)
    maps[5:30, 7:44, 0] = rng.uniform(0.51, 1.0, (25, 37))
    maps[..., 1] = rng.uniform(0.51, 1.0, (40, 48))
    kp, _ = maps_to_keypoints(maps, centroid="weighted")
    np.testing.assert_allclose(kp, reference_weighted(maps), atol=1e-9)


def test_weighted_centroid_is_the_same_on_logits_quantized_maps_and_after_a_fallback():
    rng = np.random.default_rng(8)
    raw = rng.integers(-128, 128, size=(2, 24, 24, 6)).astype(np.int8)
    probs = pp.dequantize(raw, 1 / 256, -128)
    expected, _ = maps_to_keypoints(probs, 0.5, centroid="weighted")
    got, _ = maps_to_keypoints(raw, 0.5, quantization=(1 / 256, -128), centroid="weighted")
    np.testing.assert_allclose(got, expected, atol=1e-6)
    with np.errstate(divide="ignore"):
        logits = np.log(probs.astype(np.float64)) - np.log1p(-probs.astype(np.float64))
    by_logits, _ = maps_to_keypoints(logits, 0.5, logits=True, centroid="weighted")
    np.testing.assert_allclose(by_logits, expected, atol=1e-6)
    faint = np.zeros((8, 8, 2), np.float32)
    faint[3, 2:5, 0] = [0.3, 0.3, 0.45]      # only the fallback finds it; weights (p - 0.2)^2
    kp, conf = maps_to_keypoints(faint, fallback=0.2, centroid="weighted")
    assert conf[0] == 3 and kp[0].tolist() == pytest.approx([(2 * .01 + 3 * .01 + 4 * .0625) / .0825, 3.0])


def test_decode_takes_the_centroid_and_refuses_an_unknown_one():
    maps = np.zeros((4, 4, 2), np.float32)
    maps[1, 1:3, 0] = [0.6, 0.9]
    kp, _ = decode(maps, (8, 8, 3), centroid="weighted")
    assert kp[0, 0] > decode(maps, (8, 8, 3), centroid="plain")[0][0, 0]
    with pytest.raises(UserError, match="centroid must be one of weighted, plain, got 'middle'"):
        maps_to_keypoints(maps, centroid="middle")
    assert pp.Decoding().describe().endswith("its centroid weighted by (p - 0.5)^2)")


def test_one_decoding_object_checks_its_values_and_reads_as_the_functions_do():
    with pytest.raises(UserError, match="threshold must be between 0 and 1"):
        pp.Decoding(threshold=1.0)
    with pytest.raises(UserError, match="fallback threshold must be above 0 and below the threshold 0.5"):
        pp.Decoding(fallback=0.6)
    with pytest.raises(UserError, match="centroid must be one of"):
        pp.Decoding(centroid="middle")
    maps = np.zeros((4, 4, 2), np.float32)
    maps[1, 1:3, 0] = [0.3, 0.4]  # nothing above 0.5: only the fallback finds it
    decoding = pp.Decoding(fallback=0.2, centroid="plain")
    assert decoding.to_json() == {"threshold": 0.5, "fallback": 0.2, "centroid": "plain", "cluster": "largest"}
    assert "above 0.2 (--fallback)" in decoding.describe()
    kp, conf = decoding.keypoints(maps)
    np.testing.assert_array_equal(kp, maps_to_keypoints(maps, 0.5, fallback=0.2, centroid="plain")[0])
    assert conf[0] == 2 and np.isnan(pp.Decoding().keypoints(maps)[0][0]).all()
    in_frame, _ = decoding.in_frame(maps, (8, 8, 3))
    np.testing.assert_array_equal(in_frame, decode(maps, (8, 8, 3), fallback=0.2, centroid="plain")[0])


# --------------------------------------------------------------------------------------------
# The chained choice among a map's clusters (cluster="chain")
# --------------------------------------------------------------------------------------------

def _blob(plane: np.ndarray, x: float, y: float, radius: float, peak: float = 0.95) -> None:
    yy, xx = np.mgrid[:plane.shape[0], :plane.shape[1]]
    inside = np.hypot(xx - x, yy - y) <= radius
    plane[inside] = np.maximum(plane[inside], peak - 0.3 * np.hypot(xx - x, yy - y)[inside] / max(radius, 1))


def _segment(plane: np.ndarray, a: tuple, b: tuple, width: float) -> None:
    yy, xx = np.mgrid[:plane.shape[0], :plane.shape[1]]
    d = np.subtract(b, a, dtype=float)
    t = np.clip(((xx - a[0]) * d[0] + (yy - a[1]) * d[1]) / (d @ d), 0, 1)
    plane[np.hypot(xx - a[0] - t * d[0], yy - a[1] - t * d[1]) <= width / 2] = 0.9


def _arm(points: list[tuple], size: int = 96) -> np.ndarray:
    """Maps with one blob per keypoint at `points` and the skeleton drawn between consecutive ones."""
    maps = np.zeros((size, size, len(points) + 1), np.float32)
    for k, (x, y) in enumerate(points):
        _blob(maps[..., k], x, y, 3)
    for a, b in zip(points, points[1:]):
        _segment(maps[..., -1], a, b, 6)
    return maps


def test_the_chain_agrees_with_the_largest_cluster_where_every_map_holds_one():
    """One cluster per map (or none): the chain has nothing to choose, and reads what Algorithm 1 reads, with either
    centroid, on probabilities, logits and quantized maps, with a fallback, in a batch."""
    rng = np.random.default_rng(21)
    for _ in range(6):
        points = [tuple(rng.uniform(6, 90, 2)) for _ in range(8)]
        maps = _arm(points)
        maps[..., 3] = 0.0  # a missing keypoint splits the chain
        for centroid in CENTROIDS_ALL:
            np.testing.assert_allclose(maps_to_keypoints(maps, centroid=centroid, cluster="chain")[0],
                                       maps_to_keypoints(maps, centroid=centroid)[0], atol=1e-9)
        assert (maps_to_keypoints(maps, cluster="chain")[1] == maps_to_keypoints(maps)[1]).all()
    raw = np.clip(np.rint(maps * 256) - 128, -128, 127).astype(np.int8)
    probs = pp.dequantize(raw, 1 / 256, -128)
    quantized = maps_to_keypoints(raw, quantization=(1 / 256, -128), cluster="chain")[0]
    np.testing.assert_allclose(quantized, maps_to_keypoints(probs)[0], atol=1e-6)
    with np.errstate(divide="ignore"):
        logits = np.log(probs.astype(np.float64)) - np.log1p(-probs.astype(np.float64))
    np.testing.assert_allclose(maps_to_keypoints(logits, logits=True, cluster="chain")[0],
                               maps_to_keypoints(probs)[0], atol=1e-6)
    faint = maps * np.where(np.arange(9) == 5, 0.4, 1.0).astype(np.float32)  # map 5 only above a fallback
    np.testing.assert_allclose(maps_to_keypoints(faint, fallback=0.2, cluster="chain")[0],
                               maps_to_keypoints(faint, fallback=0.2)[0], atol=1e-9)
    batch = np.stack([maps, faint])
    np.testing.assert_allclose(maps_to_keypoints(batch, cluster="chain")[0][1], maps_to_keypoints(faint)[0])
    # two clusters the skeleton joins alike (a generic chain: no limb lengths): the larger, as Algorithm 1
    line = _arm([(10, 48), (48, 48), (86, 48)])
    line[..., 1] = 0.0
    _blob(line[..., 1], 30, 48, 3)
    _blob(line[..., 1], 66, 48, 4)
    for centroid in CENTROIDS_ALL:
        chosen = maps_to_keypoints(line, centroid=centroid, cluster="chain")
        assert chosen[0][1] == pytest.approx([66, 48], abs=0.5)
        np.testing.assert_allclose(chosen[0], maps_to_keypoints(line, centroid=centroid)[0], atol=1e-9)


CENTROIDS_ALL = pp.CENTROIDS


def test_the_chain_takes_the_cluster_the_skeleton_joins_to_its_neighbours_over_a_larger_stray_one():
    """A generic chain (5 keypoints: no limb lengths): the elbow's larger cluster lies off the arm, its smaller
    one on the skeleton between its neighbours; Algorithm 1 takes the larger, the chain the joined one."""
    points = [(10, 80), (20, 60), (30, 40), (40, 20), (50, 10)]
    maps = _arm(points)
    _blob(maps[..., 2], 80, 80, 5)  # a stray cluster, larger than the elbow's own
    largest, _ = maps_to_keypoints(maps, centroid="plain")
    chained, conf = maps_to_keypoints(maps, centroid="plain", cluster="chain")
    assert largest[2] == pytest.approx([80, 80], abs=0.5)
    assert chained[2] == pytest.approx(points[2], abs=0.5) and conf[2] < maps_to_keypoints(maps)[1][2]
    np.testing.assert_allclose(np.delete(chained, 2, 0), np.delete(largest, 2, 0))


def test_the_chain_weighs_the_ur5s_limb_lengths_where_the_skeleton_cannot_tell():
    """The UR5's 8 keypoints on a straight arm whose limbs have `UR5_LIMBS`' mean lengths; wrist 2 has a second,
    larger cluster on the same line (up the arm, where the skeleton joins it to wrist 1 and 3 as well) at lengths the
    prior finds unlikely: the chain keeps the one at the right distance; through a view that stretched the frame
    (`decode`'s pixel scale) it reads the same."""
    from fcnpose_tf.keypoints import UR5_LIMBS

    lengths = np.exp(UR5_LIMBS.mean)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    side = 80.0 / along[-1]  # the box's side: the arm from end to end, 80 px
    points = [(8 + side * a, 48.0) for a in along]
    maps = _arm(points)
    wrong = ((points[1][0] + points[2][0]) / 2, 48.0)  # between the shoulder and the elbow: on the skeleton too
    _blob(maps[..., 4], *wrong, 4)
    largest, _ = maps_to_keypoints(maps, centroid="plain")
    chained, _ = maps_to_keypoints(maps, centroid="plain", cluster="chain")
    assert largest[4] == pytest.approx(wrong, abs=0.6)
    assert chained[4] == pytest.approx(points[4], abs=0.6)
    # the same frame through a view that stretched it 2x across: lengths measured in the frame's proportions agree
    in_frame, _ = decode(maps, (96, 192, 3), centroid="plain", cluster="chain")
    assert in_frame[4] == pytest.approx(keypoints_to_frame(chained, (96, 192, 3), 96)[4], abs=1e-9)
    # another robot's 8 keypoints: UR5's lengths say nothing of its limbs (the skeleton decides alone, as for any
    # other count), and a skeleton that is no serial chain is refused
    from fcnpose_tf.keypoints import UR5, KeypointSchema

    other = KeypointSchema.chain("arm8", [f"j{i}" for i in range(8)])
    unweighted, _ = maps_to_keypoints(maps, centroid="plain", cluster="chain", schema=other)
    assert unweighted[4] == pytest.approx(largest[4], abs=0.6)  # the larger cluster, both on the skeleton
    tree = KeypointSchema("tree", other.keypoints, ((0, 1), (1, 2), (1, 3), (3, 4), (4, 5), (5, 6), (6, 7)))
    with pytest.raises(UserError, match="the skeleton of schema 'tree' is not one: use --cluster largest"):
        maps_to_keypoints(maps, cluster="chain", schema=tree)
    backwards = KeypointSchema("back", other.keypoints, tuple((i + 1, i) for i in range(7)))  # the same chain
    np.testing.assert_array_equal(maps_to_keypoints(maps, centroid="plain", cluster="chain", schema=backwards)[0],
                                  unweighted)
    assert maps_to_keypoints(maps, cluster="chain", schema=UR5)[0][4] == pytest.approx(points[4], abs=0.6)


def test_the_cluster_choice_is_checked_and_travels_in_the_decoding():
    maps = _arm([(10, 10), (40, 40)])
    with pytest.raises(UserError, match="cluster must be one of largest, chain, got 'best'"):
        maps_to_keypoints(maps, cluster="best")
    with pytest.raises(UserError, match="cluster must be one of"):
        pp.Decoding(cluster="best")
    decoding = pp.Decoding(cluster="chain")
    assert decoding.to_json()["cluster"] == "chain" and decoding.describe().startswith("clusters above 0.5 chained")
    np.testing.assert_array_equal(decoding.keypoints(maps)[0], maps_to_keypoints(maps, cluster="chain")[0])


def test_limb_priors_are_read_from_labels_and_pooled():
    from fcnpose_tf.keypoints import LimbPrior

    kps = np.array([[[0, 0], [3, 4], [3, 14]], [[0, 0], [6, 8], [6, 18]], [[0, 0], [np.nan, np.nan], [1, 1]]], float)
    prior = LimbPrior.of(kps)  # box sides 10 and 14; the third frame has no limb
    assert prior.mean == pytest.approx([(np.log(5 / 14) + np.log(10 / 18)) / 2, (np.log(10 / 14) + np.log(10 / 18)) / 2])
    assert prior.sd == pytest.approx([abs(np.log(5 / 14) - np.log(10 / 18)) / 2, abs(np.log(10 / 14) - np.log(10 / 18)) / 2])
    pooled = LimbPrior.pooled([LimbPrior((0.0, -1.0), (0.3, 0.4)), LimbPrior((-1.0, -1.0), (0.5, 0.4))])
    assert pooled.mean == (-0.5, -1.0) and pooled.sd == pytest.approx([math.sqrt(0.17 + 0.25), 0.4])
    with pytest.raises(UserError, match="at least 2 frames"):
        LimbPrior.of(kps[2:])
