#!/usr/bin/env python
"""`run`'s delivered FPS on a video, sequential against pipelined, beside the invoke-only FPS, interleaved.

    python tools/bench_pipeline.py saved_models/fcnpose_ur5_p70_int8.tflite --video clip.mp4 --threads 2
    python tools/bench_pipeline.py saved_models/fcnpose_ur5_p70_int8.tflite saved_models/fcnpose_ur5_p70_fp16.tflite \
        --video clip.mp4 --threads 2 --rounds 7 --json pipe.json

Each round runs, for every model, in an order that alternates between rounds: the sequential loop and
the pipelined loop of `run_stream` over the whole video (decoded from the file, records written to a
JSON Lines file, as `fcnpose-tf run --source VIDEO --out k.jsonl` does), then the invoke-only rate:
`--invokes` bare `interpreter.invoke()` calls on the video's first frame. Delivered FPS is
`RunSummary.delivered_fps` (first frame's records written to the last's: no start-up, no warm-up).
The table gives per-model medians over rounds, the ratio of each loop's delivered FPS to the
invoke-only FPS of the same round (its median), and pipelined / sequential. The two loops' keypoints
are compared on every round (they must be identical).

A video to measure: `fcnpose-tf synth --out /tmp/seq --n 300 --motion 30` writes /tmp/seq/motion.mp4.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def invoke_only_fps(model, frame: np.ndarray, invokes: int) -> float:
    """1000 / mean ms of bare invokes on one preprocessed frame (the `FPS invoke` of `bench`)."""
    model.set_input(frame)
    model.invoke()
    start = time.perf_counter()
    for _ in range(invokes):
        model.invoke()
    return invokes / (time.perf_counter() - start)


def one_run(model, video: Path, pipelined: bool, folder: Path):
    """(delivered FPS, per-frame read-to-written p50 ms, keypoints per frame) of one pass over the video."""
    from fcnpose_tf.runtime.runner import run_stream
    from fcnpose_tf.runtime.sinks import open_record_writer
    from fcnpose_tf.runtime.sources import open_source

    keypoints = []
    path = folder / f"{'pipe' if pipelined else 'seq'}.jsonl"
    with open_record_writer(path, model.schema, force=True) as writer, open_source(video) as source:
        summary = run_stream(model, source, [writer], pipelined=pipelined,
                             on_frame=lambda frame, pred: keypoints.append(pred.keypoints.copy()))
    return summary.delivered_fps, float(np.median(summary.read_to_keypoints_ms)), np.stack(keypoints)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("models", nargs="+", type=Path, help=".tflite files")
    parser.add_argument("--video", type=Path, required=True, help="a video file")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--invokes", type=int, default=200, help="bare invokes per round for the invoke-only FPS")
    parser.add_argument("--json", type=Path, help="also write the per-round figures here")
    parser.add_argument("--force", action="store_true", help="overwrite --json if it exists")
    args = parser.parse_args(argv)

    from fcnpose_tf.fileio import check_writable, write_json

    if args.json:
        check_writable(args.json, args.force)  # before the measurement, not after

    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.runtime.sources import open_source
    from fcnpose_tf.tables import format_table

    with open_source(args.video) as source:
        first = next(iter(source)).image
    models = {path: KeypointModel(path, args.threads) for path in args.models}
    rounds: dict[str, list[dict]] = {str(p): [] for p in models}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            order = list(models.items()) if r % 2 == 0 else list(models.items())[::-1]
            for path, model in order:
                modes = (False, True) if r % 2 == 0 else (True, False)
                row, kps = {}, {}
                for pipelined in modes:
                    name = "pipelined" if pipelined else "sequential"
                    row[f"{name}_fps"], row[f"{name}_latency_p50_ms"], kps[name] = one_run(
                        model, args.video, pipelined, Path(tmp))
                row["invoke_only_fps"] = invoke_only_fps(model, first, args.invokes)
                row["identical_keypoints"] = bool(np.array_equal(kps["sequential"], kps["pipelined"],
                                                                 equal_nan=True))
                rounds[str(path)].append(row)
                print(f"round {r + 1}/{args.rounds} {path.name}: " + ", ".join(
                    f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()),
                    file=sys.stderr, flush=True)

    def med(rows, key):
        return statistics.median(row[key] for row in rows)

    table = []
    for path, rows in rounds.items():
        seq_ratio = statistics.median(row["sequential_fps"] / row["invoke_only_fps"] for row in rows)
        pipe_ratio = statistics.median(row["pipelined_fps"] / row["invoke_only_fps"] for row in rows)
        gain = statistics.median(row["pipelined_fps"] / row["sequential_fps"] for row in rows)
        table.append((Path(path).name, round(med(rows, "invoke_only_fps"), 1), round(med(rows, "sequential_fps"), 1),
                      round(med(rows, "pipelined_fps"), 1), round(seq_ratio, 3), round(pipe_ratio, 3),
                      round(gain, 3), round(med(rows, "sequential_latency_p50_ms"), 1),
                      round(med(rows, "pipelined_latency_p50_ms"), 1),
                      "yes" if all(row["identical_keypoints"] for row in rows) else "NO"))
    load = os.getloadavg()
    print(f"{args.video} ({len(next(iter(models.values())).schema.keypoints)} keypoints), {args.threads} "
          f"interpreter threads, {args.rounds} interleaved rounds, medians; {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
    print(format_table(["Model", "Invoke-only FPS", "Sequential FPS", "Pipelined FPS", "Seq / invoke",
                        "Pipe / invoke", "Pipe / seq", "Seq latency p50 (ms)", "Pipe latency p50 (ms)",
                        "Same keypoints"], table))
    print("Delivered FPS: frames/s from the first frame's records written to the last's; latency: from the "
          "source handing a frame over to its records written.")
    if args.json:
        write_json(args.json, {"video": str(args.video), "threads": args.threads, "rounds": rounds,
                               "load_average": load}, force=args.force)
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
