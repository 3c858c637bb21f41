"""The paper's whole compression for one rate: prune, retrain, quantize, and measure every step.

    base model ──► filter surgery at rate r, filters ranked by an importance criterion (L1 by
                   default; or tfmot magnitude pruning) ──► retrain (optionally distilled from
                   the base model's maps) ──► TFLite export (float16 by default), verified against Keras
    measured at each step on the same frames: PCK@0.5/0.2/0.05 (bbox), EPE, PCK-AUC,
    parameters, MACs, file sizes, inference time and FPS (Keras and TFLite, thread count stated).

`compress_model` is the library entry point (the `compress` and `sweep` commands call it); it runs
the steps below in order (measure_base, importance_step, prune_step, retrain_step, measure_retrained,
export_step, measure_quantized), each returning its part of the report (a `CompressReport`, written as
NAME_pXX_report.json). A format whose file fails its gate is a "refused" entry of the report (a `RefusedFormat`),
not the end of the run; post-training int8 refused falls back to quantization-aware training (`qat_step`,
`fcnpose_tf.compression.qat`). A pruning method is a `PruningMethod` object (`FilterPruning` with an importance
criterion from `fcnpose_tf.compression.importance`, `MagnitudePruning`); both retrain through `train.fit`.
"""

from __future__ import annotations

import gzip
import os
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence

import numpy as np

from fcnpose_tf import progress, settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
from fcnpose_tf.preprocess import FrameView
from fcnpose_tf.progress import Reporter
from fcnpose_tf.fileio import check_writable, write_json
from fcnpose_tf.records import file_sha256, training_record

if TYPE_CHECKING:
    import tf_keras as keras

    from fcnpose_tf.compression.importance import Importance
    from fcnpose_tf.training.train import FitConfig, FitResult

# TensorFlow is imported inside the functions: `sweep.jobs` and the CLI import this module (or
# read its settings) without needing TensorFlow until a compression runs.

METHODS = settings.METHOD.choices
Log = Callable[[str], None]


@settings.config_class(settings.RATE, settings.METHOD, settings.STRATEGY, settings.QUANTIZE,
                       settings.CALIBRATION_FRAMES, settings.RETRAIN_EPOCHS,
                       ("patience", settings.RETRAIN_PATIENCE), settings.BATCH_SIZE,
                       ("learning_rate", settings.COMPRESS_LEARNING_RATE), ("augment", settings.INHERITED_AUGMENT),
                       settings.AUGMENT_COPIES,
                       settings.SEED, settings.RETRAIN_FOLD, settings.THREADS,
                       ("positive_weight", settings.INHERITED_POSITIVE_WEIGHT),
                       ("lr_patience", settings.COMPRESS_LR_PATIENCE), settings.LR_SCHEDULE,
                       ("importance", settings.COMPRESS_IMPORTANCE), settings.IMPORTANCE_FRAMES, settings.DISTILL,
                       settings.FREEZE, ("min_filters", settings.COMPRESS_MIN_FILTERS), settings.PRUNED_START,
                       ("input_size", settings.COMPRESS_INPUT_SIZE), settings.QAT_EPOCHS,
                       settings.QAT_LEARNING_RATE, settings.CENTROID)
class CompressOptions:
    """Settings of one compression run: rate, method, strategy, quantize (the TFLite files, one per format),
    calibration_frames (int8), and the retraining's
    retrain_epochs, patience, batch_size, learning_rate, augment, augment_copies, seed, fold, threads,
    positive_weight (use the base model's), lr_patience and lr_schedule; importance (the filter criterion) with
    importance_frames (data-aware criteria), distill (the base model's weight as a teacher while
    retraining), freeze (conv1..convN keep their pruned weights while retraining), min_filters (the
    narrowest a pruned layer may become at the same parameter budget), start (the pruned network's weights before
    retraining: surgery, auto, or a pruned model: `pruned_start`), input_size (the side the model is rebuilt, retrained
    and exported at; None: its own), and qat_epochs / qat_learning_rate
    (quantization-aware training when post-training int8 is refused; 0 epochs: no fallback); centroid: how the
    table's keypoints are read (`postprocess.CENTROIDS`).

    The defaults are `fcnpose-tf compress`'s (`CompressOptions.preset("paper", rate=...)`: the paper's recipe);
    importance, min_filters, lr_patience and positive_weight left None are chosen per run by `resolved`
    (`compress_model` calls it). Defaults, checks and meanings: `fcnpose_tf.settings`."""

    def validate(self) -> None:
        """Check every setting (`fcnpose_tf.settings`) and the combinations no run can do; UserError if bad."""
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
        filter), lr_patience (`settings.resolved_lr_patience`), positive_weight and augment (those `base_path` was
        trained with, from its NAME_train.json; else 1, the paper's plain BCE, and the paper's copies)."""
        importance, min_filters, positive_weight, augment = (self.importance, self.min_filters, self.positive_weight,
                                                             self.augment)
        if importance is None:
            independent_surgery = self.method == "l1" and self.strategy == "independent"
            importance = settings.DEFAULT_COMPRESS_IMPORTANCE if independent_surgery else "l1"
        if min_filters is None:
            min_filters = settings.DEFAULT_COMPRESS_MIN_FILTERS if self.method == "l1" else 0
        record = training_record(base_path) if base_path is not None and None in (positive_weight, augment) else None
        if positive_weight is None:
            positive_weight = float(record.positive_weight or 1.0) if record is not None else 1.0
        if augment is None:
            inherited = record.augment if record is not None else None
            augment = inherited if inherited in settings.AUGMENT.choices else settings.AUGMENT.default
        lr_patience = settings.resolved_lr_patience(self.lr_patience, self.lr_schedule,
                                                    settings.DEFAULT_COMPRESS_LR_PATIENCE)
        return replace(self, importance=importance, min_filters=min_filters, positive_weight=positive_weight,
                       lr_patience=lr_patience, augment=augment)

    def recipe(self, min_filters_used: int | None = None) -> str:
        """One line naming how the file was made: widths, criterion, strategy, distillation, loss.

        `min_filters_used` is the floor the surgery could keep (`prune.prune_widths`) when lower than asked."""
        from fcnpose_tf.training.train import loss_name

        if None in (self.importance, self.min_filters, self.lr_patience, self.positive_weight, self.augment):
            return self.resolved().recipe(min_filters_used)

        used = self.min_filters if min_filters_used is None else min_filters_used
        floor = "" if used <= 1 else (
            f" (no layer under {used} filters, same parameter budget)" if used == self.min_filters else
            f" (no layer under {used} filters: --min-filters {self.min_filters} lowered to fit the parameter budget)")
        pruned = (f"magnitude pruning at {self.rate:g}" if self.method == "magnitude" else
                  f"filter surgery's widths at {self.rate:g}{floor}, the weights of {self.start}"
                  if self.start not in ("auto", "surgery") else
                  f"filter surgery at {self.rate:g}{floor}, filters ranked by {self.importance} ({self.strategy}"
                  + (f", {self.importance_frames} training frames" if self.importance in ("activation", "taylor")
                     else "") + ")")
        size = f", at {self.input_size}x{self.input_size}" if self.input_size else ""
        if self.retrain_epochs == 0:
            return f"{pruned}, not retrained{size}"
        epochs = f"{self.retrain_epochs} epoch{'s' if self.retrain_epochs > 1 else ''}"
        rate = (f"learning rate {self.learning_rate:g} on a cosine" if self.lr_schedule == "cosine" else
                f"learning rate {self.learning_rate:g}, halved after {self.lr_patience} stale epochs"
                if self.lr_patience else f"learning rate {self.learning_rate:g}")
        frozen = f", conv1-{self.freeze} fixed" if self.freeze > 1 else ", conv1 fixed" if self.freeze else ""
        frames = " with online augmentation" if self.augment == "online" else ""  # the paper's copies: unsaid
        return (f"{pruned}, retrained up to {epochs}{frames} on "
                f"{loss_name(self.positive_weight or 1.0, self.distill)}, {rate}{frozen}{size}")

    def fit_config(self) -> FitConfig:
        """The retraining's optimisation settings (at least one epoch; 0 retraining epochs skip `fit`)."""
        from fcnpose_tf.training.train import FitConfig

        return FitConfig(**settings.carried(self, FitConfig, epochs=max(self.retrain_epochs, 1), max_minutes=None))


# ------------------------------------------------------------------------------------------
# The report: what a run measured and wrote (NAME_pXX_report.json)
# ------------------------------------------------------------------------------------------

Step = dict[str, Any]
"""One measured step of the report, as written: the model's facts (widths, params, macs, flops, nonzero_weights; a
TFLite file's params, macs, flops), its file sizes (h5_size_bytes, h5_gzip_size_bytes, keras_size_bytes; a TFLite
file's tflite_size_bytes, tflite_gzip_size_bytes), "metrics" and "timing" (none for the pruned model before
retraining). A TFLite file's also holds "quantize", "status" ("written"), "quantization", "export"
(`TFLiteExport.to_dict`), "tflite_ops" and, when quantization-aware training made it, "qat"."""


@dataclass(frozen=True)
class RefusedFormat:
    """A --quantize format whose file failed its keypoint gate: no file written, a row of the table. Written as
    {"quantize", "status": "refused", "reason", "post_training"[, "qat"]}."""

    quantize: str
    """The format (float16, int8, ...)."""
    reason: str
    """Why it was refused: the gate's reason (after quantization-aware training, that training's)."""
    post_training: dict[str, Any] = field(default_factory=dict)
    """The post-training file's gate: its "reason" and the facts it measured."""
    qat: dict[str, Any] | None = None
    """Quantization-aware training's facts, when it was tried (int8 with --qat-epochs above 0)."""

    def to_json(self) -> dict[str, Any]:
        """The entry as the report's "refused" list holds it ("qat" only when tried)."""
        return {"quantize": self.quantize, "status": "refused", "reason": self.reason,
                "post_training": self.post_training, **({"qat": self.qat} if self.qat is not None else {})}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> RefusedFormat:
        """The entry of a parsed report's "refused" list."""
        return cls(quantize=entry["quantize"], reason=entry["reason"],
                   post_training=entry.get("post_training") or {}, qat=entry.get("qat"))


def _if_any() -> Any:
    """A section only some runs have: None when the run has none, and then not written."""
    return field(default=None, metadata={"if_any": True})


@dataclass(frozen=True, kw_only=True)
class CompressReport:
    """What `compress_model` measured and wrote: one field per top-level key of NAME_pXX_report.json, in the
    file's order (`to_json`). The measured steps stay JSON objects (`Step`); a refused format is a `RefusedFormat`.
    A section only some runs have (pruning, magnitude_sparsity, retrain_data, distillation, retraining) is None
    when the run has none and is then not written; "quantized" is written either way (null: every format refused)."""

    base_model: str
    """The model that was compressed, its file as given."""
    method: str
    """The pruning method: l1 (filter surgery, whatever the criterion) or magnitude."""
    recipe: str
    """One line naming how the file was made (`CompressOptions.recipe`); "" read back from a report older than it."""
    options: dict[str, Any]
    """The settings used, `CompressOptions` as a dict (those left None chosen for the run)."""
    evaluation_frames: str
    """The frames every step was measured on, in words."""
    pck_normalisation: str
    """What PCK's distances are divided by."""
    threads: int | None
    """CPU threads of the timed inference (None: all cores)."""
    metadata: dict[str, Any] = field(default_factory=dict)
    """The caller's further facts (`compress_model(metadata=...)`, e.g. the command's "preset"), written as top-level
    keys here; read back from a file, every key without a field (e.g. the sweep's "retimed")."""
    base: Step
    """The unpruned model (Keras)."""
    pruning: dict[str, Any] | None = _if_any()
    """Filter surgery's criterion and its facts, strategy, min_filters (the floor used), ranking_seconds."""
    magnitude_sparsity: float | None = _if_any()
    """Magnitude pruning's fraction of zeroed weights (the parameter reduction of filter surgery at the rate)."""
    pruned_before_retraining: Step
    """The pruned model before any retraining (Keras, no timing)."""
    retrain_data: dict[str, Any] | None = _if_any()
    """What the retraining trained on: data, fold, train_samples, val_frames (None: not retrained)."""
    distillation: dict[str, Any] | None = _if_any()
    """The base model as a teacher while retraining: weight and its facts (None: --distill 0)."""
    retraining: dict[str, Any] | None = _if_any()
    """How the retraining went (`retraining_report`); None: not retrained."""
    retrained: Step
    """The retrained model as saved (Keras, NAME_pXX.keras)."""
    quantized: Step | None
    """The first TFLite file written (the paper's float16 by default); None when every format was refused."""
    other_quantized: list[Step] = field(default_factory=list)
    """The other TFLite files written, in --quantize order."""
    refused: list[RefusedFormat] = field(default_factory=list)
    """The formats whose file failed its gate (nothing written for them)."""
    files: dict[str, str]
    """The files written, by `output_names` key (keras, tflite_fp16, ..., report)."""
    seconds: float
    """Wall time of the run."""

    def __post_init__(self) -> None:
        _check_metadata(self.metadata)

    @property
    def tflite_files(self) -> list[Step]:
        """The TFLite files written: "quantized" first, then "other_quantized"."""
        return [step for step in [self.quantized, *self.other_quantized] if step is not None]

    def to_json(self) -> dict[str, Any]:
        """The report as NAME_pXX_report.json holds it: the fields in order, `metadata`'s keys in its place, a
        section only some runs have left out when None."""
        report: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "metadata":
                report.update(value)
            elif f.name == "refused":
                report[f.name] = [entry.to_json() for entry in value]
            elif value is not None or not f.metadata.get("if_any"):
                report[f.name] = value
        return report

    @classmethod
    def from_json(cls, report: dict[str, Any]) -> CompressReport:
        """The report of a parsed NAME_pXX_report.json (to read a written one back, e.g. for its table). Keys that
        reports held before "recipe", "other_quantized" and "refused" existed read as "", [] and [] (one file,
        and a refused format ended those runs); a key without a field goes to `metadata`.

        Raises:
            TypeError: not a JSON object.
            ValueError: a key every report holds is missing.
        """
        if not isinstance(report, dict):
            raise TypeError(f"a compress report is a JSON object, not {type(report).__name__}")
        names = {f.name for f in fields(cls)} - {"metadata"}
        optional = {f.name for f in fields(cls) if f.metadata.get("if_any")} | {"recipe", "other_quantized", "refused"}
        missing = sorted(names - optional - report.keys())
        if missing:
            raise ValueError(f"not a compress report: no {', '.join(missing)}")
        values = {k: v for k, v in report.items() if k in names}
        values.setdefault("recipe", "")
        values["other_quantized"] = list(values.get("other_quantized") or [])
        values["refused"] = [RefusedFormat.from_json(entry) for entry in values.get("refused") or []]
        return cls(**values, metadata={k: v for k, v in report.items() if k not in names})


def _check_metadata(metadata: dict[str, Any] | None) -> None:
    """ValueError if a key of a report's further facts is one of its sections (it would overwrite it)."""
    clash = sorted(set(metadata or {}) & {f.name for f in fields(CompressReport)})
    if clash:
        raise ValueError(f"report metadata cannot hold {', '.join(clash)}: a section of the report")


def tflite_key(quantize: str) -> str:
    """The key of a TFLite file in a run's names and paths (and the report's "files"): tflite_fp16, tflite_int8."""
    return f"tflite_{settings.QUANTIZE_FILE_TAGS[quantize]}"


def output_names(base_name: str, options: CompressOptions) -> dict[str, str]:
    """File names of a run: NAME_p70.keras, NAME_p70_fp16.tflite (one per --quantize format, key
    `tflite_key`), NAME_p70_report.json (m70 for magnitude); NAME_p70_192... with --input-size 192."""
    tag = f"{pruning_method(options).tag}{round(options.rate * 100):02d}"
    stem = f"{base_name}_{tag}" + (f"_{options.input_size}" if options.input_size else "")
    return {"stem": stem, "keras": f"{stem}.keras",
            **{tflite_key(q): f"{stem}_{settings.QUANTIZE_FILE_TAGS[q]}.tflite" for q in options.quantize},
            "report": f"{stem}_report.json"}


def output_paths(base_path: str | os.PathLike, out_dir: str | os.PathLike, options: CompressOptions) -> list[Path]:
    """Every file a run writes into `out_dir`: the models, the report and (when retraining) the training side files."""
    from fcnpose_tf.training.train import output_files

    names = output_names(Path(base_path).stem, options)
    paths = [Path(out_dir) / name for key, name in names.items() if key != "stem"]
    if options.retrain_epochs > 0:
        paths += [p for p in output_files(paths[0]) if p not in paths]
    return paths


def check_outputs(base_path: str | os.PathLike, out_dir: str | os.PathLike, options: CompressOptions,
                  force: bool = False) -> None:
    """Refuse (UserError) before any work if a file the run will write exists (without force) or cannot be written."""
    for path in output_paths(base_path, out_dir, options):
        check_writable(path, force)


def file_sizes(model: keras.Model, keras_path: Path | None = None) -> dict[str, int]:
    """Bytes of the model as .keras and .h5 (no optimizer state), and gzip-compressed .h5."""
    from fcnpose_tf.training.model import h5_bytes, inference_copy, save_for_inference

    with warnings.catch_warnings():  # the paper's size is the .h5; Keras calls the format legacy
        warnings.simplefilter("ignore", UserWarning)
        h5 = h5_bytes(inference_copy(model))
    sizes = {"h5_size_bytes": len(h5), "h5_gzip_size_bytes": len(gzip.compress(h5, 9))}
    with tempfile.TemporaryDirectory() as tmp:
        if keras_path is None:
            keras_path = Path(tmp) / "m.keras"
            save_for_inference(model, keras_path)
        sizes["keras_size_bytes"] = keras_path.stat().st_size
    return sizes


def model_facts(model: keras.Model) -> dict[str, Any]:
    """Widths, parameters and MACs (FLOPs = 2 x MACs) of a model."""
    from fcnpose_tf.training.model import conv_widths, describe

    rows = describe(model)
    macs = sum(r.macs for r in rows)
    return {"widths": list(conv_widths(model)), "params": int(model.count_params()), "macs": int(macs),
            "flops": int(2 * macs), "nonzero_weights": int(sum(np.count_nonzero(w) for w in model.get_weights()))}


def _measure(predictor: Any, dataset: Any, indices: Sequence[int], label: str, log: Log,
             timing: bool = True) -> dict:
    log(f"  evaluating {label} on {len(indices)} frames ...")
    result = evaluate_predictor(predictor, dataset, indices, dataset.schema,
                                min_timed_frames=50 if timing else 1, warmup=5 if timing else 1)
    out = {"metrics": result["metrics"]}
    if timing:
        out["timing"] = result["timing"]
    return out


# ------------------------------------------------------------------------------------------
# Pruning methods: one interface, one object per method
# ------------------------------------------------------------------------------------------

FitFn = Callable[..., "FitResult"]
"""`fit_fn(model, callbacks=(), inference_model=None)`: the retraining `fit`, writing NAME_pXX.keras."""


class PruningMethod(Protocol):
    """How a method prunes the base model and retrains the result through the same `fit`."""

    name: str
    tag: str
    """First letter of the output names' rate tag: p70 (filters removed), m70 (weights zeroed)."""

    def describe(self) -> str:
        """The progress line's words for what is pruned."""

    @property
    def ranks_filters(self) -> bool:
        """Whether `prune` ranks the base model's filters by an `Importance` (else it is passed None)."""

    @property
    def trained_start(self) -> bool:
        """Whether `prune` returns trained weights of the pruned network (a pruned start), whose validation loss the
        retraining must beat: if no epoch does, the start is kept unchanged (`train.fit`'s start_is_candidate)."""

    def prune(self, base: keras.Model, importance: Importance | None) -> tuple[keras.Model, dict[str, Any]]:
        """The pruned model before retraining, and the report sections the method adds (`CompressReport` fields
        by name: pruning, magnitude_sparsity)."""

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        """Retrain `pruned` with `fit_fn`, which saves the retrained model for inference."""

    def training_record(self) -> dict[str, Any]:
        """What the retraining's NAME_train.json says about the method."""


class FilterPruning:
    """The paper's method: remove the least important filters (exact layer surgery); the paper ranks them by
    L1 norm, `fcnpose_tf.compression.importance` holds the other criteria. The method is named "l1" in reports and
    options for that reason; the criterion is recorded beside it."""

    name, tag = "l1", "p"

    def __init__(self, rate: float, strategy: str, importance: str = "l1", min_filters: int = 0,
                 start: Path | None = None, start_name: str = "") -> None:
        self.rate, self.strategy, self.importance, self.min_filters = rate, strategy, importance, min_filters
        self.start, self.start_name = start, start_name or str(start)  # a pruned model's weights (None: surgery)
        self.criterion_facts: dict[str, Any] = {"importance": importance} if start is None else {}

    @property
    def ranks_filters(self) -> bool:
        return self.start is None

    @property
    def trained_start(self) -> bool:
        return self.start is not None

    def describe(self) -> str:
        floor = f" (no layer under {self.min_filters} filters)" if self.min_filters > 1 else ""
        if self.start is not None:
            return f"filter surgery's widths at rate {self.rate:g}{floor}, the weights of {self.start_name}"
        return f"filter surgery at rate {self.rate:g}{floor}, filters ranked by {self.importance} ({self.strategy})"

    def prune(self, base: keras.Model, importance: Importance | None) -> tuple[keras.Model, dict[str, Any]]:
        from fcnpose_tf.compression.prune import prune_model

        if self.start is not None:
            return self._from_start(base)
        start = time.perf_counter()
        pruned = prune_model(base, self.rate, strategy=self.strategy, importance=importance,
                             min_filters=self.min_filters)
        self.criterion_facts = importance.describe()
        return pruned, {"pruning": {**self.criterion_facts, "strategy": self.strategy,
                                    "min_filters": self.min_filters,
                                    "ranking_seconds": round(time.perf_counter() - start, 1)}}

    def _from_start(self, base: keras.Model) -> tuple[keras.Model, dict[str, Any]]:
        """The start model's weights in the network surgery would build from `base` (same widths, the base's input
        size); UserError when its widths are not surgery's."""
        from fcnpose_tf.compression.prune import prune_widths
        from fcnpose_tf.training.model import build_fcn_pose, conv_widths, load_model, view_of

        source = load_model(self.start)
        widths = (*prune_widths(base, self.rate, self.min_filters)[0], conv_widths(base)[-1])
        if conv_widths(source) != widths:
            floor = f" with no layer under {self.min_filters} filters" if self.min_filters > 1 else ""
            raise UserError(f"--start {self.start_name}: its widths {conv_widths(source)} are not filter surgery's at "
                            f"--rate {self.rate:g}{floor} on this model, {widths}")
        pruned = build_fcn_pose(widths[:-1], view_of(base), widths[-1])
        pruned.set_weights(source.get_weights())
        return pruned, {"pruning": {"start": self.start_name, "start_file": str(self.start),
                                    "min_filters": self.min_filters}}

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        fit_fn(pruned)

    def training_record(self) -> dict[str, Any]:
        start = {"start": self.start_name} if self.start is not None else {"strategy": self.strategy}
        return {"rate": self.rate, **start, "min_filters": self.min_filters, **self.criterion_facts}


class MagnitudePruning:
    """tfmot's unstructured pruning, zeroing as many weights as L1 surgery at `rate` removes."""

    name, tag = "magnitude", "m"
    ranks_filters = trained_start = False

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.sparsity = 0.0

    def describe(self) -> str:
        return f"magnitude at rate {self.rate:g}"

    def prune(self, base: keras.Model, importance: Importance | None) -> tuple[keras.Model, dict[str, Any]]:
        from fcnpose_tf.compression.prune import magnitude_prune, prune_model

        surgery = prune_model(base, self.rate)  # only its parameter count: the same reduction as filter surgery
        self.sparsity = 1.0 - model_facts(surgery)["params"] / model_facts(base)["params"]
        return magnitude_prune(base, self.sparsity), {"magnitude_sparsity": round(self.sparsity, 6)}

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        import tensorflow_model_optimization as tfmot

        from fcnpose_tf.compression.prune import magnitude_prune

        # the same masks as `prune` (computed from the base's weights), kept while fit retrains
        magnitude_prune(base, self.sparsity, train_fn=lambda wrapped, callbacks: fit_fn(
            wrapped, callbacks=callbacks, inference_model=tfmot.sparsity.keras.strip_pruning))

    def training_record(self) -> dict[str, Any]:
        return {"rate": self.rate, "method": self.name, "sparsity": round(self.sparsity, 6)}


PRUNED_GENERALIST = "generalist-p70"
"""The bundled pruned generalist (`bundled.BUNDLED_MODELS`): `--start auto`'s choice for a model fine-tuned from the
generalist, at the widths it has (filter surgery's at 0.7 with compress's default floor, no layer under 15 filters)."""


def pruned_start(options: CompressOptions, base_path: Path, base: keras.Model, floor: int,
                 log: Log = lambda line: None) -> tuple[str, Path | None]:
    """The run's pruned start, `options.start` with auto decided: (its name, the pruned model file it names; None
    for surgery). auto is PRUNED_GENERALIST when `base_path` is the generalist or was trained from it
    (`records.lineage`) on views that vary (its record's augmentation is online: `train`'s choice for such frames)
    and the bundled file has the widths filter surgery gives here (rate, floor); else surgery, which keeps PCK@0.5
    within 0.01 on fixed-camera models (docs/compression.md, "On your own model").
    An explicit start is resolved as a model argument (a file, or a bundled name); its widths are checked when it is
    loaded (`FilterPruning.prune`)."""
    from fcnpose_tf.bundled import BUNDLED_MODELS, KERAS_SUFFIXES, generalist_model, models_dir, resolve_model
    from fcnpose_tf.compression.prune import prune_widths
    from fcnpose_tf.records import lineage
    from fcnpose_tf.training.model import conv_widths, load_model

    start = options.start
    if options.method != "l1" or start == "surgery":
        return "surgery", None
    if start != "auto":
        return start, resolve_model(start, KERAS_SUFFIXES, say=log)
    generalist = generalist_model().resolve()
    ancestry = [str(base_path), *lineage(base_path)]
    if not any(name == "generalist" or (Path(name).is_file() and Path(name).resolve() == generalist)
               for name in ancestry):
        return "surgery", None
    record = training_record(base_path)
    if record is None or record.augment != "online":  # a fixed camera: the frames show the views it will see
        return "surgery", None
    path = models_dir() / BUNDLED_MODELS[PRUNED_GENERALIST][0]
    if not path.is_file():  # an installation without it
        log(f"  pruned start: surgery (the bundled {PRUNED_GENERALIST}, {path}, is missing)")
        return "surgery", None
    widths = (*prune_widths(base, options.rate, floor)[0], conv_widths(base)[-1])
    if conv_widths(load_model(path)) != widths:
        log(f"  pruned start: surgery ({PRUNED_GENERALIST}'s widths are not filter surgery's at rate {options.rate:g} "
            f"with no layer under {floor} filters, {widths})")
        return "surgery", None
    return PRUNED_GENERALIST, path


def pruning_method(options: CompressOptions, min_filters: int | None = None, start: Path | None = None) -> PruningMethod:
    """The pruning method `options.method` names; filter surgery keeps no layer under `min_filters` (default
    options.min_filters; `compress_model` passes the floor that fits the rate's parameter budget) and takes its
    weights from the pruned model `start` when one is given (`pruned_start`)."""
    if options.method == "magnitude":
        return MagnitudePruning(options.rate)
    floor = options.min_filters if min_filters is None else min_filters
    return FilterPruning(options.rate, options.strategy, options.importance, floor, start, options.start)


# ------------------------------------------------------------------------------------------
# The steps of a compression run, each returning its part of the report
# ------------------------------------------------------------------------------------------

@dataclass
class _Run:
    """What every step of one compression run reads."""

    base_path: Path
    base: keras.Model
    method: PruningMethod
    options: CompressOptions
    paths: dict[str, Path]
    train_dataset: Any
    eval_dataset: Any
    eval_indices: Sequence[int]
    force: bool
    reporter: Reporter
    recipe: str
    fit_data: Any = None
    """The retraining's training data (`data.dataset.fold_data`), kept for quantization-aware training."""

    @property
    def input_size(self) -> FrameView:
        """What the base model sees of a frame (its crop and input size): every step prepares frames this way."""
        from fcnpose_tf.training.model import view_of

        return view_of(self.base)

    def measure(self, predictor: Any, label: str, timing: bool = True) -> dict:
        """Metrics (and timing) of a predictor on the run's frames."""
        return _measure(predictor, self.eval_dataset, self.eval_indices, label, self.log, timing=timing)

    def log(self, line: str) -> None:
        """One progress line of the run (`reporter.say`)."""
        self.reporter.say(line)

    def keras_predictor(self, model: keras.Model, path: Path | None = None) -> KerasKeypointModel:
        """`model` as a predictor with the run's threads (`path`: its file, for the report)."""
        return KerasKeypointModel(model, path, num_threads=self.options.threads, centroid=self.options.centroid)


def measure_base(run: _Run) -> Step:
    """The unpruned model (the report's "base"): widths, parameters, MACs, file sizes, metrics and timing."""
    base_path = run.base_path
    keras_file = base_path if base_path.suffix == ".keras" else None
    return {**model_facts(run.base), **file_sizes(run.base, keras_file),
            **run.measure(run.keras_predictor(run.base, base_path), "the base model (Keras)")}


def retrain_fold(run: _Run) -> int | None:
    """The fold the run retrains on: --fold, else the base model's own (its record, same data), else the hold-out split."""
    if run.options.fold is not None:
        return run.options.fold
    record = training_record(run.base_path)
    if record is None:
        return None
    return record.fold if record.data_sha256 == file_sha256(run.train_dataset.via_path) else None


def importance_frames(run: _Run, fold: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(images, target maps) of `options.importance_frames` training frames (seeded choice from the
    retraining split's training frames, never the measured ones), unaugmented, as float32."""
    from fcnpose_tf.data.dataset import TrainingData

    candidates = _training_frames(run, fold)
    if not len(candidates):
        raise UserError(f"no training frames to score filters with in {run.train_dataset.via_path}")
    count = min(run.options.importance_frames, len(candidates))
    chosen = np.sort(np.random.default_rng(run.options.seed).choice(candidates, count, replace=False))
    return TrainingData(run.train_dataset, chosen, run.input_size, 0, run.options.seed).arrays()


def importance_step(run: _Run, fold: int | None) -> Importance:
    """The run's filter importance criterion, with its frames when it is data-aware."""
    from fcnpose_tf.compression.importance import DATA_AWARE, make_importance
    from fcnpose_tf.training.train import ground_truth_loss

    name = run.options.importance
    if name not in DATA_AWARE:
        return make_importance(name)
    run.log(f"  scoring filters by {name} on up to {run.options.importance_frames} training frames ...")
    images, maps = importance_frames(run, fold)
    return make_importance(name, images=images, maps=maps, loss=ground_truth_loss(run.options.positive_weight or 1.0),
                           batch_size=run.options.batch_size)


def prune_step(run: _Run, importance: Importance | None) -> tuple[keras.Model, dict[str, Any]]:
    """Prune with the run's method (filters ranked by `importance`; None when the method takes a pruned start's
    weights); measure the result before any retraining.
    The pruned model, and its report sections (`CompressReport` fields by name: the method's and
    pruned_before_retraining)."""
    from fcnpose_tf.training.model import with_view

    pruned, entries = run.method.prune(run.base, importance)
    pruned = with_view(pruned, run.input_size)  # the crop is part of the model: surgery keeps the base's
    entries["pruned_before_retraining"] = {**model_facts(pruned), **run.measure(
        run.keras_predictor(pruned), "the pruned model before retraining", timing=False)}
    return pruned, entries


def retrain_step(run: _Run, pruned: keras.Model) -> tuple[keras.Model, dict[str, Any]]:
    """Retrain the pruned model through `train.fit` (or only save it with 0 epochs); the saved model, and the
    report sections (`CompressReport` fields by name: retrain_data, distillation, retraining; none with 0 epochs)."""
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.fileio import atomic_path
    from fcnpose_tf.training.model import load_model, save_for_inference
    from fcnpose_tf.training.train import fit

    options, keras_path = run.options, run.paths["keras"]
    if options.retrain_epochs == 0:
        with atomic_path(keras_path, run.force) as tmp:
            save_for_inference(pruned, tmp)
        return pruned, {}
    data_sha256 = file_sha256(run.train_dataset.via_path)
    fold = retrain_fold(run)
    train_data, val_data = fold_data(run.train_dataset, fold, run.input_size, options.augment_copies, options.seed,
                                     options.augment, progress=run.reporter)
    run.fit_data = train_data
    entries: dict[str, Any] = {"retrain_data": {"data": str(run.train_dataset.via_path), "fold": fold,
                                                "train_samples": len(train_data), "val_frames": len(val_data)}}
    metadata = {"data": str(run.train_dataset.via_path), "data_sha256": data_sha256, "fold": fold,
                "pruned_from": str(run.base_path), **run.method.training_record(), "input_size": run.input_size.size_record,
                "view": run.input_size.to_json(),
                "recipe": run.recipe}
    sequence = train_data.sequence(options.batch_size, seed=options.seed)
    if options.distill > 0:
        from fcnpose_tf.training.distill import with_teacher_maps

        run.log(f"  distillation: the base model's maps weigh {options.distill:g} in the retraining loss")
        sequence, facts = with_teacher_maps(train_data, sequence, run.base, options.batch_size)
        entries["distillation"] = {"weight": options.distill, **facts}
        metadata["distillation"] = entries["distillation"]

    def fit_fn(model: keras.Model, callbacks: Sequence = (), inference_model: Callable | None = None) -> FitResult:
        result = fit(model, sequence, val_data.arrays(),
                     keras_path, options.fit_config(), force=run.force, reporter=run.reporter.lines(),
                     metadata=metadata, callbacks=callbacks, inference_model=inference_model, resumable=False,
                     start_is_candidate=run.method.trained_start)
        entries["retraining"] = retraining_report(result, _loss_name(model), options.positive_weight, options.distill)
        if run.method.trained_start:
            entries["retraining"]["start_kept"] = result.best_epoch == 0
            if result.best_epoch == 0:
                run.log("  no epoch beat the pruned start's validation loss: the start is kept, unchanged")
        return result

    run.method.retrain(run.base, pruned, fit_fn)
    return load_model(keras_path), entries


def retraining_report(result: FitResult, loss: str, positive_weight: float, distill: float = 0.0) -> dict[str, Any]:
    """The report's "retraining" part: epochs, best epoch and loss (validation: against the ground truth), time,
    loss function, positive and teacher weights, learning rates."""
    return {"epochs_run": result.epochs_run, "best_epoch": result.best_epoch, "best_val_loss": result.best_val_loss,
            "seconds": round(result.seconds, 1), "loss": loss, "positive_weight": positive_weight, "distill": distill,
            "learning_rates": [float(f"{h['lr']:.6g}") for h in result.history if "lr" in h]}


def measure_retrained(run: _Run, retrained: keras.Model) -> Step:
    """The retrained Keras model as saved (the report's "retrained"): widths, parameters, MACs, file sizes, metrics
    and timing."""
    keras_path = run.paths["keras"]
    return {**model_facts(retrained), **file_sizes(retrained, keras_path),
            **run.measure(run.keras_predictor(retrained, keras_path), "the retrained model (Keras)")}


def _training_frames(run: _Run, fold: int | None) -> np.ndarray:
    """Indices of the retraining split's training frames that are not evaluation frames."""
    train_indices, _ = run.train_dataset.split(fold)
    if run.train_dataset is run.eval_dataset:
        train_indices = np.setdiff1d(train_indices, np.asarray(run.eval_indices, dtype=np.int64))
    return np.asarray(train_indices, dtype=np.int64)


def _export_frames(run: _Run, quantize: str, fold: int | None) -> tuple[np.ndarray, np.ndarray | None]:
    from fcnpose_tf.compression.export import export_frames

    return export_frames(quantize, run.input_size, run.train_dataset, _training_frames(run, fold), run.eval_dataset,
                         run.eval_indices, run.options.calibration_frames, run.options.seed)


def export_step(run: _Run, retrained: keras.Model, quantize: str, fold: int | None) -> Any:
    """Write one TFLite file, verified against Keras on real frames (`export.export_frames`: the
    first evaluation frames; int8 calibrated on the retraining split's training frames); the export result.

    Raises:
        ExportVerificationError: the file failed its gate (nothing written).
    """
    from fcnpose_tf.compression.export import write_tflite

    samples, calibration = _export_frames(run, quantize, fold)
    return write_tflite(retrained, run.paths[tflite_key(quantize)], quantize, force=run.force,
                        sample_frames=samples, calibration_frames=calibration, num_threads=run.options.threads)


def qat_step(run: _Run, retrained: keras.Model, fold: int | None) -> Any:
    """Quantization-aware training from the retrained model on the retraining's training frames, until its int8
    file passes the same gate against the retrained model (`fcnpose_tf.compression.qat`); the file is written when one
    passes. Returns the `qat.QATResult` (its export None when every epoch's file was refused)."""
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.compression.export import export_tflite
    from fcnpose_tf.fileio import write_bytes
    from fcnpose_tf.compression.qat import train_until_gate

    options = run.options
    if run.fit_data is None:  # not retrained in this run (--retrain-epochs 0): the same split's frames
        run.fit_data, _ = fold_data(run.train_dataset, fold, run.input_size, options.augment_copies, options.seed,
                                    options.augment, progress=run.reporter)
    samples, calibration = _export_frames(run, "int8", fold)

    def convert(qat_model: keras.Model) -> Any:
        return export_tflite(qat_model, "int8", sample_frames=samples, calibration_frames=calibration,
                             num_threads=options.threads, fold_upsampling=False, reference=retrained)

    sequence = run.fit_data.sequence(options.batch_size, seed=options.seed)
    result = train_until_gate(retrained, sequence, calibration, convert, epochs=options.qat_epochs,
                              learning_rate=options.qat_learning_rate, seed=options.seed,
                              reporter=run.reporter)
    if result.export is not None:
        write_bytes(run.paths[tflite_key("int8")], result.export.data, run.force)
    return result


def measure_quantized(run: _Run, export: Any, retrained_facts: Step, qat: dict[str, Any] | None = None) -> Step:
    """One TFLite file: its format, how it was quantized, size (plain and gzip), export facts, operators, metrics and
    timing (`qat`: the quantization-aware training that made it, with the post-training refusal it replaced)."""
    from fcnpose_tf.compression.export import inspect_tflite
    from fcnpose_tf.runtime.estimator import KeypointModel

    path = run.paths[tflite_key(export.quantize)]
    tflite_info = inspect_tflite(path)
    tfl = KeypointModel(path, num_threads=run.options.threads, centroid=run.options.centroid)
    return {"quantize": export.quantize, "status": "written",
            "quantization": "quantization-aware training" if qat else "post-training",
            **({"qat": qat} if qat else {}),
            "params": retrained_facts["params"], "macs": retrained_facts["macs"], "flops": retrained_facts["flops"],
            "tflite_size_bytes": export.size_bytes, "tflite_gzip_size_bytes": len(gzip.compress(export.data, 9)),
            "export": export.to_dict(), "tflite_ops": tflite_info.get("op_counts", tflite_info.get("ops")),
            **run.measure(tfl, f"the {export.quantize} TFLite model")}


def compress_model(base_path: str | os.PathLike, train_dataset: Any, eval_dataset: Any, eval_indices: Sequence[int],
                   out_dir: str | os.PathLike, options: CompressOptions, *, force: bool = False,
                   eval_description: str = "", reporter: Reporter | None = None,
                   metadata: dict[str, Any] | None = None) -> CompressReport:
    """Prune, retrain, export and measure one model at one rate; write the files; return the report.

    Args:
        base_path: the unpruned (or any) .keras/.h5 FCN-Pose.
        train_dataset: dataset to retrain on (its hold-out split, or `options.fold`).
        eval_dataset, eval_indices: the frames every step is measured on.
        out_dir: where NAME_p70.keras, NAME_p70_fp16.tflite (one file per `options.quantize` format) and
            NAME_p70_report.json go.
        options: rate, method, strategy, quantize, calibration frames, retraining settings, threads (those left
            None chosen by `CompressOptions.resolved` for `base_path`; the report's "options" holds the values used).
        force: replace existing output files.
        reporter: where the step lines and progress go (`fcnpose_tf.progress`; default: the current one): data
            preparation's progress, then the retraining one line per epoch; nothing when silent.
        metadata: more facts for the report (e.g. the command's "preset"), top-level keys of its file.
    Returns:
        The `CompressReport` (its `to_json()` written as NAME_pXX_report.json). Its `quantized` is the
        first TFLite file written (the paper's float16 by default; None if every format was refused),
        `other_quantized` the other files written, `refused` the formats whose file failed its gate
        (`RefusedFormat`: reason, the gate's facts, quantization-aware training's when it was tried). A
        refused format writes no file and does not end the run; `files` names the files written.
    Raises:
        UserError: bad options, existing outputs without force, unwritable folder, or a model whose
            maps do not match the dataset.
        ValueError: `metadata` names a section of the report.
    """
    from fcnpose_tf.training.model import at_input_size, load_model, view_of
    from fcnpose_tf.compression.prune import prune_plan, prune_widths

    base_path = Path(base_path)
    options = options.resolved(base_path)
    options.validate()
    _check_metadata(metadata)
    start = time.perf_counter()
    reporter = progress.resolve(reporter)
    say = reporter.say
    names = output_names(base_path.stem, options)
    paths = {k: Path(out_dir) / v for k, v in names.items() if k != "stem"}
    base = load_model(base_path)
    if base.output_shape[-1] != train_dataset.schema.num_maps:
        raise UserError(f"{base_path}: {base.output_shape[-1]} output maps, but the data's schema needs "
                        f"{train_dataset.schema.num_maps}")
    prune_plan(base, options.rate, strategy=options.strategy)  # a model that is not a plain chain fails here, first
    saved_view = view_of(base)
    if options.input_size:  # the height; an H x W input keeps its aspect
        width = max(32, int(round(options.input_size * saved_view.width / saved_view.height / 32)) * 32)
        base = at_input_size(base, (options.input_size, width))
    floor = prune_widths(base, options.rate, options.min_filters)[1] if options.method == "l1" else 0
    check_outputs(base_path, out_dir, options, force)
    start_name, start_path = pruned_start(options, base_path, base, floor, say)
    options = replace(options, start=start_name)
    run = _Run(base_path, base, pruning_method(options, floor, start_path), options, paths, train_dataset,
               eval_dataset, eval_indices, force, reporter, options.recipe(floor))
    steps = 4 + 2 * len(options.quantize)
    resized = f", rebuilt from its {saved_view.height}x{saved_view.width}" if saved_view != run.input_size else ""
    say(f"[1/{steps}] base model {base_path} ({run.input_size.describe(whole='')}{resized})")
    if floor < options.min_filters:
        say(f"  --min-filters {options.min_filters} does not fit the parameter budget of rate {options.rate:g}: "
            f"no layer under {floor} filters")
    base_step = measure_base(run)
    say(f"[2/{steps}] pruning: {run.method.describe()}")
    importance = importance_step(run, retrain_fold(run)) if run.method.ranks_filters else None
    pruned, pruned_sections = prune_step(run, importance)
    say(f"[3/{steps}] retraining: up to {options.retrain_epochs} epochs")
    retrained, retrained_sections = retrain_step(run, pruned)
    say(f"[4/{steps}] measuring the retrained Keras model")
    retrained_step = measure_retrained(run, retrained)
    fold = retrained_sections["retrain_data"]["fold"] if "retrain_data" in retrained_sections else options.fold
    files: list[Step] = []
    refused: list[RefusedFormat] = []
    for i, quantize in enumerate(options.quantize):
        say(f"[{5 + 2 * i}/{steps}] exporting {quantize} TFLite (verified against Keras)")
        export, qat = _export_or_refusal(run, retrained, quantize, fold, refused)
        if export is None:
            _remove_stale(run, quantize)
            continue
        say(f"[{6 + 2 * i}/{steps}] measuring the {quantize} TFLite model")
        files.append(measure_quantized(run, export, retrained_step, qat))
    written = {tflite_key(f["quantize"]) for f in files}
    report = CompressReport(
        base_model=str(base_path), method=options.method, recipe=run.recipe, options=asdict(options),
        evaluation_frames=eval_description or f"{len(eval_indices)} frames of {eval_dataset.via_path}",
        pck_normalisation="max(w, h) of the ground-truth keypoints' bounding box", threads=options.threads,
        metadata=dict(metadata or {}), base=base_step, **pruned_sections, **retrained_sections,
        retrained=retrained_step,
        # the first file written (the paper's float16 by default), None when every format was refused
        quantized=files[0] if files else None, other_quantized=files[1:], refused=refused,
        files={k: str(v) for k, v in paths.items() if not k.startswith("tflite_") or k in written},
        seconds=round(time.perf_counter() - start, 1))
    write_json(paths["report"], report.to_json(), force=force)
    return report


def _export_or_refusal(run: _Run, retrained: keras.Model, quantize: str, fold: int | None,
                       refused: list[RefusedFormat]) -> tuple[Any, dict[str, Any] | None]:
    """(the written export, the QAT facts if QAT made it), or (None, None) with the refusal appended to `refused`.

    A format refused by its gate is a row of the report, not the end of the run. Post-training int8 refused
    falls back to quantization-aware training (`options.qat_epochs` > 0)."""
    from fcnpose_tf.compression.export import FULL_INTEGER, ExportVerificationError

    try:
        return export_step(run, retrained, quantize, fold), None
    except ExportVerificationError as exc:
        ptq = {"reason": exc.reason, **exc.facts}
    run.log(f"  {quantize} refused by its gate: {ptq['reason']}")
    reason, qat = ptq["reason"], None
    if quantize == FULL_INTEGER and run.options.qat_epochs > 0:
        run.log(f"  post-training int8 refused: quantization-aware training (tfmot), up to {run.options.qat_epochs} "
                f"epoch(s) from the retrained model on the same training frames, the gate after each")
        result = qat_step(run, retrained, fold)
        qat = {**result.to_dict(), "learning_rate": run.options.qat_learning_rate, "post_training_refused": ptq}
        if result.export is not None:
            run.log(f"  quantization-aware int8 passes the gate after {result.epochs_run} epoch(s), "
                    f"{result.seconds / 60:.1f} min")
            return result.export, qat
        reason = f"after {result.epochs_run} epoch(s) of quantization-aware training: {result.reason}"
        run.log(f"  quantization-aware int8 refused too ({result.seconds / 60:.1f} min): {result.reason}")
    refused.append(RefusedFormat(quantize, reason, post_training=ptq, qat=qat))
    return None, None


def _remove_stale(run: _Run, quantize: str) -> None:
    """With --force, an earlier run's file of a format this run refused goes: it is not this model's."""
    path = run.paths[tflite_key(quantize)]
    if run.force and path.is_file():
        path.unlink()
        run.log(f"  removed {path}: an earlier file of the format this run refused")


def _loss_name(model: Any) -> str:
    """The compiled loss's name: binary_crossentropy (plain BCE) or keypoint_bce (weighted)."""
    loss = getattr(model, "loss", None)
    return str(getattr(loss, "name", loss))


PCK_DROP_BUDGET = 0.02
"""PCK@0.5 a compressed file may lose against the unpruned model on the measured frames: the paper's files stay
within it at the rates it ships, and so do the bundled 70 % files and three fixed-camera users' (docs/compression.md,
"On your own model"). Beyond it `accuracy_note` says so."""
VARIED_VIEWS_RATE = 0.5
"""The rate that kept PCK@0.5 within PCK_DROP_BUDGET on both views-that-vary models measured, where 0.7 did not
(docs/compression.md, "Views that vary: a lower rate")."""


def accuracy_note(report: CompressReport) -> str | None:
    """One line when the most accurate file written lost more than PCK_DROP_BUDGET of the unpruned model's PCK@0.5
    on the measured frames (None otherwise, and when no file was written): how much, and what to try."""
    if not report.tflite_files:
        return None
    base = report.base["metrics"]["pck@0.5_bbox"]
    best = max(report.tflite_files, key=lambda step: step["metrics"]["pck@0.5_bbox"])
    drop = base - best["metrics"]["pck@0.5_bbox"]
    if drop <= PCK_DROP_BUDGET:
        return None
    rate = report.options["rate"]
    advice = (f"a lower --rate keeps more of it: on views that vary --rate {VARIED_VIEWS_RATE:g} held within "
              f"{PCK_DROP_BUDGET:g} where 0.7 did not (docs/compression.md, \"Views that vary: a lower rate\")"
              if rate > VARIED_VIEWS_RATE else "a lower --rate keeps more of it")
    return (f"note: PCK@0.5 {best['metrics']['pck@0.5_bbox']:.3f} ({best['quantize']}) is {drop:.3f} below the "
            f"unpruned model's {base:.3f} on these frames, more than the {PCK_DROP_BUDGET:g} the paper's files lose; "
            f"{advice}")


def report_table(report: CompressReport | dict[str, Any], markdown: bool = False) -> str:
    """The compression report as a table: the unpruned model beside each step of the compressed one.

    `report`: `compress_model`'s, or a NAME_pXX_report.json as parsed (read by `CompressReport.from_json`).
    Sizes are of the file each row's model ships as (.h5 for Keras, .tflite), in KB (1000 bytes);
    "infer ms" is the forward pass alone, FPS the whole frame (preprocess, inference, keypoints).
    """
    from fcnpose_tf.tables import format_table

    def row(label: str, step: Step, size_key: str) -> list:
        m = step["metrics"]
        t = step.get("timing")
        size = step.get(size_key) if size_key else None
        return [label, step["params"], step["macs"] / 1e6, size / 1e3 if size else None,
                m["pck@0.5_bbox"], m["pck@0.2_bbox"], m["pck@0.05_bbox"], m["epe_px"],
                t["inference_ms"]["mean"] if t else None, t["fps"] if t else None]

    if not isinstance(report, CompressReport):
        report = CompressReport.from_json(report)
    rows = [row("unpruned (Keras, .h5)", report.base, "h5_size_bytes"),
            row("pruned, before retraining", report.pruned_before_retraining, ""),
            row("pruned + retrained (Keras, .h5)", report.retrained, "h5_size_bytes")]
    # (reports written before one file per format hold options.quantize as one name and no step["quantize"])
    quantize = report.options["quantize"]
    order = list(quantize) if isinstance(quantize, (list, tuple)) else []
    entries: list[tuple[Any, Step | RefusedFormat]] = [(step.get("quantize") or quantize, step)
                                                       for step in report.tflite_files]
    entries += [(entry.quantize, entry) for entry in report.refused]
    entries.sort(key=lambda entry: order.index(entry[0]) if entry[0] in order else len(order))
    for name, entry in entries:
        if isinstance(entry, RefusedFormat):
            rows.append([f"{name} TFLite: REFUSED (gate)"] + [None] * 9)
        else:
            qat = " QAT" if entry.get("quantization") == "quantization-aware training" else ""
            rows.append(row(f"{name}{qat} TFLite (.tflite)", entry, "tflite_size_bytes"))
    return format_table(["model", "params", "MMACs", "size KB", "PCK@0.5", "PCK@0.2", "PCK@0.05", "EPE px",
                         "infer ms", "FPS e2e"], rows, markdown=markdown,
                        digits=[None, None, 1, 1, 3, 3, 3, 2, 2, 1])
