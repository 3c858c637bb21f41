"""Measure a .keras or .tflite FCN-Pose on a dataset: PCK, pixel error, inference time and FPS.

PCK@0.5/0.2/0.05 are normalised by max(w, h) of the ground-truth keypoints' bounding box
(MMPose's convention; the paper reports 0.5); PCK-AUC 0-20 px is the DREAM convention; EPE is
the mean pixel error in original frame pixels. Missing predictions count as wrong. Timing: mean
and std over at least 50 frames after warm-up; FPS = 1 / (preprocess + inference + post-processing).

Which frames: on the dataset a model was trained on (recorded in NAME_train.json, and in the metadata of a
.tflite exported since 2026-12-05), its validation split; on any other dataset, every frame (--split overrides).

The worst frames are listed by name (--worst N, 5 by default): ranked by the mean over their annotated keypoints
of each error as a share of the frame's keypoint box, capped at 0.5, a missing keypoint counted at the cap.
--pictures DIR draws them: the prediction over the ground truth (a ring per annotated keypoint, a line to where
the model put it, a cross where it found nothing) - the frames to correct or to add more of.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from fcnpose_tf.settings import add_decoding_arguments

if TYPE_CHECKING:
    from fcnpose_tf.measurements import Evaluation

NAME = "evaluate"
OUTPUTS = ("json", "pictures")
FILE_OUTPUTS = ("json",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""


def USES_TENSORFLOW(args: argparse.Namespace) -> bool:  # noqa: N802 - the name every command module declares
    """A .tflite is evaluated with the LiteRT interpreter alone (a Pi install); a .keras/.h5 needs TensorFlow."""
    return Path(args.model).suffix != ".tflite"


EXAMPLES = """\
  fcnpose-tf synth --out heldout --n 100 --seed 1
  fcnpose-tf evaluate --data heldout                       # the bundled baseline on unseen frames
  fcnpose-tf evaluate workcell-p70-fp16 --data heldout --threads 1   # a bundled model by name
  fcnpose-tf evaluate generalist --data my_frames/        # the generalist on your frames, before fine-tuning
  fcnpose-tf evaluate models/arm.keras --data my_frames/ --fold 2 --json fold2.json
  fcnpose-tf evaluate models/arm.keras --data test_frames/ --worst 10 --pictures worst/   # see the mistakes
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import add_data_arguments
    from fcnpose_tf.smoothing import add_smoothing_arguments

    from fcnpose_tf.bundled import model_argument, names_help

    parser.add_argument("model", nargs="?", type=model_argument(), default="workcell", metavar="MODEL",
                        help=f"a .keras/.h5 or .tflite model, or a bundled one by name ({names_help()})")
    add_data_arguments(parser, positional=False, model_splits=True)
    parser.add_argument("--split", choices=("auto", "val", "all"), default="auto",
                        help="auto: validation frames on the model's own training data, else all frames")
    parser.add_argument("--fold", type=int, metavar="k", help="use the validation frames of fold k")
    settings.INFERENCE_THREADS.add_to(parser)
    add_decoding_arguments(parser, fallback=True)
    parser.add_argument("--sequence", type=float, metavar="FPS",
                        help="the frames, in the VIA file's order, are a video at this frame rate (synth --motion): "
                             "also report jitter and lag")
    add_smoothing_arguments(parser)
    parser.add_argument("--worst", type=int, default=5, metavar="N",
                        help="list the N worst frames by name (0: none)")
    parser.add_argument("--pictures", type=Path, metavar="DIR",
                        help="draw the --worst frames here (PNG): prediction over ground truth, each error a line")
    parser.add_argument("--json", type=Path, metavar="OUT.json", help="also write the report as JSON")
    settings.FORCE.variant(help="replace an existing --json file or pictures").add_to(parser)


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.data.args import load_from_args, splits_of_record
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
    if args.worst < 0:
        raise UserError(f"--worst must be 0 or more, got {args.worst}")
    if args.pictures is not None:
        check_pictures_folder(args.pictures, args.force, args.worst)
    if args.sequence is not None and not args.sequence > 0:
        raise UserError(f"--sequence needs the frame rate (above 0), got {args.sequence}")
    if args.smooth and args.sequence is None:
        raise UserError("--smooth filters a video's tracks: give its frame rate with --sequence FPS")
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.smoothing import params_from_args

    model_path = args.model
    predictor = open_model(model_path, args.threads, Decoding.from_args(args))
    splits_of_record(args, model_path)  # a copy of the data it was trained on: its split, not seed 0's
    dataset = load_from_args(args)
    if not predictor.names_keypoints and dataset.schema.keypoints != predictor.schema.keypoints:
        print(f"note: {Path(model_path).name} names no keypoints (a file from before 2026-12-05 without its training "
              f"record): its maps are read as the data's {', '.join(dataset.schema.keypoints)}, in that order")
    indices, description = choose_frames(dataset, model_path, args.split, args.fold)
    result = evaluate_predictor(predictor, dataset, indices, dataset.schema, progress=True)
    print(f"Model: {model_path} ({Path(model_path).stat().st_size:,} bytes)")
    print(f"Data:  {dataset.via_path}, {description}")
    print(f"Decoding: {predictor.decoding.describe()}")
    print("PCK normalised by max(bbox w, h) of the ground-truth keypoints; EPE in frame pixels")
    print(format_report(result.metrics))
    print(format_timing(result.timing))
    worst = worst_frame_rows(result.predictions, result.ground_truth, dataset, indices, args.worst)
    if worst:
        print(format_worst(worst))
    if args.pictures is not None and worst:
        print(f"Pictures: {write_pictures(args.pictures, worst, result, dataset, indices, args.force)}")
    sequence = None
    if args.sequence is not None:
        from fcnpose_tf.training.evaluate import format_sequence, sequence_report

        first = dataset.samples[indices[0]]
        sequence = sequence_report(result.predictions, result.ground_truth, args.sequence,
                                   params_from_args(args), dataset.schema.keypoints, (first.height, first.width))
        print(format_sequence(sequence))
    if args.json is not None:
        write_json(args.json, {"model": str(model_path), "size_bytes": Path(model_path).stat().st_size,
                               "data": str(dataset.via_path), "frames": description,
                               "decoding": predictor.decoding.to_json(),
                               **result.measurement().to_json(), "worst_frames": worst,
                               "keypoints": list(dataset.schema.keypoints),  # the order of per_frame's errors_px
                               "per_frame": frame_rows(result.predictions, result.ground_truth, dataset, indices),
                               **({"sequence": sequence.to_json()} if sequence is not None else {})}, force=args.force)
        print(f"Report: {args.json}")
    return 0


def check_pictures_folder(folder: Path, force: bool, worst: int) -> None:
    """Refuse, before any work, a --pictures folder that holds files (without --force), or is a file, or --worst 0."""
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_output_folder

    if worst == 0:
        raise UserError("--pictures draws the --worst frames: give --worst 1 or more")
    check_output_folder(folder, force)


def worst_frame_rows(pred, gt, dataset, indices, count: int) -> list[dict]:
    """The `count` worst frames (`metrics.worst_frames`) as JSON-ready rows: the frame's name, its score, its EPE over
    the keypoints found, the keypoints missed, and its worst keypoint."""
    import numpy as np

    from fcnpose_tf.metrics import errors_px, frame_errors, worst_frames

    score, errors = frame_errors(pred, gt), errors_px(pred, gt)
    names = dataset.schema.keypoints
    rows = []
    for rank, j in enumerate(worst_frames(score, count), 1):
        found = errors[j][np.isfinite(errors[j])]
        scored = np.where(np.isnan(errors[j]), -1.0, errors[j])
        k = int(np.argmax(scored))
        rows.append({"rank": rank, "frame": dataset.samples[indices[j]].filename, "position": j,
                     "score": round(float(score[j]), 4),
                     "epe_px": round(float(found.mean()), 2) if found.size else None,
                     "missing": int(np.isinf(errors[j]).sum()), "worst_keypoint": names[k],
                     "worst_keypoint_px": round(float(errors[j][k]), 2) if np.isfinite(errors[j][k]) else None})
    return rows


def frame_rows(pred, gt, dataset, indices) -> list[dict]:
    """Every scored frame's keypoint errors for --json ("per_frame"): {"frame", "errors_px": per keypoint, null
    where it has no ground truth or the model missed it, "missed": the keypoints the model missed}."""
    import numpy as np

    from fcnpose_tf.metrics import errors_px

    errors, names = errors_px(pred, gt), dataset.schema.keypoints
    return [{"frame": dataset.samples[i].filename,
             "errors_px": [round(float(e), 3) if np.isfinite(e) else None for e in errors[j]],
             "missed": [names[k] for k in range(len(names)) if np.isinf(errors[j][k])]}
            for j, i in enumerate(indices)]


def format_worst(rows: list[dict]) -> str:
    from fcnpose_tf.tables import format_table

    table = [[r["rank"], r["frame"], r["score"], "-" if r["epe_px"] is None else r["epe_px"], r["missing"],
              r["worst_keypoint"] + (f" {r['worst_keypoint_px']} px" if r["worst_keypoint_px"] is not None
                                     else " (missed)")] for r in rows]
    return (f"Worst {len(rows)} frame{'s' if len(rows) != 1 else ''} (mean error as a share of the keypoint box, "
            "capped at 0.5; a missed keypoint counts 0.5):\n"
            + format_table(["rank", "frame", "score", "EPE px", "missed", "worst keypoint"], table))


def write_pictures(folder: Path, rows: list[dict], result: Evaluation, dataset, indices, force: bool) -> str:
    """One PNG per worst frame in `folder` (RANK_NAME.png): `draw.draw_truth_and_prediction` with a caption."""
    from fcnpose_tf.draw import contact_sheet, draw_truth_and_prediction, png_bytes
    from fcnpose_tf.fileio import make_folder, write_bytes

    make_folder(folder)
    pictures = []
    for row in rows:
        j = row["position"]
        image = dataset.load_image(indices[j])
        caption = (f"#{row['rank']} {row['frame']}: score {row['score']:.3f}, EPE "
                   f"{'-' if row['epe_px'] is None else row['epe_px']} px, {row['missing']} missed")
        picture = draw_truth_and_prediction(image, result.ground_truth[j], result.predictions[j],
                                            dataset.schema, caption)
        pictures.append(picture)
        write_bytes(folder / f"{row['rank']:02d}_{Path(row['frame']).stem}.png", png_bytes(picture, folder),
                    force=force)
    sheet = contact_sheet(pictures, columns=min(3, len(pictures)), tile_width=320)
    write_bytes(folder / "contact_sheet.png", png_bytes(sheet, folder), force=force)
    return f"{folder} ({len(rows)} PNG and contact_sheet.png)"
