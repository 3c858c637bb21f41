"""Fitting FCN-Pose: Adam, binary cross-entropy over the maps, early stopping, resumable checkpoints.

A run writes, next to the model file NAME.keras:

    NAME.keras             the best epoch's weights (`FitConfig.keep_best`: the validation frames' keypoints
                           or the lowest validation loss), no optimizer state
    NAME_loss.csv/.png     training and validation loss per epoch (the paper's loss figure)
    NAME_train.json        configuration, epochs run, best epoch, time
    NAME.ckpt/             while running: the last epoch's model with optimizer state, the best
                           weights so far and the early-stopping state; removed when the run ends

After each epoch the checkpoint's files are written as one (`fileio.atomic_paths`: all renamed
into place only once every one is written), so an interrupted run (Ctrl-C, kill, a full disk)
loses at most the epoch in flight, never the last good checkpoint, and `resume=True` continues it.
"""

from __future__ import annotations

import functools
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence, TypedDict

import numpy as np
import tf_keras as keras

from fcnpose_tf import progress, settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.measurements import Evaluation, KeypointMetrics
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.fileio import (WriteError, atomic_path, atomic_paths, check_writable, json_text, make_folder, parts_of,
                               remove_tree, write_json, write_text)
from fcnpose_tf.training.frozen import feature_sequence, fits_in_memory, split_frozen
from fcnpose_tf.training.model import save_for_inference, view_of, with_facts_of, with_schema
from fcnpose_tf.progress import Reporter
from fcnpose_tf.records import TrainingRecord


@settings.config_class(settings.EPOCHS, ("patience", settings.TRAIN_PATIENCE), settings.BATCH_SIZE,
                       ("learning_rate", settings.TRAIN_LEARNING_RATE), settings.SEED,
                       ("positive_weight", settings.TRAIN_POSITIVE_WEIGHT),
                       ("lr_patience", settings.TRAIN_LR_PATIENCE), settings.LR_SCHEDULE,
                       ("max_minutes", settings.TRAIN_MAX_MINUTES), ("freeze", settings.TRAIN_FREEZE), settings.DISTILL,
                       ("keep_best", settings.TRAIN_KEEP_BEST))
class FitConfig:
    """Optimisation settings of one training run: epochs, patience, batch_size, learning_rate, seed,
    positive_weight and lr_patience (halve the learning rate after this many epochs without a better
    validation score, down to MIN_LEARNING_RATE; 0 keeps it constant), lr_schedule ("cosine": the rate
    of each epoch is `cosine_rate` of the budget spent, epochs or time, instead; lr_patience 0), max_minutes
    (no new epoch starts once the run has trained this long; None: no time budget), freeze (conv1..convN keep
    their weights) and distill (weight of a teacher's maps in the loss; the training batches must
    carry them, `fcnpose_tf.training.distill`).

    The defaults are `fcnpose-tf train`'s (`FitConfig.preset("paper")`: the paper's recipe); learning_rate,
    positive_weight, lr_patience and freeze left None are chosen per run by `resolved`. Defaults, checks and meanings:
    `fcnpose_tf.settings`."""

    def validate(self) -> None:
        """Check every setting and that a cosine schedule is not also asked to halve on plateaus.

        Raises:
            UserError: a setting out of its range or choices, or a cosine schedule with a plateau patience.
        """
        settings.validate_fields(self)
        settings.check_lr_schedule(self.lr_schedule, self.lr_patience or 0)

    def resolved(self, *, trained_start: bool, augment: str = "paper", architecture: str | None = None) -> FitConfig:
        """This config with the settings left None chosen for a run that starts from trained weights or not, with
        this augmentation, of this network: freeze and learning_rate (`settings.train_recipe`), lr_patience
        (`settings.resolved_lr_patience`) and positive_weight (`settings.train_positive_weight`).

        Args:
            trained_start: the run starts from trained weights (fine-tuning), not from random ones.
            augment: the run's augmentation (settings.AUGMENT).
            architecture: the network (`model.ARCHITECTURES`; None: FCN-Pose's recipe).
        Returns:
            A copy with those settings chosen; a setting given is kept.
        """
        freeze, learning_rate = settings.train_recipe(trained_start, augment, architecture)
        freeze = self.freeze if self.freeze is not None else freeze
        learning_rate = self.learning_rate if self.learning_rate is not None else learning_rate
        positive_weight = self.positive_weight if self.positive_weight is not None else \
            settings.train_positive_weight(trained_start=trained_start, augment=augment)
        lr_patience = settings.resolved_lr_patience(self.lr_patience, self.lr_schedule,
                                                    settings.DEFAULT_TRAIN_LR_PATIENCE)
        return replace(self, freeze=freeze, learning_rate=learning_rate, positive_weight=positive_weight,
                       lr_patience=lr_patience)


MIN_LEARNING_RATE = 1e-5


def cosine_rate(progress: float, learning_rate: float) -> float:
    """The learning rate once `progress` of the run's budget is spent, on a half cosine from `learning_rate` towards
    MIN_LEARNING_RATE: lr_min + (lr - lr_min)(1 + cos(pi p)) / 2.

    Args:
        progress: the share of the budget spent, 0 at the start, 1 at the end (clipped to [0, 1]).
        learning_rate: the rate at the start.
    Returns:
        The learning rate.
    """
    low = min(MIN_LEARNING_RATE, learning_rate)
    return low + (learning_rate - low) * 0.5 * (1.0 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))


def budget_progress(epoch: int, epochs: int, seconds: float, max_seconds: float | None) -> float:
    """The share of a run's budget spent when an epoch begins: the larger of the epoch and the time shares, so a cosine
    ends with whichever budget ends first.

    Args:
        epoch: the epoch beginning (0-based).
        epochs: epochs at most.
        seconds: training time so far.
        max_seconds: the time budget (None: none).
    Returns:
        The share, from 0.
    """
    spent = epoch / max(epochs, 1)
    return max(spent, seconds / max_seconds) if max_seconds else spent


@dataclass
class FitResult:
    """What a finished run produced."""

    model_path: Path
    epochs_run: int
    best_epoch: int
    best_val_loss: float
    seconds: float
    stopped_early: bool
    history: list[dict[str, float]] = field(default_factory=list)
    stopped_by_time_budget: bool = False
    """The time budget (`FitConfig.max_minutes`) ended the run before its epochs and early stopping did."""
    best_keypoints: KeptScore | None = None
    """The kept epoch's validation keypoints (`ValidationKeypoints.score`) when they chose it (keep_best
    "keypoints")."""


class KeptScore(TypedDict):
    """The validation frames' keypoints measured after an epoch (`ValidationKeypoints.score`; NAME_train.json's
    "best_val_keypoints")."""

    mean_pck: float
    """`metrics.mean_pck`: the mean of PCK@0.5, @0.2 and @0.05 (bbox), the score compared first."""
    pck_fine: float
    """PCK@0.05 (bbox), for the progress line."""
    epe_px: float | None
    """Mean end-point error in input pixels (None: no keypoint found); compared when the mean PCK ties, lower
    better."""


def better_score(score: KeptScore, best: KeptScore | None) -> bool:
    """Whether `score` beats `best` (None: nothing yet): a higher mean PCK, or the same with a lower EPE."""
    if best is None:
        return True
    if score["mean_pck"] != best["mean_pck"]:
        return score["mean_pck"] > best["mean_pck"]
    inf = math.inf
    return (score["epe_px"] if score["epe_px"] is not None else inf) < \
        (best["epe_px"] if best["epe_px"] is not None else inf)


def describe_kept(epoch: int, val_loss: float, keypoints: KeptScore | None) -> str:
    """The kept epoch and what chose it, in words.

    Args:
        epoch: the kept epoch (0: the start).
        val_loss: its validation loss.
        keypoints: its validation keypoints when they chose it, else None (the loss did).
    Returns:
        `best validation keypoints at epoch N (mean PCK m, PCK@0.05 f, EPE e input px)` or `best validation loss L at
        epoch N`.
    """
    if keypoints is None:
        return f"best validation loss {val_loss:.5f} at epoch {epoch}"
    return f"best validation keypoints at epoch {epoch} ({keypoints_text(keypoints)})"


def keypoints_text(keypoints: KeptScore) -> str:
    """`mean PCK 0.912, PCK@0.05 0.803, EPE 7.10 input px`: a validation keypoints' score in words (the EPE in the
    model's input pixels, not the frame's)."""
    epe = "no keypoint found" if keypoints["epe_px"] is None else f"EPE {keypoints['epe_px']:.2f} input px"
    return f"mean PCK {keypoints['mean_pck']:.3f}, PCK@0.05 {keypoints['pck_fine']:.3f}, {epe}"


@dataclass(frozen=True)
class ValidationKeypoints:
    """The validation frames' true keypoints and how the model's are read: what `fit` scores each epoch with when
    `FitConfig.keep_best` is "keypoints" (`score`).

    The loss weighs every pixel of every map; a keypoint is read from the cluster of its map above the threshold, and
    two epochs of nearly the same loss can place it a pixel or two apart (docs/compression.md, "Retraining in
    fcnpose-tf compress", the kept epoch)."""

    keypoints: np.ndarray
    """N x K x 2 in input pixels, NaN where missing, row for row with the validation arrays
    (`data.dataset.TrainingData.keypoints`)."""
    names: tuple[str, ...]
    """The K keypoint names."""
    decoding: Decoding = field(default_factory=Decoding)
    """How maps become keypoints (the files' own, from the command's settings)."""
    schema: KeypointSchema | None = None
    """The keypoints the maps stand for (the chain's skeleton and limb lengths: `postprocess.maps_to_keypoints`)."""

    @classmethod
    def of(cls, data: Any, decoding: Decoding | None = None) -> ValidationKeypoints:
        """The keypoints of validation `data` (a `TrainingData` without augmented copies).

        Args:
            data: the validation frames as `data.dataset.fold_data` returns them.
            decoding: how maps become keypoints (None: the commands' default).
        Returns:
            The keypoints to score with.
        """
        return cls(np.asarray(data.keypoints, np.float64), tuple(data.schema.keypoints),
                   decoding if decoding is not None else Decoding(), data.schema)

    def score(self, model: keras.Model, inputs: Any, batch_size: int) -> KeptScore:
        """The model's keypoints on the validation inputs against the true ones.

        Args:
            model: the model being trained (its outputs are the maps; a frozen prefix's head takes the features).
            inputs: the validation inputs as `fit` passes them to Keras (images, or the prefix's features).
            batch_size: frames per forward pass.
        Returns:
            The mean PCK, PCK@0.05 and EPE in input pixels.
        """
        from fcnpose_tf.metrics import keypoint_report, mean_pck

        maps = model.predict(inputs, batch_size=batch_size, verbose=0)
        predicted, _ = self.decoding.keypoints(maps, schema=self.schema)
        report = keypoint_report(predicted, self.keypoints, self.names)
        epe = report.epe_px
        return KeptScore(mean_pck=round(mean_pck(report), 6), pck_fine=round(float(report.pck.get(0.05) or 0.0), 6),
                         epe_px=None if epe is None or not math.isfinite(epe) else round(float(epe), 4))


def run_paths(model_path: Path) -> dict[str, Path]:
    """Files belonging to the run that writes `model_path`.

    Args:
        model_path: the model file the run writes.
    Returns:
        Key -> path: model, loss_csv, loss_png, train_json and the checkpoint's (ckpt_dir, ckpt_model, ...).
    """
    stem = model_path.with_suffix("")
    ckpt = Path(f"{stem}.ckpt")
    return {
        "model": model_path,
        "loss_csv": Path(f"{stem}_loss.csv"),
        "loss_png": Path(f"{stem}_loss.png"),
        "train_json": Path(f"{stem}_train.json"),
        "ckpt_dir": ckpt,
        "ckpt_model": ckpt / "last.keras",
        "ckpt_best": ckpt / "best.npz",
        "ckpt_whole": ckpt / "whole_start.npz",
        "ckpt_state": ckpt / "state.json",
    }


def output_files(model_path: Path) -> list[Path]:
    """The files a finished run leaves: the model, its loss curves (.csv, .png) and NAME_train.json.

    Args:
        model_path: the model file the run writes.
    Returns:
        The paths.
    """
    paths = run_paths(Path(model_path))
    return [paths[key] for key in ("model", "loss_csv", "loss_png", "train_json")]


def check_outputs(model_path: Path, force: bool = False) -> None:
    """Refuse before any work a run whose files cannot be written.

    Args:
        model_path: the model file the run writes.
        force: existing files may be replaced.
    Raises:
        UserError: a file the run will write exists (without `force`) or cannot be written.
    """
    for path in output_files(model_path):
        check_writable(path, force)


class RunIdentity(TypedDict):
    """What a checkpoint records about its run (`run_identity`; its state.json's "identity"): the data file, its
    SHA-256 and the RESUME_SETTINGS, None where a caller gave none."""

    data: str
    data_sha256: str
    input_size: int | list[int] | None
    """S, or [H, W] (`FrameView.size_record`)."""
    crop: list[int] | None
    """The view's crop [x, y, w, h] in frame pixels; None: the whole frame."""
    augment: str | None
    augment_copies: int | None
    fold: int | None
    folds: int | None
    split_seed: int | None
    seed: int | None
    batch_size: int | None
    learning_rate: float | None
    positive_weight: float | None
    lr_patience: int | None
    lr_schedule: str | None
    freeze: int | None
    keep_best: str | None
    """Checkpoints written before it have none: their runs keep the lowest validation loss."""


RESUME_SETTINGS = tuple(name for name in RunIdentity.__annotations__ if name not in ("data", "data_sha256"))
"""The settings that change what a run learns: a checkpoint is resumed only with the same ones (and data).
Epochs and patience may change: continuing a run for longer is what --resume is for."""


def run_identity(data_path: str | Path, config: FitConfig, **facts: Any) -> RunIdentity:
    """What a checkpoint records about its run: the data file, its SHA-256 and the RESUME_SETTINGS.

    Args:
        data_path: the annotation file trained on.
        config: the run's settings (resolved).
        **facts: the settings that are not in `config` (input_size, crop, augment, augment_copies, fold, folds,
            split_seed).
    Returns:
        The identity a resumed checkpoint must match (`check_checkpoint`).
    """
    from fcnpose_tf.records import file_sha256

    values = {**asdict(config), **facts}
    return RunIdentity(data=str(data_path), data_sha256=file_sha256(data_path),
                       **{name: values.get(name) for name in RESUME_SETTINGS})


def check_checkpoint(model_path: str | Path, *, resume: bool, force: bool,
                     identity: RunIdentity | None = None, resumable: bool = True) -> None:
    """Refuse a run its checkpoint does not allow. For a caller that cannot resume (`resumable=False`: compress), a
    checkpoint a killed run left behind is of no use to anyone: it is removed.

    Cheap (reads state.json only): commands call it before they prepare any data.

    Args:
        model_path: the model file the run writes (its checkpoint is beside it).
        resume: the run continues its checkpoint.
        force: the run starts over, its checkpoint discarded.
        identity: what the run is (`run_identity`), compared with the checkpoint's when resuming.
        resumable: whether the caller can resume at all.
    Raises:
        UserError: a resume without a checkpoint, a checkpoint neither resumed nor forced away, an unreadable
            checkpoint state, or a resume whose data or RESUME_SETTINGS differ from those it was started with.
    """
    paths = run_paths(Path(model_path))
    if not resumable:
        remove_tree(paths["ckpt_dir"])
        return
    has_ckpt = paths["ckpt_state"].is_file() and paths["ckpt_model"].is_file()
    if resume and not has_ckpt:
        raise UserError(f"{paths['ckpt_dir']}: no checkpoint to resume from")
    if has_ckpt and not resume and not force:
        raise UserError(f"{paths['ckpt_dir']}: an interrupted run's checkpoint exists; "
                        "pass --resume to continue it or --force to start over")
    if not (resume and identity):
        return
    try:
        started = json.loads(paths["ckpt_state"].read_text()).get("identity")
    except (OSError, ValueError, AttributeError):
        raise UserError(f"{paths['ckpt_state']}: unreadable checkpoint state; pass --force (without --resume) "
                        "to start over") from None
    if not started:  # a checkpoint from before identities were recorded
        return
    differ = [name for name in RESUME_SETTINGS if name in started and started[name] != identity.get(name)]
    if differ or started.get("data_sha256") != identity.get("data_sha256"):
        raise UserError(f"{paths['ckpt_dir']} was started {_describe_run(started, differ)}, not "
                        f"{_describe_run(identity, differ)}; resume with the same settings or pass --force "
                        "(without --resume) to start over")


def _describe_run(identity: dict[str, Any], names: Sequence[str]) -> str:
    """`with --input-size 64 on DATA (sha256 0123456789ab)`: the named settings as options, then the data."""
    flags = " ".join(f"--{name.replace('_', '-')} {identity.get(name)}" for name in names)
    data = f"on {identity.get('data')} (sha256 {str(identity.get('data_sha256'))[:12]})"
    return f"with {flags} {data}" if flags else data


@keras.utils.register_keras_serializable(package="fcnpose_tf")
class KeypointBinaryCrossentropy(keras.losses.Loss):
    """Binary cross-entropy over all maps, with the active pixels of the keypoint maps weighted.

    With positive_weight 1 this is exactly Keras' BinaryCrossentropy (the paper's loss). A keypoint
    disc covers about 0.2% of its map, so plain BCE spends many epochs predicting empty maps
    before any disc crosses 0.5; weighting the disc pixels (not the skeleton map, which is
    large) shortens that phase several-fold at the same optimum location of each disc.
    """

    def __init__(self, positive_weight: float = 1.0, name: str = "keypoint_bce", **kwargs):
        super().__init__(name=name, **kwargs)
        self.positive_weight = float(positive_weight)

    def call(self, y_true, y_pred):
        """Keras's per-pixel loss.

        Args:
            y_true: the target maps (N x H x W x K).
            y_pred: the model's maps, same shape.
        Returns:
            The loss per pixel (N x H x W): the keypoint maps' positive term weighted, the skeleton map's not.
        """
        import tensorflow as tf

        y_true = tf.cast(y_true, y_pred.dtype)
        eps = keras.backend.epsilon()
        p = tf.clip_by_value(y_pred, eps, 1.0 - eps)
        pos = y_true * tf.math.log(p)
        if self.positive_weight != 1.0:
            channels = tf.shape(y_true)[-1]
            weights = tf.concat([tf.fill([channels - 1], self.positive_weight), tf.ones([1])], axis=0)
            pos = pos * tf.cast(weights, pos.dtype)
        return -tf.reduce_mean(pos + (1.0 - y_true) * tf.math.log(1.0 - p), axis=-1)

    def get_config(self) -> dict:
        """Keras's serialisation.

        Returns:
            The base loss's config with "positive_weight".
        """
        return {**super().get_config(), "positive_weight": self.positive_weight}


def freeze_first_convolutions(model: keras.Model, count: int) -> None:
    """Make conv1..conv`count` of `model` untrainable and every other layer trainable (before compiling).

    A checkpoint saved while training keeps these flags, so a resumed run trains the same layers; the
    model files a run writes have every layer trainable again (`model.save_for_inference`).

    Args:
        model: an FCN-Pose model.
        count: convolutions to keep fixed (0: every layer trains).
    Raises:
        UserError: `count` leaves no convolution to train.
    """
    convolutions = [layer for layer in model.layers if isinstance(layer, keras.layers.Conv2D)]
    if count >= len(convolutions):
        raise UserError(f"--freeze {count} would leave nothing to train: the model has {len(convolutions)} "
                        "convolutions")
    for layer in model.layers:
        layer.trainable = True
    for layer in convolutions[:count]:
        layer.trainable = False


@keras.utils.register_keras_serializable(package="fcnpose_tf")
class DistillationLoss(keras.losses.Loss):
    """(1 - W) x the training loss against the ground-truth maps + W x the same loss against a teacher's maps.

    Training targets carry both, concatenated on the channel axis (C ground-truth maps, then the
    teacher's C maps of the same augmented frame; `fcnpose_tf.training.distill`). Targets with only C channels
    (the validation data) get the ground-truth term alone, so the validation loss, and with it early
    stopping and the best epoch, is measured against the truth at every W.
    """

    def __init__(self, weight: float, positive_weight: float = 1.0, name: str = "distillation", **kwargs):
        super().__init__(name=name, **kwargs)
        self.weight = float(weight)
        self.positive_weight = float(positive_weight)
        self.base = ground_truth_loss(self.positive_weight)

    def call(self, y_true, y_pred):
        """Keras's per-pixel loss.

        Args:
            y_true: the target maps, the teacher's maps after them on the channel axis (the ground truth alone when
                validating).
            y_pred: the model's maps.
        Returns:
            The loss per pixel: the ground truth's and the teacher's terms mixed by `weight`.
        """
        channels = y_pred.shape[-1]
        if y_true.shape[-1] == channels:
            return self.base.call(y_true, y_pred)
        truth, teacher = y_true[..., :channels], y_true[..., channels:]
        return (1.0 - self.weight) * self.base.call(truth, y_pred) + self.weight * self.base.call(teacher, y_pred)

    def get_config(self) -> dict:
        """Keras's serialisation.

        Returns:
            The base loss's config with "weight" and "positive_weight".
        """
        return {**super().get_config(), "weight": self.weight, "positive_weight": self.positive_weight}


def ground_truth_loss(positive_weight: float = 1.0) -> keras.losses.Loss:
    """Binary cross-entropy over all maps (the paper's), or with keypoint pixels weighted.

    Args:
        positive_weight: the keypoint maps' active pixels' weight (1: plain BCE).
    Returns:
        The loss.
    """
    if positive_weight == 1.0:
        return keras.losses.BinaryCrossentropy()
    return KeypointBinaryCrossentropy(positive_weight)


def training_loss(positive_weight: float = 1.0, distill: float = 0.0) -> keras.losses.Loss:
    """The one training loss: `ground_truth_loss`, or with distill W > 0 a `DistillationLoss` around it.

    With distill 0 it is exactly the ground-truth loss (the same object type and values).

    Args:
        positive_weight: the keypoint maps' active pixels' weight (1: plain BCE).
        distill: the teacher's weight W in the loss (0: none).
    Returns:
        The loss.
    """
    if distill == 0:
        return ground_truth_loss(positive_weight)
    return DistillationLoss(distill, positive_weight)


def compile_for_training(model: keras.Model, learning_rate: float, positive_weight: float = 1.0,
                         distill: float = 0.0) -> keras.Model:
    """Adam and `training_loss`: binary cross-entropy over all maps (the paper's), optionally weighting keypoint
    pixels and mixing in a teacher's maps.

    Args:
        model: the model to train.
        learning_rate: Adam's learning rate.
        positive_weight: the keypoint maps' active pixels' weight.
        distill: the teacher's weight (0: none).
    Returns:
        `model`, compiled.
    """
    model.compile(optimizer=keras.optimizers.Adam(learning_rate), loss=training_loss(positive_weight, distill),
                  jit_compile=False)
    return model


BUDGET_MIN_EPOCHS = 15
"""Fewer epochs than this in the time budget earn a warning after the first one: fine-tuning from the generalist
needed about this many or more to reach its best validation loss on the held-out proxies, and a busy 2-core machine
trains fewer than that in 30 minutes at 384 x 384 (docs/training.md; the runs: docs/results.md, "The crop's edge,
and the time budget's epoch warning")."""


class _CheckpointAndStop(keras.callbacks.Callback):
    """Per epoch: record losses (and the validation keypoints' score, `validation`), keep the best weights, write a
    resumable checkpoint, stop early; say the epoch's time and the run's ETA, and after the first epoch whether the
    time budget allows the epochs fine-tuning needs (to `reporter`; None: nothing said).

    The best epoch is the one whose validation keypoints score best (`better_score`) when `validation` is given, else
    the one of the lowest validation loss; patience and the plateau's halving wait on the same."""

    def __init__(self, paths: dict[str, Path], state: dict[str, Any], patience: int, lr_patience: int = 0,
                 max_minutes: float | None = None, rate_of_progress: Callable[[float], float] | None = None,
                 epochs: int = 1, reporter: Reporter | None = None,
                 validation: tuple[ValidationKeypoints, Any, int] | None = None):
        super().__init__()
        self.reporter = reporter
        self.validation = validation
        self.first_epoch = int(state["epoch"])
        self.paths = paths
        self.state = state
        self.patience = patience
        self.lr_patience = lr_patience
        self.rate_of_progress = rate_of_progress
        self.epochs = epochs
        self.max_seconds = None if max_minutes is None else 60.0 * max_minutes
        self.seconds_before = float(state["seconds"])
        self.start = time.perf_counter()

    def trained_seconds(self) -> float:
        """Seconds of training in this run, those before a resume included."""
        return self.seconds_before + time.perf_counter() - self.start

    def on_epoch_begin(self, epoch: int, logs: dict | None = None) -> None:
        if self.rate_of_progress is not None:
            progress = budget_progress(epoch, self.epochs, self.trained_seconds(), self.max_seconds)
            keras.backend.set_value(self.model.optimizer.learning_rate, self.rate_of_progress(progress))

    def on_epoch_end(self, epoch: int, logs: dict | None = None) -> None:
        logs = logs or {}
        lr_var = self.model.optimizer.learning_rate
        lr = float(keras.backend.get_value(lr_var))
        row = {"epoch": epoch + 1, "loss": float(logs["loss"]), "val_loss": float(logs["val_loss"]), "lr": lr}
        if not (math.isfinite(row["loss"]) and math.isfinite(row["val_loss"])):  # the weights are lost: stop here
            self.state["diverged_at"] = epoch + 1
            self.model.stop_training = True
            return
        if self.validation is not None:
            keypoints, inputs, batch_size = self.validation
            score = keypoints.score(self.model, inputs, batch_size)
            row.update(val_mean_pck=score["mean_pck"], val_pck_fine=score["pck_fine"], val_epe_px=score["epe_px"])
            improved = better_score(score, self.state.get("best_keypoints"))
        else:
            score, improved = None, row["val_loss"] < self.state["best_val_loss"]
        self.state["history"].append(row)
        if improved:
            self.state.update(best_val_loss=row["val_loss"], best_epoch=epoch + 1, wait=0, best_keypoints=score)
        else:
            self.state["wait"] += 1
            if self.lr_patience and self.state["wait"] % self.lr_patience == 0 and lr > MIN_LEARNING_RATE:
                keras.backend.set_value(lr_var, max(lr * 0.5, MIN_LEARNING_RATE))  # saved with the optimizer
        self.state["epoch"] = epoch + 1
        self.state["seconds"] = self.trained_seconds()
        # the budget stops the run only when epochs are left: one reached by the last epoch stopped nothing
        self.state["out_of_time"] = (self.max_seconds is not None and self.state["seconds"] >= self.max_seconds
                                     and epoch + 1 < self.epochs)
        files = [self.paths["ckpt_best"]] if improved else []
        files += [self.paths["ckpt_model"], self.paths["ckpt_state"]]  # the state renamed last: the epoch is complete
        with parts_of(self.paths["ckpt_dir"]), atomic_paths(files, force=True) as temporaries:
            if improved:
                _save_weights(self.model, temporaries[0])
            self.model.save(temporaries[-2])
            temporaries[-1].write_text(json_text(self.state))
        if self.state["wait"] >= self.patience:
            self.state["stopped_early"] = True
            self.model.stop_training = True
        if self.state["out_of_time"]:  # a resume with a larger --max-minutes continues
            self.model.stop_training = True
        if self.reporter is not None:
            self._say_progress(epoch + 1)

    def _say_progress(self, done: int) -> None:
        """The epoch's line (time, best so far, ETA), and after this run's first epoch the budget's warning."""
        epoch_s = (self.trained_seconds() - self.seconds_before) / max(1, done - self.first_epoch)
        left = self.epochs - done
        if self.max_seconds is not None:
            left = min(left, max(0, math.ceil((self.max_seconds - self.state["seconds"]) / epoch_s)))
        stopping = self.model.stop_training
        eta = "done" if stopping or left == 0 else \
            f"ETA {left * epoch_s / 60:.0f} min ({left} more epoch{'s' if left != 1 else ''} at most)"
        say = self.reporter.say
        kept = describe_kept(self.state["best_epoch"], self.state["best_val_loss"], self.state.get("best_keypoints"))
        say(f"epoch {done}: {epoch_s:.0f} s/epoch, {kept}; {eta}")
        if done == self.first_epoch + 1 and self.max_seconds is not None:
            affordable = int(self.max_seconds // epoch_s)
            if affordable < min(BUDGET_MIN_EPOCHS, self.epochs):
                say(f"note: at {epoch_s:.0f} s an epoch the {self.max_seconds / 60:.3g}-minute budget trains about "
                    f"{affordable} epochs, fewer than the {BUDGET_MIN_EPOCHS} that fine-tuning and retraining "
                    f"needed on the proxies; give it --max-minutes {math.ceil(BUDGET_MIN_EPOCHS * epoch_s / 60)}, "
                    "or fewer input pixels (--input-size), or a machine with fewer other jobs")


def _save_weights(model: keras.Model, path: Path) -> None:
    """The model's weights as .npz: numpy writes them with Python I/O, where a full disk is an OSError (an .h5
    written by HDF5 can kill the process instead, see `model.h5_bytes`)."""
    with open(path, "wb") as fh:  # in layer order: a model's own order puts frozen layers last
        np.savez(fh, *[weight for layer in model.layers for weight in layer.get_weights()])


def _load_weights(model: keras.Model, path: Path) -> None:
    """Weights written by `_save_weights` (or an .h5 of `save_weights`, in checkpoints of earlier versions)."""
    if path.suffix == ".h5":
        model.load_weights(path)
        return
    with np.load(path) as saved:
        weights = iter(saved[f"arr_{i}"] for i in range(len(saved.files)))
        for layer in model.layers:
            layer.set_weights([next(weights) for _ in layer.get_weights()])


def fit(model: keras.Model, train_data: keras.utils.Sequence, val_data: tuple[np.ndarray, np.ndarray],
        model_path: str | Path, config: FitConfig, *, resume: bool = False, force: bool = False,
        metadata: dict[str, Any] | None = None, reporter: Reporter | None = None,
        callbacks: Sequence[keras.callbacks.Callback] = (),
        inference_model: Callable[[keras.Model], keras.Model] | None = None,
        identity: RunIdentity | None = None, resumable: bool = True, start_is_candidate: bool = False,
        val_keypoints: ValidationKeypoints | None = None) -> FitResult:
    """Train `model` on `train_data` (batches of (images, maps)) with validation and early stopping.

    Args:
        model: an FCN-Pose (or any maps-to-maps) tf_keras model; compiled here.
        train_data: a keras Sequence of (images float32 N x S x S x 3, maps float32 N x S x S x C).
        val_data: validation (images, maps) arrays; the validation loss drives early stopping.
        model_path: where the best model is saved (.keras or .h5), without optimizer state.
        config: epochs, patience, batch size, learning rate, seed (settings left None: `FitConfig.resolved`, for
            a trained start when `start_is_candidate`, with the paper's copies).
        resume: continue an interrupted run from `model_path`'s checkpoint.
        force: replace an existing model file / start over despite a checkpoint.
        metadata: extra facts recorded in NAME_train.json (data, split, input size...).
        reporter: where messages and progress go (`fcnpose_tf.progress`; default: the current one): Keras' progress
            bar on a terminal, one line per epoch in a log or with --quiet, nothing when silent.
        callbacks: more Keras callbacks, run before the checkpointing one each epoch (tfmot's
            UpdatePruningStep, which must mask the weights before they are kept as the best).
        inference_model: what to save as `model_path` from the trained model (tfmot's
            strip_pruning for a model wrapped for pruning); default: the model itself.
        identity: what a resumed checkpoint must match (`run_identity`); stored in the checkpoint.
        resumable: whether the caller can resume (`train --resume`); if not (`compress`), a run that
            fails or is interrupted removes its checkpoint instead of pointing at --resume.
        start_is_candidate: `model` holds trained weights: its validation score before the first epoch is the one
            to beat (epoch 0), and if no epoch beats it the saved model is the start, unchanged: a few hundred
            frames of a kind the start already knows well can make it worse.
        val_keypoints: the validation frames' keypoints, row for row with `val_data` (`ValidationKeypoints.of`);
            needed when `config.keep_best` is "keypoints", which then scores them after every epoch. A resumed run
            keeps the rule it was started with.
    Returns:
        FitResult with the epochs run, the best epoch, its validation loss and (keep_best "keypoints") keypoints.
    Raises:
        ValueError: keep_best "keypoints" without `val_keypoints`, or distillation without the teacher's maps.
        UserError: output exists without force, nothing to resume, a checkpoint exists
            and neither resume nor force was given, or the checkpoint was started on other data or settings.
    """
    reporter = progress.resolve(reporter)
    config = config.resolved(trained_start=start_is_candidate)  # what train_fold has not chosen yet
    config.validate()
    if config.keep_best == "keypoints" and val_keypoints is None:
        raise ValueError("keep_best 'keypoints' scores the validation frames' keypoints: pass val_keypoints "
                         "(ValidationKeypoints.of)")
    if config.distill and not getattr(train_data, "carries_teacher_maps", False):
        raise ValueError("distillation needs training batches that carry the teacher's maps "
                         "(fcnpose_tf.training.distill.with_teacher_maps)")
    model_path = Path(model_path)
    if model_path.suffix not in (".keras", ".h5"):
        raise UserError(f"{model_path}: the model file must end in .keras or .h5")
    paths = run_paths(model_path)
    check_checkpoint(model_path, resume=resume, force=force, identity=identity, resumable=resumable)
    if not resume:
        check_outputs(model_path, force)
        if paths["ckpt_dir"].exists():
            shutil.rmtree(paths["ckpt_dir"])
    make_folder(paths["ckpt_dir"])

    keras.utils.set_random_seed(config.seed)
    state: dict[str, Any] = {"epoch": 0}
    whole, prefix = model, None
    try:
        if resume:
            state = json.loads(paths["ckpt_state"].read_text())
            if state.get("frozen_prefix"):  # the checkpoint holds the head; the fixed layers are the start's
                freeze_first_convolutions(whole, config.freeze)
                _load_weights(whole, paths["ckpt_whole"])
                prefix = split_frozen(whole)
                model = keras.models.load_model(paths["ckpt_model"])  # the head, with optimizer state
                train_data, val_data = _past_prefix(prefix, train_data, val_data)
            else:
                model = with_facts_of(keras.models.load_model(paths["ckpt_model"]), whole)  # with optimizer state
            if state["epoch"] >= config.epochs or state.get("stopped_early"):
                reporter.say(f"checkpoint already finished ({state['epoch']} epochs); writing the model")
        else:
            state = {"epoch": 0, "best_val_loss": math.inf, "best_epoch": 0, "wait": 0, "stopped_early": False,
                     "history": [], "seconds": 0.0, "config": asdict(config), "identity": identity,
                     "keep_best": config.keep_best}
            freeze_first_convolutions(model, config.freeze)
            if not (config.distill or callbacks or inference_model):
                prefix = _prefix_worth_keeping(whole, train_data, len(val_data[0]), reporter)
            if prefix is not None:
                with parts_of(paths["ckpt_dir"]), atomic_path(paths["ckpt_whole"], force=True) as tmp:
                    _save_weights(whole, tmp)
                state["frozen_prefix"] = list(prefix.cut)
                model = prefix.head
                train_data, val_data = _past_prefix(prefix, train_data, val_data)
            compile_for_training(model, config.learning_rate, config.positive_weight, config.distill)
            if start_is_candidate:
                state["start_val_loss"] = state["best_val_loss"] = _validation_loss(model, val_data,
                                                                                    config.batch_size)
                said = f"validation loss {state['start_val_loss']:.5f}"
                if config.keep_best == "keypoints":
                    state["start_keypoints"] = state["best_keypoints"] = val_keypoints.score(model, val_data[0],
                                                                                             config.batch_size)
                    said = f"validation keypoints: {keypoints_text(state['start_keypoints'])}; {said}"
                reporter.say(f"epoch 0 (the starting model): {said}")
                with parts_of(paths["ckpt_dir"]), atomic_path(paths["ckpt_best"], force=True) as tmp:
                    _save_weights(model, tmp)

        schedule = None
        if config.lr_schedule == "cosine":
            schedule = functools.partial(cosine_rate, learning_rate=config.learning_rate)
        by_keypoints = state.get("keep_best", "loss") == "keypoints"  # a resumed run keeps its own rule
        if by_keypoints and val_keypoints is None:
            raise ValueError("this checkpoint keeps the epoch by the validation frames' keypoints: pass val_keypoints")
        callback = _CheckpointAndStop(paths, state, config.patience, config.lr_patience, config.max_minutes,
                                      schedule, epochs=config.epochs, reporter=reporter,
                                      validation=(val_keypoints, val_data[0], config.batch_size) if by_keypoints
                                      else None)
        if state["epoch"] < config.epochs and not state["stopped_early"]:
            if hasattr(train_data, "epoch"):  # online augmentation: a resumed run draws the epochs it would have
                train_data.epoch = state["epoch"]
            model.fit(train_data, validation_data=val_data, validation_batch_size=config.batch_size,
                      initial_epoch=state["epoch"], epochs=config.epochs, callbacks=[*callbacks, callback],
                      verbose=reporter.keras_verbose)
    except KeyboardInterrupt:
        raise _interrupted(state, config, paths, resumable) from None
    except WriteError as exc:
        raise _resumable(exc, paths, resumable) from None
    try:
        if prefix is not None:
            inference_model = functools.partial(prefix.weights_into, whole)
        return _finish(model, model_path, whole, state, config, paths, resumable, reporter, inference_model, metadata)
    except KeyboardInterrupt:  # a stop while the model is written: no file was renamed into place
        raise _interrupted(state, config, paths, resumable) from None


def _interrupted(state: dict[str, Any], config: FitConfig, paths: dict[str, Path], resumable: bool) -> UserError:
    """The error a stop signal ends `fit` with; a checkpoint no one can resume is removed first."""
    if not resumable or not paths["ckpt_state"].is_file():  # nothing to resume: no epoch-0 leftovers either
        remove_tree(paths["ckpt_dir"])
        if resumable:
            return UserError("interrupted before the first epoch ended: nothing to resume; run the command "
                             "again to start over")
        return UserError(f"stopped after {state['epoch']} of {config.epochs} epochs; this run cannot be resumed (its "
                         "checkpoint is removed): run the same command again to start it over")
    return UserError(f"interrupted after {state['epoch']} complete epochs; "
                     f"continue with --resume (checkpoint in {paths['ckpt_dir']})")


def _finish(model: keras.Model, model_path: Path, whole: keras.Model, state: dict[str, Any], config: FitConfig,
            paths: dict[str, Path], resumable: bool, reporter: Any, inference_model: Any,
            metadata: dict[str, Any] | None) -> FitResult:
    """After the last epoch: the best epoch's weights saved as `model_path` with the view and schema of `whole` (the
    model `fit` was given), its loss curves and record; the checkpoint removed."""
    best = paths["ckpt_best"] if paths["ckpt_best"].is_file() else paths["ckpt_dir"] / "best.h5"
    if "diverged_at" in state:
        diverged = (f"the loss became NaN or infinite in epoch {state['diverged_at']} (learning rate "
                    f"{config.learning_rate:g}: try a lower --learning-rate)")
        if not best.is_file():
            remove_tree(paths["ckpt_dir"])
            raise UserError(f"{diverged}; no epoch before it to keep: {model_path} not written")
        reporter.say(f"training stopped: {diverged}; the best epoch before it is kept")
    if best.is_file():
        _load_weights(model, best)
    try:
        with atomic_path(model_path, force=True) as tmp:
            kept = inference_model(model) if inference_model else model
            save_for_inference(with_facts_of(kept, whole), tmp)  # view and schema, also past an inference_model
        write_loss_curves(state["history"], paths["loss_csv"], paths["loss_png"], state["best_epoch"],
                          config.positive_weight, config.distill, start_val_loss=state.get("start_val_loss"))
        write_json(paths["train_json"], {
            **(metadata or {}), "config": asdict(config), "epochs_run": state["epoch"],
            "start_val_loss": state.get("start_val_loss"),
            "best_epoch": state["best_epoch"], "best_val_loss": state["best_val_loss"],
            "kept_by": state.get("keep_best", "loss"), "best_val_keypoints": state.get("best_keypoints"),
            "start_val_keypoints": state.get("start_keypoints"),
            "stopped_early": state["stopped_early"], "stopped_by_time_budget": bool(state.get("out_of_time")),
            "diverged_at_epoch": state.get("diverged_at"), "train_seconds": round(state["seconds"], 1),
        }, force=True)
    except WriteError as exc:
        raise _resumable(exc, paths, resumable) from None
    remove_tree(paths["ckpt_dir"])
    return FitResult(model_path, state["epoch"], state["best_epoch"], state["best_val_loss"], state["seconds"],
                     state["stopped_early"], state["history"], bool(state.get("out_of_time")),
                     state.get("best_keypoints"))


def _prefix_worth_keeping(model: keras.Model, train_data: Any, val_rows: int, reporter: Reporter) -> Any:
    """The fixed prefix to compute once (`training.frozen`), when training has one: fixed layers in front, fixed
    samples (the paper's copies: `train_data` a `TrainingData.sequence`) and room in memory for the features; else
    None (the whole network trains, its fixed layers run every batch)."""
    if not hasattr(getattr(train_data, "data", None), "images") or not hasattr(train_data, "rows"):
        return None  # online augmentation: new samples every epoch
    prefix = split_frozen(model)
    if prefix is None:
        return None
    rows = len(train_data.data.images) + val_rows
    size = prefix.feature_bytes(rows)
    size = f"{size / 2 ** 30:.1f} GB" if size >= 2 ** 30 else f"{size / 2 ** 20:.1f} MB"
    if not fits_in_memory(prefix, rows):
        reporter.say(f"Fixed layers run every batch: their outputs for {rows} samples ({size}) would take more than "
                     "half the memory available")
        return None
    reporter.say(f"Fixed layers computed once: {', '.join(prefix.cut)}'s outputs for {rows} samples ({size}); each "
                 "epoch trains the layers after them")
    return prefix


def _past_prefix(prefix: Any, train_data: Any, val_data: tuple[np.ndarray, ...]) -> tuple[Any, tuple]:
    """The training batches and validation arrays with the prefix's features in place of the images."""
    features = prefix.features(val_data[0])
    return feature_sequence(prefix, train_data), (features[0] if len(features) == 1 else features, *val_data[1:])


def _validation_loss(model: keras.Model, val_data: tuple[np.ndarray, ...], batch_size: int) -> float:
    """The compiled model's loss on the validation frames, as `fit` measures it after each epoch."""
    return float(model.evaluate(*val_data, batch_size=batch_size, verbose=0))


def _resumable(exc: WriteError, paths: dict[str, Path], resumable: bool) -> WriteError:
    """A write that failed during a run (a full disk), with how to continue when a complete checkpoint is kept
    (a run that cannot be resumed removes its checkpoint)."""
    if not resumable:
        remove_tree(paths["ckpt_dir"])
        return exc
    try:
        epoch = json.loads(paths["ckpt_state"].read_text())["epoch"]
    except (OSError, ValueError, KeyError):  # no complete checkpoint yet (the start's weights at most): starts over
        remove_tree(paths["ckpt_dir"])
        return exc
    return WriteError(f"{exc}; the checkpoint of epoch {epoch} is intact: free some space, "
                      "then continue with --resume")


class AugmentChoice(TypedDict):
    """What `augment="auto"` chose and why (`resolve_augment`; NAME_train.json's "augment_auto", as written)."""

    view_variation: float
    """How much the frames differ from their median, in std (`data.views.view_variation`), rounded to 4 decimals."""
    fixed_camera_max: float
    """The variation up to which the frames are one fixed camera (`data.views.FIXED_CAMERA_MAX_VARIATION`)."""
    chose: str
    """"paper" (one fixed camera) or "online" (views that vary)."""


def resolve_augment(frames: Sequence[Any], reporter: Reporter | None = None) -> AugmentChoice:
    """What `augment="auto"` (train's default) means for these frames: the paper's copies for one fixed camera, online
    augmentation when the views vary (`data.views`), said through `reporter`.

    Args:
        frames: `data.via` frames (their image paths are read).
        reporter: where the choice is said (default: the current one).
    Returns:
        The choice (`chose`) and what it was based on, for NAME_train.json.
    """
    from fcnpose_tf.data.views import FIXED_CAMERA_MAX_VARIATION, choose_augment, view_variation

    variation = view_variation([f.image_path for f in frames])
    augment = choose_augment(variation)
    camera = "one fixed camera" if augment == "paper" else "views that vary"
    progress.resolve(reporter).say(
        f"Augmentation: auto -> {augment} ({camera}: the frames differ from their median by {variation:.2f} std; a "
        f"fixed camera measures <= {FIXED_CAMERA_MAX_VARIATION})")
    return AugmentChoice(view_variation=round(variation, 4), fixed_camera_max=FIXED_CAMERA_MAX_VARIATION, chose=augment)


def initial_model(init: str | Path, schema: Any, input_size: Any = None) -> keras.Model:
    """FCN-Pose holding the weights of the model file `init` (trained at any input size).

    The convolutions do not depend on the input size, so a model pretrained at 160 starts a run at 224.

    Args:
        init: the model file training starts from.
        schema: the keypoints the data has.
        input_size: S, (H, W) or a `preprocess.FrameView` whose crop it takes (None: the view it was saved with).
    Returns:
        The model at that input size, its maps named by `schema` (a model of the same keypoints in another order: its
        maps put in the data's, `training.model.in_keypoint_order`).
    Raises:
        UserError: `init` is no keypoint-map model, predicts other maps than `schema` needs, or names other keypoints
            (its file's schema, else its training record's).
    """
    from fcnpose_tf.training.model import at_input_size, conv_widths, given_schema, in_keypoint_order, load_model

    source = load_model(init)
    widths = conv_widths(source)
    out_shape, in_shape = tuple(source.output_shape), tuple(source.input_shape)
    if not widths or len(out_shape) != 4 or out_shape[1:3] != in_shape[1:3]:
        raise UserError(f"{init}: not a keypoint-map model (input {in_shape[1:]}, output {out_shape[1:]}); --init "
                        "takes an FCN-Pose model file that train or compress wrote, whose maps have its input's size")
    advice = "pass --init none to train from scratch, or --init MODEL with a model of this schema"
    if widths[-1] != schema.num_maps:
        named = given_schema(source)
        names = ", ".join(named.keypoints) if named is not None else f"{widths[-1] - 1} keypoints"
        raise UserError(f"{init}: trained for {names}, but the data's schema {schema.name!r} has "
                        f"{', '.join(schema.keypoints)}; {advice}")
    source = in_keypoint_order(source, schema, str(init), advice)
    return source if input_size is None else at_input_size(source, input_size)


def train_fold(dataset: Any, fold: int | None, model_path: str | Path, config: FitConfig, *, input_size: Any,
               augment_copies: int, augment: str = "paper", init: str | Path | None = None, resume: bool = False, force: bool = False,
               metadata: dict[str, Any] | None = None, threads: int | None = None, label: str | None = None,
               reporter: Reporter | None = None, test_data: Any = None,
               test_start: tuple[str, KeypointMetrics] | None = None, size_was_chosen: bool = False,
               decoding: Decoding | None = None, architecture: str | None = None) -> TrainingRecord:
    """Train one fold's model, measure it on the fold's validation frames and write its record.

    The one way a model is trained from a dataset (`train` per fold, the sweep per base job):
    build FCN-Pose (or start from `init`'s weights, which are then the model to beat: epoch 0), `fit` it on the
    fold's training frames with
    `augment_copies` copies each, then evaluate the best model (Keras, `threads` threads) on the
    fold's validation frames and add that as "validation" to NAME_train.json.

    Args:
        dataset: a loaded dataset with its splits (`data.dataset.load_dataset`).
        fold: K-fold index (0-based), or None for the 80/20 hold-out split.
        model_path: where the best model goes (.keras or .h5); the run's files go beside it.
        config: optimisation settings (those left None chosen by `FitConfig.resolved` for `init` and `augment`);
            `config.seed` also seeds the augmentation.
        input_size: the model's view: S (S x S over the whole frame), (H, W) or a `preprocess.FrameView` (a crop
            and its input size, e.g. `resolve_view`'s); sides multiples of 32.
        augment_copies: offline augmented copies per training frame (augment "paper").
        augment: "paper" (fixed offline copies) or "online" (fresh random transforms every epoch).
        init: a model whose weights training starts from (same input size and maps), else a fresh one.
        resume, force: as for `fit`.
        metadata: more facts for NAME_train.json; they override the dataset's (e.g. "data" as given).
        threads: TensorFlow threads of the validation timing (None: all cores).
        decoding: how the measurements read keypoints (`postprocess.Decoding`; default the commands').
        architecture: the network (`model.ARCHITECTURES`): None keeps `init`'s own (FCN-Pose from random weights);
            "fcn-pose-skip" adds the skip to an FCN-Pose start (`model.as_architecture`).
        label: prefix of the progress lines (default: the model path).
        reporter: where messages and progress go (`fcnpose_tf.progress`; default: the current one): bars on a
            terminal, lines in a log, one line per epoch with --quiet, nothing when silent.
        test_data: a fixed test set (a loaded dataset of the same schema, never trained on): the trained model
            is measured on all its frames and the result added as "test" (`record_of_test_set`).
        test_start: the starting model's name as recorded and its metrics on `test_data` (`start_on_test_set`), None
            for random weights.
        size_was_chosen: `input_size` is `train --input-size auto`'s choice, not the user's: the start as saved,
            at its own size, is then a candidate too (`keep_start_if_better`).
    Returns:
        The NAME_train.json record as written (`records.TrainingRecord`: its `validation` typed, `raw` the whole file:
        data, split, sizes, config, epochs, best epoch, seconds, validation and test).
    Raises:
        UserError: an `init` model that does not fit the data or input size, or anything `fit` refuses.
    """
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
    from fcnpose_tf.records import file_sha256
    from fcnpose_tf.training.model import ARCHITECTURES, architecture_of, as_architecture, build_fcn_pose, load_model

    model_path = Path(model_path)
    view = FrameView.of(input_size)
    label = label or str(model_path)
    reporter = progress.resolve(reporter)
    log = reporter.say
    if config.positive_weight is None:
        weight = settings.train_positive_weight(trained_start=init is not None, augment=augment)
        log(f"Keypoint weight: {weight:g} (" + ("fine-tuning a trained model on the paper's copies"
                                               if init is not None and augment == "paper"
                                               else "random weights or online augmentation")
            + "; --positive-weight sets it)")
    if architecture is None:  # the start's own network (FCN-Pose from random weights)
        architecture = architecture_of(load_model(init)) if init is not None else "fcn-pose"
    chosen = config.freeze is None or config.learning_rate is None
    config = config.resolved(trained_start=init is not None, augment=augment, architecture=architecture)
    if chosen:
        fixed = f"conv1-{config.freeze} fixed" if config.freeze > 1 else "conv1 fixed" if config.freeze else \
            "every layer trained"
        log(f"Recipe: {fixed}, learning rate {config.learning_rate:g} ({architecture}, "
            f"{'a trained start' if init is not None else 'random weights'}, {augment} augmentation; --freeze and "
            "--learning-rate set them)")
    identity = run_identity(dataset.via_path, config, input_size=view.size_record, crop=view.to_json()["crop_xywh"],
                            augment=augment,
                            augment_copies=augment_copies,
                            fold=fold, folds=dataset.splits.k, split_seed=dataset.splits.seed)
    check_checkpoint(model_path, resume=resume, force=force, identity=identity)  # before any frame is prepared
    num_maps = dataset.schema.num_maps
    if init is not None and not resume:
        model = as_architecture(initial_model(init, dataset.schema, view), architecture)
    else:  # random weights, or the checkpoint's (`fit` loads them) in the network that wrote it
        model = build_fcn_pose(input_size=view, num_maps=num_maps, skip=ARCHITECTURES[architecture])
    with_schema(model, dataset.schema)  # the data's keypoint names go with the model file
    folds = dataset.splits.k
    split_name = "hold-out 80/20" if fold is None else f"fold {fold} of {folds}"
    train_data, val_data = fold_data(dataset, fold, view, augment_copies, config.seed, augment,
                                     progress=reporter)
    log(f"{label}: {'resuming' if resume else 'training'} on {split_name}: {train_data.describe()}, "
        f"{len(val_data)} validation frames, {view.describe()}, up to {config.epochs} epochs")
    facts = {"data": str(dataset.via_path), "data_sha256": file_sha256(dataset.via_path), "num_frames": len(dataset),
             "split": split_name, "fold": fold, "folds": folds, "split_seed": dataset.splits.seed,
             "input_size": view.size_record, "view": view.to_json(), "augment": augment,
             "augment_copies": augment_copies if augment == "paper" else None, "train_samples": len(train_data),
             "val_frames": len(val_data), "schema": dataset.schema.to_dict(), "architecture": architecture_of(model)}
    result = fit(model, train_data.sequence(config.batch_size, shuffle=True, seed=config.seed), val_data.arrays(),
                 model_path, config, resume=resume, force=force, metadata={**facts, **(metadata or {})},
                 reporter=reporter, identity=identity, start_is_candidate=init is not None,
                 val_keypoints=ValidationKeypoints.of(val_data, decoding))
    log(f"{label}: {describe_kept(result.best_epoch, result.best_val_loss, result.best_keypoints)} of "
        f"{result.epochs_run}{' (the starting model: no epoch improved on it)' if init is not None and result.best_epoch == 0 else ''}"
        f"{' (early stop)' if result.stopped_early else ''}"
        f"{' (time budget reached)' if config.max_minutes and result.seconds >= 60 * config.max_minutes else ''}; "
        f"{result.seconds / 60:.1f} min")

    predictor = KerasKeypointModel(load_model(model_path), model_path, num_threads=threads, decoding=decoding)
    _, val_idx = dataset.split(fold)
    log(f"{label}: evaluating on {len(val_idx)} validation frames")
    report = evaluate_predictor(predictor, dataset, val_idx, dataset.schema)
    paths = run_paths(model_path)
    record = json.loads(paths["train_json"].read_text())
    if init is not None and size_was_chosen:
        kept = keep_start_if_better(init, dataset, val_idx, report, model_path, view, threads=threads,
                                    reporter=reporter, label=label, decoding=decoding)
        if kept is not None:
            record["start_as_saved"], start_predictor, start_report = kept
            if record["start_as_saved"]["chose"] == "start":
                predictor, report = start_predictor, start_report
                record["input_size"], record["view"] = start_predictor.view.size_record, start_predictor.view.to_json()
    record["validation"] = report.measurement().to_json()
    if test_data is not None:
        log(f"{label}: evaluating on the {len(test_data)} frames of the test set {test_data.via_path}")
        start_model, start = test_start if test_start is not None else (None, None)
        record["test"] = record_of_test_set(test_data, measure_on_test_set(predictor, test_data), start_model,
                                            start).to_json()
    write_json(paths["train_json"], record, force=True)
    return TrainingRecord.from_json(record)


class StartAsSaved(TypedDict):
    """The start as saved weighed against the trained model (`keep_start_if_better`; NAME_train.json's
    "start_as_saved")."""

    input_size: int | list[int]
    """The start's input size (`FrameView.size_record`)."""
    view: dict[str, Any]
    """The start's view (`FrameView.to_json`)."""
    start_mean_pck: float
    """`metrics.mean_pck` of the start on the validation frames, at its own view."""
    trained_mean_pck: float
    """The same of the trained model, at the run's view."""
    trained_view: dict[str, Any]
    chose: str
    """"start" or "trained"."""


def keep_start_if_better(init: str | Path, dataset: Any, val_idx: Sequence[int], trained_report: Evaluation,
                         model_path: Path, view: Any, *, threads: int | None = None,
                         reporter: Reporter | None = None, label: str = "",
                         decoding: Decoding | None = None) -> tuple[StartAsSaved, Any, Evaluation] | None:
    """The start as saved is a candidate too when the run trained at another view (`preprocess.FrameView`: crop and
    input size) than the start's own (one `train --input-size auto` chose: a size the user asked for is kept).

    `fit` already keeps the start when no epoch beats it at the run's size (epoch 0); a start pretrained at
    another size may still be better at its own, e.g. a generalist pretrained at 224 on views like the user's,
    which training at a larger size can only approach with a few hundred frames. Both are measured on the
    same validation frames, in frame pixels, and compared by `metrics.mean_pck` (validation losses at two sizes
    do not compare); the start replaces the model file only when it scores higher.

    Args:
        init: the starting model's file.
        dataset: the run's dataset.
        val_idx: the frames both models are measured on.
        trained_report: the trained model's measurement on them.
        model_path: the trained model's file (replaced by the start when the start scores higher).
        view: the view the run trained at.
        threads: threads of the start's forward pass.
        reporter: where the comparison is said (default: the current one).
        label: prefix of the lines.
        decoding: how keypoints are read (`postprocess.Decoding`; default the commands').
    Returns:
        None when the start's view is the run's, or its crop was set on frames of another aspect than the validation
        frames (stretched on them, it would warn on every frame); else (the record's "start_as_saved": its view, both scores and
        "chose": "start" or "trained"; the start's predictor; its validation measurement).
    """
    from fcnpose_tf.metrics import mean_pck
    from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor

    start = initial_model(init, dataset.schema)
    start_view = view_of(start)
    if start_view == view:
        return None
    start_size, input_size = start_view.describe(), view.describe()
    reporter = progress.resolve(reporter)
    stretched = next(((sample.width, sample.height) for sample in (dataset.samples[i] for i in val_idx)
                      if start_view.aspect_note((sample.height, sample.width))), None)
    if stretched is not None:  # kept, it would warn on every frame it reads (`choose_view` does not keep it either)
        cw, ch = start_view.frame_size
        reporter.say(f"{label}: the starting model as saved is not weighed: its crop was set on {cw}x{ch} frames, "
                     f"of another aspect than these {stretched[0]}x{stretched[1]} ones")
        return None
    reporter.say(f"{label}: evaluating the starting model as saved ({start_size}) on the same "
                 f"{len(val_idx)} validation frames")
    predictor = KerasKeypointModel(start, Path(init), num_threads=threads, decoding=decoding)
    report = evaluate_predictor(predictor, dataset, val_idx, dataset.schema)
    start_score, trained_score = mean_pck(report.metrics), mean_pck(trained_report.metrics)
    chose = "start" if start_score > trained_score else "trained"
    figures = (f"mean of PCK@0.5/0.2/0.05 on validation: the start at {start_size} {start_score:.3f}, "
               f"the model trained at {input_size} {trained_score:.3f}")
    if chose == "start":
        with atomic_path(model_path, force=True) as tmp:
            save_for_inference(start, tmp)
        reporter.say(f"{label}: kept the starting model as saved, at its own view {start_size} ({figures}); "
                     f"--input-size {start_view.height}x{start_view.width}"
                     f"{' --crop none' if start_view.crop is None else ''} trains at that view")
    else:
        reporter.say(f"{label}: kept the trained model ({figures})")
    entry = StartAsSaved(input_size=start_view.size_record, view=start_view.to_json(),
                         start_mean_pck=round(start_score, 4), trained_mean_pck=round(trained_score, 4),
                         trained_view=view.to_json(), chose=chose)
    return entry, predictor, report


TEST_DEFINITIONS = ("PCK@a: distance / max(w, h) of the ground truth's bounding box below a (missing = wrong), mean "
                    "over keypoints; EPE: mean pixel error in the original frames (docs/training.md, metric "
                    "definitions)")


def measure_on_test_set(predictor: Any, test_data: Any) -> KeypointMetrics:
    """Keypoint metrics (`metrics.keypoint_report`, per keypoint too) of a predictor on every frame of a test set.

    Args:
        predictor: a model ready to run (`evaluate.KerasKeypointModel`, `runtime.estimator.KeypointModel`).
        test_data: the test set (a loaded dataset).
    Returns:
        The metrics.
    """
    from fcnpose_tf.training.evaluate import evaluate_predictor

    report = evaluate_predictor(predictor, test_data, range(len(test_data)), test_data.schema, min_timed_frames=0,
                                warmup=1)
    return report.metrics


def start_on_test_set(init: str | Path, test_data: Any, threads: int | None = None) -> KeypointMetrics:
    """The starting model as saved (its own input size: what the user would run without training) measured on a
    test set.

    Args:
        init: the starting model's file.
        test_data: the test set (a loaded dataset).
        threads: threads of its forward pass (None: all cores).
    Returns:
        The metrics.
    Raises:
        UserError: as `initial_model`.
    """
    from fcnpose_tf.training.evaluate import KerasKeypointModel

    return measure_on_test_set(KerasKeypointModel(initial_model(init, test_data.schema), Path(init),
                                                  num_threads=threads), test_data)


@dataclass(frozen=True)
class FixedTestSetRecord:
    """A model measured on a fixed test set against its start (NAME_train.json's "test", `record_of_test_set`)."""

    data: str
    """The test set's annotation file."""
    data_sha256: str
    num_frames: int
    definitions: str
    """How the figures are defined (TEST_DEFINITIONS)."""
    start_model: str | None
    """The starting model, as `train --init` named it; None for random weights."""
    start: KeypointMetrics | None
    """The starting model's metrics on the test set; None for random weights."""
    end: KeypointMetrics
    """The trained model's."""

    def to_json(self) -> dict[str, Any]:
        """{"data", "data_sha256", "num_frames", "definitions", "start_model", "start", "end"}.

        Returns:
            The object, keys in this order.
        """
        return {"data": self.data, "data_sha256": self.data_sha256, "num_frames": self.num_frames,
                "definitions": self.definitions, "start_model": self.start_model,
                "start": self.start.to_json() if self.start is not None else None, "end": self.end.to_json()}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> FixedTestSetRecord:
        """The record of a parsed "test" object.

        Args:
            entry: the parsed JSON object.
        Returns:
            The record, its metrics typed.
        Raises:
            KeyError: a key every record holds is missing (all but "start_model" and "start").
        """
        start = entry.get("start")
        return cls(data=entry["data"], data_sha256=entry["data_sha256"], num_frames=entry["num_frames"],
                   definitions=entry["definitions"], start_model=entry.get("start_model"),
                   start=KeypointMetrics.from_json(start) if start is not None else None,
                   end=KeypointMetrics.from_json(entry["end"]))


def record_of_test_set(test_data: Any, end: KeypointMetrics, start_model: str | None = None,
                       start: KeypointMetrics | None = None) -> FixedTestSetRecord:
    """A model measured on a fixed test set, beside its start.

    Args:
        test_data: the test set (a loaded dataset).
        end: the trained model's metrics on it (`measure_on_test_set`).
        start_model: the starting model as `train --init` named it (None: random weights).
        start: the starting model's metrics on it (`start_on_test_set`; None: random weights).
    Returns:
        NAME_train.json's "test".
    """
    from fcnpose_tf.records import file_sha256

    return FixedTestSetRecord(data=str(test_data.via_path), data_sha256=file_sha256(test_data.via_path),
                              num_frames=len(test_data), definitions=TEST_DEFINITIONS, start_model=start_model,
                              start=start, end=end)


TEST_FIGURES: tuple[tuple[Callable[[KeypointMetrics], float | None], str, int, int], ...] = (
    (lambda m: m.pck.get(0.5), "PCK@0.5", 3, 1), (lambda m: m.pck.get(0.2), "PCK@0.2", 3, 1),
    (lambda m: m.pck.get(0.05), "PCK@0.05", 3, 1), (lambda m: m.epe_px, "EPE", 2, -1),
    (lambda m: m.missing_fraction, "missing", 3, -1))
"""(figure, label, decimals, +1 when higher is better) of the test line."""


def format_test_set_line(test: FixedTestSetRecord) -> str:
    """One line: the test set, then start -> end of each figure, and whether the end is worse than the start.

    Args:
        test: NAME_train.json's "test".
    Returns:
        The line.
    """
    start, end = test.start, test.end

    def num(value: Any, decimals: int) -> str:
        return "n/a" if value is None else f"{value:.{decimals}f}"

    parts = []
    worse = []
    for figure, name, decimals, sign in TEST_FIGURES:
        unit = " px" if name == "EPE" else ""
        if start is None:
            parts.append(f"{name} {num(figure(end), decimals)}{unit}")
            continue
        parts.append(f"{name} {num(figure(start), decimals)} -> {num(figure(end), decimals)}{unit}")
        a, b = figure(start), figure(end)
        if a is not None and b is not None and sign * (round(b, decimals) - round(a, decimals)) < 0:
            worse.append(name)  # as printed: a change below the last digit shown is not a change
    head = f"Test set {test.data} ({test.num_frames} frames): "
    if start is None:
        return head + ", ".join(parts) + "; no starting model to compare (--init none: random weights)"
    verdict = f"; WORSE than the start in {', '.join(worse)}" if worse else "; no figure worse than the start"
    return head + ", ".join(parts) + f" (start: {test.start_model}){verdict}"


def loss_name(positive_weight: float, distill: float = 0.0) -> str:
    """What the training loss is, for labels: the paper's BCE, or BCE with keypoint pixels weighted (and a
    teacher's maps mixed in).

    Args:
        positive_weight: the keypoint maps' active pixels' weight.
        distill: the teacher's weight (0: none).
    Returns:
        The words.
    """
    name = "binary cross-entropy" if positive_weight == 1 else \
        f"binary cross-entropy, keypoint pixels weighted {positive_weight:g}"
    return name if not distill else f"{name}, teacher weight {distill:g}"


KEYPOINT_COLUMNS = ("val_mean_pck", "val_pck_fine", "val_epe_px")
"""The loss CSV's columns of the validation keypoints' score, when it chose the kept epoch (`KeptScore`: mean PCK,
PCK@0.05, EPE in input pixels)."""


def write_loss_curves(history: list[dict[str, float]], csv_path: Path, png_path: Path, best_epoch: int,
                      positive_weight: float = 1.0, distill: float = 0.0, start_val_loss: float | None = None) -> None:
    """Write the per-epoch losses as CSV and as a PNG plot, with the validation keypoints' score (KEYPOINT_COLUMNS)
    when it chose the kept epoch.

    Args:
        history: one {"epoch", "loss", "val_loss"} per epoch (and KEYPOINT_COLUMNS with keep_best "keypoints").
        csv_path: the CSV file.
        png_path: the plot (not written without epochs).
        best_epoch: the kept epoch, marked.
        positive_weight, distill: the loss, named in the plot (`loss_name`).
        start_val_loss: the starting model's validation loss, plotted as epoch 0 (None: a random start).
    """
    scored = bool(history) and all("val_mean_pck" in h for h in history)  # keep_best "keypoints"
    columns = ["epoch", "loss", "val_loss", *(KEYPOINT_COLUMNS if scored else ())]

    def line(h: dict[str, Any]) -> str:
        values = [h[c] for c in columns]
        return ",".join("" if v is None else str(v) if isinstance(v, int) else f"{v:.6g}" for v in values)

    lines = [",".join(columns)] + [line(h) for h in history]
    write_text(csv_path, "\n".join(lines) + "\n", force=True)
    if not history:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ax.plot(epochs, [h["loss"] for h in history], label="training")
    ax.plot(epochs, [h["val_loss"] for h in history], label="validation")
    if start_val_loss is not None:
        ax.plot([0], [start_val_loss], marker="o", linestyle="none", color="C1", label="validation, starting model")
    ax.axvline(best_epoch, color="grey", linestyle=":", label=f"kept (epoch {best_epoch})")
    ax.set_xlabel("epoch")
    ax.set_ylabel(loss_name(positive_weight, distill))
    ax.set_yscale("log")
    ax.set_title("FCN-Pose training loss" + (" and validation keypoints" if scored else ""))
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if scored:  # the score that chose the kept epoch, on its own axis
        right = ax.twinx()
        right.plot(epochs, [h["val_mean_pck"] for h in history], color="C2", label="validation keypoints (mean PCK)")
        right.set_ylabel("validation mean PCK (@0.5, @0.2, @0.05)")
        more_handles, more_labels = right.get_legend_handles_labels()
        handles, labels = handles + more_handles, labels + more_labels
    ax.legend(handles, labels, fontsize="small")
    fig.tight_layout()
    with atomic_path(png_path, force=True) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
