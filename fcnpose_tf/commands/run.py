"""Run a .tflite model on a camera, a video, an image folder or an image: keypoints per frame, FPS.

Needs only numpy, OpenCV and the LiteRT interpreter (`pip install 'fcnpose-tf[pi]'`).
Each frame's keypoints are written and flushed at once (--out .jsonl or .csv),
optionally drawn on a saved video (--save-video) or a window (--show), with a
rolling FPS on the terminal and a summary of per-stage latencies at the end (for a
camera, also the latency from capture to keypoints written). --via saves the frames
with their keypoints as a VIA project, to correct and train on (docs/data.md).
The Raspberry Pi camera module is read through Picamera2 (--source picamera2; see
docs/raspberry-pi.md for the install). Stop a camera run with Ctrl-C (or q/Esc in the
window); what was processed is kept and named (exit status 130 for Ctrl-C, 143 for SIGTERM, 0 for q/Esc).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fcnpose_tf.settings import add_decoding_arguments

NAME = "run"
PIPELINE_DEFAULT = True
"""`run` pipelines by default: more frames/s than the sequential loop in every measured round
(docs/runtime.md, "Pipelined run"); --no-pipeline gives the lower per-frame latency."""
OUTPUTS = ("out", "save_video", "via")
FILE_OUTPUTS = ("out", "save_video", "via")
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
EXAMPLES = """\
  fcnpose-tf run model.tflite --source 0 --show                        # camera 0 in a window
  fcnpose-tf run model.tflite --source /dev/video0 --out k.jsonl --threads 4
  fcnpose-tf run model.tflite --source clip.mp4 --out k.jsonl --save-video overlay.mp4
  fcnpose-tf run model.tflite --source frames/ --out k.csv             # every image in a folder
  fcnpose-tf run workcell-p70-int8 --source frame.png --out k.jsonl --force  # the bundled int8 file, by name
  fcnpose-tf run model.tflite --source picamera2 --out k.jsonl         # Pi camera module (Picamera2)
  fcnpose-tf run model.tflite --source picamera2:1 --camera-size 1280x720 --out k.jsonl
  fcnpose-tf run model.tflite --source 0 --via hard/frames.json --via-every 30  # 1 frame/s to correct in VIA
  fcnpose-tf run model.tflite --source clip.mp4 --track --out k.jsonl  # a crop following the arm, frame to frame
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.smoothing import add_smoothing_arguments

    from fcnpose_tf.bundled import TFLITE_SUFFIXES, model_argument, names_help

    parser.add_argument("model", type=model_argument(TFLITE_SUFFIXES), metavar="MODEL",
                        help=f"an FCN-Pose .tflite model, a file or a bundled one by name ({names_help(TFLITE_SUFFIXES)})")
    parser.add_argument("--source", required=True,
                        help="camera index (0), /dev/videoN, stream URL, picamera2[:N] (Pi camera module), "
                             "video file, image folder or image")
    settings.RUN_THREADS.add_to(parser)
    parser.add_argument("--out", action="append", default=[], metavar="FILE",
                        help="keypoints per frame, .jsonl or .csv (may be given twice)")
    parser.add_argument("--save-video", type=Path, metavar="FILE",
                        help="video with keypoints, skeleton and FPS drawn (.mp4, .avi, .mkv, .mov)")
    parser.add_argument("--show", action="store_true", help="show the overlay in a window (q/Esc to stop)")
    settings.MAX_FRAMES.add_to(parser)
    add_decoding_arguments(parser, fallback=True)
    parser.add_argument("--camera-size", metavar="WxH",
                        help="ask the camera for this resolution, e.g. 640x480 (picamera2's default: 640x480)")
    parser.add_argument("--via", type=Path, metavar="OUT.json",
                        help="also write a VIA project of the processed frames (saved as PNGs in images/ "
                             "beside it, image files referenced) with their keypoints, to correct in VIA")
    parser.add_argument("--via-every", type=int, default=1, metavar="N",
                        help="with --via: keep every Nth processed frame (a camera's frames add up fast)")
    parser.add_argument("--pipeline", action=argparse.BooleanOptionalAction, default=PIPELINE_DEFAULT,
                        help="run the interpreter on its own thread, overlapping it with reading and "
                             "preprocessing the next frame and writing the previous one (same keypoints; "
                             "docs/runtime.md, pipelined run)")
    parser.add_argument("--track", action="store_true",
                        help="read each frame over a crop about the previous frame's keypoints (their box and a "
                             "quarter of it on each side, at the input's aspect; the model's own view for the first "
                             "frame and after one that lost the arm): on video where views vary, the arm gets the "
                             "input's pixels instead of its share of the whole frame (docs/runtime.md, \"A crop that "
                             "follows the arm\"); sequential, no pipelining")
    add_smoothing_arguments(parser)
    add_backend_argument(parser)
    settings.FORCE.add_to(parser)


def add_backend_argument(parser: argparse.ArgumentParser) -> None:
    """--backend, shared by `run` and `bench`; the choices are the runtime's own fallback list."""
    from fcnpose_tf.runtime.interpreter import BACKENDS  # numpy only, no TensorFlow

    parser.add_argument("--backend", default="auto", choices=("auto", *BACKENDS),
                        help="interpreter package (auto: LiteRT, then tflite_runtime, then tf.lite)")


def run(args: argparse.Namespace) -> int:
    import sys

    from fcnpose_tf import settings
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_writable, stop_signals_as_interrupt, stop_signals_ignored
    from fcnpose_tf.correction.prelabel import ViaPredictions, check_via_output
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.runtime.runner import ProgressLine, check_display, run_stream
    from fcnpose_tf.runtime.sinks import VideoSink, open_record_writer, parse_outputs
    from fcnpose_tf.runtime.sources import open_source, parse_size
    from fcnpose_tf.smoothing import params_from_args
    from fcnpose_tf.system import oversubscription_note

    settings.MAX_FRAMES.validate(args.max_frames)
    oversubscribed = oversubscription_note([args.threads]) if args.threads else None
    if oversubscribed:
        print(f"warning: {oversubscribed}", file=sys.stderr)
    # Every output is checked before the model loads or the camera opens: fail in a second, not after a run.
    outs = parse_outputs(args.out)
    for path in outs:
        check_writable(path, args.force)
    if args.save_video is not None:
        if args.save_video.resolve() in {p.resolve() for p in outs}:
            raise UserError(f"{args.save_video}: given both as --out and --save-video")
        check_writable(args.save_video, args.force)
    if args.via is not None:
        check_via_output(args.via, args.force, every=args.via_every)
    camera_size = parse_size(args.camera_size) if args.camera_size else None
    if args.show:
        check_display()

    model = KeypointModel(args.model, args.threads, Decoding.from_args(args), backend=args.backend)
    if model.backend.skipped:
        print(f"note: using {model.backend.label} ({'; '.join(model.backend.skipped)})", file=sys.stderr)
    if args.track:
        from fcnpose_tf.runtime.tracking import TrackingCrop

        model = TrackingCrop(model)
    writers = []
    video = None
    source = open_source(args.source, camera_size)
    collected = None
    finished = False
    try:
        for path in outs:
            writers.append(open_record_writer(path, model.schema, args.force))
        if args.save_video is not None:
            video = VideoSink(args.save_video, source.fps, args.force)
        if args.via is not None:
            collected = ViaPredictions(args.via, model.schema, source, args.force, every=args.via_every)
        print(f"{model.describe()}; {source.describe()}", file=sys.stderr, flush=True)
        with stop_signals_as_interrupt():  # Ctrl-C or a `kill` ends the run: outputs closed, summary printed
            summary = run_stream(model, source, writers, video, args.show, args.max_frames, ProgressLine(),
                                 on_frame=collected.add if collected is not None else None,
                                 smooth=params_from_args(args), pipelined=args.pipeline)
        finished = True
    finally:
        with stop_signals_ignored():  # the outputs closed whole: a further Ctrl-C or `kill` waits for them
            source.close()
            for writer in writers:
                writer.close()
            if not finished:
                if video is not None:
                    video.discard()
                if collected is not None:
                    collected.discard()
    with stop_signals_ignored():
        try:
            if summary.frames == 0:  # before the report: the outputs it would name are removed with the error
                raise UserError(f"{args.source}: no frame was processed ({summary.end_reason})")
            if collected is not None:
                written_via = collected.close()
                summary.outputs.append(f"{written_via}: {collected.describe()}" if written_via else
                                       f"{args.via}: not written (no frames)")
            if video is not None:
                written = video.close()
                summary.outputs.append(f"{written} ({video.count} frames)" if written else
                                       f"{args.save_video}: not written (no frames)")
        finally:
            if video is not None:
                video.discard()  # one a failure above left unfinished: no temporary file stays (no-op after close)
    print(summary.report(model, source))
    if source.failed:  # the frames ended because the camera failed, not by a stop or --max-frames: a script sees it
        print(f"error: {source.end_reason}: the run ended early (its outputs are kept)", file=sys.stderr)
        return 1
    return 0
