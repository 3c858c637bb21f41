"""Pre-annotate frames: a model's keypoints written as a VIA project, to correct in VIA and train on.

Runs a .keras or .tflite FCN-Pose (a .tflite needs only LiteRT, no TensorFlow) over the images
of a folder, one image, or every Nth frame of a video, and writes a VIA 2.x project with one
named `point` region per keypoint found. Keypoints not found, or found with a confidence (pixels
of the keypoint's cluster in the output map) below --min-confidence, get no point and are counted.
Image files are referenced where they are; video frames are saved as PNGs in images/ beside the
VIA file. Open the project in VIA 2 (Project > Load), move, add or delete points, save the
project, and train on it: `fcnpose-tf train --data out.json`. See docs/data.md, "Pre-annotation".

With --select N only the N frames most worth correcting are written (--by uniform, uncertain, jump or
disagree; never two within --min-gap frames): every processed frame is scored first, then the picked
ones are read again and written (docs/data.md, "Correcting and merging rounds").

With --draw DIR every frame written is also drawn in DIR with the points it gets (skeleton, dots, names), and
DIR/contact_sheet.png shows up to 12 of them (all the picks of --select N <= 12): look before you correct.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from fcnpose_tf.settings import add_decoding_arguments

NAME = "predict"
OUTPUTS = ("via", "draw")
FILE_OUTPUTS = ("via",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
EXAMPLES = """\
  fcnpose-tf predict generalist --source frames/ --via frames/pre.json     # a bundled model by name
  fcnpose-tf predict models/arm.keras --source clip.mp4 --every 10 --via clip_labels/pre.json
  fcnpose-tf predict model.tflite --source frames/ --via pre.json --min-confidence 20 --force
  fcnpose-tf predict models/arm.keras --source clip.mp4 --via round2/pre.json --select 40          # spread evenly
  fcnpose-tf predict models/arm.keras --source clip.mp4 --via round2/pre.json --select 40 --by jump --min-gap 15
  fcnpose-tf predict models/arm.keras --source frames/ --via pre.json --select 12 --by uncertain --draw picks/
  fcnpose-tf data inspect frames/pre.json                  # what the project holds, as training sees it
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.smoothing import add_smoothing_arguments

    from fcnpose_tf.bundled import model_argument, names_help

    parser.add_argument("model", nargs="?", type=model_argument(), default="workcell", metavar="MODEL",
                        help=f"a .keras/.h5 or .tflite model, or a bundled one by name ({names_help()})")
    parser.add_argument("--source", required=True, help="image folder, image file or video file")
    parser.add_argument("--via", type=Path, required=True, metavar="OUT.json",
                        help="the VIA 2.x project to write (video frames go to images/ beside it)")
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="use every Nth frame of the video or image folder")
    parser.add_argument("--min-confidence", type=float, default=0.0, metavar="C",
                        help="leave out keypoints whose map cluster has fewer than C pixels")
    settings.MAX_FRAMES.add_to(parser)
    settings.INFERENCE_THREADS.add_to(parser)
    parser.add_argument("--select", type=int, default=None, metavar="N",
                        help="write only the N frames most worth correcting (scored over every processed frame)")
    settings.SELECT_BY.add_to(parser)
    parser.add_argument("--min-gap", type=int, default=None, metavar="FRAMES",
                        help="--select: no two picks closer than this many source frames (default: one second of "
                             "video at its frame rate; 1 for images)")
    parser.add_argument("--draw", type=Path, default=None, metavar="DIR",
                        help="draw every frame written with its points in DIR, and DIR/contact_sheet.png")
    add_decoding_arguments(parser, fallback=True)
    add_smoothing_arguments(parser, video_only=True)
    settings.FORCE.variant(help="replace an existing VIA file, earlier saved frames of the same names, and pictures "
                                "in --draw's folder").add_to(parser)


def run(args: argparse.Namespace) -> int:
    import sys

    from fcnpose_tf import settings
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.training.evaluate import open_model
    from fcnpose_tf.fileio import stop_signals_as_interrupt, stop_signals_ignored
    from fcnpose_tf.correction.prelabel import check_via_output
    from fcnpose_tf.runtime.runner import ProgressLine, run_stream
    from fcnpose_tf.runtime.sources import open_source
    from fcnpose_tf.smoothing import params_from_args

    if args.every < 1:
        raise UserError(f"--every must be at least 1, got {args.every}")
    settings.MAX_FRAMES.validate(args.max_frames)
    if args.select is not None and args.select < 1:
        raise UserError(f"--select must be at least 1, got {args.select}")
    if args.min_gap is not None and args.min_gap < 1:
        raise UserError(f"--min-gap must be at least 1, got {args.min_gap}")
    if args.select is None and (args.by != "uniform" or args.min_gap is not None):
        raise UserError("--by and --min-gap choose frames for --select N; pass --select")
    if args.select is not None and params_from_args(args) is not None:
        raise UserError("--smooth and --select do not go together: a pick's pre-labels are its own frame's "
                        "predictions (smoothing would also hide the jumps --by jump looks for)")
    check_via_output(args.via, args.force, args.min_confidence)  # before the model loads: fail in a second
    if args.draw is not None:
        from fcnpose_tf.fileio import check_output_folder

        check_output_folder(args.draw, args.force)
    model_path = args.model
    if Path(model_path).suffix in (".keras", ".h5"):
        from fcnpose_tf.training.tfsetup import import_tensorflow_quietly

        import_tensorflow_quietly()
    predictor = open_model(model_path, args.threads, Decoding.from_args(args))
    source = open_source(args.source, refuse_cameras="predict reads image folders, images and videos; for a "
                         "camera use `fcnpose-tf run MODEL.tflite --source ... --via OUT.json`")
    if args.select is not None:
        return _select(args, predictor, source)
    with _via_collection(args, predictor, source) as collected:
        print(f"{predictor.describe()}; {source.describe()}", file=sys.stderr, flush=True)
        with stop_signals_as_interrupt():  # Ctrl-C or a `kill` ends it: the frames done so far, in the VIA file
            summary = run_stream(predictor, source, max_frames=args.max_frames, progress=ProgressLine(),
                                 on_frame=collected.add, every=args.every, smooth=params_from_args(args))
        with stop_signals_ignored():  # the project and its frames written whole: a further Ctrl-C waits for them
            written = collected.close()
    if written is not None:
        summary.outputs.append(f"{written}: {collected.describe()}")
    print(summary.report(predictor, source))
    if written is None:
        raise UserError(f"{args.source}: no frame was processed ({summary.end_reason}); no VIA file written")
    return 0


@contextlib.contextmanager
def _via_collection(args: argparse.Namespace, predictor, source):
    """The VIA file of --via, collected from `source`'s frames: discarded if anything fails or stops the command
    before it is closed (nothing half-written), `source` closed either way."""
    from fcnpose_tf.correction.prelabel import ViaPredictions

    collected = None
    try:
        collected = ViaPredictions(args.via, predictor.schema, source, args.force, args.min_confidence,
                                   pictures=args.draw)
        yield collected
    except BaseException:
        if collected is not None:
            collected.discard()
        raise
    finally:
        source.close()


def _select(args: argparse.Namespace, predictor, source) -> int:
    """--select N: score every processed frame, pick N, read the source again and write the picks' pre-labels."""
    import sys

    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import stop_signals_as_interrupt, stop_signals_ignored
    from fcnpose_tf.runtime.estimator import Prediction
    from fcnpose_tf.runtime.runner import ProgressLine, run_stream
    from fcnpose_tf.runtime.sources import open_source
    from fcnpose_tf.correction.selection import FrameScores, default_min_gap

    gap = args.min_gap or default_min_gap(source.fps, source.kind)
    scores = FrameScores(args.by, predictor)
    if args.by == "jump" and source.kind == "images":
        print("note: --by jump scores how far the keypoints moved since the previous frame, so it reads the "
              "folder's images in name order as a video; for stills that are not a sequence use --by uncertain or "
              "disagree", file=sys.stderr)
    try:
        print(f"{predictor.describe()}; {source.describe()}; scoring frames for --select {args.select} --by {args.by}"
              f"{' (each frame predicted 3 times: plain, flipped, zoomed out)' if args.by == 'disagree' else ''}",
              file=sys.stderr, flush=True)
        with stop_signals_as_interrupt():  # Ctrl-C or a `kill` ends the scoring: the picks come from frames done
            summary = run_stream(predictor, source, max_frames=args.max_frames, progress=ProgressLine(),
                                 on_frame=scores.add, every=args.every)
    finally:
        source.close()
    print(summary.report(predictor, source))
    if not scores.records:
        raise UserError(f"{args.source}: no frame was processed ({summary.end_reason}); no VIA file written")
    picks = scores.pick(args.select, gap)
    wanted = {record.index: record for record in picks}
    names: dict[int, str] = {}  # a picked image's file name; a video's frames by number
    again = open_source(args.source, refuse_cameras="predict reads image folders, images and videos")
    with _via_collection(args, predictor, again) as collected:
        for frame in again:
            record = wanted.get(frame.index)
            if record is None:
                continue
            names[frame.index] = Path(frame.name).name if again.kind == "images" else f"frame {frame.index}"
            if tuple(frame.image.shape) != record.shape:
                raise UserError(f"{args.source}: frame {frame.index} reads as {frame.image.shape} now, "
                                f"{record.shape} when scored; the source changed while predict ran")
            collected.add(frame, Prediction(record.keypoints, record.confidence, None, record.shape))
            if len(collected.frames) == len(wanted):
                break
        if len(collected.frames) != len(wanted):
            raise UserError(f"{args.source}: {len(wanted) - len(collected.frames)} picked frame(s) could not be "
                            "read again; no VIA file written")
        with stop_signals_ignored():
            written = collected.close()
    score = dict(zip((r.index for r in scores.records), scores.scores()))
    fewer = (f" (only {len(picks)} fit {gap} frames apart in {len(scores.records)} processed frames)"
             if len(picks) < args.select else "")
    print(f"Selected {len(picks)} of {len(scores.records)} processed frames by {args.by}, at least {gap} frame(s) "
          f"apart{fewer}: {_picks_named(picks, names, score if args.by != 'uniform' else None, written)}")
    print(f"{written}: {collected.describe()}")
    return 0


def _picks_named(picks: list, names: dict[int, str], score: dict[int, float] | None, via) -> str:
    """The picks by name (with their scores) in source order; more than the contact sheet's SHEET_TILES of them: the
    highest-scoring SHEET_TILES, highest first (a uniform choice: the first), and how many more `via` holds."""
    from fcnpose_tf.correction.prelabel import SHEET_TILES

    shown = picks
    if len(picks) > SHEET_TILES:
        shown = sorted(picks, key=lambda r: -score[r.index])[:SHEET_TILES] if score else picks[:SHEET_TILES]
    listed = ", ".join(names[r.index] + (f" ({score[r.index]:.3g})" if score else "") for r in shown)
    if len(shown) == len(picks):
        return listed
    which = "highest-scoring" if score else "first"
    return f"the {len(shown)} {which}: {listed}; the other {len(picks) - len(shown)} in {via}"
