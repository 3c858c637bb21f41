"""Benchmark a .tflite model: invoke-only and end-to-end latency and FPS per thread count.

Prints the model's parameters, MACs and file size, then one row per thread
count: invoke and end-to-end (preprocess + invoke + postprocess) median and
p95 latency, mean ± std, the share of pre/post-processing, and FPS
(1000 / mean end-to-end ms) next to the invoke-only rate. Needs only the `pi`
extra. The frame is synthetic unless --image is given (post-processing time
depends on what the model sees: use a real frame for a trained model).
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "bench"
EXAMPLES = """\
  fcnpose-tf bench model.tflite                              # 1, 2, 4 ... up to all cores
  fcnpose-tf bench model.tflite --threads 1,2,4 --frames 200 --json bench.json
  fcnpose-tf bench model.tflite --image frame.png --markdown # a real frame; a table for docs
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.settings import thread_counts

    parser.add_argument("model", type=Path, help="an FCN-Pose .tflite model")
    parser.add_argument("--threads", type=thread_counts, default=None, metavar="N,N,...",
                        help="thread counts to compare (default: 1, 2, 4 ... up to all cores)")
    parser.add_argument("--frames", type=int, default=200, help="timed frames per thread count (>= 50 advised)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames first, per thread count")
    parser.add_argument("--image", type=Path, help="benchmark on this image instead of a synthetic frame")
    parser.add_argument("--frame-size", default="640x480", metavar="WxH", help="size of the synthetic frame")
    parser.add_argument("--threshold", type=float, default=0.5, help="post-processing threshold")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the results as JSON")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    from fcnpose_tf.commands.run import add_backend_argument

    add_backend_argument(parser)
    parser.add_argument("--force", action="store_true", help="replace an existing --json file")


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.fileio import check_writable, write_json
    from fcnpose_tf.runtime.bench import benchmark, load_frame, print_progress
    from fcnpose_tf.runtime.sources import parse_size

    threads = args.threads or None
    if args.json is not None:
        check_writable(args.json, args.force)
    frame, label = load_frame(args.image, parse_size(args.frame_size))
    report = benchmark(args.model, threads, args.frames, args.warmup, frame, label, args.backend,
                       args.threshold, progress=print_progress)
    print(report.report(markdown=args.markdown))
    if args.json is not None:
        write_json(args.json, report.to_dict(), force=args.force)
        print(f"Wrote:   {args.json}")
    return 0 if all(r.ok for r in report.results) else 1
