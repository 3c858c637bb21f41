"""Train FCN-Pose on a dataset: Adam, binary cross-entropy, early stopping, resumable checkpoints.

By default it fine-tunes the bundled UR5 generalist (pretrained on domain-randomised scenes), given a skip from
conv2's half-resolution block to conv10 (fcn-pose-skip: finer small keypoints), on your frames (augmentation chosen
from the frames: the paper's 2 fixed copies per frame for one fixed camera, fresh random transforms every epoch when
the views vary), keypoint pixels weighted 8 on one fixed camera (20 when the views vary or from scratch), conv2
onwards trained at 3e-3 on one fixed camera (conv1-2 fixed at 1e-3 when the views vary), the view chosen from where the arm
is and how large (a fixed camera's workspace crop, part of the model and its exports, at its own aspect and at most
224x288 input pixels; the whole frame at 224 to 384 where views vary), the learning rate halved after
4 epochs without progress and a 30-minute budget (docs/training.md, "Training on your own frames"); the paper's recipe
is the last example below. Without --folds the model trains on the 80/20 hold-out split; --folds K
trains one model per fold of the dataset's stored K-fold splits (or only --fold k) and reports mean
and std. Next to the model it writes
NAME_loss.csv/.png (loss curves) and NAME_train.json (settings, epochs, validation metrics).
With --test-data T, a fixed test set (frames never trained on) is measured with the starting model
before training and with every trained model at its end: both go into NAME_train.json ("test") and
one line compares them, so a round of new labels that made the model worse shows.
Ctrl-C or a kill loses at most one epoch: rerun with --resume.
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "train"
OUTPUTS = ("out",)
USES_TENSORFLOW = True
EXAMPLES = """\
  fcnpose-tf train --data my_frames/ --out models/arm.keras         # fine-tune the bundled generalist, <= 30 min
  fcnpose-tf train --data my_frames/ --out models/arm.keras --resume                     # after Ctrl-C
  fcnpose-tf train --data my_frames/ --out models/arm.keras --max-minutes 90             # a longer budget
  fcnpose-tf train --data my_frames/ --out models/arm.keras --folds 5                    # 5-fold CV
  fcnpose-tf train --data labels.json --images frames/ --out models/arm.keras --input-size 224  # the whole frame
  fcnpose-tf train --data my_frames/ --out models/arm.keras --input-size 384 --crop none  # finer, 2.6x the MACs
  fcnpose-tf train --data my_frames/ --out models/arm.keras --augment online   # fresh transforms, whatever the views
  fcnpose-tf train --data merged.json --out models/arm2.keras --init models/arm.keras --test-data test/  # a round
  fcnpose-tf train --data data/ur5 --out models/paper.keras --preset paper  # the paper's recipe (from scratch)
"""




def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import add_data_arguments, add_test_data_arguments

    add_data_arguments(parser, positional=False, folds_option=False)
    parser.add_argument("--out", type=Path, required=True, metavar="MODEL.keras",
                        help="where to save the best model (.keras or .h5); with --folds, NAME_foldK.keras")
    settings.add_preset_argument(parser)
    for setting in (settings.EPOCHS, settings.TRAIN_PATIENCE, settings.TRAIN_KEEP_BEST, settings.BATCH_SIZE,
                    settings.TRAIN_LEARNING_RATE, settings.TRAIN_LR_PATIENCE, settings.LR_SCHEDULE, settings.TRAIN_MAX_MINUTES,
                    settings.TRAIN_POSITIVE_WEIGHT, settings.TRAIN_FREEZE, settings.TRAIN_INPUT_SIZE, settings.TRAIN_CROP,
                    settings.TRAIN_AUGMENT, settings.TRAIN_AUGMENT_COPIES, settings.TRAIN_FOLDS):
        setting.add_to(parser)
    settings.FOLD.add_to(parser)
    settings.SEED.add_to(parser)
    settings.INIT.add_to(parser)
    settings.ARCHITECTURE.variant(default=None, help=settings.ARCHITECTURE.help + " (default: "
                                  f"{settings.FINE_TUNE_ARCHITECTURE} from the bundled generalist, the --init model's "
                                  "own otherwise, fcn-pose from random weights)").add_to(parser)
    add_test_data_arguments(parser, "a fixed test set (dataset folder or VIA file; frames never trained on): the "
                            "starting model and every trained one are measured on it (PCK@0.5/0.2/0.05, EPE, missing, "
                            "per keypoint), in NAME_train.json and one line comparing them")
    settings.THREADS.add_to(parser)
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run from its checkpoint")
    settings.FORCE.variant(help="replace existing model files / start over").add_to(parser)


def initial_weights(init: str) -> Path | None:
    """The model file --init names: None for "none", else `bundled.resolve_model`'s (a file, or a bundled name)."""
    from fcnpose_tf.bundled import KERAS_SUFFIXES, resolve_model

    if init == "none":
        return None
    return resolve_model(init, KERAS_SUFFIXES)


def written_outputs(args: argparse.Namespace) -> tuple[str, ...]:
    """The output options written under the name given, refused up front when they exist (`cli`): --out, unless
    folds write NAME_foldK.keras instead or --resume continues into it."""
    return () if args.resume or args.folds or args.fold is not None else ("out",)


def fold_model_path(out: Path, fold: int | None) -> Path:
    """NAME.keras for the hold-out split, NAME_foldK.keras for fold K."""
    return out if fold is None else out.with_name(f"{out.stem}_fold{fold}{out.suffix}")


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import load_from_args, load_test_data
    from fcnpose_tf.data.dataset import resolve_data
    from fcnpose_tf.data.splits import stored_seed
    from fcnpose_tf.keypoints import describe_mirror
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.training.evaluate import format_timing
    from fcnpose_tf.training.tfsetup import set_tensorflow_threads
    from fcnpose_tf.metrics import format_report
    from fcnpose_tf.training.train import (FitConfig, FixedTestSetRecord, check_checkpoint, check_outputs,
                                           format_test_set_line, resolve_augment, run_identity, start_on_test_set,
                                           train_fold)

    init = initial_weights(args.init)
    config = settings.from_args(args, FitConfig)  # settings left None: chosen per run (resolved)
    config.validate()
    for setting in (settings.TRAIN_INPUT_SIZE, settings.TRAIN_CROP, settings.TRAIN_AUGMENT, settings.TRAIN_AUGMENT_COPIES,
                    settings.TRAIN_FOLDS, settings.FOLD, settings.THREADS):
        setting.validate(getattr(args, setting.name))
    if args.out.suffix not in (".keras", ".h5"):
        raise UserError(f"{args.out}: --out must end in .keras or .h5")
    k = args.folds or settings.FOLDS.default
    if args.fold is not None and not 0 <= args.fold < k:
        raise UserError(f"--fold must be between 0 and {k - 1} for {k} folds, got {args.fold}")
    folds: list[int | None]
    if args.fold is not None:
        folds = [args.fold]
    elif args.folds:
        folds = list(range(k))
    else:
        folds = [None]
    if not args.resume:
        for fold in folds:  # fail before any training, not after the first fold
            check_outputs(fold_model_path(args.out, fold), args.force)
    via_path, images_dir = resolve_data(args.data, args.images)
    if args.split_seed is None:  # the stored splits' seed, else 0: what the checkpoint's identity records
        args.split_seed = stored_seed(via_path) or 0
    finished = _finished_folds(args, folds, via_path) if args.resume and len(folds) > 1 else {}
    resumes = {fold: args.resume and fold not in finished and (len(folds) == 1 or _has_checkpoint(args.out, fold))
               for fold in folds}  # --resume --folds K: each fold's checkpoint continued, the folds never begun started
    if args.resume and len(folds) > 1:
        if not finished and not any(resumes.values()):
            raise UserError(f"{args.out}: no fold of {len(folds)} was finished or left a checkpoint: nothing to resume")
        for fold in [f for f in folds if f not in finished and not resumes[f]]:
            check_outputs(fold_model_path(args.out, fold), args.force)
    # a bundled start is recorded by its name (its path is this machine's), a user's model by the path given
    from fcnpose_tf.bundled import BUNDLED_MODELS

    metadata: dict = {"init": args.init if args.init in BUNDLED_MODELS else (str(init) if init else None),
                      "preset": args.preset,
                      # where the frames are, from any folder: `export` and `compress` find them without --data
                      "data_absolute": str(via_path.resolve()),
                      "images": str(Path(args.images).resolve()) if args.images is not None else None}
    if args.architecture is None and args.init == "generalist":
        args.architecture = metadata["architecture_auto"] = settings.FINE_TUNE_ARCHITECTURE
        print(f"Architecture: {args.architecture} (fine-tuning the generalist: conv2's half-resolution block added "
              "before conv10, at zero; --architecture fcn-pose keeps the paper's network)")
    # auto settings are resolved before the checkpoint check: a checkpoint records what ran
    size_was_chosen = args.input_size == settings.AUTO_INPUT_SIZE
    from fcnpose_tf.data.arm_size import resolve_view
    from fcnpose_tf.data.via import read_via
    from fcnpose_tf.data.views import FIXED_CAMERA_MAX_VARIATION, view_variation

    frames = read_via(via_path, images_dir, attribute=args.keypoint_attr, min_visible=args.min_visible,
                      skip_bad=args.skip_bad).frames
    if args.augment == "auto":
        choice = resolve_augment(frames)
        args.augment, metadata["augment_auto"] = choice["chose"], choice
        fixed_camera = args.augment == "paper"
    else:
        fixed_camera = args.crop == "auto" and size_was_chosen and \
            view_variation([f.image_path for f in frames]) <= FIXED_CAMERA_MAX_VARIATION
    from fcnpose_tf.training.model import architecture_of, load_model, view_of

    start_model = load_model(init) if init is not None else None  # read once: its view and its network
    start_view = view_of(start_model) if size_was_chosen and start_model is not None else None
    view_choice = resolve_view(frames, args.input_size, args.crop, fixed_camera, start=start_view)
    view, metadata["view_auto"] = view_choice.chose, view_choice.to_json()
    args.input_size = view
    if args.architecture is None:  # the start's own network
        args.architecture = architecture_of(start_model) if start_model is not None else "fcn-pose"
    resolved = config.resolved(trained_start=init is not None, augment=args.augment, architecture=args.architecture)
    if args.augment_copies is None:
        args.augment_copies = settings.train_augment_copies(init is not None, args.augment, args.architecture)
        if args.augment == "paper":
            print(f"Augmented copies: {args.augment_copies} a frame ("
                  + ("fine-tuning an fcn-pose-skip network on one fixed camera"
                     if settings.skip_fine_tune(init is not None, args.augment, args.architecture)
                     else "the paper's") + "; --augment-copies sets it)")
    for fold in [f for f in folds if f not in finished]:  # a checkpoint that cannot be resumed: refused before the data
        check_checkpoint(fold_model_path(args.out, fold), resume=resumes[fold], force=args.force,
                         identity=run_identity(via_path, resolved, input_size=view.size_record,
                                               crop=view.to_json()["crop_xywh"], fold=fold, folds=k,
                                               augment=args.augment, augment_copies=args.augment_copies,
                                               split_seed=args.split_seed))
    dataset = load_from_args(args)  # --folds K or a --fold: K folds required of the data; else the hold-out split
    if args.augment == "online" and (pairs := describe_mirror(dataset.schema)):
        print(f"Flips swap the labels of {pairs} (names that differ only in a side word)")
    test = load_test_data(args, dataset) if args.test_data is not None else None

    set_tensorflow_threads(args.threads)
    test_start = None
    if test is not None and init is not None:
        print(f"Measuring the starting model ({metadata['init']}) on the {len(test)} frames of the test set "
              f"{test.via_path}")
        test_start = (metadata["init"], start_on_test_set(init, test, args.threads))
    reports = []
    test_lines = []
    for fold in folds:
        if fold in finished:
            record = finished[fold]
            print(f"{fold_model_path(args.out, fold)}: fold {fold} was finished before (its record)")
        else:
            try:
                record = train_fold(dataset, fold, fold_model_path(args.out, fold), config,
                                    input_size=args.input_size, augment_copies=args.augment_copies,
                                    augment=args.augment, init=init, resume=resumes[fold], force=args.force,
                                    metadata=metadata, threads=args.threads, test_data=test, test_start=test_start,
                                    size_was_chosen=size_was_chosen, architecture=args.architecture)
            except UserError as exc:
                if len(folds) > 1 and fold != folds[0]:  # the folds before it are finished: --resume skips them
                    done = ", ".join(str(f) for f in folds[:folds.index(fold)])
                    raise UserError(f"{exc} (fold{'s' if ',' in done else ''} {done} finished: `--resume` "
                                    f"continues from fold {fold})") from None
                raise
        print(f"Validation ({record.split}, {record.raw['val_frames']} frames, PCK normalised by max(bbox w, h)):")
        validation = record.validation
        print(format_report(validation.metrics))
        print(format_timing(validation.timing))
        reports.append((fold, validation))
        if test is not None:
            line = format_test_set_line(FixedTestSetRecord.from_json(record.raw["test"]))
            test_lines.append(line if len(folds) == 1 else f"fold {fold}: {line}")
            print(line)
    if len(reports) > 1:
        _print_fold_summary(reports)
        for line in test_lines:
            print(line)
    return 0


def _has_checkpoint(out: Path, fold: int | None) -> bool:
    """Whether the run writing that fold's model left a checkpoint to resume."""
    from fcnpose_tf.training.train import run_paths

    paths = run_paths(fold_model_path(out, fold))
    return paths["ckpt_state"].is_file() and paths["ckpt_model"].is_file()


def _finished_folds(args: argparse.Namespace, folds: list, via_path: Path) -> dict:
    """`--resume --folds K`: fold -> the record of each fold an earlier run of this command finished (its model and
    record written, no checkpoint left); refused when one was trained on other frames or another split."""
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.records import file_sha256, training_record

    finished = {}
    for fold in folds:
        path = fold_model_path(args.out, fold)
        if _has_checkpoint(args.out, fold) or not path.is_file():
            continue
        record = training_record(path)
        if record is None or record.validation is None or record.fold != fold or record.folds != len(folds) \
                or record.data_sha256 != file_sha256(via_path):
            raise UserError(f"{path}: not a finished fold {fold} of {len(folds)} of {via_path} (its record says "
                            "otherwise, or it has none); pass --force (without --resume) to train every fold again")
        finished[fold] = record
    if len(finished) == len(folds):
        raise UserError(f"all {len(folds)} folds of {args.out} are finished: nothing to resume")
    return finished


def _print_fold_summary(reports: list) -> None:
    import numpy as np

    from fcnpose_tf.tables import format_table

    keys = ["pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox", "epe_px"]
    rows = []
    for fold, rep in reports:
        m, t = rep.metrics, rep.timing
        rows.append([f"fold {fold}", m.pck[0.5], m.pck[0.2], m.pck[0.05], m.epe_px, t.inference_ms.mean, t.fps])
    values = np.array([[r[i] if r[i] is not None else np.nan for i in range(1, len(r))] for r in rows], float)
    rows.append(["mean"] + [round(float(v), 4) for v in np.nanmean(values, axis=0)])
    rows.append(["std"] + [round(float(v), 4) for v in np.nanstd(values, axis=0)])
    print(f"\n{len(reports)}-fold summary (PCK normalised by max(bbox w, h)):")
    print(format_table(["fold"] + keys + ["inference_ms", "fps"], rows))
