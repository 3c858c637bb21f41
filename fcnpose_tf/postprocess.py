"""From FCN-Pose's output maps to keypoints: the paper's Expansion Clustering (Algorithm 1). numpy + OpenCV only.

The network emits C maps per frame, H x W x C: one map per keypoint, then the skeleton map (ignored
here). Each keypoint map is thresholded; the active pixels are grouped by Algorithm 1 with M = 1
(a pixel joins a cluster when it lies within Euclidean distance 1 of one of its pixels, i.e.
4-connectivity on the pixel grid); the cluster with the most pixels wins and its centroid is the
keypoint, its pixel count the confidence.

Rules (see docs/postprocess.md):

- **Active pixel**: ``value > threshold`` (strictly). A map that sits exactly at the threshold --
  for instance an untrained network's sigmoid(0) = 0.5 everywhere -- yields nothing, and
  ``logit > 0`` is the same test as ``sigmoid > 0.5``. NaN values are never active.
- **Ties**: among clusters of equal, largest size the one created first by Algorithm 1 wins. The
  set of points is scanned in row-major order (y, then x), so that is the cluster holding the
  earliest pixel in row-major order.
- **Missing**: no active pixel (or a largest cluster smaller than ``min_size``) gives NaN
  coordinates and confidence 0, never an exception.
- **Coordinates**: (x, y) in map pixels with the pixel-centre convention (pixel (i, j) has its
  centre at x = j, y = i), so the centroid is the mean of the cluster's pixel indices.
  :func:`decode` maps them to frame pixels with :func:`fcnpose_tf.preprocess.keypoints_to_frame`.
- **Weighted centroid** (``centroid="weighted"``, not the paper's): the same cluster, its position the mean
  of its pixel indices weighted by (p - threshold)^2, p the pixel's probability (a logit's sigmoid, a
  quantized value dequantized): the sure middle of a blob counts more than its rim. Measured against the
  plain centroid on held-out looks at 288-384 px (docs/postprocess.md): PCK@0.05 +0.02-0.04, the rest
  unchanged.
- **Chained choice** (``cluster="chain"``, not the paper's): instead of each map's largest cluster, one cluster per
  map chosen jointly along the arm's chain (`_chain`: cluster sizes, the skeleton map between neighbours, the UR5's
  limb lengths); the same keypoints where every map holds one cluster. PCK@0.5 +0.01-0.03 on held-out looks, about
  1 ms more a frame (docs/postprocess.md, "`--cluster chain`").

How it stays under a millisecond per 224 x 224 frame of 8 maps: all maps are thresholded in one
contiguous pass (numpy is ~9x slower on a strided per-map slice), de-interleaved with one
``cv2.transpose``, and each map is labelled by ``cv2.connectedComponents`` only inside the bounding
box of its active pixels (``cv2.boundingRect``); in a big, sparse box the lone pixels (no active
edge neighbour: clusters of one, the largest only when every cluster is) are dropped first (one
``cv2.dilate``), and the empty rows and columns between far-apart active pixels squeezed out.
OpenCV's own statistics are not used: they cost per pixel of the labelled area, background
included; cluster sizes come from the labels (of the active pixels only when the window is
sparse), the centroid from exact integer sums of the kept cluster's pixel coordinates (read from
the labels; ``cv2.moments`` of the window when it holds one cluster), a fully active window's in
closed form. Labelling itself is the floor: on coin-flip maps (thousands of clusters per map) it
is ~70 % of the frame (docs/postprocess.md, section 4).
``tools/bench_postprocess.py`` measures this against the plain per-map
``cv2.connectedComponentsWithStats``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from fcnpose_tf import settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, UR5_LIMBS, KeypointSchema, LimbPrior, schema_for_maps
from fcnpose_tf.preprocess import FrameView, keypoints_to_frame

__all__ = ["maps_to_keypoints", "decode", "check_fallback", "check_centroid", "Decoding",
           "largest_cluster", "probability_to_logit", "dequantize", "quantized_cut", "CENTROIDS", "CLUSTERS"]

CENTROIDS = settings.CENTROID.choices
"""How a keypoint's position is read from its cluster: the plain mean of its pixels (Algorithm 1) or weighted
by (p - threshold)^2."""
CLUSTERS = settings.CLUSTER.choices
"""Which of a map's clusters is the keypoint: the largest (Algorithm 1) or the one the chain chooses (`_chain`)."""
SUPPORT_WEIGHT = 4.0
"""The chain's weight of log(skeleton support) between two consecutive clusters against log(size / the map's largest
size) of each (docs/postprocess.md, "`--cluster chain`": 1 and 4 measured, 4 no worse anywhere)."""
LENGTH_WEIGHT = 0.25
"""The chain's weight of a limb's squared z-score (its log length against `keypoints.UR5_LIMBS`), halved."""
SUPPORT_FLOOR = 0.02
"""The least skeleton support a pair is scored at: log(0) would forbid a pair the skeleton map misses."""
SUPPORT_SAMPLES = 16
"""Points of the skeleton map read along the segment between two clusters."""


def probability_to_logit(threshold: float) -> float:
    """The logit z with sigmoid(z) = threshold, for thresholding pre-sigmoid maps.

    Args:
        threshold: a probability strictly between 0 and 1.

    Returns:
        log(threshold / (1 - threshold)); 0.0 for 0.5.

    Example:
        >>> probability_to_logit(0.5)
        0.0
    """
    t = float(threshold)
    if not 0.0 < t < 1.0:
        raise UserError(f"threshold for logit maps must be a probability strictly between 0 and 1, got {threshold!r}")
    return math.log(t) - math.log1p(-t)


def dequantize(values: np.ndarray, scale: float, zero_point: int, out: np.ndarray | None = None) -> np.ndarray:
    """Real values of affine-quantized integers: (q - zero_point) * scale, in float32.

    The one dequantization of maps in this package (the runtime's `read_maps`, the exporter's
    check), so that `quantized_cut` finds exactly the pixels thresholding these values finds.
    """
    out = np.subtract(values, zero_point, out=out, dtype=np.float32)
    out *= np.float32(scale)
    return out


@functools.lru_cache(maxsize=64)  # a runtime asks for the same cut every frame
def quantized_cut(threshold: float, scale: float, zero_point: int, dtype: np.dtype | type) -> int:
    """The integer cut for thresholding quantized maps without dequantizing them.

    ``q > quantized_cut(t, scale, zp, dtype)`` selects exactly the integers q whose
    `dequantize` (float32) value is ``> t``: every level of the dtype is dequantized and compared,
    so float rounding at the threshold cannot make the two tests differ.

    Args:
        threshold: the probability threshold (strict: a pixel is active above it).
        scale, zero_point: the maps' affine quantization (scale > 0).
        dtype: the maps' integer type (int8 or uint8).
    Returns:
        The largest level that is not active (the type's minimum - 1 when every level is active).
    Example:
        >>> quantized_cut(0.5, 1 / 256, -128, np.int8)   # the int8 sigmoid output: q > 0 is above 0.5
        0
    """
    info = np.iinfo(dtype)
    if not scale > 0:
        raise UserError(f"quantized maps need a positive scale, got {scale!r}")
    levels = np.arange(info.min, info.max + 1, dtype=np.int64).astype(dtype)
    inactive = np.flatnonzero(~(dequantize(levels, scale, zero_point) > _cut(threshold, False)))
    return int(info.min) - 1 if inactive.size == 0 else int(levels[inactive[-1]])


def largest_cluster(mask: np.ndarray, min_size: int = 1) -> tuple[float, float, int]:
    """Algorithm 1 (M = 1) on one binary mask: centroid and size of the largest cluster.

    Args:
        mask: H x W array; nonzero pixels are the active points.
        min_size: a largest cluster with fewer pixels than this counts as missing.

    Returns:
        (x, y, size): the centroid in pixel indices (x = column, y = row) and the pixel count of
        the largest 4-connected cluster, ties going to the cluster with the earliest pixel in
        row-major order; (nan, nan, 0) when there is none.

    Example:
        >>> m = np.zeros((4, 6), np.uint8); m[1, 1:4] = 1; m[3, 5] = 1
        >>> largest_cluster(m)
        (2.0, 1.0, 3)
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise UserError(f"expected a 2-D mask, got shape {mask.shape}")
    plane = np.ascontiguousarray(mask != 0).view(np.uint8)
    return _largest_cluster(plane, int(min_size))


_SQUEEZE_MIN_AREA = 1024
"""Windows larger than this (a 6 px disc fits in 13 x 13) are checked for empty rows/columns."""


def _squeeze_index(occupied: np.ndarray) -> np.ndarray:
    """Lines to keep along one axis: each occupied line and the first empty line after each run.

    Occupied lines that were adjacent stay adjacent and separated ones stay separated, so
    4-connectivity, every cluster's size and the row-major order of the pixels are unchanged.
    """
    keep = occupied.copy()
    keep[1:] |= occupied[:-1]
    return np.flatnonzero(keep)


_LONE_MAX_DENSITY = 8
"""Lone pixels are looked for in windows (larger than _SQUEEZE_MIN_AREA) where at most 1 pixel in this many is active:
one `cv2.dilate` and `cv2.bitwise_and`, ~30 us on a 224 x 224 window on one slow core, against ~150 us of squeezing
and labelling the speckles they remove; a dense window (a coin-flip map) would pay it for nothing."""

_EDGE_NEIGHBOURS = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.uint8)
"""Algorithm 1's neighbourhood with M = 1 (the four edge neighbours, not the pixel itself), as a `cv2.dilate` kernel:
its dilation of a mask marks the pixels that have an active neighbour."""


_LABELS_16U_MAX_AREA = 131068
"""Windows up to this many pixels are labelled as uint16 (4-connected clusters <= area / 2 + 1 <= 65535 labels):
half the label memory of int32, and counted by `cv2.calcHist` instead of `np.bincount` (which widens to int64)."""


_CALCHIST_MIN_AREA = 4096
"""From this many labels on, `cv2.calcHist` counts uint16 labels faster than `np.bincount` (on a few hundred its
set-up costs more than the count)."""


def _centroid(size: int, sum_x: int, sum_y: int, x0: int, y0: int, min_size: int) -> tuple[float, float, int]:
    """(x, y, size) from exact integer sums in window coordinates: one division per axis, so the result is
    bit-identical to sum(x) / n over the cluster's pixels in map coordinates."""
    if size < min_size:
        return math.nan, math.nan, 0
    return (sum_x + x0 * size) / size, (sum_y + y0 * size) / size, size


def _largest_cluster(plane: np.ndarray, min_size: int, pixels: list | None = None) -> tuple[float, float, int]:
    """Largest 4-connected cluster of a C-contiguous 0/1 uint8 plane (see largest_cluster). With a list as
    `pixels`, the kept cluster is appended to it, for a weighted centroid: as its (rows, cols) index arrays in map
    coordinates, or, where it is every active pixel of their window, as (y0, x0, h, w, mask), the window and its
    active pixels (an h x w array, nonzero on them; None: all of it)."""
    x0, y0, w, h = cv2.boundingRect(plane)
    if w == 0:
        return math.nan, math.nan, 0
    # Label only the window around the active pixels: the cost follows where the activity is,
    # not the map size. Raster order inside the window is the map's raster order.
    win = plane[y0:y0 + h, x0:x0 + w]
    if w != plane.shape[1]:
        win = np.ascontiguousarray(win)
    active = cv2.countNonZero(win)
    if active * _LONE_MAX_DENSITY <= w * h and w * h > _SQUEEZE_MIN_AREA:
        # A big window with few active pixels: a blob and far-off speckles, most of them lone pixels (no active
        # edge neighbour). A lone pixel is a cluster of one, the largest only when every cluster is; the others
        # keep their pixels and raster order without them. So drop them and label the (tighter) window of the rest.
        paired = cv2.bitwise_and(win, cv2.dilate(win, _EDGE_NEIGHBOURS, borderType=cv2.BORDER_CONSTANT,
                                                 borderValue=0))
        in_pairs = cv2.countNonZero(paired)
        if in_pairs == 0:  # every cluster is one pixel: the tie rule keeps the first in raster order
            col, row = (int(v) for v in cv2.findNonZero(win).reshape(-1, 2)[0])
            if pixels is not None:
                pixels.append((np.array([row + y0]), np.array([col + x0])))
            return _centroid(1, col, row, x0, y0, min_size)
        if in_pairs < active:
            dx, dy, w, h = cv2.boundingRect(paired)
            win = np.ascontiguousarray(paired[dy:dy + h, dx:dx + w])
            x0, y0, active = x0 + dx, y0 + dy, in_pairs
    if active == w * h:  # every pixel of the window active: one cluster, the rectangle's centre
        if pixels is not None:
            pixels.append((y0, x0, h, w, None))
        return _centroid(active, h * (w * (w - 1) // 2), w * (h * (h - 1) // 2), x0, y0, min_size)
    img, xs, ys = win, None, None
    if 2 * active <= w * h and w * h > _SQUEEZE_MIN_AREA:
        # A blob plus far-off speckles gives a big, mostly empty window: drop the empty rows and
        # columns between them (keeping one as a separator) before labelling. It is squeezed only when
        # the grid of kept lines is at most half the window, and that grid holds every active pixel,
        # so a window more than half active never is: a lone blob's (a disc fills ~3/4 of its
        # bounding box) skips the search for empty lines.
        # (REDUCE_SUM to int32 is vectorised in OpenCV; REDUCE_MAX on uint8 rows is ~50x slower.)
        row_sums = cv2.reduce(win, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S)
        col_sums = cv2.reduce(win, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)
        if cv2.countNonZero(row_sums) < h or cv2.countNonZero(col_sums) < w:  # some line is empty
            ys = _squeeze_index(row_sums.ravel() != 0)
            xs = _squeeze_index(col_sums.ravel() != 0)
            if 2 * ys.size * xs.size <= w * h:
                img = np.ascontiguousarray(win[ys][:, xs])
            else:
                xs = ys = None
    small = img.size <= _LABELS_16U_MAX_AREA
    n, labels = cv2.connectedComponents(img, connectivity=4, ltype=cv2.CV_16U if small else cv2.CV_32S)
    if n > 2:  # several clusters (else the one cluster is every active pixel: its moments below)
        sparse = active * 8 <= img.size
        if sparse:
            # Look at the active pixels only (findNonZero scans in raster order).
            pts = cv2.findNonZero(img).reshape(-1, 2)
            lab = labels[pts[:, 1], pts[:, 0]]
            counts = np.bincount(lab, minlength=n)
        else:
            lab = labels.ravel()
            if small and img.size >= _CALCHIST_MIN_AREA:  # float32 counts, exact below 2**24
                counts = cv2.calcHist([labels], [0], None, [n], [0, n]).ravel().astype(np.int64)
            else:
                counts = np.bincount(lab, minlength=n)
        counts[0] = 0  # the background (absent from a sparse count)
        best = int(counts.argmax())
        tied = counts == counts[best]
        if np.count_nonzero(tied) > 1:
            # Tie rule: the cluster holding the earliest pixel in row-major order, which is the
            # one Algorithm 1 creates first when it scans S in that order. (OpenCV numbers
            # labels in that order when single-threaded; we do not rely on it.)
            best = int(lab[np.argmax(tied[lab])])
        # The kept cluster's pixels straight from the labels: exact integer sums of their columns and
        # rows (raster indices divided by the image's width; through xs and ys back to the window's
        # lines when it was squeezed), no pass over a mask image.
        if sparse:
            mine = pts[lab == best]
            cols, rows = mine[:, 0], mine[:, 1]
        else:
            rows, cols = np.divmod(np.flatnonzero(lab == best), img.shape[1])
        if xs is not None:
            cols, rows = xs[cols], ys[rows]
        if pixels is not None:
            pixels.append((rows + y0, cols + x0))
        return _centroid(len(cols), int(cols.sum()), int(rows.sum()), x0, y0, min_size)
    if pixels is not None:  # one cluster: every active pixel of the (unsqueezed) window
        pixels.append((y0, x0, h, w, win))
    if xs is None:
        # Window coordinates are map coordinates minus (x0, y0). The binary image moments are
        # exact integers (pixel count, sums of column and row indices), so one division gives a
        # result bit-identical to sum(x) / n over the cluster's pixels, in one OpenCV call.
        m = cv2.moments(img, True)
        return _centroid(int(m["m00"]), int(m["m10"]), int(m["m01"]), x0, y0, min_size)
    # Centroid from per-column and per-row pixel counts of the squeezed image, at the columns and rows
    # they came from: exact integer sums, one division.
    cols = cv2.reduce(img, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.int64)
    rows = cv2.reduce(img, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.int64)
    size = int(cols.sum())
    return _centroid(size, int(cols @ xs.astype(np.int64)), int(rows @ ys.astype(np.int64)), x0, y0, min_size)


def _check_maps(maps: np.ndarray) -> np.ndarray:
    arr = np.asarray(maps)
    if arr.ndim not in (3, 4):
        raise UserError(f"expected maps of shape H x W x C or N x H x W x C, got shape {arr.shape}")
    if arr.shape[-1] < 2:
        raise UserError(f"expected at least 2 maps (keypoint maps, then the skeleton map), got {arr.shape[-1]}")
    if 0 in arr.shape[:-1]:
        raise UserError(f"maps have an empty dimension: shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
            or arr.dtype == np.bool_):
        raise UserError(f"expected numeric maps, got dtype {arr.dtype}")
    return arr


def _cut(threshold: float, logits: bool) -> float:
    if logits:
        return probability_to_logit(threshold)
    t = float(threshold)
    if math.isnan(t):
        raise UserError("threshold must be a number, got nan")
    return t


def _weighted_centroid(values: np.ndarray, cluster: tuple, weights, level: int, x: float,
                       y: float) -> tuple[float, float]:
    """The cluster's pixel indices averaged with `weights(p, level)` of its map `values` (H x W); (x, y), its
    plain centroid, where the weights sum to zero. `cluster` is what `_largest_cluster` appended to `pixels`."""
    if len(cluster) == 2:  # index arrays: the cluster is a small part of its window
        rows, cols = cluster
        weight = weights(values[rows, cols], level)
        total = weight.sum()
        if not total > 0:
            return x, y
        # Elementwise products, not `@`: a dot goes to BLAS, whose threads wait for busy cores
        return float((cols * weight).sum() / total), float((rows * weight).sum() / total)
    y0, x0, h, w, mask = cluster
    image = weights(values[y0:y0 + h, x0:x0 + w], level)  # float64, h x w
    if mask is not None:
        image *= mask
    m = cv2.moments(image)  # float64 moments: the weights' sum, and their sums times the column and row indices
    if not m["m00"] > 0:
        return x, y
    return x0 + m["m10"] / m["m00"], y0 + m["m01"] / m["m00"]


def _frame_keypoints(maps3: np.ndarray, cut: float, min_size: int,
                     out_kp: np.ndarray, out_conf: np.ndarray, fallback_cut: float | None = None,
                     weights=None) -> None:
    h, w, c = maps3.shape
    k = c - 1
    # One contiguous comparison over all maps, then one transpose to K planes: far cheaper
    # than comparing each strided channel slice (see tools/bench_postprocess.py).
    maps3 = np.ascontiguousarray(maps3)
    active = np.greater(maps3, cut)
    planes = cv2.transpose(active.view(np.uint8).reshape(h * w, c))
    for i in range(k):
        pixels: list | None = None if weights is None else []
        x, y, size = _largest_cluster(planes[i].reshape(h, w), min_size, pixels)
        level = 0
        if size == 0 and fallback_cut is not None:  # nothing above the threshold: read the map above the fallback
            pixels, level = (None if weights is None else []), 1
            x, y, size = _largest_cluster(np.greater(maps3[..., i], fallback_cut).view(np.uint8), min_size, pixels)
        if size and pixels:
            x, y = _weighted_centroid(maps3[..., i], pixels[0], weights, level, x, y)
        out_kp[i, 0] = x
        out_kp[i, 1] = y
        out_conf[i] = size


Candidate = tuple[int, int, float, float, tuple[int, int, int, int]]
"""A cluster the chain may choose: (label, pixels, x, y, its box (x0, y0, w, h)), (x, y) its plain centroid."""


def _candidates(active: np.ndarray, min_size: int) -> tuple[np.ndarray | None, tuple[int, int], list[Candidate]]:
    """The 4-connected clusters of a boolean map (Algorithm 1's, M = 1), labelled inside the box of its active
    pixels: the labels, the box's corner (x, y) in the map, and the clusters of at least `min_size` pixels, in the
    order of their first pixel in row-major order (Algorithm 1's tie order), in map pixels."""
    plane = active.view(np.uint8)
    x0, y0, w, h = cv2.boundingRect(plane)
    if not w:
        return None, (0, 0), []
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(plane[y0:y0 + h, x0:x0 + w], connectivity=4)
    return labels, (x0, y0), [
        (j, int(stats[j, cv2.CC_STAT_AREA]), x0 + float(centroids[j, 0]), y0 + float(centroids[j, 1]),
         tuple(int(v) for v in stats[j, :4])) for j in range(1, count) if stats[j, cv2.CC_STAT_AREA] >= min_size]


def _skeleton_support(skeleton: np.ndarray, probability, before: np.ndarray, now: np.ndarray) -> np.ndarray:
    """The skeleton map's mean probability at SUPPORT_SAMPLES points on each segment from a centroid of `before`
    (A x 2, x and y) to one of `now` (B x 2): A x B. `skeleton` holds the map's raw values (`probability` reads
    them)."""
    t = np.linspace(0.0, 1.0, SUPPORT_SAMPLES)
    a, b = before[:, None, None, :], now[None, :, None, :]
    points = np.rint(a + t[None, None, :, None] * (b - a)).astype(np.intp)
    xs = np.clip(points[..., 0], 0, skeleton.shape[1] - 1)
    ys = np.clip(points[..., 1], 0, skeleton.shape[0] - 1)
    return probability(skeleton[ys, xs]).mean(axis=2)


def _chain_prior(schema: KeypointSchema | None, k: int) -> LimbPrior | None:
    """The limb lengths the chain holds k keypoints' maps to: UR5's for UR5's names (`schema` None: the default for
    k + 1 maps, `keypoints.schema_for_maps`), else none; UserError for a schema that is no serial chain or other
    maps."""
    schema = schema if schema is not None else schema_for_maps(k + 1)
    if schema.num_keypoints != k:
        raise UserError(f"schema {schema.name!r} has {schema.num_keypoints} keypoints, the maps {k}")
    if {frozenset(edge) for edge in schema.edges} != {frozenset((i, i + 1)) for i in range(k - 1)}:
        raise UserError(f"--cluster chain follows a serial chain of keypoints (each joined to the next in the "
                        f"schema's order); the skeleton of schema {schema.name!r} is not one: use --cluster largest")
    return UR5_LIMBS if schema.keypoints == UR5.keypoints else None


def _chain(maps3: np.ndarray, cut: float, min_size: int, out_kp: np.ndarray, out_conf: np.ndarray,
           fallback_cut: float | None, weights, probability, pixel_scale: tuple[float, float] | None,
           prior: LimbPrior | None) -> None:
    """One cluster per keypoint map, chosen jointly along the serial chain (keypoint k joined to k + 1) by Viterbi:
    each cluster scores log(its pixels / the map's largest cluster's), each consecutive pair SUPPORT_WEIGHT x
    log(the skeleton map's mean along the segment between them, at least SUPPORT_FLOOR) and, with a `prior` (UR5's
    names: `_chain_prior`), - LENGTH_WEIGHT x z^2 / 2, z the pair's log length as a share of the box of the maps'
    largest clusters against the prior in its standard deviations (lengths in the frame's proportions: `pixel_scale`). A
    map without a cluster (after the fallback) is missing and splits the chain. Writes what `_frame_keypoints` does:
    the chosen cluster's centroid (weighted by `weights` when given) and its pixel count."""
    k = maps3.shape[-1] - 1
    maps3 = np.ascontiguousarray(maps3)
    sx, sy = pixel_scale or (1.0, 1.0)
    found = []
    for i in range(k):
        labels, corner, candidates = _candidates(maps3[..., i] > cut, min_size)
        level = 0
        if not candidates and fallback_cut is not None:
            labels, corner, candidates = _candidates(maps3[..., i] > fallback_cut, min_size)
            level = 1
        found.append((labels, corner, candidates, level))
    side = 1.0
    if prior is not None:
        largest = np.array([[c[2] * sx, c[3] * sy] for _, _, cs, _ in found if cs
                            for c in [max(cs, key=lambda c: c[1])]])
        side = max(float(np.ptp(largest, axis=0).max()) if len(largest) > 1 else 0.0, 4.0 * max(sx, sy))
    skeleton = maps3[..., k]

    def unary(candidates):
        sizes = np.array([c[1] for c in candidates], np.float64)
        return np.log(sizes / sizes.max())

    chosen: list[int | None] = [None] * k
    start = 0
    while start < k:
        if not found[start][2]:
            start += 1
            continue
        end = start
        while end + 1 < k and found[end + 1][2]:
            end += 1
        score, back = unary(found[start][2]), []
        for i in range(start + 1, end + 1):
            before = np.array([c[2:4] for c in found[i - 1][2]])  # the clusters' centroids, x and y
            now = np.array([c[2:4] for c in found[i][2]])
            pair = SUPPORT_WEIGHT * np.log(np.maximum(_skeleton_support(skeleton, probability, before, now),
                                                      SUPPORT_FLOOR))
            if prior is not None:
                step = (before[:, None, :] - now[None, :, :]) * (sx, sy)
                length = np.log(np.maximum(np.hypot(step[..., 0], step[..., 1]), 1e-3) / side)
                pair -= LENGTH_WEIGHT * ((length - prior.mean[i - 1]) / prior.sd[i - 1]) ** 2 / 2
            total = score[:, None] + pair + unary(found[i][2])[None, :]
            back.append(total.argmax(axis=0))
            score = total.max(axis=0)
        j = int(score.argmax())
        for i in range(end, start - 1, -1):
            chosen[i] = j
            if i > start:
                j = int(back[i - 1 - start][j])
        start = end + 1
    for i, j in enumerate(chosen):
        if j is None:
            out_kp[i] = np.nan
            out_conf[i] = 0
            continue
        labels, (left, top), candidates, level = found[i]
        label, size, x, y, (bx, by, bw, bh) = candidates[j]
        if weights is not None:
            mask = labels[by:by + bh, bx:bx + bw] == label
            x, y = _weighted_centroid(maps3[..., i], (top + by, left + bx, bh, bw, mask), weights, level, x, y)
        out_kp[i, 0], out_kp[i, 1] = x, y
        out_conf[i] = size


@dataclass(frozen=True)
class Decoding:
    """How a model's maps become keypoints, passed whole from the settings to every decoder: Algorithm 1's
    `threshold`, the `fallback` threshold a map with nothing above it is read at (None: missing, the paper's), and
    the `centroid` (where in its cluster a keypoint is read: CENTROIDS). Defaults: `settings.THRESHOLD`,
    `settings.FALLBACK`, `settings.CENTROID`; UserError for a value out of range."""

    threshold: float = settings.THRESHOLD.default
    fallback: float | None = settings.FALLBACK.default
    centroid: str = settings.CENTROID.default
    cluster: str = settings.CLUSTER.default

    def __post_init__(self) -> None:
        if not 0.0 < float(self.threshold) < 1.0:
            raise UserError(f"threshold must be between 0 and 1 (exclusive), got {self.threshold}")
        object.__setattr__(self, "threshold", float(self.threshold))
        object.__setattr__(self, "fallback", check_fallback(self.threshold, self.fallback))
        check_centroid(self.centroid)
        check_cluster(self.cluster)

    @classmethod
    def from_args(cls, args: Any) -> Decoding:
        """The decoding a command's options ask for.

        Args:
            args: the parsed options: --threshold, --centroid and --cluster (`settings.add_decoding_arguments`),
                and --fallback when the command has it (else none).
        Returns:
            The decoding.
        Raises:
            UserError: a value out of range.
        """
        return cls(args.threshold, getattr(args, "fallback", None), args.centroid, args.cluster)

    def describe(self) -> str:
        """One line naming the decoding, for reports."""
        weighted = f" weighted by (p - {self.threshold:g})^2" if self.centroid == "weighted" else ""
        if self.cluster == "chain":
            text = (f"clusters above {self.threshold:g} chained along the arm (one per map: size, skeleton map, UR5's "
                    f"limb lengths for UR5's keypoints), its centroid{weighted}")
        else:
            text = f"Algorithm 1 (largest cluster above {self.threshold:g}, its centroid{weighted})"
        return text if self.fallback is None else f"{text}; a map with none: above {self.fallback:g} (--fallback)"

    def to_json(self) -> dict[str, Any]:
        """{"threshold", "fallback", "centroid", "cluster"}: what reports record."""
        return {"threshold": self.threshold, "fallback": self.fallback, "centroid": self.centroid,
                "cluster": self.cluster}

    def keypoints(self, maps: np.ndarray, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints in map pixels: `maps_to_keypoints` with this decoding.

        Args:
            maps: H x W x C (or N x H x W x C) output maps, keypoints first and the skeleton map last.
            **kwargs: `maps_to_keypoints`' logits, quantization, min_size, schema.
        Returns:
            (keypoints, confidence) as `maps_to_keypoints` returns them: (x, y) in map pixels, NaN where missing.
        """
        return maps_to_keypoints(maps, self.threshold, fallback=self.fallback, centroid=self.centroid,
                                 cluster=self.cluster, **kwargs)

    def in_frame(self, maps: np.ndarray, frame_shape: tuple[int, ...], **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints in frame pixels: `decode` with this decoding.

        Args:
            maps: H x W x C (or N x H x W x C) output maps.
            frame_shape: the shape of the frame the model's input was made from.
            **kwargs: `decode`'s logits, quantization, min_size, view, schema.
        Returns:
            (keypoints, confidence) as `decode` returns them: (x, y) in frame pixels, NaN where missing.
        """
        return decode(maps, frame_shape, self.threshold, fallback=self.fallback, centroid=self.centroid,
                      cluster=self.cluster, **kwargs)


def check_centroid(centroid: str) -> str:
    """`centroid` if it is one of CENTROIDS, else UserError."""
    if centroid not in CENTROIDS:
        raise UserError(f"centroid must be one of {', '.join(CENTROIDS)}, got {centroid!r}")
    return centroid


def check_cluster(cluster: str) -> str:
    """`cluster` if it is one of CLUSTERS, else UserError naming them."""
    if cluster not in CLUSTERS:
        raise UserError(f"cluster must be one of {', '.join(CLUSTERS)}, got {cluster!r}")
    return cluster


def check_fallback(threshold: float, fallback: float | None) -> float | None:
    """`fallback` as a float (None: no fallback), refused (UserError) unless 0 < fallback < threshold."""
    if fallback is None:
        return None
    f = float(fallback)
    if not 0.0 < f < float(threshold):
        raise UserError(f"the fallback threshold must be above 0 and below the threshold {threshold}, got {fallback}")
    return f


def maps_to_keypoints(maps: np.ndarray, threshold: float = 0.5, *, logits: bool = False,
                      quantization: tuple[float, int] | None = None,
                      min_size: int = 1, fallback: float | None = None,
                      centroid: str = settings.CENTROID.default, cluster: str = settings.CLUSTER.default,
                      pixel_scale: tuple[float, float] | None = None,
                      schema: KeypointSchema | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints from FCN-Pose output maps by Expansion Clustering (the paper's Algorithm 1, M = 1).

    Args:
        maps: H x W x C (one frame) or N x H x W x C (a batch) maps, keypoint maps first and the
            skeleton map last (ignored). Any real dtype and memory layout.
        threshold: a pixel is active when its value is strictly greater than this (compared in
            the maps' floating precision, numpy's rule for a Python scalar).
        logits: the maps are pre-sigmoid logits; ``threshold`` stays a probability and is
            compared as logit(threshold) (0 for 0.5). Same pixels as thresholding the sigmoid,
            except logits within float rounding of the cut (|z| < ~3e-8 at 0.5 in float32),
            where the float sigmoid itself rounds onto the threshold.
        quantization: (scale, zero_point) of integer maps straight from a quantized model (the
            int8 export); ``threshold`` stays a probability and is compared as the integer
            `quantized_cut`: the same pixels as thresholding ``dequantize(maps)``, without
            making a float copy of the maps.
        min_size: a largest cluster of fewer pixels is reported missing. The default 1 is the
            paper's algorithm; a larger value rejects lone speckles.
        fallback: None (the paper's algorithm) or a probability below ``threshold``: a keypoint
            missing at ``threshold`` is read by the same algorithm above ``fallback`` instead (its
            confidence is then that cluster's pixel count). Finds keypoints whose map stays under
            ``threshold`` on unfamiliar views; docs/postprocess.md has the measurements.
        centroid: "plain" (the paper's: the mean of the cluster's pixel indices) or "weighted" (weighted by
            (p - t)^2, p the pixel's probability and t the threshold that made the cluster).
        cluster: "largest" (the paper's: each map's largest cluster) or "chain" (one cluster per map, chosen
            jointly along the serial chain: `_chain`); where every map holds one cluster the two agree.
        pixel_scale: frame pixels per map pixel in x and y (`decode` passes the view's): the chain compares limb
            lengths in the frame's proportions; None: square pixels.
        schema: the keypoints the maps stand for (None: `keypoints.schema_for_maps`, UR5's for 9 maps). The chain
            needs a serial chain of keypoints; it holds limbs to `keypoints.UR5_LIMBS` only for UR5's names.

    Returns:
        (keypoints, confidence): keypoints float64 of shape (C-1, 2), or (N, C-1, 2), holding
        (x, y) in map pixels (pixel-centre convention: the mean of the cluster's column and row
        indices), NaN for a missing keypoint; confidence int64 of shape (C-1,) or (N, C-1), the
        kept cluster's pixel count, 0 when missing.

    Raises:
        UserError: maps that are not H x W x C / N x H x W x C with C >= 2, a bad threshold, or the chain asked of a
            schema whose skeleton is not a serial chain.

    Example:
        >>> maps = np.zeros((8, 8, 3), np.float32)
        >>> maps[2:4, 5:7, 0] = 0.9                   # a 2 x 2 blob in map 0
        >>> kp, conf = maps_to_keypoints(maps)
        >>> kp[0].tolist(), int(conf[0]), bool(np.isnan(kp[1]).all()), int(conf[1])
        ([5.5, 2.5], 4, True, 0)
    """
    arr = _check_maps(maps)
    if quantization is None:
        cut: float | int = _cut(threshold, logits)
    elif logits or not np.issubdtype(arr.dtype, np.integer):
        raise UserError(f"quantized maps are integers holding probabilities, got {arr.dtype} maps"
                        + (" with logits=True" if logits else ""))
    else:
        cut = quantized_cut(threshold, quantization[0], quantization[1], arr.dtype)
    fallback = check_fallback(threshold, fallback)
    if fallback is None:
        fallback_cut = None
    elif quantization is None:
        fallback_cut = _cut(fallback, logits)
    else:
        fallback_cut = quantized_cut(fallback, quantization[0], quantization[1], arr.dtype)
    min_size = int(min_size)
    if min_size < 1:
        raise UserError(f"min_size must be at least 1, got {min_size}")
    if quantization is not None:
        scale, zero_point = float(quantization[0]), int(quantization[1])

        def probability(values):
            return (values.astype(np.float64) - zero_point) * scale
    elif logits:
        def probability(values):
            return 1.0 / (1.0 + np.exp(-values.astype(np.float64)))
    else:
        def probability(values):
            return values.astype(np.float64)
    levels = (float(threshold), fallback)

    def weighted(values, level):
        return (probability(values) - levels[level]) ** 2

    weights = weighted if check_centroid(centroid) == "weighted" else None
    chained = check_cluster(cluster) == "chain"
    batch = arr.ndim == 4
    frames = arr if batch else arr[None]
    n, k = frames.shape[0], frames.shape[-1] - 1
    prior = _chain_prior(schema, k) if chained else None
    keypoints = np.empty((n, k, 2), np.float64)
    confidence = np.empty((n, k), np.int64)
    for j in range(n):
        if chained:
            _chain(frames[j], cut, min_size, keypoints[j], confidence[j], fallback_cut, weights, probability,
                   pixel_scale, prior)
        else:
            _frame_keypoints(frames[j], cut, min_size, keypoints[j], confidence[j], fallback_cut, weights)
    return (keypoints, confidence) if batch else (keypoints[0], confidence[0])


def decode(maps: np.ndarray, frame_shape: tuple[int, ...], threshold: float = 0.5, *,
           logits: bool = False, quantization: tuple[float, int] | None = None,
           min_size: int = 1, fallback: float | None = None,
           centroid: str = settings.CENTROID.default, cluster: str = settings.CLUSTER.default,
           view: FrameView | None = None, schema: KeypointSchema | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints in the original frame's pixels: :func:`maps_to_keypoints`, then
    :func:`fcnpose_tf.preprocess.keypoints_to_frame`.

    The maps have the model input's size, and the input is the view's crop of the frame (the whole frame
    when `view` is None) resized to it, so frame pixels follow from map pixels by the inverse of that resize.

    Args:
        maps: H x W x C or N x H x W x C maps (see :func:`maps_to_keypoints`).
        frame_shape: the original frame's shape, (height, width[, channels]).
        threshold, logits, quantization, min_size, fallback, centroid, cluster, schema: as in
            :func:`maps_to_keypoints`.
        view: the model's `FrameView` (its crop); None: the whole frame at the maps' size.

    Returns:
        (keypoints, confidence): keypoints (C-1, 2) or (N, C-1, 2) float64, (x, y) in frame pixels
        (pixel-centre convention), NaN where missing; confidence as in :func:`maps_to_keypoints`.

    Example:
        >>> maps = np.zeros((4, 4, 2), np.float32); maps[1, 2, 0] = 1.0
        >>> kp, conf = decode(maps, (8, 16, 3))       # frame 16 wide, 8 high
        >>> kp.tolist(), conf.tolist()
        ([[9.5, 2.5]], [1])
    """
    arr = _check_maps(maps)
    h, w = arr.shape[-3], arr.shape[-2]
    if view is None:
        view = FrameView(h, w)
    elif view.shape != (h, w):
        raise UserError(f"maps of {h} x {w} do not match the model's {view.height} x {view.width} input")
    if len(frame_shape) < 2 or min(frame_shape[:2]) < 1:
        raise UserError(f"expected a frame shape (height, width[, channels]), got {tuple(frame_shape)}")
    box = view.box(tuple(frame_shape))
    keypoints, confidence = maps_to_keypoints(arr, threshold, logits=logits, quantization=quantization,
                                              min_size=min_size, fallback=fallback, centroid=centroid, cluster=cluster,
                                              pixel_scale=(box[2] / w, box[3] / h), schema=schema)
    return keypoints_to_frame(keypoints, tuple(frame_shape), view), confidence
