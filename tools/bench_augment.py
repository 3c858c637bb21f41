"""What online augmentation costs per training epoch, against the paper's offline copies.

Trains the same model for one epoch on each feed, interleaved for several rounds, and prints the
median epoch time of each and their ratio (one Keras epoch = the same number of samples for both:
3 x the frames, as two offline copies give). Also prints the feed alone (building the batches
without training), so the share of the augmentation in an epoch is visible.

    python tools/bench_augment.py --data DATA [--frames 64] [--input-size 224] [--rounds 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="dataset folder or VIA file")
    parser.add_argument("--frames", type=int, default=64, help="training frames used (default 64)")
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="TensorFlow threads (default: all cores)")
    args = parser.parse_args()

    from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_threads

    import_tensorflow_quietly()
    set_tensorflow_threads(args.threads)
    from fcnpose_tf.data.dataset import TrainingData, load_dataset
    from fcnpose_tf.data.online import OnlineTrainingData
    from fcnpose_tf.training.model import build_fcn_pose
    from fcnpose_tf.tables import format_table
    from fcnpose_tf.training.train import compile_for_training

    dataset = load_dataset(args.data)
    indices = list(range(min(args.frames, len(dataset))))
    feeds = {"paper (2 offline copies)": TrainingData(dataset, indices, args.input_size, 2, seed=0),
             "online": OnlineTrainingData(dataset, indices, args.input_size, seed=0)}
    model = compile_for_training(build_fcn_pose(input_size=args.input_size), 1e-3, 20.0)
    epoch_s: dict[str, list[float]] = {name: [] for name in feeds}
    feed_s: dict[str, list[float]] = {name: [] for name in feeds}
    for _ in range(args.rounds):
        for name, feed in feeds.items():
            sequence = feed.sequence(8, seed=0)
            start = time.perf_counter()
            for batch in range(len(sequence)):
                sequence[batch]
            feed_s[name].append(time.perf_counter() - start)
            start = time.perf_counter()
            model.fit(feed.sequence(8, seed=0), epochs=1, verbose=0)
            epoch_s[name].append(time.perf_counter() - start)
    base = statistics.median(epoch_s["paper (2 offline copies)"])
    rows = [[name, len(feeds[name]), statistics.median(feed_s[name]), statistics.median(epoch_s[name]),
             statistics.median(epoch_s[name]) / base] for name in feeds]
    print(f"{len(indices)} frames at {args.input_size}x{args.input_size}, {args.threads or 'all'} TensorFlow "
          f"thread(s), median of {args.rounds} interleaved rounds")
    print(format_table(["feed", "samples/epoch", "feed alone s", "epoch s", "epoch vs paper"], rows,
                       digits=[None, None, 2, 2, 2]))
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
