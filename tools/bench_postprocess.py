#!/usr/bin/env python
"""Benchmark the post-processing (maps -> keypoints) variants on one core, in one run.

Usage:
    python tools/bench_postprocess.py                      # 224 x 224 x 9 maps, 1 thread, 300 rounds
    python tools/bench_postprocess.py --threads 2 --json bench_pp.json
    python tools/bench_postprocess.py --litert-sigmoid     # also time a LiteRT LOGISTIC op (needs TF)

Every variant runs on the same frames, interleaved round by round in a shuffled order so that
load from other processes and cache effects hit them alike; the table gives medians and p95 in microseconds per frame (8 keypoint
maps + 1 skeleton map) and the speed-up over the plain per-map implementation. Each variant's
keypoints are checked against the library's before timing.

Scenarios are synthetic model outputs: sigmoid discs of radius 6 px (the training targets'
radius) on a low-noise background, with or without isolated speckles, plus worst cases (every map
empty, every map fully active, every pixel active with p = 0.5 -- thousands of clusters per map).
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from typing import Callable

import cv2
import numpy as np

from fcnpose_tf.postprocess import maps_to_keypoints
from fcnpose_tf.tables import format_table

Maps = np.ndarray
Result = tuple[np.ndarray, np.ndarray]


# ---------------------------------------------------------------------------- synthetic outputs

def _disc_logits(size: int, cx: float, cy: float, radius: float = 6.0, sharpness: float = 1.5) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    return ((radius - np.hypot(xx - cx, yy - cy)) * sharpness).astype(np.float32)


def make_logits(scenario: str, size: int, num_maps: int, rng: np.random.Generator) -> np.ndarray:
    """Pre-sigmoid maps (logits) for one scenario; the probabilities are their sigmoid."""
    k = num_maps - 1
    z = rng.normal(-6.0, 1.0, (size, size, num_maps)).astype(np.float32)    # confident background
    if scenario in ("clean", "speckled", "noisy"):
        speckles = {"clean": (0, 0), "speckled": (0, 4), "noisy": (30, 60)}[scenario]
        for i in range(k):
            cx, cy = rng.uniform(8, size - 9, 2)
            z[..., i] = np.maximum(z[..., i], _disc_logits(size, cx, cy))
            n = int(rng.integers(*speckles)) if speckles[1] else 0
            ys, xs = rng.integers(0, size, (2, n))
            z[ys, xs, i] = rng.uniform(0.1, 3.0, n)
        z[..., -1] = rng.normal(0.0, 2.0, (size, size))                      # skeleton: ignored
    elif scenario == "empty":
        pass
    elif scenario == "full":
        z = np.abs(z)
    elif scenario == "random50":
        z = rng.normal(0.0, 1.0, z.shape).astype(np.float32)
    else:
        raise ValueError(scenario)
    return np.ascontiguousarray(z)


SCENARIOS = ("clean", "speckled", "noisy", "empty", "full", "random50")


# ---------------------------------------------------------------------------- variants

def _pick(n: int, stats: np.ndarray, centroids: np.ndarray, labels: np.ndarray) -> tuple[float, float, int]:
    """Largest component from OpenCV's stats; ties to the first pixel in row-major order."""
    if n < 2:
        return math.nan, math.nan, 0
    areas = stats[1:, cv2.CC_STAT_AREA]
    tied = np.flatnonzero(areas == areas.max()) + 1
    best = int(tied[0]) if tied.size == 1 else int(min(tied, key=lambda lab: int(np.argmax(labels.ravel() == lab))))
    return float(centroids[best, 0]), float(centroids[best, 1]), int(areas[best - 1])


def naive(maps: Maps, t: float = 0.5) -> Result:
    """The obvious implementation: per map, threshold the channel slice, label the whole map with stats."""
    k = maps.shape[2] - 1
    kp, conf = np.full((k, 2), np.nan), np.zeros(k, np.int64)
    for i in range(k):
        mask = (maps[..., i] > t).astype(np.uint8)
        n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=4, ltype=cv2.CV_32S)
        x, y, conf[i] = _pick(n, stats, cents, labels)
        kp[i] = x, y
    return kp, conf


def _planes(maps: Maps, t: float) -> np.ndarray:
    h, w, c = maps.shape
    active = np.greater(maps, t)
    return cv2.transpose(active.view(np.uint8).reshape(h * w, c)).reshape(c, h, w)


def planes_stats(maps: Maps, t: float = 0.5) -> Result:
    """One contiguous threshold + transpose, then whole-map labelling with OpenCV's stats."""
    planes = _planes(maps, t)
    k = maps.shape[2] - 1
    kp, conf = np.full((k, 2), np.nan), np.zeros(k, np.int64)
    for i in range(k):
        n, labels, stats, cents = cv2.connectedComponentsWithStats(planes[i], connectivity=4, ltype=cv2.CV_32S)
        x, y, conf[i] = _pick(n, stats, cents, labels)
        kp[i] = x, y
    return kp, conf


def planes_nostats(maps: Maps, t: float = 0.5) -> Result:
    """Contiguous threshold + transpose, whole-map labels without stats, areas by bincount."""
    planes = _planes(maps, t)
    k = maps.shape[2] - 1
    kp, conf = np.full((k, 2), np.nan), np.zeros(k, np.int64)
    for i in range(k):
        n, labels = cv2.connectedComponents(planes[i], connectivity=4, ltype=cv2.CV_32S)
        if n < 2:
            continue
        flat = labels.ravel()
        counts = np.bincount(flat, minlength=n)
        counts[0] = 0
        tied = np.flatnonzero(counts == counts.max())
        best = int(tied[0]) if tied.size == 1 else int(min(tied, key=lambda lab: int(np.argmax(flat == lab))))
        m = cv2.moments((labels == best).view(np.uint8), binaryImage=True)
        kp[i] = m["m10"] / m["m00"], m["m01"] / m["m00"]
        conf[i] = int(m["m00"])
    return kp, conf


def library(maps: Maps, t: float = 0.5) -> Result:
    """fcnpose_tf.postprocess.maps_to_keypoints, Algorithm 1: planes + labelling only the active pixels' bbox."""
    return maps_to_keypoints(maps, t, centroid="plain")


def sigmoid_numpy(z: Maps) -> np.ndarray:
    """What thresholding logits saves when the runtime would otherwise apply the sigmoid itself."""
    out = np.negative(z)
    np.exp(out, out=out)
    out += 1.0
    np.reciprocal(out, out=out)
    return out


# ---------------------------------------------------------------------------- timing

def _litert_sigmoid(shape: tuple[int, ...], threads: int) -> Callable[[], None] | None:
    """A one-op LiteRT model (LOGISTIC) on the map tensor, built with TensorFlow; None without TF."""
    try:
        import tensorflow as tf
    except ImportError:
        print("--litert-sigmoid: TensorFlow is not importable; skipped", file=sys.stderr)
        return None
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:
        Interpreter = tf.lite.Interpreter

    @tf.function(input_signature=[tf.TensorSpec((1, *shape), tf.float32)])
    def fn(x):
        return tf.math.sigmoid(x)

    conv = tf.lite.TFLiteConverter.from_concrete_functions([fn.get_concrete_function()], fn)
    interp = Interpreter(model_content=conv.convert(), num_threads=threads)
    interp.allocate_tensors()
    inp = interp.get_input_details()[0]["index"]
    interp.set_tensor(inp, np.zeros((1, *shape), np.float32))
    return interp.invoke


def run(args: argparse.Namespace) -> dict:
    cv2.setNumThreads(args.threads)
    rng = np.random.default_rng(args.seed)
    variants: dict[str, Callable[[Maps], object]] = {
        "naive per-map WithStats": naive,
        "planes + full-map WithStats": planes_stats,
        "planes + full-map labels": planes_nostats,
        "library (bbox window)": library,
    }
    rows, results = [], []
    for scenario in args.scenarios:
        z = make_logits(scenario, args.size, args.maps, rng)
        p = sigmoid_numpy(z).astype(np.float32)
        expected = maps_to_keypoints(p, centroid="plain")
        np.testing.assert_array_equal(maps_to_keypoints(z, logits=True, centroid="plain")[1], expected[1])
        # the weighted read (the package's default) keeps Algorithm 1's clusters
        np.testing.assert_array_equal(maps_to_keypoints(p, centroid="weighted")[1], expected[1])
        for name, fn in variants.items():
            kp, conf = fn(p)
            np.testing.assert_array_equal(conf, expected[1], err_msg=f"{name} on {scenario}")
            np.testing.assert_allclose(kp, expected[0], rtol=0, atol=1e-9, err_msg=f"{name} on {scenario}")
        calls: dict[str, Callable[[], object]] = {name: (lambda fn=fn: fn(p)) for name, fn in variants.items()}
        calls["library, logits > 0"] = lambda: maps_to_keypoints(z, logits=True, centroid="plain")
        calls["library, weighted centroid"] = lambda: maps_to_keypoints(p, centroid="weighted")
        calls["(sigmoid in numpy)"] = lambda: sigmoid_numpy(z)
        if args.litert_sigmoid:
            op = _litert_sigmoid(z.shape, args.threads)
            if op is not None:
                calls["(LiteRT LOGISTIC op)"] = op
        times = {name: [] for name in calls}
        clock = time.thread_time_ns if args.clock == "cpu" else time.perf_counter_ns
        for _ in range(args.warmup):
            for call in calls.values():
                call()
        order = list(calls)
        for _ in range(args.rounds):
            rng.shuffle(order)  # no variant always runs right after the cache-thrashing one
            for name in order:
                call = calls[name]
                t0 = clock()
                call()
                times[name].append(clock() - t0)
        active = int(np.count_nonzero(p[..., :-1] > 0.5)) / (args.maps - 1)
        base = float(np.median(times["naive per-map WithStats"]))
        for name, ts in times.items():
            med, p95 = float(np.median(ts)) / 1e3, float(np.percentile(ts, 95)) / 1e3
            speedup = base / 1e3 / med if not name.startswith("(") else None
            rows.append([scenario, round(active, 1), name, round(med, 1), round(p95, 1),
                         None if speedup is None else round(speedup, 1)])
            results.append({"scenario": scenario, "active_px_per_map": active, "variant": name,
                            "median_us": med, "p95_us": p95, "speedup_vs_naive": speedup})
    print(format_table(["scenario", "active px/map", "variant", "median µs", "p95 µs", "x naive"], rows,
                       markdown=args.markdown))
    worst = {label: max((r for r in results if r["variant"] == variant), key=lambda r: r["median_us"])
             for label, variant in (("Algorithm 1", "library (bbox window)"),
                                    ("weighted", "library, weighted centroid"))}
    print(f"\n{args.size}x{args.size}x{args.maps} maps, OpenCV threads={args.threads}, {args.rounds} rounds, "
          f"{args.clock} clock, "
          f"numpy {np.__version__}, OpenCV {cv2.__version__}, {platform.machine()}; library worst median: "
          + ", ".join(f"{label} {r['median_us']:.0f} µs ({r['scenario']})" for label, r in worst.items())
          + "; target <= 1000 µs per frame")
    return {"size": args.size, "maps": args.maps, "threads": args.threads, "rounds": args.rounds, "clock": args.clock,
            "numpy": np.__version__, "opencv": cv2.__version__, "machine": platform.machine(),
            "results": results}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=224, help="map height and width (default 224)")
    ap.add_argument("--maps", type=int, default=9, help="maps per frame incl. skeleton (default 9)")
    ap.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads (default 1)")
    ap.add_argument("--rounds", type=int, default=300, help="timed rounds per scenario (default 300)")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="wall: perf_counter; cpu: this thread's CPU time (thread_time), which leaves out the "
                         "time other processes hold the core: the figure to quote from a loaded machine")
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    ap.add_argument("--litert-sigmoid", action="store_true",
                    help="also time a one-op LiteRT model applying the sigmoid to the maps (needs TensorFlow)")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("--force", action="store_true", help="overwrite --json if it exists")
    args = ap.parse_args(argv)
    report = run(args)
    if args.json:
        from fcnpose_tf.fileio import write_json
        write_json(args.json, report, force=args.force)
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
