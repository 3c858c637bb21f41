#!/usr/bin/env python
"""What distillation costs while retraining (docs/compression.md, "Importance criteria and distillation").

Retrains the bundled baseline pruned at --rate for one epoch at a time on the same training rows,
alternating plain epochs (the ground-truth loss) with distilled ones (--distill W, the teacher's maps
cached once beforehand, as `compress` does for the paper's offline copies), so both see the same
load; then, for online augmentation, times epochs whose teacher maps are computed per batch.
Prints the median epoch time of each, the one-off cost of caching the teacher's maps, and the
ratio of a whole retraining (--epochs epochs plus the cache) with and without distillation.

    python tools/bench_distill.py --threads 1 --frames 32 --rounds 3
"""

from __future__ import annotations

import argparse
import statistics
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=0.7)
    parser.add_argument("--distill", type=float, default=0.5)
    parser.add_argument("--frames", type=int, default=32, help="training frames (x3 rows with the paper's copies)")
    parser.add_argument("--rounds", type=int, default=3, help="plain/distilled epoch pairs")
    parser.add_argument("--epochs", type=int, default=25, help="retraining budget the total ratio is put for")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--online", action="store_true", help="also time online augmentation (per-batch teacher)")
    args = parser.parse_args()

    from fcnpose_tf.training.tfsetup import set_tensorflow_threads

    set_tensorflow_threads(args.threads)
    import tf_keras as keras

    from fcnpose_tf.data import synthcache
    from fcnpose_tf.bundled import baseline_model
    from fcnpose_tf.data.dataset import TrainingData, load_dataset
    from fcnpose_tf.training.distill import with_teacher_maps
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.compression.prune import prune_model
    from fcnpose_tf.training.train import compile_for_training

    teacher = load_model(baseline_model())
    size = int(teacher.input_shape[1])
    dataset = load_dataset(synthcache.default_training_data())
    train_idx, _ = dataset.split(None)
    data = TrainingData(dataset, train_idx[:args.frames], size, 2, seed=0)

    def student(distill: float) -> keras.Model:
        model = prune_model(teacher, args.rate)
        return compile_for_training(model, 1e-3, 20.0, distill)

    def epoch(model: keras.Model, sequence) -> float:
        start = time.perf_counter()
        model.fit(sequence, epochs=1, verbose=0)
        return time.perf_counter() - start

    plain_model, distilled_model = student(0.0), student(args.distill)
    plain_seq = data.sequence(8, seed=0)
    start = time.perf_counter()
    distilled_seq, _ = with_teacher_maps(data, data.sequence(8, seed=0), teacher)
    cache_seconds = time.perf_counter() - start
    epoch(plain_model, plain_seq), epoch(distilled_model, distilled_seq)  # warm-up: tracing, first allocations
    plain, distilled = [], []
    for i in range(args.rounds):
        order = [(plain_model, plain_seq, plain), (distilled_model, distilled_seq, distilled)]
        for model, sequence, times in (order if i % 2 == 0 else order[::-1]):
            times.append(epoch(model, sequence))
    p = statistics.median(plain)
    ratio = statistics.median(b / a for a, b in zip(plain, distilled))  # pairs ran back to back: same load
    print(f"{len(data)} rows at {size}x{size}, rate {args.rate:g}, {args.threads} thread(s), {args.rounds} rounds")
    print(f"plain epoch        {['%.2f' % t for t in plain]} s (median {p:.2f})")
    print(f"distilled epoch    {['%.2f' % t for t in distilled]} s; median ratio of the pairs {ratio:.2f}x")
    print(f"teacher maps cached once: {cache_seconds:.2f} s (= {cache_seconds / p:.2f} median plain epochs)")
    total = (args.epochs * ratio + cache_seconds / p) / args.epochs
    print(f"{args.epochs}-epoch retraining with distillation / without: {total:.2f}x "
          f"(1 epoch: {ratio + cache_seconds / p:.2f}x)")
    if args.online:
        from fcnpose_tf.data.online import OnlineTrainingData

        online = OnlineTrainingData(dataset, train_idx[:args.frames], size, seed=0)
        plain_online = online.sequence(8)
        distilled_online, _ = with_teacher_maps(online, online.sequence(8), teacher)
        epoch(plain_model, plain_online), epoch(distilled_model, distilled_online)
        po, do = [], []
        for i in range(args.rounds):
            order = [(plain_model, plain_online, po), (distilled_model, distilled_online, do)]
            for model, sequence, times in (order if i % 2 == 0 else order[::-1]):
                times.append(epoch(model, sequence))
        online_ratio = statistics.median(b / a for a, b in zip(po, do))
        print(f"online: plain epoch {['%.2f' % t for t in po]} s, per-batch teacher {['%.2f' % t for t in do]} s; "
              f"median ratio of the pairs {online_ratio:.2f}x")
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
