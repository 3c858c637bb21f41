"""Is fine localisation limited by decoding? Several ways of reading a position from the same maps.

    python tools/compare_decoders.py MODEL.keras --data DATA [--threads 1]

Runs MODEL once per frame of DATA and reads every keypoint map with: Algorithm 1 (the paper's: the
largest 4-connected cluster above 0.5, its centroid; `fcnpose_tf.postprocess`), the same at
thresholds 0.3 and 0.7, the cluster's centroid weighted by (p - 0.5) and (p - 0.5)^2, and the
argmax of the map blurred by a 2-pixel Gaussian, and Algorithm 1 with a fallback (a map with nothing
above 0.5 read above 0.2 or 0.1: `--fallback`, docs/postprocess.md). Two readings choose among a map's clusters
instead of taking the largest: the chain (one cluster per keypoint, chosen jointly along the serial chain by the
clusters' sizes and the skeleton map's support between consecutive keypoints) and, as a bound on any such choice,
the cluster nearest the ground truth (an oracle: not a decoder); and the package's own chain (`--cluster chain`:
the same choice weighing the UR5's limb lengths too, read at the plain centroid). Prints PCK@0.5/0.2/0.05, EPE and
the median error per decoder, and PCK@0.05 per keypoint. docs/training.md ("Training on your own frames") and
docs/results.md have its figures.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np


def cluster_centroid(maps: np.ndarray, threshold: float, power: float) -> np.ndarray:
    """Per keypoint map: the largest 4-connected cluster above threshold, its centroid weighted by
    (p - threshold) ** power (power 0: the plain centroid of Algorithm 1). (K, 2) map pixels, NaN if none."""
    out = np.full((maps.shape[-1] - 1, 2), np.nan)
    for k in range(maps.shape[-1] - 1):
        m = maps[..., k]
        n, labels = cv2.connectedComponents((m > threshold).astype(np.uint8), connectivity=4)
        if n < 2:
            continue
        counts = np.bincount(labels.ravel(), minlength=n)
        counts[0] = 0
        ys, xs = np.nonzero(labels == counts.argmax())
        weights = (m[ys, xs] - threshold) ** power if power else np.ones(len(xs))
        out[k] = [np.sum(xs * weights) / weights.sum(), np.sum(ys * weights) / weights.sum()]
    return out


def with_fallback(maps: np.ndarray, threshold: float, floor: float) -> np.ndarray:
    """Algorithm 1 above `threshold`; a map with no cluster there is read above `floor` instead."""
    out = cluster_centroid(maps, threshold, 0)
    empty = np.isnan(out[:, 0])
    if empty.any():
        out[empty] = cluster_centroid(maps, floor, 0)[empty]
    return out


def blurred_argmax(maps: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """Per keypoint map: the argmax after a Gaussian blur of `sigma` map pixels. (K, 2) map pixels."""
    out = np.empty((maps.shape[-1] - 1, 2))
    for k in range(maps.shape[-1] - 1):
        blurred = cv2.GaussianBlur(maps[..., k].astype(np.float32), (0, 0), sigma)
        y, x = np.unravel_index(np.argmax(blurred), blurred.shape)
        out[k] = [x, y]
    return out


def clusters(plane: np.ndarray, threshold: float = 0.5) -> list[tuple[float, float, int]]:
    """(x, y, pixels) of every 8-connected cluster above threshold: its centroid in map pixels and its size."""
    n, _, stats, centroids = cv2.connectedComponentsWithStats((plane > threshold).astype(np.uint8), connectivity=8)
    return [(float(centroids[j][0]), float(centroids[j][1]), int(stats[j, cv2.CC_STAT_AREA])) for j in range(1, n)]


def skeleton_support(skeleton: np.ndarray, a: tuple, b: tuple, samples: int = 16) -> float:
    """Mean of the skeleton map along the segment from a to b (map pixels)."""
    t = np.linspace(0.0, 1.0, samples)
    xs = np.clip(np.round(a[0] + t * (b[0] - a[0])).astype(int), 0, skeleton.shape[1] - 1)
    ys = np.clip(np.round(a[1] + t * (b[1] - a[1])).astype(int), 0, skeleton.shape[0] - 1)
    return float(skeleton[ys, xs].mean())


def cluster_chain(maps: np.ndarray, threshold: float = 0.5, floor: float = 0.02) -> np.ndarray:
    """One cluster per keypoint map, chosen jointly along the serial chain (Viterbi): each cluster scores
    log(size / the map's largest size), each consecutive pair log(skeleton support between them) (at least
    `floor`); a keypoint without clusters is missing and splits the chain. (K, 2) map pixels, NaN if missing."""
    k_count = maps.shape[-1] - 1
    skeleton = maps[..., k_count].astype(np.float32)
    found = [clusters(maps[..., k].astype(np.float32), threshold) for k in range(k_count)]
    out = np.full((k_count, 2), np.nan)
    k = 0
    while k < k_count:
        if not found[k]:
            k += 1
            continue
        run = [k]
        while run[-1] + 1 < k_count and found[run[-1] + 1]:
            run.append(run[-1] + 1)

        def unary(i: int) -> np.ndarray:
            sizes = np.array([c[2] for c in found[i]], float)
            return np.log(sizes / sizes.max())

        score, back = unary(run[0]), []
        for prev, cur in zip(run, run[1:]):
            pair = np.log(np.maximum([[skeleton_support(skeleton, a, b) for b in found[cur]] for a in found[prev]],
                                     floor))
            total = score[:, None] + pair + unary(cur)[None, :]
            back.append(total.argmax(axis=0))
            score = total.max(axis=0)
        j = int(score.argmax())
        for i in range(len(run) - 1, -1, -1):
            out[run[i]] = found[run[i]][j][:2]
            if i:
                j = int(back[i - 1][j])
        k = run[-1] + 1
    return out


def nearest_cluster(maps: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The oracle: per keypoint map, the cluster above 0.5 nearest the ground truth `truth` (K x 2 map pixels,
    NaN where unannotated; the largest cluster there). A bound on what any choice among clusters can reach."""
    out = np.full((maps.shape[-1] - 1, 2), np.nan)
    for k in range(maps.shape[-1] - 1):
        found = clusters(maps[..., k].astype(np.float32))
        if not found:
            continue
        points = np.array([c[:2] for c in found])
        if np.isfinite(truth[k]).all():
            out[k] = points[np.argmin(np.linalg.norm(points - truth[k], axis=1))]
        else:
            out[k] = points[int(np.argmax([c[2] for c in found]))]
    return out


DECODERS = {
    "Algorithm 1 (above 0.5, centroid)": lambda m: cluster_centroid(m, 0.5, 0),
    "above 0.3, centroid": lambda m: cluster_centroid(m, 0.3, 0),
    "above 0.7, centroid": lambda m: cluster_centroid(m, 0.7, 0),
    "above 0.5, weighted by p-0.5": lambda m: cluster_centroid(m, 0.5, 1),
    "above 0.5, weighted by (p-0.5)^2": lambda m: cluster_centroid(m, 0.5, 2),
    "blurred argmax (2 px)": blurred_argmax,
    "above 0.5, else above 0.2": lambda m: with_fallback(m, 0.5, 0.2),
    "above 0.5, else above 0.1": lambda m: with_fallback(m, 0.5, 0.1),
    "clusters chained along the skeleton": cluster_chain,
}
ORACLE = "oracle: the cluster nearest the truth"
CHAIN = "--cluster chain (and limb lengths)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--data", required=True)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    from fcnpose_tf import metrics
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.training.evaluate import open_model
    from fcnpose_tf.preprocess import keypoints_to_frame, keypoints_to_input

    dataset = load_dataset(args.data)
    model = open_model(args.model, threads=args.threads)
    gt = np.stack([s.keypoints for s in dataset.samples])
    from fcnpose_tf.postprocess import decode

    preds: dict[str, list[np.ndarray]] = {name: [] for name in [*DECODERS, CHAIN, ORACLE]}
    for i in range(len(dataset.samples)):
        frame = dataset.load_image(i)
        model.set_input(frame)
        model.invoke()
        maps = model.read_maps()
        maps = maps[0] if maps.ndim == 4 else maps
        for name, decoder in DECODERS.items():
            preds[name].append(keypoints_to_frame(decoder(maps), frame.shape, maps.shape[0]))
        preds[CHAIN].append(decode(maps, frame.shape, centroid="plain", cluster="chain", view=model.view)[0])
        truth = keypoints_to_input(gt[i], frame.shape, maps.shape[0])  # the maps have the input's size
        preds[ORACLE].append(keypoints_to_frame(nearest_cluster(maps, truth), frame.shape, maps.shape[0]))
    names = dataset.schema.keypoints
    print(f"{args.model} on {args.data}: {len(gt)} frames; errors in frame pixels")
    print(f"{'decoder':38s} {'PCK@.5':>7s} {'@.2':>6s} {'@.05':>6s} {'EPE':>6s} {'median':>6s}  PCK@.05: "
          + " ".join(n[:6] for n in names))
    for name, p in preds.items():
        p = np.stack(p)
        print(f"{name:38s} {metrics.pck(p, gt, .5):7.3f} {metrics.pck(p, gt, .2):6.3f} {metrics.pck(p, gt, .05):6.3f} "
              f"{metrics.epe(p, gt):6.2f} {np.nanmedian(metrics.errors_px(p, gt)):6.2f}  "
              + " ".join(f"{v:6.2f}" for v in metrics.pck_per_keypoint(p, gt, .05)))


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
