#!/usr/bin/env python
"""The Pi path's speed against the paper's desktop path, measured in one run (docs/runtime.md, "Speed targets").

Compares, on the same frames, machine and thread count, interleaved frame by frame (the order
alternating every frame) so all paths see the same load:
  A. the unpruned Keras model called directly (the paper's desktop path), and
  B. the compressed TFLite model through the LiteRT runtime (the Pi path; default: the bundled 70 %
     full-integer int8 file, with the bundled 70 % float16 file as C for comparison),
  C... more TFLite files (--tflite again) and float16 exports of Keras models made on
     the fly (--export, verified against the Keras model; --fold exports them with
     fcnpose_tf.compression.inference_graph.fold_upsampling, --no-fold without, --both both ways),
each end to end (preprocess + forward pass + post-processing). Prints medians, p95, each path's
FPS ratio to A, and the share of its frame time spent outside the interpreter (pre + post).

    python tools/bench_speedup.py --threads 1 --frames 200
    python tools/bench_speedup.py --threads 1 --frames 100 --export saved_models/fcnpose_ur5_p70.keras --both
    python tools/bench_speedup.py --keras saved_models/fcnpose_ur5.keras \
        --tflite saved_models/fcnpose_ur5_p70_fp16.tflite --data DIR --frames 200 --threads 1

Targets (docs/runtime.md, speed targets): B's FPS >= 10 x A's for the int8 file (8 x was the float16
file's); B's pre + post <= 15 % of its frame time (70 % model, 224, one thread). Each forward pass is
also put as a throughput, GMAC/s = the network's multiply-accumulates per frame / its median
forward-pass time, and the line at the end says what throughput B's forward pass would need for
10x: the budget that target leaves once A's frame time and B's own pre + post are fixed. For scale it also measures this machine's float32 matrix-multiply
throughput on the same thread count (numpy's OpenBLAS sgemm, 512 x 512, best of 200, in a
subprocess): what a well-tuned float32 kernel reaches on these cores, which no convolution beats.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

_MATMUL_PROBE = """
import time, numpy as np
n = 512
a, b = (np.random.default_rng(i).random((n, n), dtype=np.float32) for i in (0, 1))
times = []
for _ in range(200):
    start = time.perf_counter()
    a @ b
    times.append(time.perf_counter() - start)
print(n ** 3 / min(times) / 1e9)
"""


TARGET_RATIO = 10
"""End-to-end FPS of the 70 % int8 file over the unpruned Keras model (docs/runtime.md, speed targets)."""


def matmul_gmac_per_s(threads: int) -> float:
    """Best float32 matrix-multiply throughput (GMAC/s) of `threads` threads, measured in a fresh process
    (OpenBLAS reads its thread count at import)."""
    env = {**os.environ, **{name: str(threads) for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}}
    out = subprocess.run([sys.executable, "-c", _MATMUL_PROBE], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def interleaved_times(models: list, frames: list, count: int, warmup: int) -> list[list]:
    """Each model's per-frame `times` (preprocess, invoke, postprocess, end_to_end) on `count` frames, the models
    taking turns frame by frame in an order reversed every frame, so all see the same load; `warmup` untimed frames
    each first."""
    for i in range(warmup):
        for model in models:
            model.predict(frames[i % len(frames)])
    times: list[list] = [[] for _ in models]
    order = list(range(len(models)))
    for i in range(count):
        frame = frames[i % len(frames)]
        for k in (order if i % 2 == 0 else order[::-1]):
            times[k].append(models[k].predict(frame).times)
    return times


def latency_stats(times: list) -> dict:
    """Medians (ms) of one model's `interleaved_times`: preprocess, inference, postprocess, end to end (and its p95),
    FPS from the end-to-end median, and the median share of pre + post in a frame."""
    import numpy as np

    from fcnpose_tf.runtime.timing import LatencyLog

    log = LatencyLog(times)
    s = log.summary()
    share = (log.values("preprocess") + log.values("postprocess")) / log.values("end_to_end")
    return {"total_ms_median": s["end_to_end"]["median"], "total_ms_p95": s["end_to_end"]["p95"],
            "preprocess_ms_median": s["preprocess"]["median"], "inference_ms_median": s["invoke"]["median"],
            "postprocess_ms_median": s["postprocess"]["median"], "fps_median": 1000.0 / s["end_to_end"]["median"],
            "pre_post_share_percent": float(100 * np.median(share))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keras", type=Path, help="unpruned Keras model (default: bundled baseline)")
    parser.add_argument("--tflite", type=Path, action="append",
                        help="compressed .tflite; repeat for more (default: the bundled 70%% int8, then float16)")
    parser.add_argument("--export", type=Path, action="append", default=[],
                        help="also export this Keras model to float16 TFLite (into a temporary folder) and time it")
    fold = parser.add_mutually_exclusive_group()
    fold.add_argument("--fold", dest="fold", action="store_const", const="fold", default="fold",
                      help="--export with fold_upsampling (default)")
    fold.add_argument("--no-fold", dest="fold", action="store_const", const="plain", help="--export without it")
    fold.add_argument("--both", dest="fold", action="store_const", const="both", help="--export both ways")
    parser.add_argument("--data", type=Path, help="dataset whose frames are used (default: held-out synthetic)")
    parser.add_argument("--frames", type=int, default=200, help="timed frames per model")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, help="write the figures as JSON")
    parser.add_argument("--force", action="store_true", help="overwrite --json if it exists")
    args = parser.parse_args()
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    if args.json:
        from fcnpose_tf.fileio import check_writable

        check_writable(args.json, args.force)  # before the measurement, not after

    import numpy as np

    from fcnpose_tf.bundled import baseline_model, models_dir
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.training.evaluate import KerasKeypointModel
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.data.synthcache import heldout_data
    from fcnpose_tf.training.tfsetup import set_tensorflow_threads

    set_tensorflow_threads(args.threads)
    keras_path = args.keras or baseline_model()
    tflite_paths = args.tflite or [models_dir() / "fcnpose_ur5_p70_int8.tflite",
                                   models_dir() / "fcnpose_ur5_p70_fp16.tflite"]
    dataset = load_dataset(args.data or heldout_data())
    frames = [dataset.load_image(i) for i in range(min(len(dataset), 50))]

    tmp = tempfile.TemporaryDirectory(prefix="bench_speedup_")
    labels = [f"{p.name} (LiteRT)" for p in tflite_paths]
    if args.export:
        from fcnpose_tf.compression.export import write_tflite
        from fcnpose_tf.training.model import load_model
        from fcnpose_tf.preprocess import preprocess_frame

        for source in args.export:
            model = load_model(source)
            size = int(model.input_shape[1])
            samples = np.stack([preprocess_frame(f, size) for f in frames[:4]])
            for folded in {"fold": [True], "plain": [False], "both": [False, True]}[args.fold]:
                path = Path(tmp.name) / f"{source.stem}_fp16{'_folded' if folded else ''}.tflite"
                export = write_tflite(model, path, "float16", sample_frames=samples, fold_upsampling=folded)
                print(f"exported {source.name} -> {path.name}: {export.size_bytes:,} bytes, max abs map difference "
                      f"{export.parity.max_abs_diff:.2g} vs Keras"
                      + (f", {len(export.graph_rewrites)} upsampling layers folded" if folded else ""), flush=True)
                tflite_paths.append(path)
                labels.append(f"{source.stem} fp16 {'folded' if folded else 'plain'} (export)")

    a = KerasKeypointModel(keras_path, keras_path, num_threads=args.threads)
    others = [KeypointModel(p, num_threads=args.threads) for p in tflite_paths]
    times = interleaved_times([a] + others, frames, args.frames, args.warmup)
    stats = latency_stats

    from fcnpose_tf.training.model import describe

    def throughput(macs: int, inference_ms: float) -> float:
        return macs / inference_ms / 1e6  # GMAC/s

    keras_stats = stats(times[0])
    keras_stats["macs"] = int(sum(row.macs for row in describe(a.model)))
    keras_stats["gmac_per_s"] = throughput(keras_stats["macs"], keras_stats["inference_ms_median"])
    variants = []
    for label, path, ts, model in zip(labels, tflite_paths, times[1:], others):
        s = stats(ts)
        s.update(label=label, model=str(path), size_bytes=path.stat().st_size,
                 fps_ratio=s["fps_median"] / keras_stats["fps_median"],
                 inference_ratio=keras_stats["inference_ms_median"] / s["inference_ms_median"],
                 macs=int(model.stats().macs), gmac_per_s=throughput(model.stats().macs, s["inference_ms_median"]))
        budget_ms = keras_stats["total_ms_median"] / TARGET_RATIO - s["preprocess_ms_median"] - s["postprocess_ms_median"]
        s[f"forward_ms_for_{TARGET_RATIO}x"] = budget_ms
        s[f"gmac_per_s_for_{TARGET_RATIO}x"] = throughput(model.stats().macs, budget_ms) if budget_ms > 0 else None
        variants.append(s)
    matmul = matmul_gmac_per_s(args.threads)
    result = {"threads": args.threads, "frames": args.frames, "keras_model": str(keras_path),
              "matmul_gmac_per_s": matmul,
              "tflite_model": str(tflite_paths[0]), "tflite_backend": others[0].backend.label,
              "keras": keras_stats, "tflite": variants[0], "fps_ratio": variants[0]["fps_ratio"],
              "variants": variants}
    print(f"{args.frames} frames each, interleaved, {args.threads} thread(s); medians in ms")
    print(f"{'path':<46} {'pre':>6} {'infer':>7} {'post':>6} {'total':>7} {'p95':>7} {'FPS':>7} {'xA':>6} "
          f"{'pre+post':>9} {'MMACs':>7} {'GMAC/s':>7}")
    rows = [(f"A unpruned Keras direct ({keras_path.name})", keras_stats, None)]
    rows += [(f"{chr(ord('B') + i)} {v['label']}", v, v["fps_ratio"]) for i, v in enumerate(variants)]
    for label, s, ratio in rows:
        print(f"{label[:46]:<46} {s['preprocess_ms_median']:6.2f} {s['inference_ms_median']:7.2f} "
              f"{s['postprocess_ms_median']:6.2f} {s['total_ms_median']:7.2f} {s['total_ms_p95']:7.2f} "
              f"{s['fps_median']:7.1f} {'' if ratio is None else f'{ratio:5.1f}x':>6} "
              f"{s['pre_post_share_percent']:8.1f}% {s['macs'] / 1e6:7.1f} {s['gmac_per_s']:7.1f}")
    print(f"FPS ratio B/A: {result['fps_ratio']:.1f}x (target >= {TARGET_RATIO}x for the int8 file; "
          "the paper's desktop 41.90/11.71 = 3.6x)")
    print(f"B pre+post share of frame time: {result['tflite']['pre_post_share_percent']:.1f}% (target <= 15%)")
    for i, v in enumerate(variants):
        need = v[f"gmac_per_s_for_{TARGET_RATIO}x"]
        print(f"for {TARGET_RATIO}x, {chr(ord('B') + i)}'s forward pass needs <= {v[f'forward_ms_for_{TARGET_RATIO}x']:.2f} ms"
              + (f" = {need:.1f} GMAC/s on its {v['macs'] / 1e6:.1f} M MACs (it runs {v['gmac_per_s']:.1f}; "
                 f"A runs {keras_stats['gmac_per_s']:.1f}; float32 matmul here {matmul:.1f})" if need else " (impossible: pre + post alone exceed it)"))
    if args.json:
        from fcnpose_tf.fileio import write_json

        write_json(args.json, result, force=args.force)
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
