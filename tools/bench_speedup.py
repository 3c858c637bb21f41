#!/usr/bin/env python
"""Issue 6 point 5: the Pi path's speed against the paper's desktop path, measured in one run.

Compares, on the same frames, machine and thread count, interleaved frame by frame so both see
the same load:
  A. the unpruned Keras model called directly (the paper's desktop path), and
  B. the compressed float16 TFLite model through the LiteRT runtime (the Pi path),
each end to end (preprocess + forward pass + post-processing). Prints medians, p95, the FPS
ratio B/A, and the share of B's frame time spent outside the interpreter (pre + post).

    python tools/bench_speedup.py --threads 1
    python tools/bench_speedup.py --keras saved_models/fcnpose_ur5.keras \
        --tflite saved_models/fcnpose_ur5_p70_fp16.tflite --data DIR --frames 200 --threads 1

Targets (issue 6): B's FPS >= 8 x A's; B's pre + post <= 15 % of its frame time (70 % model,
224, one thread).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keras", type=Path, help="unpruned Keras model (default: bundled baseline)")
    parser.add_argument("--tflite", type=Path, help="compressed .tflite (default: bundled 70%% float16)")
    parser.add_argument("--data", type=Path, help="dataset whose frames are used (default: held-out synthetic)")
    parser.add_argument("--frames", type=int, default=200, help="timed frames per model")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, help="write the figures as JSON")
    args = parser.parse_args()
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

    import numpy as np

    from fcnpose_tf.bundled import baseline_model, models_dir
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.evaluate import KerasKeypointModel, set_tensorflow_threads
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.synthcache import heldout_data

    set_tensorflow_threads(args.threads)
    keras_path = args.keras or baseline_model()
    tflite_path = args.tflite or models_dir() / "fcnpose_ur5_p70_fp16.tflite"
    dataset = load_dataset(args.data or heldout_data())
    frames = [dataset.load_image(i) for i in range(min(len(dataset), 50))]
    a = KerasKeypointModel(keras_path, keras_path, num_threads=args.threads)
    b = KeypointModel(tflite_path, num_threads=args.threads)
    for i in range(args.warmup):
        a.predict(frames[i % len(frames)])
        b.predict(frames[i % len(frames)])
    times = {"keras": [], "tflite": []}
    for i in range(args.frames):
        frame = frames[i % len(frames)]
        times["keras"].append(a.predict(frame).times)
        times["tflite"].append(b.predict(frame).times)

    def stats(ts):
        total = np.array([t.total_ms for t in ts])
        pre = np.array([t.preprocess_ms for t in ts])
        inv = np.array([t.invoke_ms for t in ts])
        post = np.array([t.postprocess_ms for t in ts])
        return {"total_ms_median": float(np.median(total)), "total_ms_p95": float(np.percentile(total, 95)),
                "preprocess_ms_median": float(np.median(pre)), "inference_ms_median": float(np.median(inv)),
                "postprocess_ms_median": float(np.median(post)), "fps_median": 1000.0 / float(np.median(total)),
                "pre_post_share_percent": float(100 * np.median((pre + post) / total))}

    result = {"threads": args.threads, "frames": args.frames, "keras_model": str(keras_path),
              "tflite_model": str(tflite_path), "tflite_backend": b.backend.label,
              "keras": stats(times["keras"]), "tflite": stats(times["tflite"])}
    result["fps_ratio"] = result["tflite"]["fps_median"] / result["keras"]["fps_median"]
    print(f"{args.frames} frames each, interleaved, {args.threads} thread(s); medians in ms")
    print(f"{'path':<38} {'pre':>6} {'infer':>7} {'post':>6} {'total':>7} {'p95':>7} {'FPS':>7} {'pre+post':>9}")
    for key, label in (("keras", f"A unpruned Keras direct ({keras_path.name})"),
                       ("tflite", f"B {tflite_path.name} (LiteRT)")):
        s = result[key]
        print(f"{label[:38]:<38} {s['preprocess_ms_median']:6.2f} {s['inference_ms_median']:7.2f} "
              f"{s['postprocess_ms_median']:6.2f} {s['total_ms_median']:7.2f} {s['total_ms_p95']:7.2f} "
              f"{s['fps_median']:7.1f} {s['pre_post_share_percent']:8.1f}%")
    print(f"FPS ratio B/A: {result['fps_ratio']:.1f}x (target >= 8x; the paper's desktop 41.90/11.71 = 3.6x)")
    print(f"B pre+post share of frame time: {result['tflite']['pre_post_share_percent']:.1f}% (target <= 15%)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
