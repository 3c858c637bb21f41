"""The steps of one compression run up to its retrained model (`compress.compress_model` runs them in order), each
returning its part of the report: measure_base, importance_step, prune_step, retrain_step, measure_retrained; then,
per format, `fcnpose_tf.compression.export_steps`'. Every step reads the run's `Run`; `SharedScoring` carries the base
model's measurement and filter scores from one rate to the next.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from fcnpose_tf.compression.methods import FitFn, MethodRecord, PruningMethod
from fcnpose_tf.compression.options import CompressOptions, OutputFiles
from fcnpose_tf.compression.costs import file_sizes, model_facts
from fcnpose_tf.compression.report import ModelStep, PruningSections, RetrainSections, Retraining
from fcnpose_tf.errors import UserError
from fcnpose_tf.measurements import Measurement
from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.preprocess import FrameView
from fcnpose_tf.progress import Reporter
from fcnpose_tf.records import file_sha256, training_record

if TYPE_CHECKING:
    import tf_keras as keras

    from fcnpose_tf.compression.importance import CriterionFacts, Importance
    from fcnpose_tf.training.train import FitResult

# TensorFlow is imported inside the functions: the CLI imports this module (through compress) without needing
# TensorFlow until a compression runs.


def _measure(predictor: Any, dataset: Any, indices: Sequence[int], label: str, reporter: Reporter,
             timing: bool = True) -> Measurement:
    reporter.say(f"  evaluating {label} on {len(indices)} frames ...")
    result = evaluate_predictor(predictor, dataset, indices, dataset.schema,
                                min_timed_frames=50 if timing else 1, warmup=5 if timing else 1)
    return result.measurement(timed=timing)


# ------------------------------------------------------------------------------------------
# The steps of a compression run, each returning its part of the report
# ------------------------------------------------------------------------------------------

@dataclass
class Run:
    """What every step of one compression run reads."""

    base_path: Path
    base: keras.Model
    method: PruningMethod
    options: CompressOptions
    files: OutputFiles
    train_dataset: Any
    eval_dataset: Any
    eval_indices: Sequence[int]
    force: bool
    reporter: Reporter
    fit_data: Any = None
    """The retraining's training data (`data.dataset.fold_data`), kept for quantization-aware training."""
    method_record: MethodRecord | None = None
    """What the pruning step says about its method in the retraining's NAME_train.json (`methods.Pruned.record`)."""

    @functools.cached_property
    def data_sha256(self) -> str:
        """The training data file's SHA-256, hashed once per run (the fold's choice and the retraining record)."""
        return file_sha256(self.train_dataset.via_path)

    @functools.cached_property
    def fold(self) -> int | None:
        """The fold whose training frames the run scores filters on, retrains on and calibrates int8 on
        (`retrain_fold`), decided once: with 0 retraining epochs too, so the file is calibrated on the frames the
        model it converts was trained on."""
        return retrain_fold(self)

    @property
    def polishes(self) -> bool:
        """Whether the retraining is polished on the user's frames alone afterwards: frames were added to it
        (`compress --more-frames`) and `options.polish_minutes` is not 0."""
        return self.train_dataset.added is not None and self.options.polish_minutes > 0 \
            and self.options.retrain_epochs > 0

    @property
    def input_size(self) -> FrameView:
        """What the base model sees of a frame (its crop and input size): every step prepares frames this way."""
        from fcnpose_tf.training.model import view_of

        return view_of(self.base)

    def measure(self, predictor: Any, label: str, timing: bool = True) -> Measurement:
        """Metrics (and timing) of a predictor on the run's evaluation frames.

        Args:
            predictor: a `KeypointPredictor`.
            label: the progress line's name for it.
            timing: time it (at least 50 frames after 5 warm-up ones); False: the timing is left out.
        Returns:
            The measurement (timing None when not timed).
        """
        return _measure(predictor, self.eval_dataset, self.eval_indices, label, self.reporter, timing=timing)

    @property
    def training_frames(self) -> np.ndarray:
        """Indices of the training frames of the run's fold (`fold`) that are not evaluation frames: what filters are
        scored on and int8 is calibrated on."""
        train_indices, _ = self.train_dataset.split(self.fold)
        if self.train_dataset is self.eval_dataset:
            train_indices = np.setdiff1d(train_indices, np.asarray(self.eval_indices, dtype=np.int64))
        return np.asarray(train_indices, dtype=np.int64)

    @property
    def decoding(self) -> Decoding:
        """How every measurement reads keypoints (the options' centroid and cluster choice, the commands'
        threshold)."""
        return Decoding(centroid=self.options.centroid, cluster=self.options.cluster)

    def log(self, line: str) -> None:
        """One progress line of the run (`reporter.say`).

        Args:
            line: the line.
        """
        self.reporter.say(line)

    def keras_predictor(self, model: keras.Model, path: Path | None = None) -> KerasKeypointModel:
        """A Keras model as a predictor with the run's threads and decoding.

        Args:
            model: the model.
            path: its file, for the report (None: not saved).
        Returns:
            The `KerasKeypointModel`.
        """
        return KerasKeypointModel(model, path, num_threads=self.options.threads, decoding=self.decoding)


@dataclass
class SharedScoring:
    """What the rates of one base model share (`compress --rates`): the base model's measurement and its filters'
    importance scores, each computed by the first rate that needs it and read by the others.

    Valid for one base model file, one set of frames and one importance setting (the rates' options differ only in
    the rate); `compress_model` fills it. The base model is measured once per input view: a rate whose pruned start
    rebuilds it at another height (`methods.start_height`) measures it there.
    """

    base_steps: dict[FrameView, ModelStep] = field(default_factory=dict)
    importance: Importance | None = None


class _ScoredOnce:
    """An importance criterion that scores the base model once: the scores of its first call answer every later
    one (the base model is loaded again for each rate, with the same weights)."""

    def __init__(self, criterion: Importance) -> None:
        self.criterion = criterion
        self.name = criterion.name
        self._scores: dict[str, np.ndarray] | None = None

    def __call__(self, model: keras.Model) -> dict[str, np.ndarray]:
        if self._scores is None:
            self._scores = self.criterion(model)
        return self._scores

    def describe(self) -> CriterionFacts:
        """What the report records about the criterion (the wrapped one's facts)."""
        return self.criterion.describe()


def measure_base(run: Run) -> ModelStep:
    """The unpruned model (the report's "base"): widths, parameters, MACs, file sizes, metrics and timing.

    Args:
        run: the compression run.
    Returns:
        The report's "base" step.
    """
    base_path = run.base_path
    keras_file = base_path if base_path.suffix == ".keras" else None
    return ModelStep.of(model_facts(run.base),
                        run.measure(run.keras_predictor(run.base, base_path), "the base model (Keras)"),
                        file_sizes(run.base, keras_file))


def retrain_fold(run: Run) -> int | None:
    """The fold the run retrains on: --fold, else the base model's own (its record, same data), else the hold-out split.

    Args:
        run: the compression run.
    Returns:
        The fold, or None for the hold-out 80/20 split.
    """
    if run.options.fold is not None:
        return run.options.fold
    record = training_record(run.base_path)
    if record is None:
        return None
    return record.fold if record.data_sha256 == run.data_sha256 else None


def importance_frames(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """The frames a data-aware criterion scores filters on: a seeded choice of `options.importance_frames` of the
    training frames of the run's fold (`Run.fold`; never the measured ones), unaugmented.

    Args:
        run: the compression run.
    Returns:
        (images, target maps), float32.
    Raises:
        UserError: the split has no training frames.
    """
    from fcnpose_tf.data.dataset import TrainingData

    candidates = run.training_frames
    if not len(candidates):
        raise UserError(f"no training frames to score filters with in {run.train_dataset.via_path}")
    count = min(run.options.importance_frames, len(candidates))
    chosen = np.sort(np.random.default_rng(run.options.seed).choice(candidates, count, replace=False))
    return TrainingData(run.train_dataset, chosen, run.input_size, 0, run.options.seed).arrays()


def importance_step(run: Run) -> Importance:
    """The run's filter importance criterion, with its frames when it is data-aware (`importance_frames`).

    Args:
        run: the compression run (its options name the criterion).
    Returns:
        The criterion (`importance.make_importance`).
    """
    from fcnpose_tf.compression.importance import DATA_AWARE, make_importance
    from fcnpose_tf.training.train import ground_truth_loss

    name = run.options.importance
    if name not in DATA_AWARE:
        return make_importance(name)
    run.log(f"  scoring filters by {name} on up to {run.options.importance_frames} training frames ...")
    images, maps = importance_frames(run)
    return make_importance(name, images=images, maps=maps, loss=ground_truth_loss(run.options.positive_weight or 1.0),
                           batch_size=run.options.batch_size)


def shared_importance(run: Run, shared: SharedScoring) -> Importance:
    """The run's criterion; a data-aware one scores the base model once for every rate that shares `shared` (the
    weight norms read the kernels, as cheap as a lookup, and the greedy strategy ranks pruned kernels with them).

    Args:
        run: the compression run.
        shared: what the rates of one base model share.
    Returns:
        The criterion (`importance_step`'s, scored once when data-aware).
    """
    from fcnpose_tf.compression.importance import DATA_AWARE

    name = run.options.importance
    if name not in DATA_AWARE:
        return importance_step(run)
    if shared.importance is None or shared.importance.name != name:
        shared.importance = _ScoredOnce(importance_step(run))
    else:
        run.log(f"  filters scored already (the first rate's {name} scores of the base model)")
    return shared.importance


def prune_step(run: Run, importance: Importance | None) -> tuple[keras.Model, PruningSections, ModelStep]:
    """Prune with the run's method and measure the result before any retraining; the method's record is kept for the
    retraining (`Run.method_record`).

    Args:
        run: the compression run.
        importance: the criterion filters are ranked by; None when the method takes a pruned start's weights.
    Returns:
        The pruned model, the method's report sections, and the report's pruned_before_retraining.
    """
    from fcnpose_tf.training.model import schema_of, with_schema, with_view

    pruned, sections, run.method_record = run.method.prune(run.base, importance)
    # the crop and the keypoint names are part of the model: surgery keeps the base's
    pruned = with_schema(with_view(pruned, run.input_size), schema_of(run.base))
    return pruned, sections, ModelStep.of(model_facts(pruned), run.measure(
        run.keras_predictor(pruned), "the pruned model before retraining", timing=False))


def retrain_step(run: Run, pruned: keras.Model) -> tuple[keras.Model, RetrainSections]:
    """Retrain the pruned model through `train.fit`, or only save it with 0 retraining epochs; with frames added
    (`Run.polishes`), polish it afterwards on the user's frames alone (`CompressOptions.polish_config`), the retrained
    model the epoch to beat.

    Args:
        run: the compression run.
        pruned: the pruned model (`prune_step`).
    Returns:
        The model as saved, and the report sections (retrain_data, distillation, retraining, polish; none with 0
        epochs).
    """
    import tempfile

    from fcnpose_tf.data.dataset import own_frames
    from fcnpose_tf.fileio import atomic_path
    from fcnpose_tf.training.model import load_model, save_for_inference

    options, keras_path = run.options, run.files.paths["keras"]
    if options.retrain_epochs == 0:
        with atomic_path(keras_path, run.force) as tmp:
            save_for_inference(pruned, tmp)
        return pruned, RetrainSections()
    entries: dict[str, Any] = {}
    if not run.polishes:
        run.method.retrain(run.base, pruned, _fitting(run, run.train_dataset, keras_path, entries))
        return load_model(keras_path), RetrainSections(**entries)
    with tempfile.TemporaryDirectory(prefix="fcnpose-retrain-") as folder:  # the retraining's files: the polish's kept
        run.method.retrain(run.base, pruned, _fitting(run, run.train_dataset, Path(folder) / keras_path.name, entries))
        retrained = load_model(Path(folder) / keras_path.name)
    own = own_frames(run.train_dataset)
    config = options.polish_config()
    run.log(f"  polish: up to {config.max_minutes:g} min more on the {len(own.split(run.fold)[0])} training frames of "
            f"{own.via_path} alone, learning rate {config.learning_rate:g}"
            + (f", conv1-{config.freeze} fixed" if config.freeze > 1 else ""))
    # magnitude pruning masks the retrained model's own zeros again, at the same sparsity
    run.method.retrain(retrained, retrained, _fitting(run, own, keras_path, entries, polish=True))
    return load_model(keras_path), RetrainSections(**entries)


def _fitting(run: Run, dataset: Any, keras_path: Path, entries: dict[str, Any], polish: bool = False) -> FitFn:
    """The fit function a method's `retrain` calls: `train.fit` on `dataset`'s training frames of the run's fold,
    saving the kept model as `keras_path` and its report section in `entries` ("retraining", with "retrain_data" and
    "distillation"; "polish" when `polish`, with `CompressOptions.polish_config` and its start the epoch to beat).

    Args:
        run: the compression run (its fit data set to this retraining's, for quantization-aware training).
        dataset: the frames (the run's, or the user's own for the polish).
        keras_path: where the kept model goes.
        entries: the report sections, filled when the function runs.
        polish: the polish after a retraining with frames added.
    Returns:
        The function (`methods.FitFn`).
    """
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.training.train import ValidationKeypoints, fit

    options = run.options
    train_data, val_data = fold_data(dataset, run.fold, run.input_size, options.augment_copies, options.seed,
                                     options.augment, progress=run.reporter)
    run.fit_data = train_data
    metadata = {"data": str(dataset.via_path), "data_sha256": run.data_sha256, "fold": run.fold,
                "folds": dataset.splits.k, "split_seed": dataset.splits.seed, "schema": dataset.schema.to_dict(),
                "pruned_from": str(run.base_path), **(run.method_record or {}), "input_size": run.input_size.size_record,
                "view": run.input_size.to_json(),
                "recipe": run.method.recipe}
    if run.train_dataset.added is not None:  # frames in the training split only (`compress --more-frames`)
        metadata["added_frames"] = run.train_dataset.added.to_json()
    if polish:
        metadata["retraining_before_polish"] = entries["retraining"].to_json()
    else:
        entries["retrain_data"] = {"data": str(dataset.via_path), "fold": run.fold, "train_samples": len(train_data),
                                   "val_frames": len(val_data)}
        if dataset.added is not None:
            entries["retrain_data"]["added_frames"] = metadata["added_frames"]
    sequence = train_data.sequence(options.batch_size, seed=options.seed)
    if options.distill > 0:
        from fcnpose_tf.training.distill import with_teacher_maps

        if not polish:
            run.log(f"  distillation: the base model's maps weigh {options.distill:g} in the retraining loss")
        sequence, facts = with_teacher_maps(train_data, sequence, run.base, options.batch_size)
        entries["distillation"] = {"weight": options.distill, **facts}
        metadata["distillation"] = entries["distillation"]
    config = options.polish_config() if polish else options.fit_config()
    trained_start = polish or run.method.trained_start
    key = "polish" if polish else "retraining"

    def fit_fn(model: keras.Model, callbacks: Sequence = (), inference_model: Callable | None = None) -> FitResult:
        result = fit(model, sequence, val_data.arrays(), keras_path, config, force=run.force,
                     reporter=run.reporter.lines(), metadata=metadata, callbacks=callbacks,
                     inference_model=inference_model, resumable=False, start_is_candidate=trained_start,
                     val_keypoints=ValidationKeypoints.of(val_data, run.decoding))
        entries[key] = retraining_report(result, _loss_name(model), options.positive_weight, options.distill)
        if trained_start:
            entries[key] = replace(entries[key], start_kept=result.best_epoch == 0)
            if result.best_epoch == 0:
                judged = "keypoints" if result.best_keypoints is not None else "loss"
                start, kept = ("the retrained model", "it") if polish else ("the pruned start", "the start")
                run.log(f"  no epoch beat {start}'s validation {judged}: {kept} is kept, unchanged")
        return result

    return fit_fn


def retraining_report(result: FitResult, loss: str, positive_weight: float, distill: float = 0.0) -> Retraining:
    """The report's "retraining" part: epochs, best epoch and loss (validation: against the ground truth), time,
    loss function, positive and teacher weights, learning rates, whether the time budget ended it, what chose the
    kept epoch and (keypoints) its validation keypoints.

    Args:
        result: what `train.fit` returned.
        loss: the compiled loss's name.
        positive_weight: the keypoint maps' weight in the loss.
        distill: the teacher's weight (0: no distillation).
    Returns:
        The section.
    """
    return Retraining(epochs_run=result.epochs_run, best_epoch=result.best_epoch, best_val_loss=result.best_val_loss,
                      seconds=round(result.seconds, 1), loss=loss, positive_weight=positive_weight, distill=distill,
                      learning_rates=[float(f"{h['lr']:.6g}") for h in result.history if "lr" in h],
                      stopped_by_time_budget=result.stopped_by_time_budget,
                      kept_by="loss" if result.best_keypoints is None else "keypoints",
                      best_val_keypoints=result.best_keypoints)


def measure_retrained(run: Run, retrained: keras.Model) -> ModelStep:
    """The retrained Keras model as saved (the report's "retrained"): widths, parameters, MACs, file sizes, metrics
    and timing.

    Args:
        run: the compression run.
        retrained: the retrained model (`retrain_step`).
    Returns:
        The report's "retrained" step.
    """
    keras_path = run.files.paths["keras"]
    return ModelStep.of(model_facts(retrained),
                        run.measure(run.keras_predictor(retrained, keras_path), "the retrained model (Keras)"),
                        file_sizes(retrained, keras_path))


def _loss_name(model: Any) -> str:
    """The compiled loss's name: binary_crossentropy (plain BCE) or keypoint_bce (weighted)."""
    loss = getattr(model, "loss", None)
    return str(getattr(loss, "name", loss))
