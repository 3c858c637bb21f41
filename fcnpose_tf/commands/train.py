"""Train FCN-Pose on a dataset: Adam, binary cross-entropy, early stopping, resumable checkpoints.

Without --folds the model trains on the 80/20 hold-out split; --folds K trains one model per
fold of the dataset's stored K-fold splits (or only --fold k) and reports mean and std. Training
frames get --augment-copies offline rotation/padding copies each (the paper: 2). Next to the model
it writes NAME_loss.csv/.png (loss curves) and NAME_train.json (settings, epochs, validation
metrics). Ctrl-C or a kill loses at most one epoch: rerun with --resume.
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "train"
USES_TENSORFLOW = True
EXAMPLES = """\
  fcnpose-tf synth --out data/ur5 --n 500
  fcnpose-tf train --data data/ur5 --out saved_models/my_ur5.keras --epochs 60
  fcnpose-tf train --data data/ur5 --out saved_models/my_ur5.keras --epochs 60 --resume   # after Ctrl-C
  fcnpose-tf train --data my_frames/ --out models/arm.keras --folds 5 --epochs 100         # 5-fold CV
  fcnpose-tf train --data labels.json --images frames/ --out models/arm.keras --input-size 160
  fcnpose-tf train --data my_frames/ --out models/arm.keras --init saved_models/fcnpose_ur5.keras  # fine-tune
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.commands.data import add_data_arguments

    add_data_arguments(parser, positional=False, folds_option=False)
    parser.add_argument("--out", type=Path, required=True, metavar="MODEL.keras",
                        help="where to save the best model (.keras or .h5); with --folds, NAME_foldK.keras")
    parser.add_argument("--epochs", type=int, default=500, help="maximum epochs (the paper: 500)")
    parser.add_argument("--patience", type=int, default=20,
                        help="stop after this many epochs without a lower validation loss")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--learning-rate", type=float, default=1e-3, help="Adam learning rate")
    parser.add_argument("--lr-patience", type=int, default=0, metavar="N",
                        help="halve the learning rate after N epochs without a better validation loss "
                             "(again after N more; floor 1e-5); 0 keeps it constant, as the paper does")
    parser.add_argument("--positive-weight", type=float, default=1.0,
                        help="weight of keypoint-disc pixels in the binary cross-entropy (1 = the paper's plain "
                             "BCE; 20 converges several times faster on small discs, see docs/training.md)")
    parser.add_argument("--input-size", type=int, default=224, help="model input side, a multiple of 32")
    parser.add_argument("--augment-copies", type=int, default=2,
                        help="offline augmented copies per training frame (the paper: 2)")
    parser.add_argument("--folds", type=int, metavar="K",
                        help="train one model per fold of K-fold cross-validation (the paper: 5)")
    parser.add_argument("--fold", type=int, metavar="k", help="train only fold k (0-based) of the K folds")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights, augmentation and batch order")
    parser.add_argument("--init", type=Path, metavar="MODEL",
                        help="start from this model's weights (e.g. fine-tune the synthetic baseline on real frames)")
    parser.add_argument("--threads", type=int, help="TensorFlow CPU threads (default: all cores)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run from its checkpoint")
    parser.add_argument("--force", action="store_true", help="replace existing model files / start over")
    parser.add_argument("--quiet", action="store_true", help="one line per epoch instead of a progress bar (for logs)")


def fold_model_path(out: Path, fold: int | None) -> Path:
    """NAME.keras for the hold-out split, NAME_foldK.keras for fold K."""
    return out if fold is None else out.with_name(f"{out.stem}_fold{fold}{out.suffix}")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from fcnpose_tf.commands.data import load_from_args
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_writable
    from fcnpose_tf.model import check_input_size

    check_input_size(args.input_size)
    if args.out.suffix not in (".keras", ".h5"):
        raise UserError(f"{args.out}: --out must end in .keras or .h5")
    if args.folds is not None and args.folds < 2:
        raise UserError(f"--folds must be at least 2, got {args.folds}")
    k = args.folds or 5
    if args.fold is not None and not 0 <= args.fold < k:
        raise UserError(f"--fold must be between 0 and {k - 1} for {k} folds, got {args.fold}")
    if args.augment_copies < 0:
        raise UserError(f"--augment-copies must be >= 0, got {args.augment_copies}")
    folds: list[int | None]
    if args.fold is not None:
        folds = [args.fold]
    elif args.folds:
        folds = list(range(k))
    else:
        folds = [None]
    if not args.resume:
        for fold in folds:  # fail before any training, not after the first fold
            check_writable(fold_model_path(args.out, fold), args.force)
    args.folds = k
    dataset = load_from_args(args)

    from fcnpose_tf.tfsetup import set_tensorflow_threads

    set_tensorflow_threads(args.threads)
    reports = [(fold, _train_one(args, dataset, fold)) for fold in folds]
    if len(reports) > 1:
        _print_fold_summary(reports, np)
    return 0


def _train_one(args: argparse.Namespace, dataset, fold: int | None) -> dict:
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.evaluate import KerasKeypointModel, evaluate_predictor, format_timing
    from fcnpose_tf.records import file_sha256
    from fcnpose_tf.fileio import write_json
    from fcnpose_tf.metrics import format_report
    from fcnpose_tf.model import build_fcn_pose
    from fcnpose_tf.train import FitConfig, fit, run_paths

    path = fold_model_path(args.out, fold)
    if args.init is not None:
        from fcnpose_tf.errors import UserError
        from fcnpose_tf.model import load_model

        model = load_model(args.init)
        if tuple(model.input_shape[1:3]) != (args.input_size, args.input_size) \
                or model.output_shape[-1] != dataset.schema.num_maps:
            raise UserError(f"{args.init}: input {model.input_shape[1:3]} and {model.output_shape[-1]} maps do not "
                            f"match --input-size {args.input_size} and the data's {dataset.schema.num_maps} maps")
    else:
        model = build_fcn_pose(input_size=args.input_size, num_maps=dataset.schema.num_maps)
    split_name = "hold-out 80/20" if fold is None else f"fold {fold} of {args.folds}"
    train_data, val_data = fold_data(dataset, fold, args.input_size, args.augment_copies, args.seed,
                                     progress=not args.quiet)
    print(f"{path}: training on {split_name}: {len(train_data)} samples "
          f"({len(train_data) // (1 + args.augment_copies)} frames + {args.augment_copies} augmented copies each), "
          f"{len(val_data)} validation frames at {args.input_size}x{args.input_size}")
    config = FitConfig(epochs=args.epochs, patience=args.patience, batch_size=args.batch_size,
                       learning_rate=args.learning_rate, seed=args.seed, positive_weight=args.positive_weight,
                       lr_patience=args.lr_patience)
    metadata = {"data": str(dataset.via_path), "data_sha256": file_sha256(dataset.via_path),
                "num_frames": len(dataset), "split": split_name,
                "fold": fold, "folds": args.folds, "split_seed": args.split_seed, "input_size": args.input_size,
                "augment_copies": args.augment_copies, "train_samples": len(train_data),
                "val_frames": len(val_data), "schema": dataset.schema.to_dict(),
                "init": str(args.init) if args.init else None}
    result = fit(model, train_data.sequence(args.batch_size, shuffle=True, seed=args.seed),
                 val_data.arrays(), path, config, resume=args.resume, force=args.force, metadata=metadata,
                 verbose=2 if args.quiet else 1)
    print(f"{path}: best validation loss {result.best_val_loss:.5f} at epoch {result.best_epoch} of "
          f"{result.epochs_run}{' (early stop)' if result.stopped_early else ''}; {result.seconds / 60:.1f} min")

    from fcnpose_tf.model import load_model

    predictor = KerasKeypointModel(load_model(path), path, num_threads=args.threads)
    _, val_idx = dataset.split(fold)
    report = evaluate_predictor(predictor, dataset, val_idx, dataset.schema)
    print(f"Validation ({split_name}, {len(val_idx)} frames, PCK normalised by max(bbox w, h)):")
    print(format_report(report["metrics"]))
    print(format_timing(report["timing"]))
    paths = run_paths(path)
    import json

    summary = json.loads(paths["train_json"].read_text())
    summary["validation"] = {"metrics": report["metrics"], "timing": report["timing"]}
    write_json(paths["train_json"], summary, force=True)
    return summary["validation"]


def _print_fold_summary(reports: list, np) -> None:
    from fcnpose_tf.tables import format_table

    keys = ["pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox", "epe_px"]
    rows = []
    for fold, rep in reports:
        m, t = rep["metrics"], rep["timing"]
        rows.append([f"fold {fold}"] + [m[k] for k in keys] + [t["inference_ms"]["mean"], t["fps"]])
    values = np.array([[r[i] if r[i] is not None else np.nan for i in range(1, len(r))] for r in rows], float)
    rows.append(["mean"] + [round(float(v), 4) for v in np.nanmean(values, axis=0)])
    rows.append(["std"] + [round(float(v), 4) for v in np.nanstd(values, axis=0)])
    print(f"\n{len(reports)}-fold summary (PCK normalised by max(bbox w, h)):")
    print(format_table(["fold"] + keys + ["inference_ms", "fps"], rows))
