"""Export a trained .keras/.h5 model to TFLite files, each verified (FCN-Pose on keypoints) before it is written.

One file per --quantize format, next to the model unless --out-dir says otherwise: NAME_fp16.tflite
(the paper's float16), NAME_int8.tflite (full integer: int8 weights and activations calibrated on
--calibration-frames training frames, a uint8 pixel input; the fastest file on a Raspberry Pi 3/4),
NAME_fp32.tflite, NAME_int8w.tflite, NAME_fp16native.tflite (float16 with reduced-precision metadata:
computed in float16 on a Raspberry Pi 5, docs/raspberry-pi.md). Frames come from --data (default:
the frames the model was trained on, as its NAME_train.json names them, else the synthetic frames the
bundled models were trained on): int8 is calibrated on the training split's frames and every file is
verified on the validation split's first 16 frames (topped up with training frames when it has fewer), never
calibrated on them. --input-size S rebuilds the model at S
with its weights (nothing retrained) and names the files NAME_S_fp16.tflite: a file for `run --track`.

Any other model (a Keras 3 model, a classifier, a pruned MobileNetV2: anything whose output is not 2-D maps of a
tf_keras model) is verified by output parity instead: every file keeps a float32 input and output, is run on 16
seeded random inputs in --input-range (or the --data frames, scaled to it) and must match the Keras outputs
within its format's bound (settings.TFLITE_FORMATS: max difference relative to the output's scale, 1e-2 for
float16, 0.1 for int8; a classifier's top-1 class on 90 % of the clear samples for int8, all for float16); int8
is calibrated on --calibration-frames random inputs in --input-range, or on --data's training frames.

A format whose file fails its keypoint gate is a row, not a failure: the others are still written,
the table (and --json's "refused") shows it as REFUSED with the gate's reason, and the last lines
name every file written. export trains nothing, so a refused int8 gets no quantization-aware
training here: `fcnpose-tf compress --rate 0 --retrain-epochs 0 --model MODEL --data DIR` gives
the same model's int8 file through compress's QAT fallback.

Exit status: 0 when every format was written, and also when a format of the default --quantize
(float16,int8) was refused but at least one file was written; 2 (after the table, with an `error:`
line naming the refused format and the files kept) when a format named with --quantize was refused
or no file could be written; 2 for bad input, before any work.
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "export"
USES_TENSORFLOW = True
OUTPUTS = ("out_dir", "json")
FILE_OUTPUTS = ("json",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
EXAMPLES = """\
  fcnpose-tf export saved_models/fcnpose_ur5_p70.keras --quantize int8     # -> saved_models/fcnpose_ur5_p70_int8.tflite
  fcnpose-tf export models/arm_p70.keras --data my_frames/ --out-dir models/  # float16 and int8 files
  fcnpose-tf export models/arm_p70.keras --data my_frames/ --quantize float16,int8  # exit 2 if either is refused
  fcnpose-tf export mnv2_p50.keras --input-range=-1,1 --quantize float16,int8  # any CNN: verified by output parity
  fcnpose-tf export models/arm_p70.keras --input-size 192 --data my_frames/  # arm_p70_192_int8.tflite, for run --track
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import add_data_arguments

    from fcnpose_tf.bundled import KERAS_SUFFIXES, model_argument, names_help

    parser.add_argument("model", type=model_argument(KERAS_SUFFIXES), metavar="MODEL",
                        help=f"a trained .keras/.h5 FCN-Pose, or a bundled one by name ({names_help(KERAS_SUFFIXES)})")
    add_data_arguments(parser, positional=False, required=False, model_splits=True)
    parser.add_argument("--out-dir", type=Path, help="folder for the .tflite files (default: the model's folder)")
    for setting in (settings.QUANTIZE, settings.CALIBRATION_FRAMES, settings.CALIBRATION_SEED, settings.THREADS,
                    settings.EXPORT_INPUT_SIZE):
        setting.add_to(parser)
    parser.add_argument("--input-range", type=_input_range, default=(0.0, 1.0), metavar="LOW,HIGH",
                        help="a model that is not a keypoint model: the range of its input values, where its random "
                             "verification and calibration inputs are drawn (and --data frames scaled to); e.g. -1,1 "
                             "for Keras' MobileNetV2, written --input-range=-1,1 (default: 0,1)")
    parser.add_argument("--json", type=Path, metavar="OUT.json",
                        help="also write what was exported: per file its format, size, calibration, verification "
                             "gate and graph rewrites")
    settings.FORCE.variant(help="replace existing .tflite (and --json) files").add_to(parser)


def _input_range(text: str) -> tuple[float, float]:
    try:
        low, high = (float(part) for part in str(text).split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LOW,HIGH, e.g. -1,1") from None
    if not (low < high) or not all(abs(v) < float("inf") for v in (low, high)):
        raise argparse.ArgumentTypeError(f"{text!r}: expected two finite numbers LOW < HIGH, e.g. -1,1")
    return low, high


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import default_data, load_from_args, splits_of_record
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.compression.export import ExportOptions, write_tflite
    from fcnpose_tf.compression.summary import finish_formats
    from fcnpose_tf.compression.frames import check_enough_frames, describe_check_frames, export_frames
    from fcnpose_tf.compression.verify import ExportVerificationError
    from fcnpose_tf.fileio import check_writable, write_json
    from fcnpose_tf.records import training_record
    from fcnpose_tf.training.model import schema_of, view_of
    from fcnpose_tf.tables import format_table
    from fcnpose_tf.training.tfsetup import set_tensorflow_threads

    named = "quantize" in args.given_settings  # formats the user named: refusing one is an error (exit status 2)
    options = settings.from_args(args, ExportOptions)
    options.validate()
    if not args.model.is_file():
        raise UserError(f"{args.model}: model file not found")
    out_dir = args.out_dir or args.model.parent
    if args.input_size is not None:
        settings.EXPORT_INPUT_SIZE.validate(args.input_size)
    stem = args.model.stem + (f"_{args.input_size}" if args.input_size else "")
    paths = {q: out_dir / f"{stem}_{settings.QUANTIZE_FILE_TAGS[q]}.tflite" for q in options.quantize}
    for path in [*paths.values(), *([args.json] if args.json else [])]:  # before anything is converted
        check_writable(path, args.force)
    set_tensorflow_threads(options.threads)
    from fcnpose_tf.compression.export import is_keypoint_model
    from fcnpose_tf.compression.keras_file import load_any

    model = load_any(args.model)  # a tf_keras file as `load_model` reads it
    if not is_keypoint_model(model):
        if args.input_size:
            raise UserError(f"{args.model}: --input-size rebuilds an FCN-Pose keypoint model; this one is not")
        return _run_generic(args, model, options, paths, named)
    if args.input_size:
        from fcnpose_tf.training.model import at_input_height

        model = at_input_height(model, args.input_size)
    if args.data is None:
        args.data, args.images = default_data(args.model, args.images)
    splits_of_record(args, args.model)  # calibrated on its training frames, verified on its validation frames
    dataset = load_from_args(args)
    train, val = dataset.split(None)
    view = view_of(model)  # verification and calibration frames as the model sees them: its crop, its H x W
    trained_on = record.deployed() if (record := training_record(args.model)) is not None else None
    check_enough_frames(paths, len(val), len(train), dataset.via_path)  # before anything is converted or written
    rows, records, refused = [], [], []
    for quantize, path in paths.items():
        samples, calibration = export_frames(quantize, view, dataset, train, dataset, val, options.calibration_frames,
                                             options.seed)
        try:
            export = write_tflite(model, path, quantize, force=args.force, sample_frames=samples,
                                  calibration_frames=calibration, num_threads=options.threads, trained_on=trained_on)
        except ExportVerificationError as exc:  # a row, not the end of the run
            rows.append(_refused(refused, path, quantize, exc, args.force, columns=8))
            continue
        records.append({"file": str(path), "status": "written", **export.to_dict()})
        p = export.parity
        rows.append([path.name, export.size_bytes / 1e3, export.calibration_frames or None, p.frames,
                     f"{p.keypoints_within_px}/{p.keypoints_compared}", p.keypoints_lost_or_gained,
                     p.max_keypoint_px, p.max_abs_diff, "folded" if export.graph_rewrites else "plain"])
    checked = describe_check_frames(len(samples), len(val))
    print(f"Verified against {args.model} on {checked} of {dataset.via_path} "
          f"(keypoints in map px; int8 gate: >= 95 % within 2 px, none lost or gained)")
    print(format_table(["file", "size KB", "calibrated on", "frames", "kp within", "lost/gained", "max kp px",
                        "max map diff", "upsampling"], rows, digits=[None, 1, None, None, None, None, 2, 3, None]))
    for entry in refused:
        print(f"{entry['quantize']}: REFUSED, no file written: {entry['reason']}")
    if args.json:
        write_json(args.json, {"model": str(args.model), "data": str(dataset.via_path),
                               "schema": schema_of(model).to_dict(),
                               "verification_frames": checked,
                               "calibration": f"seeded choice (seed {options.seed}) of the training split's "
                                              f"{len(train)} frames", "files": records, "refused": refused},
                   force=args.force)
    written = [Path(r["file"]) for r in records] + ([args.json] if args.json else [])
    return finish_formats(written, [entry["quantize"] for entry in refused], bool(records), named)


def _generic_inputs(args: argparse.Namespace, model, options) -> tuple:
    """(verification inputs or None, calibration inputs or None, what they are) for a model verified by parity."""
    import numpy as np

    from fcnpose_tf.errors import UserError

    if args.data is None:
        return None, None, (f"seeded random inputs uniform in [{args.input_range[0]:g}, {args.input_range[1]:g}]")
    from fcnpose_tf.compression.frames import GENERIC_SAMPLES, calibration_frames
    from fcnpose_tf.data.args import load_from_args
    from fcnpose_tf.preprocess import preprocess_frame

    shape = tuple(model.inputs[0].shape)
    if len(shape) != 4 or shape[-1] != 3:
        raise UserError(f"--data frames are RGB images; model {model.name} takes inputs of shape {shape[1:]}")
    dataset = load_from_args(args)
    train, val = dataset.split(None)
    size = (int(shape[1]), int(shape[2]))
    chosen = (list(val) + list(train))[:GENERIC_SAMPLES]
    low, high = args.input_range
    samples = np.stack([preprocess_frame(dataset.load_image(int(i)), size) for i in chosen])
    calibration = calibration_frames(dataset, train, min(options.calibration_frames, len(train)), size,
                                     options.seed) if len(train) else None
    scale = (lambda x: None if x is None else (low + (high - low) * x).astype(np.float32))
    return scale(samples), scale(calibration), (f"{len(chosen)} frames of {dataset.via_path} (calibration: up to "
                                                f"{options.calibration_frames} of its training split), scaled to "
                                                f"[{low:g}, {high:g}]")


def _run_generic(args: argparse.Namespace, model, options, paths: dict, named: bool) -> int:
    """export of a model that is not a keypoint model: each format verified by output parity."""
    from fcnpose_tf import fileio, settings
    from fcnpose_tf.compression.export import export_generic
    from fcnpose_tf.compression.summary import finish_formats
    from fcnpose_tf.compression.verify import ExportVerificationError
    from fcnpose_tf.tables import format_table

    samples, calibration, source = _generic_inputs(args, model, options)
    print(f"{args.model}: not a keypoint model (output {tuple(model.outputs[0].shape)}): each file verified by "
          f"output parity on {source}")
    rows, records, refused = [], [], []
    for quantize, path in paths.items():
        try:
            export = export_generic(model, quantize, sample_inputs=samples, calibration_inputs=calibration,
                                    calibration_count=options.calibration_frames, input_range=args.input_range,
                                    seed=options.seed, num_threads=options.threads)
        except ExportVerificationError as exc:  # a row, not the end of the run
            rows.append(_refused(refused, path, quantize, exc, args.force, columns=6))
            continue
        fileio.write_bytes(path, export.data, args.force)
        records.append({"file": str(path), "status": "written", **export.to_dict()})
        p, fmt = export.parity, settings.TFLITE_FORMATS[quantize]
        top1 = None if p.top1_compared is None else f"{p.top1_agree}/{p.top1_compared}"
        rows.append([path.name, export.size_bytes / 1e3, export.calibration_frames or None, p.frames,
                     p.max_abs_diff, f"{p.relative_diff:.2g} <= {fmt.output_rtol:g}", top1])
    print(format_table(["file", "size KB", "calibrated on", "inputs", "max abs diff", "relative", "top-1 agree"],
                       rows, digits=[None, 1, None, None, None, None, None]))
    for entry in refused:
        print(f"{entry['quantize']}: REFUSED, no file written: {entry['reason']}")
    if args.json:
        fileio.write_json(args.json, {"model": str(args.model), "gate": "output parity", "inputs": source,
                                      "files": records, "refused": refused}, force=args.force)
    written = [Path(r["file"]) for r in records] + ([args.json] if args.json else [])
    return finish_formats(written, [entry["quantize"] for entry in refused], bool(records), named,
                          gate="output-parity gate")


def _refused(refused: list, path: Path, quantize: str, exc, force: bool, columns: int) -> list:
    """A format the gate refused: its record appended to `refused`, an earlier file of its name removed with
    --force (it is not this model's); the table row to print."""
    refused.append({"file": str(path), "quantize": quantize, "status": "refused", "reason": exc.reason,
                    **({"parity": exc.facts} if exc.facts else {})})
    if force and path.is_file():
        path.unlink()
        print(f"removed {path}: an earlier file of the format this run refused")
    return [f"{path.name}: REFUSED"] + [None] * columns
