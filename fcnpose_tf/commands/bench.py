"""Benchmark .tflite models: invoke-only and end-to-end latency and FPS per thread count.

Prints the model's parameters, MACs and file size, then one row per thread
count: invoke and end-to-end (preprocess + invoke + postprocess) median and
p95 latency, mean ± std, the share of pre/post-processing, and FPS
(1000 / mean end-to-end ms) next to the invoke-only rate. Needs only the `pi`
extra. The frame is synthetic unless --image is given (post-processing time
depends on what the model sees: use a real frame for a trained model; a synthetic one is of the
frames the model's crop was set on). Several models are measured one after the other on the same
frame (synthetic: of the same size, where their crops were set on frames of one size), each with its
own table (the bundled int8 file beside the float16 one, for instance); compare them with the same
thread count.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fcnpose_tf.settings import add_decoding_arguments

NAME = "bench"
OUTPUTS = ("json",)
FILE_OUTPUTS = ("json",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
MAX_FRAME_SIDE = 8192
"""The largest synthetic frame side --frame-size takes (8192x8192 is 200 MB of pixels)."""
EXAMPLES = """\
  fcnpose-tf bench model.tflite                              # 1, 2, 4 ... up to all cores
  fcnpose-tf bench model.tflite --threads 1,2,4 --frames 200 --json bench.json
  fcnpose-tf bench model.tflite --image frame.png --markdown # a real frame; a table for docs
  fcnpose-tf bench workcell-p70-int8 workcell-p70-fp16 --threads 1   # the bundled files, by name
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings

    from fcnpose_tf.bundled import TFLITE_SUFFIXES, model_argument, names_help

    parser.add_argument("model", type=model_argument(TFLITE_SUFFIXES), nargs="+", metavar="MODEL",
                        help=f"one or more FCN-Pose .tflite models, files or bundled ones by name "
                             f"({names_help(TFLITE_SUFFIXES)})")
    settings.BENCH_THREADS.add_to(parser)
    parser.add_argument("--frames", type=int, default=200, help="timed frames per thread count (>= 50 advised)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed frames first, per thread count")
    parser.add_argument("--image", type=Path, help="benchmark on this image instead of a synthetic frame")
    parser.add_argument("--frame-size", default=None, metavar="WxH",
                        help="size of the synthetic frame (default: for each model the frames its crop was set on, "
                             "else 640x480)")
    add_decoding_arguments(parser, fallback=False)
    parser.add_argument("--json", type=Path, metavar="FILE",
                        help="also write the results as JSON (several models: {\"models\": [one result each]})")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    from fcnpose_tf.commands.run import add_backend_argument

    add_backend_argument(parser)
    settings.FORCE.variant(help="replace an existing --json file").add_to(parser)


def run(args: argparse.Namespace) -> int:
    import signal
    import sys

    from fcnpose_tf import fileio
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_writable, write_json
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.progress import Reporter
    from fcnpose_tf.runtime.bench import benchmark, comparison_table, crop_frame_size, load_frame
    from fcnpose_tf.runtime.sources import parse_size

    threads = args.threads or None
    if args.json is not None:
        check_writable(args.json, args.force)
    frame_size = parse_size(args.frame_size) if args.frame_size is not None else None
    if frame_size is not None and max(frame_size) > MAX_FRAME_SIDE:  # 30000x30000: 2.7 GB of pixels
        raise UserError(f"--frame-size {args.frame_size}: at most {MAX_FRAME_SIDE} pixels a side (an 8K frame is "
                        "7680x4320); for a real camera's frame pass --image")
    sizes = [frame_size or crop_frame_size(model) for model in args.model]  # each model's own frames: no aspect warning
    frames = {size: load_frame(args.image, size) for size in set(sizes)}
    reports = []
    progress = Reporter(stream=sys.stderr)  # the tables go to stdout
    for i, (model, size) in enumerate(zip(args.model, sizes)):
        frame, label = frames[size]
        try:
            reports.append(benchmark(model, threads, args.frames, args.warmup, frame, label, args.backend,
                                     decoding=Decoding.from_args(args), reporter=progress))
        except KeyboardInterrupt:  # stopped before this model's first count finished: the earlier models stand
            if not reports:
                raise
            stopped = True
        else:
            print(("\n" if i else "") + reports[-1].report(markdown=args.markdown))
            stopped = reports[-1].stopped_after is not None
        if stopped:  # what finished is printed (and written with --json); the exit path says stopped, status 130
            if fileio.stop_signal() is None:  # a KeyboardInterrupt no handler of ours saw
                fileio.note_stop_signal(signal.SIGINT)
            break
    if len(reports) > 1:
        print("\nComparison (the models ran one after the other; for a speed claim, repeat in the other order):")
        print(comparison_table(reports, markdown=args.markdown))
    if args.json is not None:
        data = reports[0].to_dict() if len(reports) == 1 else {"models": [r.to_dict() for r in reports]}
        write_json(args.json, data, force=args.force)
        print(f"Wrote:   {args.json}")
    return 0 if all(r.ok for report in reports for r in report.results) else 1
