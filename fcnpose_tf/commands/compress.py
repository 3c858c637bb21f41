"""Compress FCN-Pose as the paper does: filter pruning, retraining, float16 and int8 TFLite — and measure it.

Writes NAME_p70.keras (pruned, retrained), NAME_p70_fp16.tflite (the paper's float16 file) and
NAME_p70_int8.tflite (full integer, calibrated on 100 training frames: the fastest file on a
Raspberry Pi 3/4), each verified against Keras before it is written, and NAME_p70_report.json,
and prints the unpruned model beside every step and each file:
parameters, MACs, size, PCK@0.5/0.2/0.05 (normalised by max(bbox w, h)), EPE, inference time
and FPS. Without --data it retrains on the frames the model was trained on (its NAME_train.json names
them), else on the first 400 of the 1,200 synthetic frames the bundled baseline was trained on; with no
--model and no --data it compresses the bundled baseline and measures on 100 held-out synthetic frames
(both sets generated once into a cache). --method magnitude runs
tfmot's unstructured pruning to the same parameter reduction instead, for comparison. --importance
chooses how filters are ranked: first-order Taylor on 256 training frames by default (measured ahead of
the paper's L1 norm on fine localisation), --importance l1 for the paper's, l2, or mean activation;
--min-filters N keeps every layer at least N filters wide within the parameter budget the paper's
per-layer rule gives at --rate (by default FCN-Pose's bottleneck keeps 8 filters instead of 3 at 0.7, and
conv1 15 instead of 39; --min-filters 0 is the paper's widths); --distill W mixes the unpruned model's maps
into the retraining loss.

A format whose file fails its keypoint gate is a row, not a failure: the run goes on, the table and
NAME_p70_report.json ("refused") show the format as REFUSED with the gate's reason, and the last
lines name every file written. When post-training int8 is refused, compress falls back to
quantization-aware training (tfmot; up to --qat-epochs epochs from the retrained model on the same
training frames, the int8 file converted and held to the same gate after each epoch) and says so;
its minutes and result are in the report (--qat-epochs 0: no fallback). When the best file written loses more
than 0.02 PCK@0.5 (the paper's budget), or more than 0.03 PCK@0.05 (fine localisation), against the unpruned model
on the measured frames, a `note:` line after the table says by how much and what to try: more frames of your camera
labelled by your model (--more-frames), else a lower --rate (`accuracy_note`).

--more-frames VIDEO_OR_FOLDER: up to --more-frames-count frames of your camera (720, evenly spread), labelled by the
model being compressed, join the retraining's training frames (never its validation frames), and the time budgets
left at their defaults grow in proportion to the frames: on views that vary this kept the 70 % files nearest the
unpruned model (docs/compression.md, "More frames of your look"). --more-frames-via OUT.json keeps the labelled frames
as a VIA project to look at and correct; --more-frames OUT.json then adds them with their labels as they are.

Exit status: 0 when every format was written, and also when a format of the default --quantize
(float16,int8) was refused but at least one .tflite file was written; 2 (after the table, with an
`error:` line naming the refused format and the files kept) when a format named with --quantize was
refused or no .tflite file could be written; 2 for bad input, before any work.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fcnpose_tf.compression.options import OutputFiles
    from fcnpose_tf.compression.report import CompressReport

NAME = "compress"
USES_TENSORFLOW = True
OUTPUTS = ("out_dir", "more_frames_via")
FILE_OUTPUTS = ("more_frames_via",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
EXAMPLES = """\
  fcnpose-tf compress --rate 0.7                       # bundled baseline, synthetic data, ./compressed/
  fcnpose-tf compress --rate 0.7 --preset paper        # the paper's recipe: L1 ranking, its widths, 1e-3, float16
  fcnpose-tf compress --rate 0.5 --retrain-epochs 100  # the paper's retraining budget
  fcnpose-tf compress --rate 0.7 --method magnitude    # tfmot unstructured sparsity, for comparison
  fcnpose-tf compress --rate 0.7 --quantize float16    # the paper's file only
  fcnpose-tf compress --rate 0.7 --importance l1       # the paper's L1-norm ranking (default: taylor)
  fcnpose-tf compress --rate 0.7 --min-filters 0       # the paper's widths (default: no layer under 15)
  fcnpose-tf compress --rate 0.7 --max-minutes 30      # a longer retraining budget (default: 10 minutes)
  fcnpose-tf compress --rates 0.5,0.6,0.7 --model models/arm.keras --data my_frames/  # the trade-off, one table
  fcnpose-tf compress --rate 0.7 --model models/arm.keras --data my_frames/ --more-frames cell.mp4  # + 720 frames
  fcnpose-tf compress --rate 0.7 --model models/arm.keras --data my_frames/ --more-frames cell.mp4 \\
      --more-frames-via more/more.json                 # and keep the labelled frames, to look at and correct
  fcnpose-tf compress --rate 0.7 --model models/arm.keras --data my_frames/ --more-frames more/more.json  # as corrected
  fcnpose-tf compress --rate 0.7 --distill 0.5         # retrain half on the unpruned model's maps
  fcnpose-tf compress --rate 0.7 --input-size 192      # files at 192x192: 0.73x the MACs of 224
  fcnpose-tf compress --rate 0.7 --model models/arm.keras --data my_frames/ --out-dir models/
  fcnpose-tf compress --rate 0.7 --model models/arm.keras --data my_frames/ --qat-epochs 0  # no QAT fallback
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import add_data_arguments, add_test_data_arguments

    settings.RATE.add_to(parser)
    parser._option_string_actions["--rate"].required = False  # or --rates
    parser.add_argument("--rates", type=_rate_list, metavar="R,R,...",
                        help="several rates of one model in one run instead of --rate: a file set and a table row "
                             "set per rate, and the highest rate within the paper's PCK@0.5 budget named (and the "
                             "highest within 0.03 PCK@0.05 too when that one loses more)")
    settings.add_preset_argument(parser)
    from fcnpose_tf.bundled import KERAS_SUFFIXES, model_argument, names_help

    parser.add_argument("--model", type=model_argument(KERAS_SUFFIXES), default="workcell", metavar="MODEL",
                        help=f"the .keras/.h5 model to compress, or a bundled one by name ({names_help(KERAS_SUFFIXES)})")
    add_data_arguments(parser, positional=False, required=False, model_splits=True)
    add_test_data_arguments(parser, "frames to measure on, never trained on (default: --data's validation split; "
                            "without --data, held-out synthetic frames)")
    settings.RETRAIN_EPOCHS.add_to(parser)
    settings.COMPRESS_RETRAIN_PATIENCE.add_to(parser, "--patience")
    settings.KEEP_BEST.add_to(parser)
    settings.COMPRESS_MAX_MINUTES.add_to(parser)
    settings.COMPRESS_TOTAL_MINUTES.add_to(parser)
    parser.add_argument("--out-dir", type=Path, default=Path("compressed"), help="folder for the outputs")
    for setting in (settings.QUANTIZE, settings.CALIBRATION_FRAMES, settings.QAT_EPOCHS, settings.QAT_LEARNING_RATE,
                    settings.METHOD, settings.STRATEGY, settings.COMPRESS_MIN_FILTERS, settings.PRUNED_START,
                    settings.COMPRESS_INPUT_SIZE, settings.COMPRESS_IMPORTANCE, settings.IMPORTANCE_FRAMES, settings.DISTILL):
        setting.add_to(parser)
    settings.MORE_FRAMES.add_to(parser)
    settings.MORE_FRAMES_COUNT.add_to(parser)
    settings.MORE_FRAMES_VIA.add_to(parser)
    settings.POLISH_MINUTES.add_to(parser)
    settings.RETRAIN_FOLD.add_to(parser)
    settings.INHERITED_AUGMENT.add_to(parser)
    for setting in (settings.BATCH_SIZE, settings.COMPRESS_LEARNING_RATE, settings.COMPRESS_LR_PATIENCE,
                    settings.LR_SCHEDULE, settings.FREEZE, settings.INHERITED_AUGMENT_COPIES,
                    settings.INHERITED_POSITIVE_WEIGHT, settings.SEED, settings.THREADS, settings.CENTROID,
                    settings.CLUSTER):
        setting.add_to(parser)
    settings.FORCE.add_to(parser)


def _rate_list(text: str) -> tuple[float, ...]:
    """argparse type of --rates: `0.5,0.6,0.7` (each checked by the rate setting when the options are made)."""
    try:
        rates = tuple(float(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected rates separated by commas, e.g. 0.5,0.6,0.7, got {text!r}") from None
    if len(rates) < 2 or len(set(rates)) != len(rates):
        raise argparse.ArgumentTypeError(f"expected two or more different rates, got {text!r} (one rate: --rate)")
    return tuple(sorted(rates))


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf import settings
    from fcnpose_tf.data import synthcache
    from fcnpose_tf.bundled import baseline_model
    from fcnpose_tf.compression.compress import compress_model
    from fcnpose_tf.compression.steps import SharedScoring
    from fcnpose_tf.compression.options import CompressOptions, check_outputs
    from fcnpose_tf.compression.summary import accuracy_note, report_table
    from fcnpose_tf.data.args import default_data, load_from_args, load_test_data, splits_of_record
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.training.tfsetup import set_tensorflow_threads
    from fcnpose_tf.fileio import removed_if_left_empty
    from fcnpose_tf.system import available_cores

    named = "quantize" in args.given_settings  # formats the user named: refusing one is an error (exit status 2)
    if args.rate is not None and args.rates is not None:
        raise UserError("--rate and --rates both given: one rate is --rate R, several --rates R,R,...")
    if args.rate is None and args.rates is None:
        raise UserError("give the pruning rate: --rate R, or --rates R,R,... for several in one run")
    rates = args.rates or (args.rate,)
    args.rate = rates[0]
    model_path = args.model
    if not Path(model_path).is_file():
        raise UserError(f"{model_path}: model file not found")
    if args.more_frames is not None:  # the source opened once, before anything heavy: a wrong one fails at once
        from fcnpose_tf.correction.pseudolabel import VIA_NAME, check_source, is_project

        settings.MORE_FRAMES_COUNT.validate(args.more_frames_count)
        if args.retrain_epochs == 0:
            raise UserError("--more-frames adds frames to the retraining; --retrain-epochs 0 retrains nothing")
        settings.MORE_FRAMES_VIA.validate(args.more_frames_via)
        if args.more_frames_via is not None and is_project(args.more_frames):
            raise UserError(f"--more-frames-via keeps the frames the model labels; --more-frames {args.more_frames} "
                            "is a VIA project, whose labels are used as they are")
        check_source(args.more_frames)
    elif args.more_frames_via is not None:
        raise UserError("--more-frames-via keeps the frames --more-frames labels; give --more-frames VIDEO_OR_FOLDER")
    options = settings.from_args(args, CompressOptions, renamed={"patience": "retrain_patience"})
    # checked once (None settings: the run's choice; a wrong --start refused before the data), then each other rate
    checked = options.checked(model_path)
    every = [checked, *(checked.at_rate(rate) for rate in rates[1:])]
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise UserError(f"{args.out_dir}: exists and is not a folder")
    with removed_if_left_empty(args.out_dir):  # a folder this run creates goes again if anything fails
        outputs = [check_outputs(model_path, args.out_dir, each.options, args.force)
                   for each in every]  # before the data
        set_tensorflow_threads(args.threads)
        if args.data is None:
            args.data, args.images = default_data(model_path, args.images)
        splits_of_record(args, model_path)  # retrained on its training frames, measured on its validation frames
        train_dataset = load_from_args(args)
        bundled_task = False  # the bundled baseline on its own synthetic frames: the README's command
        if args.test_data is not None:
            eval_dataset = load_test_data(args, train_dataset)
            eval_indices = list(range(len(eval_dataset)))
            description = f"all {len(eval_dataset)} frames of {args.test_data}"
        elif Path(model_path) == baseline_model() and args.images is None \
                and Path(args.data) == synthcache.default_training_data():
            eval_dataset = load_dataset(synthcache.heldout_data())
            eval_indices = list(range(len(eval_dataset)))
            bundled_task = True
            description = (f"{len(eval_dataset)} held-out synthetic frames (seed {synthcache.HELDOUT_SEED}, "
                           "never used for training)")
        else:
            eval_dataset = train_dataset
            _, val = train_dataset.split(args.fold)
            eval_indices = [int(i) for i in val]
            description = f"{len(val)} validation frames of {train_dataset.via_path}"
        shared = SharedScoring()  # --rates: the base model measured and its filters scored once
        with contextlib.ExitStack() as stack:
            if args.more_frames is not None:  # labelled into a folder kept until the last rate's retraining is done
                via = args.more_frames_via
                if via is None and not is_project(args.more_frames):
                    via = os.path.join(stack.enter_context(tempfile.TemporaryDirectory(prefix="fcnpose-more-frames-")),
                                       VIA_NAME)
                grown, every = _more_frames(args, model_path, train_dataset, eval_dataset, every, via)
                # measured on the validation frames: the same frames, first in the grown dataset
                eval_dataset = grown if eval_dataset is train_dataset else eval_dataset
                train_dataset = grown
            reports = [compress_model(model_path, train_dataset, eval_dataset, eval_indices, args.out_dir, each,
                                      force=args.force, eval_description=description,
                                      metadata={"preset": args.preset}, shared=shared, outputs=files)
                       for each, files in zip(every, outputs)]
    if len(reports) > 1:
        return _several_rates(reports, outputs, named, description + _reading(args))
    report = reports[0]
    threads = args.threads if args.threads is not None else f"all {available_cores()}"
    print(f"\nCompression at rate {args.rate:g} ({report.recipe}{_added(report)}); measured on {description}"
          f"{_reading(args)}; "
          f"PCK normalised by max(bbox w, h); timing on {threads} thread(s), mean of >= 50 frames")
    print(report_table(report))
    base = report.base
    for final in report.tflite_files:
        print(f"{final.quantize}: parameters {base.params:,} -> {final.params:,} "
              f"({100 * (1 - final.params / base.params):.1f}% fewer); "
              f"MACs {base.macs / 1e6:.1f} M -> {final.macs / 1e6:.1f} M; "
              f"size {base.h5_size_bytes / 1e3:.0f} KB (.h5) -> {final.tflite_size_bytes / 1e3:.1f} KB (.tflite); "
              f"FPS {base.timing.fps:.1f} (Keras) -> {final.timing.fps:.1f} (TFLite); "
              f"PCK@0.5 {base.metrics.pck[0.5]:.3f} -> {final.metrics.pck[0.5]:.3f} "
              f"({final.metrics.pck[0.5] - base.metrics.pck[0.5]:+.4f})")
        export, parity = final.export, final.parity
        calibration = f"calibrated on {export['calibration_frames']} training frames; " \
            if export["calibration_frames"] else ""
        print(f"  {calibration}verified on {parity.frames} frames: {parity.keypoints_within_px} of "
              f"{parity.keypoints_compared} keypoints within {parity.keypoint_px:g} map px of Keras "
              f"({parity.min_keypoint_share:.0%} required), {parity.keypoints_lost_or_gained} lost or gained; "
              f"upsampling {'folded' if export['graph_rewrites'] else 'not folded'}")
        if final.qat:
            qat = final.qat
            print(f"  quantization-aware training: post-training int8 was refused "
                  f"({qat.post_training_refused['reason']}); {qat.epochs_run} QAT epoch(s), "
                  f"{qat.minutes:.1f} min, gave this file")
    for entry in report.refused:
        print(f"{entry.quantize}: REFUSED, no file written: {entry.reason}")
        if entry.qat:
            print(f"  (post-training: {entry.post_training['reason']}; quantization-aware training "
                  f"{entry.qat.epochs_run} epoch(s), {entry.qat.minutes:.1f} min)")
    note = accuracy_note(report, bundled_task)
    if note:
        print(note)
    return _finish(report, outputs[0], named)


def _more_frames(args: argparse.Namespace, model_path: Path, dataset, eval_dataset, every: list,
                 via: str | None):
    """--more-frames: the source's frames labelled by the model to compress into the VIA project `via` (or a VIA
    project's frames with their own labels), added to the training split of `dataset`; the time budgets of `every`
    rate's options grown for them (`with_added_frames`).

    Returns:
        (the dataset with the frames, the options of every rate).
    """
    import time
    from dataclasses import replace

    from fcnpose_tf.correction.pseudolabel import is_project, label_frames, project_frames
    from fcnpose_tf.data.dataset import with_training_frames
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.progress import current
    from fcnpose_tf.settings import GIVEN
    from fcnpose_tf.training.evaluate import open_model

    started = time.perf_counter()
    options = every[0].options
    known = [sample.image_path for sample in (*dataset.samples, *eval_dataset.samples)]
    kept = ""
    if is_project(args.more_frames):
        extra, added = project_frames(args.more_frames, dataset.schema, dataset.min_visible, args.more_frames_count,
                                      known_images=known)
    else:
        labeller = open_model(model_path, args.threads, Decoding(centroid=options.centroid, cluster=options.cluster))
        labelled = label_frames(labeller, args.more_frames, via, args.more_frames_count, force=args.force,
                                known_images=known, labelled_by=str(model_path))
        extra = labelled.load(dataset.schema, dataset.min_visible)
        added = labelled.added(len(extra), dataset.min_visible)
        if args.more_frames_via is not None:
            kept = (f"; kept in {labelled.via_path} (look: `fcnpose-tf data inspect {labelled.via_path} --out "
                    f"preview.png`; correct in VIA, then pass it as --more-frames {labelled.via_path})")
    grown = with_training_frames(dataset, extra, added)
    training = len(dataset.split(args.fold)[0])
    minutes = (time.perf_counter() - started) / 60
    every = [replace(each, options=each.options.with_added_frames(training, len(extra), minutes,
                                                                   getattr(args, GIVEN, ())))
             for each in every]
    budget = every[0].options
    polish = f", then {budget.polish_minutes:g} min on the {training} alone" \
        if budget.polish_minutes and len(extra) else ""
    current().say(f"more frames: {added.description}{kept}; retraining on {training} + {len(extra)} "
                  f"frames, time budget {_minutes(budget.max_minutes)} of retraining{polish}, "
                  f"{_minutes(budget.total_minutes)} in all (docs/compression.md, \"More frames of your look\")")
    return grown, every


def _added(report: CompressReport) -> str:
    """The frames --more-frames added to the retraining, in words for the table's title ("" without)."""
    added = report.added_frames
    if not added:
        return ""
    how = f" labelled by {added['labelled_by']}" if added["labelled_by"] else ", their labels as they are"
    polish = report.polish
    polished = "" if polish is None or not polish.learning_rates else \
        (f", then {polish.epochs_run} epoch{'s' if polish.epochs_run != 1 else ''} on your frames alone at learning "
         f"rate {polish.learning_rates[0]:g}")
    return f", with {added['frames']} more frames of {added['source']}{how}{polished}"


def _minutes(value: float | None) -> str:
    return "none" if value is None else f"{value:.1f} min"


def _reading(args: argparse.Namespace) -> str:
    """How the table's keypoints were read, in words, when not by each map's largest cluster."""
    return ", each map's cluster chosen along the arm (--cluster chain)" if args.cluster == "chain" else ""


def _several_rates(reports: list, outputs: list, named: bool, description: str) -> int:
    """`--rates`: one table of every rate's rows, the best rate within the PCK budget named, every file named."""
    from fcnpose_tf.compression.summary import best_rate_note, rates_table

    rates = ", ".join(f"{report.options['rate']:g}" for report in reports)
    print(f"\nCompression at rates {rates} ({reports[0].recipe}{_added(reports[0])}); "
          f"measured on {description}; PCK normalised by max(bbox w, h); one report per rate")
    print(rates_table(reports))
    print(best_rate_note(reports))
    status = 0
    for report, files in zip(reports, outputs):
        status = max(status, _finish(report, files, named))
    return status


def _finish(report: CompressReport, outputs: OutputFiles, named: bool) -> int:
    """Name every file written; the exit status (see the module doc): 2 when a named format was refused or no
    .tflite file was written, else 0."""
    from fcnpose_tf.compression.summary import finish_formats

    written = [Path(p) for p in report.files.values()]
    written += [p for p in outputs.every if p.is_file() and p not in written
                and p.suffix != ".tflite"]  # the retraining's record and loss curves
    return finish_formats(written, [entry.quantize for entry in report.refused], report.quantized is not None, named)

