"""Dataset options on the command line and loading a dataset from them.

Every data-reading command (`data`, `train`, `evaluate`, `compress`, `sweep`) shares these options
and loads its frames the same way; this module holds both, so no command module imports another.
Imports nothing heavy at module level (the CLI builds its parser from it).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from fcnpose_tf.errors import UserError
from fcnpose_tf.settings import FOLDS


def add_data_arguments(parser: argparse.ArgumentParser, positional: bool = True, required: bool = True,
                       folds_option: bool = True, model_splits: bool = False) -> None:
    """The dataset options every data-reading command shares (DATA, --images, labels, drops, splits).

    `positional=False` makes it `--data DATA` (train, evaluate, compress); `folds_option=False`
    leaves --folds to the command (train uses it for "one model per fold"), K then defaulting to 5;
    `model_splits=True` for a command that reads a model's splits from its training record (`splits_of_record`).
    """
    if positional:
        parser.add_argument("data", type=Path, metavar="DATA", help="dataset folder or VIA .json file")
    else:
        parser.add_argument("--data", type=Path, metavar="DATA", required=required,
                            help="dataset folder (one VIA .json + its images) or a VIA .json file")
    parser.add_argument("--images", type=Path, metavar="DIR", help="folder of the images the VIA file names")
    parser.add_argument("--keypoint-attr", default="keypoint", metavar="NAME",
                        help="VIA region attribute holding each point's keypoint name")
    parser.add_argument("--min-visible", type=int, metavar="N",
                        help="drop frames with fewer annotated keypoints (default: half the schema's, 4 of 8)")
    parser.add_argument("--skip-bad", action="store_true",
                        help="skip frames with bad regions or missing images instead of stopping")
    if folds_option:  # unset (None): the default K, and no folds on a dataset smaller than that
        FOLDS.variant(default=None, paper=None, help=f"{FOLDS.help}; default {FOLDS.default}, refused for fewer frames "
                      "when given").add_to(parser)
    recorded = " (or the model's training record's, for the data it was trained on)" if model_splits else ""
    parser.add_argument("--split-seed", type=int, default=None,
                        help=f"seed of the splits: left out, the stored splits'{recorded}, else 0 for new ones")
    parser.add_argument("--resplit", action="store_true", help="replace the stored splits")


def add_test_data_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """`--test-data T` (`what` it is for) and `--test-images DIR`, read by `load_test_data`."""
    parser.add_argument("--test-data", type=Path, metavar="T", help=f"{what}; images found as for --data")
    parser.add_argument("--test-images", type=Path, metavar="DIR",
                        help="folder of the images --test-data's VIA file names, as --images is for --data")


def load_test_data(args: argparse.Namespace, dataset: Any) -> Any:
    """The --test-data set (its images in --test-images, else where its VIA file says), loaded as --data is (the same
    keypoint attribute, drops) without writing splits beside it.

    Its keypoints are read by name in the data's order (a VIA file whose dropdown lists them in another order, or
    whose schema has another name or skeleton, holds the same keypoints).

    Raises:
        UserError: it names other keypoints than `dataset`, or it holds frames of `dataset` (the same pixels under any
            name: `correction.merge.image_fingerprint`).
    """
    from fcnpose_tf.correction.merge import image_fingerprint
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.keypoints import keypoint_difference

    def load(schema=None):
        try:
            return load_dataset(args.test_data, getattr(args, "test_images", None), attribute=args.keypoint_attr,
                                schema=schema, min_visible=args.min_visible, skip_bad=args.skip_bad,
                                write_splits=False)
        except UserError as exc:  # the reader names --data's option; the test set's is --test-images
            raise UserError(str(exc).replace("pass --images DIR", "pass --test-images DIR")) from None

    test = load()
    if set(test.schema.keypoints) != set(dataset.schema.keypoints):
        raise UserError(f"--test-data {test.via_path}: keypoint schema {test.schema.name!r} "
                        f"({', '.join(test.schema.keypoints)}) differs from the data's {dataset.schema.name!r} "
                        f"({', '.join(dataset.schema.keypoints)}): "
                        f"{keypoint_difference(dataset.schema.keypoints, test.schema.keypoints, 'the data', 'it')}")
    if test.schema != dataset.schema:
        test = load(dataset.schema)
    known = {image_fingerprint(s.image_path) for s in dataset.samples} - {None}
    shared = [s.filename for s in test.samples if image_fingerprint(s.image_path) in known]
    if shared:
        raise UserError(f"--test-data {test.via_path}: {len(shared)} of its {len(test)} frames are also frames of "
                        f"--data {dataset.via_path} ({', '.join(shared[:3])}{', ...' if len(shared) > 3 else ''}); "
                        "a test set must hold frames never trained on (the same images, under any name)")
    return test


def load_from_args(args: argparse.Namespace) -> Any:
    """load_dataset with the options of add_data_arguments.

    K is the command's --folds, or the default when a --fold index is given (its folds must then
    exist); with neither, the default K is not required of the data.
    """
    from fcnpose_tf.data.dataset import load_dataset

    folds = getattr(args, "folds", None)
    if folds is None and getattr(args, "fold", None) is not None:
        folds = FOLDS.default
    return load_dataset(args.data, args.images, attribute=args.keypoint_attr, min_visible=args.min_visible,
                        skip_bad=args.skip_bad, folds=folds, split_seed=args.split_seed, resplit=args.resplit)


def splits_of_record(args: argparse.Namespace, model_path: str | Path) -> None:
    """With no --split-seed (and no --folds) given, the seed and K of the splits `model_path` was trained with, when
    `args.data` is the annotation file it was trained on (its training record's, or a .tflite's own, SHA-256): new
    splits of a copy of the data (no splits file beside it) then hold the model's validation frames, not seed 0's.
    Sets `args.split_seed` (and `args.folds`) in place."""
    from fcnpose_tf.data.dataset import resolve_data
    from fcnpose_tf.records import file_sha256, training_record

    if getattr(args, "split_seed", None) is not None or getattr(args, "data", None) is None:
        return
    record = training_record(model_path)
    if record is None or record.split_seed is None or not record.data_sha256:
        return
    try:
        via_path, _ = resolve_data(args.data, getattr(args, "images", None))
        same = file_sha256(via_path) == record.data_sha256
    except (UserError, OSError):  # loading the data says what is wrong with it
        return
    if same:
        args.split_seed = record.split_seed
        if getattr(args, "folds", None) is None and getattr(args, "fold", None) is None and record.folds:
            args.folds = record.folds


def recorded_data(model_path: str | Path, record: Any) -> tuple[Path, Path | None] | None:
    """The annotation file `model_path` was trained on and its images' folder (None: where the file says), as its
    training record (`records.training_record`, or None) names them, when that file is still there unchanged (the
    same SHA-256); None otherwise. Looked up at its absolute path, then (an older record's path as given) from the
    current folder and from the model's."""
    from fcnpose_tf.records import file_sha256

    if record is None or not record.data or not record.data_sha256:
        return None
    recorded = Path(record.data)
    candidates = [Path(record.data_absolute)] if record.data_absolute else []
    candidates += [recorded, Path(model_path).parent / recorded] if not recorded.is_absolute() else [recorded]
    for candidate in candidates:
        try:
            if candidate.is_file() and file_sha256(candidate) == record.data_sha256:
                return candidate, Path(record.images) if record.images else None
        except OSError:
            continue
    return None


def default_data(model_path: str | Path, images: str | Path | None = None,
                 say: Any = print) -> tuple[Path, Path | None]:
    """`--data` left out: (the annotation file, its images' folder) `model_path` was trained on (`recorded_data`;
    `images`, the command's --images, wins), else the synthetic frames the bundled models were trained on. Says which.

    Raises:
        UserError: a model of the user's (not bundled) whose training record names frames that are not found or have
            changed: another set of frames, the synthetic ones least of all, is never taken in their place.
    """
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.data import synthcache
    from fcnpose_tf.records import training_record

    name = Path(model_path).name
    record = training_record(model_path)
    recorded = recorded_data(model_path, record)
    if recorded is not None:
        say(f"Data: {recorded[0]}, the frames {name} was trained on (its training record)")
        return recorded[0], images if images is not None else recorded[1]
    try:
        bundled = Path(model_path).resolve().parent == models_dir().resolve()
    except UserError:  # no bundled models on this machine
        bundled = False
    if record is not None and record.data and not bundled:
        raise UserError(f"{model_path}: its training record names {record.data_absolute or record.data} as the frames "
                        f"it was trained on, and that file is not there or has changed; give them with --data")
    data = synthcache.default_training_data()
    say(f"Data: {data}, the synthetic frames the bundled models were trained on "
        f"({'a bundled model' if bundled else f'no training record names the frames {name} was trained on'})")
    return data, images
