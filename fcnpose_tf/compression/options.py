"""What a compression run is asked to do: `CompressOptions` (resolved and validated once: `CheckedOptions`) and the
files it writes.

The options are the `compress` command's settings (`fcnpose_tf.settings`), the same for `sweep`; `output_files` names
every file a run writes (`OutputFiles`), once, so a command can refuse an existing one before any work.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Collection

from fcnpose_tf import settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import check_writable
from fcnpose_tf.records import training_record

if TYPE_CHECKING:
    from fcnpose_tf.training.train import FitConfig

METHODS = settings.METHOD.choices


@settings.config_class(settings.RATE, settings.METHOD, settings.STRATEGY, settings.QUANTIZE,
                       settings.CALIBRATION_FRAMES, settings.RETRAIN_EPOCHS,
                       ("patience", settings.COMPRESS_RETRAIN_PATIENCE), ("max_minutes", settings.COMPRESS_MAX_MINUTES),
                       settings.COMPRESS_TOTAL_MINUTES, settings.BATCH_SIZE,
                       ("learning_rate", settings.COMPRESS_LEARNING_RATE), ("augment", settings.INHERITED_AUGMENT),
                       ("augment_copies", settings.INHERITED_AUGMENT_COPIES),
                       settings.SEED, settings.RETRAIN_FOLD, settings.THREADS,
                       ("positive_weight", settings.INHERITED_POSITIVE_WEIGHT),
                       ("lr_patience", settings.COMPRESS_LR_PATIENCE), settings.LR_SCHEDULE,
                       ("importance", settings.COMPRESS_IMPORTANCE), settings.IMPORTANCE_FRAMES, settings.DISTILL,
                       settings.FREEZE, ("min_filters", settings.COMPRESS_MIN_FILTERS), settings.PRUNED_START,
                       ("input_size", settings.COMPRESS_INPUT_SIZE), settings.QAT_EPOCHS,
                       settings.QAT_LEARNING_RATE, settings.CENTROID, settings.CLUSTER, settings.KEEP_BEST,
                       settings.POLISH_MINUTES)
class CompressOptions:
    """Settings of one compression run: rate, method, strategy, quantize (the TFLite files, one per format),
    calibration_frames (int8), and the retraining's
    retrain_epochs, patience, batch_size, learning_rate, augment, augment_copies, seed, fold, threads,
    positive_weight (use the base model's), lr_patience, lr_schedule and keep_best (the retraining's kept epoch:
    `train.FitConfig`), polish_minutes (a retraining with frames added, `compress --more-frames`: the minutes more on
    the user's frames alone, `polish_config`); importance (the filter criterion) with
    importance_frames (data-aware criteria), distill (the base model's weight as a teacher while
    retraining), freeze (conv1..convN keep their pruned weights while retraining), min_filters (the
    narrowest a pruned layer may become at the same parameter budget), start (the pruned network's weights before
    retraining: surgery, auto, or a pruned model: `pruned_start`), input_size (the side the model is rebuilt, retrained
    and exported at; None: its own), and qat_epochs / qat_learning_rate
    (quantization-aware training when post-training int8 is refused; 0 epochs: no fallback); centroid and cluster:
    how the table's keypoints are read (`postprocess.CENTROIDS`, `postprocess.CLUSTERS`).

    The defaults are `fcnpose-tf compress`'s (`CompressOptions.preset("paper", rate=...)`: the paper's recipe);
    importance, min_filters, lr_patience, positive_weight, augment and augment_copies left None are chosen per run by
    `resolved`
    (`checked` resolves and validates them once, for `compress_model`). Defaults, checks and meanings: `fcnpose_tf.settings`."""

    def validate(self) -> None:
        """Check every setting (`fcnpose_tf.settings`) and the combinations no run can do.

        Raises:
            UserError: a setting out of its range or choices, a cosine schedule with a plateau patience, or
                a combination no run can do (magnitude pruning with a filter criterion, --freeze, --min-filters or a
                pruned start; the greedy strategy with a data-aware criterion).
        """
        from fcnpose_tf.compression.importance import DATA_AWARE

        settings.validate_fields(self)
        settings.check_lr_schedule(self.lr_schedule, self.lr_patience or 0)
        if self.method == "magnitude" and self.importance not in (None, "l1"):
            raise UserError(f"--importance {self.importance} ranks filters for filter surgery (--method l1); "
                            "magnitude pruning zeroes the smallest weights")
        if self.method == "magnitude" and self.freeze:
            raise UserError(f"--freeze {self.freeze} keeps the first convolutions of filter surgery's model fixed; "
                            "magnitude pruning retrains every weight it masks (use --freeze 0)")
        if self.method == "magnitude" and self.min_filters:
            raise UserError(f"--min-filters {self.min_filters} sets the widths of filter surgery's layers (--method "
                            "l1); magnitude pruning keeps every filter (use --min-filters 0)")
        if self.method == "magnitude" and self.start not in ("auto", "surgery"):
            raise UserError(f"--start {self.start} gives filter surgery's pruned network its weights (--method l1); "
                            "magnitude pruning masks the base model's own (use --start surgery)")
        if self.strategy == "greedy" and self.importance in DATA_AWARE:
            raise UserError(f"--strategy greedy re-ranks kernels without the removed input channels; the "
                            f"{self.importance} criterion ranks filters by their outputs (use --strategy independent)")

    def resolved(self, base_path: str | os.PathLike | None = None) -> CompressOptions:
        """These options with the settings left None chosen for the run: importance (`settings.DEFAULT_COMPRESS_IMPORTANCE`
        for filter surgery with the independent strategy, else the paper's l1: greedy ranking reads kernels only),
        min_filters (`settings.DEFAULT_COMPRESS_MIN_FILTERS` for filter surgery; magnitude pruning keeps every
        filter), lr_patience (`settings.resolved_lr_patience`), positive_weight, augment and augment_copies (those
        `base_path` was trained with, from its NAME_train.json; else 1, the paper's plain BCE, and the paper's 2 copies).

        Args:
            base_path: the model to compress, whose NAME_train.json is read (None: none is read).
        Returns:
            A copy with those settings chosen; nothing is validated.
        """
        importance, min_filters, positive_weight, augment = (self.importance, self.min_filters, self.positive_weight,
                                                             self.augment)
        if importance is None:
            independent_surgery = self.method == "l1" and self.strategy == "independent"
            importance = settings.DEFAULT_COMPRESS_IMPORTANCE if independent_surgery else "l1"
        if min_filters is None:
            min_filters = settings.DEFAULT_COMPRESS_MIN_FILTERS if self.method == "l1" else 0
        augment_copies = self.augment_copies
        record = training_record(base_path) if base_path is not None and None in (positive_weight, augment,
                                                                                   augment_copies) else None
        if positive_weight is None:
            positive_weight = float(record.positive_weight or 1.0) if record is not None else 1.0
        if augment is None:
            inherited = record.augment if record is not None else None
            augment = inherited if inherited in settings.AUGMENT.choices else settings.AUGMENT.default
        if augment_copies is None:
            inherited = record.augment_copies if record is not None and record.augment == "paper" else None
            augment_copies = inherited if inherited is not None and inherited >= 0 else \
                int(settings.AUGMENT_COPIES.default)
        lr_patience = settings.resolved_lr_patience(self.lr_patience, self.lr_schedule,
                                                    settings.DEFAULT_COMPRESS_LR_PATIENCE)
        return replace(self, importance=importance, min_filters=min_filters, positive_weight=positive_weight,
                       lr_patience=lr_patience, augment=augment, augment_copies=augment_copies)

    def checked(self, base_path: str | os.PathLike | None = None) -> CheckedOptions:
        """These options resolved for `base_path` (`resolved`) and validated (`validate`), an explicit pruned start
        found (a file or a bundled name, before any data is read): what `compress_model` takes, checked once by its
        caller (`CheckedOptions.at_rate` for the other rates of `compress --rates`).

        Args:
            base_path: the model to compress (its NAME_train.json is read by `resolved`).
        Returns:
            The resolved copy, with the explicit start's file (`CheckedOptions`).
        Raises:
            UserError: as `validate`; an explicit start that is neither a file nor a bundled Keras model.
        """
        from fcnpose_tf.bundled import KERAS_SUFFIXES, resolve_model
        from fcnpose_tf.progress import SILENT

        options = self.resolved(base_path)
        options.validate()
        explicit = options.method == "l1" and options.start not in ("auto", "surgery")
        # found silently here, named when the run takes its weights (`methods.pruned_start`)
        return CheckedOptions(options, resolve_model(options.start, KERAS_SUFFIXES, reporter=SILENT)
                              if explicit else None)

    def retraining_minutes(self, spent_minutes: float, ranking_minutes: float = 0.0,
                           polish_minutes: float = 0.0) -> float | None:
        """The retraining's time budget once `spent_minutes` went to the steps before it.

        The steps after the retraining (measuring the retrained model, exporting, verifying and measuring each file)
        are kept twice what the steps before it took apart from ranking filters (measuring the base model, surgery,
        measuring the pruned model), which nothing after repeats; a polish after it (`polish_config`) keeps its own
        minutes.

        Args:
            spent_minutes: what the run took before its retraining.
            ranking_minutes: the part of it spent ranking filters (a data-aware criterion's pass over its frames).
            polish_minutes: the polish's budget, when the run polishes (frames added: `with_added_frames`).
        Returns:
            `max_minutes`, shortened so that the run ends within `total_minutes`: what is left of it after
            `spent_minutes`, the polish and the steps after, but at least `settings.MIN_RETRAIN_MINUTES`; None (no
            budget) when both are None.
        """
        if self.total_minutes is None:
            return self.max_minutes
        after = 2 * max(spent_minutes - ranking_minutes, 0.0) + polish_minutes
        left = max(self.total_minutes - spent_minutes - after, settings.MIN_RETRAIN_MINUTES)
        return left if self.max_minutes is None else min(self.max_minutes, left)

    def with_added_frames(self, training_frames: int, added: int, spent_minutes: float,
                          given: Collection[str] = ()) -> CompressOptions:
        """The time budgets of a run whose retraining gets `added` frames beside the `training_frames` of the user's
        split (`compress --more-frames`), `spent_minutes` after labelling them.

        An epoch takes (training_frames + added) / training_frames as long, so a retraining budget left at its
        default (not in `given`) grows by that factor, and the total budget by the minutes the retraining gained and
        the polish's (`polish_minutes`, after the retraining on the user's frames alone: `polish_config`); a total
        budget (given or not) loses the minutes the labelling took, down to `settings.MIN_RETRAIN_MINUTES`. A
        retraining budget the user gave keeps its value.

        Args:
            training_frames: the training frames of the user's split (at least 1).
            added: the frames added to it.
            spent_minutes: what labelling them took.
            given: the settings the command line gave (`settings.GIVEN`): "max_minutes", "total_minutes".
        Returns:
            A copy with `max_minutes` and `total_minutes` set.
        """
        max_minutes, total_minutes = self.max_minutes, self.total_minutes
        if max_minutes is not None and "max_minutes" not in given:
            max_minutes = max_minutes * (training_frames + added) / max(training_frames, 1)
        if total_minutes is not None:
            polish = self.polish_minutes if added else 0.0
            grown = total_minutes + (max_minutes or 0.0) - (self.max_minutes or 0.0) + polish
            total_minutes = max(grown - spent_minutes, settings.MIN_RETRAIN_MINUTES)
        return replace(self, max_minutes=max_minutes, total_minutes=total_minutes)

    def fit_config(self) -> FitConfig:
        """The retraining's optimisation settings, carried from these options.

        Returns:
            The `train.FitConfig` (at least one epoch; 0 retraining epochs skip `fit`).
        """
        from fcnpose_tf.training.train import FitConfig

        return settings.carried(self, FitConfig, epochs=max(self.retrain_epochs, 1))

    def polish_config(self) -> FitConfig:
        """The polish's optimisation settings: after a retraining with frames added (`compress --more-frames`), the
        retraining's own settings on the user's frames alone, `polish_minutes` long, at
        `settings.POLISH_LEARNING_RATE_SCALE` of its learning rate, conv1-2 fixed as `train` fine-tunes a trained model
        (`settings.DEFAULT_FINE_TUNE_FREEZE`; magnitude pruning retrains every weight it masks).

        Returns:
            The `train.FitConfig`.
        """
        freeze = max(self.freeze, settings.DEFAULT_FINE_TUNE_FREEZE) if self.method == "l1" else self.freeze
        return replace(self.fit_config(), learning_rate=self.learning_rate * settings.POLISH_LEARNING_RATE_SCALE,
                       max_minutes=self.polish_minutes, freeze=freeze)


@dataclass(frozen=True)
class CheckedOptions:
    """A run's options as `CompressOptions.checked` leaves them, resolved and validated once, with what the check found:
    what `compress_model` takes, checking nothing again."""

    options: CompressOptions
    """The options, every setting `CompressOptions.resolved` chooses per run chosen."""
    start_file: Path | None = None
    """The file an explicit --start names (its path, or a bundled model's file), found once; None for surgery and for
    auto, which the run decides with its plan (`methods.pruned_start`)."""

    def at_rate(self, rate: float) -> CheckedOptions:
        """These options at another rate (`compress --rates`), only the rate checked: every other setting is the same.

        Args:
            rate: the pruning rate.
        Returns:
            The options at `rate`, the same start file.
        Raises:
            UserError: a rate outside [0, 1) (`settings.RATE`).
        """
        return replace(self, options=replace(self.options, rate=settings.RATE.validate(rate)))


RATE_TAGS = {"l1": "p", "magnitude": "m"}
"""First letter of the output names' rate tag, per --method: p70 (filters removed), m70 (weights zeroed)."""


def tflite_key(quantize: str) -> str:
    """The key of a TFLite file in a run's names and paths (and the report's "files"): tflite_fp16, tflite_int8.

    Args:
        quantize: the format (`settings.TFLITE_FORMATS`).
    Returns:
        The key.
    """
    return f"tflite_{settings.QUANTIZE_FILE_TAGS[quantize]}"


def output_names(base_name: str, options: CompressOptions) -> dict[str, str]:
    """File names of a run: NAME_p70.keras, NAME_p70_fp16.tflite (one per --quantize format, key
    `tflite_key`), NAME_p70_report.json (m70 for magnitude); NAME_p70_192... with --input-size 192.

    Args:
        base_name: the compressed model's file stem.
        options: the run's options.
    Returns:
        Key -> file name: "stem", "keras", one `tflite_key` per format, "report".
    """
    tag = f"{RATE_TAGS[options.method]}{round(options.rate * 100):02d}"
    stem = f"{base_name}_{tag}" + (f"_{options.input_size}" if options.input_size else "")
    return {"stem": stem, "keras": f"{stem}.keras",
            **{tflite_key(q): f"{stem}_{settings.QUANTIZE_FILE_TAGS[q]}.tflite" for q in options.quantize},
            "report": f"{stem}_report.json"}


@dataclass(frozen=True)
class OutputFiles:
    """Every file one run writes, named once (`output_files`): the command refuses an existing one with it before any
    work (`check_outputs`) and names the files kept with it at the end; every step of the run writes to it."""

    stem: str
    """NAME_p70 (NAME_p70_192 with --input-size 192)."""
    paths: dict[str, Path]
    """Key -> path, the report's "files" keys in order: "keras", one `tflite_key` per format, "report"."""
    tflite: dict[str, Path]
    """Format -> its .tflite (the same paths)."""
    side: tuple[Path, ...] = ()
    """The retraining's record and loss curves (none with 0 retraining epochs)."""

    @property
    def every(self) -> list[Path]:
        """The models, the report, then the side files."""
        return [*self.paths.values(), *self.side]


def output_files(base_path: str | os.PathLike, out_dir: str | os.PathLike, options: CompressOptions) -> OutputFiles:
    """Every file a run writes into `out_dir`: the models, the report and (when retraining) the training side files.

    Args:
        base_path: the model being compressed.
        out_dir: the folder the files go to.
        options: the run's options.
    Returns:
        The run's `OutputFiles`.
    """
    from fcnpose_tf.training.train import output_files as training_files

    names = output_names(Path(base_path).stem, options)
    paths = {key: Path(out_dir) / name for key, name in names.items() if key != "stem"}
    side = [p for p in training_files(paths["keras"]) if p not in paths.values()] if options.retrain_epochs > 0 else []
    return OutputFiles(names["stem"], paths, {q: paths[tflite_key(q)] for q in options.quantize}, tuple(side))


def check_outputs(base_path: str | os.PathLike, out_dir: str | os.PathLike, options: CompressOptions,
                  force: bool = False) -> OutputFiles:
    """Refuse before any work a run whose files cannot be written.

    Args:
        base_path: the model being compressed.
        out_dir: the folder the files go to.
        options: the run's options.
        force: existing files may be replaced.
    Returns:
        The run's files (`output_files`), for `compress_model` and the command's last lines.
    Raises:
        UserError: a file the run will write exists (without `force`) or cannot be written.
    """
    files = output_files(base_path, out_dir, options)
    for path in files.every:
        check_writable(path, force)
    return files
