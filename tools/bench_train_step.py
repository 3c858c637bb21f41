#!/usr/bin/env python
"""Time one FCN-Pose training step (Adam, keypoint-weighted BCE) with conv1..convN frozen, N = 0..3, through the whole
network and, with N >= 1, past the fixed prefix computed once (`training.frozen`: what `train` does on the paper's
copies when the features fit in memory).

Usage:
    python tools/bench_train_step.py                         # 224 x 224, batch 8, 1 thread, 6 rounds
    python tools/bench_train_step.py --threads 2 --rounds 10 --input-size 160
    python tools/bench_train_step.py --rate 0.7              # the 70 %-pruned network (compress's retraining)
    python tools/bench_train_step.py --input-size 224x256 --skip --max-frozen 2   # held-out fixed camera's network

All variants train on the same random batch, interleaved round by round, so load from other
processes hits them alike; the table gives the median seconds per batch and the speed-up over
training every layer (what `train --freeze` buys per step; docs/training.md).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--input-size", default="224", help="S or HxW (default 224)")
    parser.add_argument("--skip", action="store_true", help="FCN-Pose with its skip (fcn-pose-skip)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--max-frozen", type=int, default=3, help="time --freeze 0..N (default 3)")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="time the network pruned at this rate (the keep rule's widths; default 0: unpruned)")
    args = parser.parse_args()

    from fcnpose_tf.training.tfsetup import set_tensorflow_threads

    set_tensorflow_threads(args.threads)
    from fcnpose_tf.training.model import DEFAULT_WIDTHS, build_fcn_pose
    from fcnpose_tf.compression.keep_rule import pruned_widths
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.settings import input_size_or_auto
    from fcnpose_tf.training.frozen import split_frozen
    from fcnpose_tf.training.train import compile_for_training, freeze_first_convolutions

    rng = np.random.default_rng(0)
    view, batch = FrameView.of(input_size_or_auto(args.input_size)), args.batch_size
    height, width = view.shape
    pixels = rng.integers(0, 256, (batch, height, width, 3), dtype=np.uint8)
    images = pixels.astype(np.float32) / 255
    maps = (rng.random((batch, height, width, 9)) > 0.97).astype(np.float32)
    variants = {}  # (frozen, past the prefix) -> (model, its input)
    for frozen in range(args.max_frozen + 1):
        model = build_fcn_pose(pruned_widths(DEFAULT_WIDTHS, args.rate), input_size=view, skip=args.skip)
        freeze_first_convolutions(model, frozen)
        variants[frozen, False] = model, images
        prefix = split_frozen(model)
        if prefix is not None:
            features = prefix.features(pixels)
            variants[frozen, True] = prefix.head, features[0] if len(features) == 1 else features
    for model, inputs in variants.values():
        compile_for_training(model, 1e-3, 20.0)
        for _ in range(2):  # trace and warm up
            model.train_on_batch(inputs, maps)
    seconds = {key: [] for key in variants}
    for _ in range(args.rounds):
        for key, (model, inputs) in variants.items():
            start = time.perf_counter()
            model.train_on_batch(inputs, maps)
            seconds[key].append(time.perf_counter() - start)
    every_layer = float(np.median(seconds[0, False]))
    print(f"{view.describe(whole='')}{' with the skip' if args.skip else ''}, widths "
          f"{pruned_widths(DEFAULT_WIDTHS, args.rate)}, batch {batch}, {args.threads} thread(s), {args.rounds} "
          "interleaved rounds, medians")
    print("| --freeze | fixed layers | s/batch | s/image | speed-up |")
    print("|---|---|---|---|---|")
    for (frozen, past), values in seconds.items():
        median = float(np.median(values))
        how = "computed once" if past else "every batch" if frozen else "-"
        print(f"| {frozen} | {how} | {median:.3f} | {median / batch:.4f} | {every_layer / median:.2f}x |")
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
