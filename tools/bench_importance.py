#!/usr/bin/env python
"""Time a data-aware filter criterion (taylor, activation) as compress runs it: each batch one TensorFlow graph,
against the same code run eagerly (`tf.config.run_functions_eagerly`), interleaved round by round.

Usage:
    python tools/bench_importance.py                               # taylor, fcn-pose-skip at 288 x 288, 16 frames
    python tools/bench_importance.py --model hr.keras --frames 32 --threads 2 --rounds 3
    python tools/bench_importance.py --criterion activation --input-size 224x256

Each round scores the model once per variant on the same random frames (a fresh criterion, so a round's first
call includes building the graph, as in one compress run); the table gives each variant's median seconds, per frame,
and the ratio.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", help="a .keras/.h5 model (default: an untrained fcn-pose-skip at --input-size)")
    parser.add_argument("--input-size", default="288", help="S or HxW without --model (default 288)")
    parser.add_argument("--criterion", choices=("taylor", "activation"), default="taylor")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()

    from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_threads

    import_tensorflow_quietly()
    set_tensorflow_threads(args.threads)
    import tensorflow as tf

    from fcnpose_tf.compression.importance import make_importance
    from fcnpose_tf.settings import input_size_or_auto
    from fcnpose_tf.tables import format_table
    from fcnpose_tf.training.model import build_fcn_pose, load_model
    from fcnpose_tf.training.train import ground_truth_loss

    model = load_model(args.model) if args.model else build_fcn_pose(input_size=input_size_or_auto(args.input_size),
                                                                     skip=True)
    height, width = int(model.input.shape[1]), int(model.input.shape[2])
    maps = int(model.output.shape[-1])
    rng = np.random.default_rng(0)
    images = rng.random((args.frames, height, width, 3), dtype=np.float32)
    targets = (rng.random((args.frames, height, width, maps)) > 0.95).astype(np.float32)
    extra = {"maps": targets, "loss": ground_truth_loss(20.0)} if args.criterion == "taylor" else {}

    times: dict[str, list[float]] = {"graph": [], "eager": []}
    for _ in range(args.rounds):
        for variant in times:
            tf.config.run_functions_eagerly(variant == "eager")
            criterion = make_importance(args.criterion, images=images, batch_size=args.batch_size, **extra)
            start = time.perf_counter()
            criterion(model)
            times[variant].append(time.perf_counter() - start)
    tf.config.run_functions_eagerly(False)

    medians = {variant: statistics.median(values) for variant, values in times.items()}
    rows = [[variant, f"{medians[variant]:.2f}", f"{medians[variant] / args.frames:.3f}",
             f"{medians['eager'] / medians[variant]:.2f}x"] for variant in times]
    print(f"{args.criterion} on {args.frames} frames at {height}x{width}, batch {args.batch_size}, "
          f"{args.threads} thread(s), median of {args.rounds} interleaved rounds")
    print(format_table(["variant", "s", "s / frame", "speed-up over eager"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
