"""Measure a .keras or .tflite FCN-Pose on a dataset: PCK, pixel error, inference time and FPS.

PCK@0.5/0.2/0.05 are normalised by max(w, h) of the ground-truth keypoints' bounding box
(MMPose's convention; the paper reports 0.5); PCK-AUC 0-20 px is the DREAM convention; EPE is
the mean pixel error in original frame pixels. Missing predictions count as wrong. Timing: mean
and std over at least 50 frames after warm-up; FPS = 1 / (preprocess + inference + post-processing).

Which frames: on the dataset a model was trained on (recorded in NAME_train.json), its
validation split; on any other dataset, every frame (--split overrides).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fcnpose_tf.settings import add_decoding_arguments

NAME = "evaluate"
OUTPUTS = ("json",)
USES_TENSORFLOW = True
EXAMPLES = """\
  fcnpose-tf synth --out heldout --n 100 --seed 1
  fcnpose-tf evaluate --data heldout                       # the bundled baseline on unseen frames
  fcnpose-tf evaluate workcell-p70-fp16 --data heldout --threads 1   # a bundled model by name
  fcnpose-tf evaluate generalist --data my_frames/        # the generalist on your frames, before fine-tuning
  fcnpose-tf evaluate models/arm.keras --data my_frames/ --fold 2 --json fold2.json
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.data.args import add_data_arguments
    from fcnpose_tf.settings import thread_count
    from fcnpose_tf.smoothing import add_smoothing_arguments

    from fcnpose_tf.bundled import model_argument, names_help

    parser.add_argument("model", nargs="?", type=model_argument(), default="workcell", metavar="MODEL",
                        help=f"a .keras/.h5 or .tflite model, or a bundled one by name ({names_help()})")
    add_data_arguments(parser, positional=False)
    parser.add_argument("--split", choices=("auto", "val", "all"), default="auto",
                        help="auto: validation frames on the model's own training data, else all frames")
    parser.add_argument("--fold", type=int, metavar="k", help="use the validation frames of fold k")
    parser.add_argument("--threads", type=thread_count, help="inference threads (default: all cores)")
    add_decoding_arguments(parser, fallback=True)
    parser.add_argument("--sequence", type=float, metavar="FPS",
                        help="the frames, in the VIA file's order, are a video at this frame rate (synth --motion): "
                             "also report jitter and lag")
    add_smoothing_arguments(parser)
    parser.add_argument("--json", type=Path, metavar="OUT.json", help="also write the report as JSON")
    parser.add_argument("--force", action="store_true", help="replace an existing --json file")


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.data.args import load_from_args
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.training.evaluate import choose_frames, evaluate_predictor, format_timing, open_model
    from fcnpose_tf.fileio import check_writable, write_json
    from fcnpose_tf.metrics import format_report
    from fcnpose_tf.settings import FOLDS

    if args.fold is not None:
        if args.split == "all":
            raise UserError("--fold selects validation frames; it cannot be combined with --split all")
        args.split = "val"
        k = args.folds or FOLDS.default
        if not 0 <= args.fold < k:
            raise UserError(f"--fold must be between 0 and {k - 1}, got {args.fold}")
    if args.json is not None:
        check_writable(args.json, args.force)
    if args.sequence is not None and not args.sequence > 0:
        raise UserError(f"--sequence needs the frame rate (above 0), got {args.sequence}")
    if args.smooth and args.sequence is None:
        raise UserError("--smooth filters a video's tracks: give its frame rate with --sequence FPS")
    from fcnpose_tf.postprocess import describe_decoding
    from fcnpose_tf.smoothing import params_from_args

    model_path = args.model
    predictor = open_model(model_path, args.threads, args.threshold, args.fallback, args.centroid)
    dataset = load_from_args(args)
    indices, description = choose_frames(dataset, model_path, args.split, args.fold)
    result = evaluate_predictor(predictor, dataset, indices, dataset.schema, progress=True)
    print(f"Model: {model_path} ({Path(model_path).stat().st_size:,} bytes)")
    print(f"Data:  {dataset.via_path}, {description}")
    print(f"Decoding: {describe_decoding(predictor.threshold, predictor.fallback, predictor.centroid)}")
    print("PCK normalised by max(bbox w, h) of the ground-truth keypoints; EPE in frame pixels")
    print(format_report(result["metrics"]))
    print(format_timing(result["timing"]))
    sequence = None
    if args.sequence is not None:
        from fcnpose_tf.training.evaluate import format_sequence, sequence_report

        sequence = sequence_report(result["predictions"], result["ground_truth"], args.sequence,
                                   params_from_args(args), dataset.schema.keypoints)
        print(format_sequence(sequence))
    if args.json is not None:
        write_json(args.json, {"model": str(model_path), "size_bytes": Path(model_path).stat().st_size,
                               "data": str(dataset.via_path), "frames": description,
                               "decoding": {"threshold": predictor.threshold, "fallback": predictor.fallback,
                                            "centroid": predictor.centroid},
                               "metrics": result["metrics"], "timing": result["timing"],
                               **({"sequence": sequence} if sequence is not None else {})}, force=args.force)
        print(f"Report: {args.json}")
    return 0
