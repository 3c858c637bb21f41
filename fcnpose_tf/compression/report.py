"""What a compression run measured and wrote: `CompressReport` (NAME_pXX_report.json) and its steps; what it says to
a reader (its table, the accuracy note): `fcnpose_tf.compression.summary`; what a model costs, the facts a step starts
from: `fcnpose_tf.compression.costs`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any

from fcnpose_tf.compression.verify import ParityReport
from fcnpose_tf.measurements import KeypointMetrics, Measurement, Timing

if TYPE_CHECKING:
    from fcnpose_tf.compression.costs import ModelFacts
    from fcnpose_tf.compression.qat import QATResult


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
    qat: QATFacts | None = None
    """Quantization-aware training's facts, when it was tried (int8 with --qat-epochs above 0)."""

    def to_json(self) -> dict[str, Any]:
        """The entry as the report's "refused" list holds it.

        Returns:
            {"quantize", "status": "refused", "reason", "post_training"[, "qat" when tried]}.
        """
        return {"quantize": self.quantize, "status": "refused", "reason": self.reason,
                "post_training": self.post_training,
                **({"qat": self.qat.to_json()} if self.qat is not None else {})}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> RefusedFormat:
        """The entry of a parsed report's "refused" list.

        Args:
            entry: the parsed JSON object.
        Returns:
            The refused format.
        Raises:
            KeyError: no "quantize" or "reason".
        """
        return cls(quantize=entry["quantize"], reason=entry["reason"],
                   post_training=entry.get("post_training") or {},
                   qat=QATFacts.from_json(entry["qat"]) if entry.get("qat") is not None else None)


def _if_any() -> Any:
    """A section only some runs have: None when the run has none, and then not written."""
    return field(default=None, metadata={"if_any": True})


def _fields_json(section: Any) -> dict[str, Any]:
    """A section as the report holds it: its fields in order (a measurement by its `to_json`), a field only some
    sections have left out when None, then the keys a file held without a field (`extra`)."""
    out: dict[str, Any] = {}
    for f in fields(section):
        value = getattr(section, f.name)
        if f.name == "extra":
            out.update(value)
        elif value is None and f.metadata.get("if_any"):
            continue
        else:
            out[f.name] = value.to_json() if isinstance(value, (KeypointMetrics, Timing, QATFacts)) else value
    return out


def _known(cls: type, entry: dict[str, Any]) -> dict[str, Any]:
    """The keys of a parsed section that are fields of `cls`; TypeError if it is no JSON object."""
    if not isinstance(entry, dict):
        raise TypeError(f"a report's {cls.__name__} is a JSON object, not {type(entry).__name__}")
    names = {f.name for f in fields(cls)} - {"extra"}
    return {k: v for k, v in entry.items() if k in names}


def _unknown(cls: type, entry: dict[str, Any]) -> dict[str, Any]:
    """The keys of a parsed section without a field of `cls` (kept, and written back)."""
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in entry.items() if k not in names}


class _Section:
    """A part of the report read and written field by field: a field a file did not hold is None (or its default)
    and not written back when it is marked `_if_any`, a key without a field is kept in `extra`."""

    def to_json(self) -> dict[str, Any]:
        """The part as the report holds it.

        Returns:
            Its fields in order (metrics, timing and QAT facts by their `to_json`), those it does not have (`_if_any`)
            left out, then `extra`'s keys.
        """
        return _fields_json(self)

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> Any:
        """The part of a parsed report.

        Args:
            entry: the parsed JSON object; a key without a field goes to `extra`.
        Returns:
            The part, of this class.
        Raises:
            TypeError: not a JSON object.
        """
        return cls(**_known(cls, entry), extra=_unknown(cls, entry))


@dataclass(frozen=True, kw_only=True)
class QATFacts(_Section):
    """Quantization-aware training as a report records it (`TFLiteStep.qat` when it made the file, `RefusedFormat.qat`
    when its files were refused too): written as {"passed", "epochs_run", "seconds", "minutes", "epochs"[, "reason"],
    "learning_rate", "post_training_refused"}. A field a file did not hold is None and not written back; a key without
    a field is kept in `extra`."""

    passed: bool | None = _if_any()
    """Whether an epoch's int8 file passed the gate."""
    epochs_run: int | None = _if_any()
    """Epochs trained (0: the calibrated copy passed before any training)."""
    seconds: float | None = _if_any()
    """Training plus the per-epoch conversions and gates, rounded to 0.1 s."""
    minutes: float | None = _if_any()
    """The same time in minutes, rounded to 0.01."""
    epochs: list[dict[str, Any]] | None = _if_any()
    """Per epoch: {"epoch", "loss", "passed", "reason" (the gate's, when refused), "max_abs_diff", ...the gate's
    facts} (`qat.QATResult.epochs`)."""
    reason: str | None = _if_any()
    """The last refusal's reason when no epoch passed."""
    learning_rate: float | None = _if_any()
    post_training_refused: dict[str, Any] | None = _if_any()
    """The post-training file's gate that sent the run to quantization-aware training: its "reason" and the facts it
    measured."""
    extra: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, result: QATResult, learning_rate: float, post_training_refused: dict[str, Any]) -> QATFacts:
        """The facts of one quantization-aware training.

        Args:
            result: what `qat.train_until_gate` returned.
            learning_rate: its learning rate.
            post_training_refused: the refused post-training file's gate (reason and facts).
        Returns:
            The facts (`QATResult.to_dict`'s, and these two).
        """
        return cls(**result.to_dict(), learning_rate=learning_rate, post_training_refused=post_training_refused)


def _step_from_json(cls: type, entry: dict[str, Any]) -> Any:
    """The step of a parsed report entry: "metrics", "timing" (and a file's "qat") typed, a key without a field kept
    in `extra`."""
    values = _known(cls, entry)
    values["metrics"] = KeypointMetrics.from_json(entry["metrics"])
    values["timing"] = Timing.from_json(entry["timing"]) if entry.get("timing") else None
    if values.get("qat") is not None:
        values["qat"] = QATFacts.from_json(values["qat"])
    return cls(**values, extra=_unknown(cls, entry))


@dataclass(frozen=True, kw_only=True)
class ModelStep(_Section):
    """A Keras model of the report, measured (base, pruned_before_retraining, retrained): its facts, its file sizes
    (none for the pruned model before retraining), its metrics and timing (none before retraining). A key a file
    held without a field is kept in `extra` and written back."""

    widths: list[int] | None = _if_any()
    params: int
    macs: int
    flops: int | None = _if_any()
    nonzero_weights: int | None = _if_any()
    h5_size_bytes: int | None = _if_any()
    """The .h5 without optimizer state (the paper's size)."""
    h5_gzip_size_bytes: int | None = _if_any()
    keras_size_bytes: int | None = _if_any()
    metrics: KeypointMetrics
    timing: Timing | None = _if_any()
    extra: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, facts: ModelFacts, measurement: Measurement, sizes: dict[str, int] | None = None) -> ModelStep:
        """A model's step, measured.

        Args:
            facts: what the model costs (`costs.model_facts`).
            measurement: its metrics and timing (timing None: not timed).
            sizes: its `costs.file_sizes` (None: no file, as before retraining).
        Returns:
            The step.
        """
        return cls(**asdict(facts), **(sizes or {}), metrics=measurement.metrics, timing=measurement.timing)

    @property
    def measurement(self) -> Measurement:
        """Metrics and timing."""
        return Measurement(self.metrics, self.timing)

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> ModelStep:
        """The step of a parsed report entry (base, pruned_before_retraining, retrained).

        Args:
            entry: the parsed JSON object; a key without a field goes to `extra`.
        Returns:
            The step, its metrics and timing typed.
        Raises:
            TypeError: not a JSON object.
            KeyError: no "metrics".
        """
        return _step_from_json(cls, entry)


@dataclass(frozen=True, kw_only=True)
class TFLiteStep(_Section):
    """A TFLite file of the report, measured ("quantized", "other_quantized"): its format and how it was made, its
    cost and size, the export's facts, operators, metrics and timing. Reports written before one file per format
    hold no quantize, status nor quantization (None, not written back). A key a file held without a field is kept in
    `extra` and written back."""

    quantize: str | None = _if_any()
    """The format (float16, int8, ...)."""
    status: str | None = _if_any()
    """"written"."""
    quantization: str | None = _if_any()
    """"post-training" or "quantization-aware training"."""
    qat: QATFacts | None = _if_any()
    """Quantization-aware training's facts when it made the file (with the post-training refusal it replaced)."""
    params: int
    macs: int
    flops: int | None = _if_any()
    tflite_size_bytes: int | None = _if_any()
    tflite_gzip_size_bytes: int | None = _if_any()
    export: dict[str, Any] | None = _if_any()
    """The export's facts as written (`TFLiteExport.to_dict`: sizes, seconds, parity, graph rewrites, calibration)."""
    tflite_ops: Any = _if_any()
    """Operator counts by name."""
    metrics: KeypointMetrics
    timing: Timing | None = _if_any()
    extra: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def parity(self) -> ParityReport | None:
        """The export's comparison with Keras, None if not recorded."""
        parity = (self.export or {}).get("parity")
        return ParityReport.from_dict(parity) if parity is not None else None

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> TFLiteStep:
        """The step of a parsed "quantized" or "other_quantized" entry; its argument, result and errors are
        `ModelStep.from_json`'s."""
        return _step_from_json(cls, entry)


Step = ModelStep | TFLiteStep
"""One measured step of the report."""


@dataclass(frozen=True, kw_only=True)
class Retraining(_Section):
    """How the retraining of the pruned model went (the report's "retraining", `compress.retraining_report`). A key a
    file held without a field is kept in `extra` and written back."""

    epochs_run: int | None = None
    """Epochs trained (early stopping or the time budget may end it before the epochs asked)."""
    best_epoch: int | None = None
    """The epoch whose model was kept (0: the start)."""
    best_val_loss: float | None = None
    """The kept epoch's validation loss (against the ground truth): the lowest when the loss chose it."""
    seconds: float | None = None
    """Wall time of the retraining, rounded to 0.1 s."""
    loss: str | None = None
    """The compiled loss's name: binary_crossentropy (plain BCE), keypoint_bce (weighted) or distillation."""
    positive_weight: float | None = None
    distill: float | None = None
    """The teacher's weight in the loss (0: no distillation)."""
    learning_rates: list[float] = field(default_factory=list)
    """The learning rate of every epoch."""
    start_kept: bool | None = _if_any()
    """A pruned start's run: True when no epoch beat the start, which is then kept unchanged."""
    stopped_by_time_budget: bool | None = _if_any()
    """Whether the time budget (`--max-minutes`, `--total-minutes`) ended the retraining before its epochs and early
    stopping did (reports before it: not known)."""
    kept_by: str | None = _if_any()
    """What chose the kept epoch (`--keep-best`): "keypoints" or "loss" (reports before it: the loss)."""
    best_val_keypoints: dict[str, Any] | None = _if_any()
    """The kept epoch's validation keypoints when they chose it (`train.KeptScore`: mean_pck, pck_fine, epe_px)."""
    extra: dict[str, Any] = field(default_factory=dict, repr=False)


@dataclass(frozen=True)
class PruningSections:
    """What a pruning method adds to the report (`PruningMethod.prune`): filter surgery its "pruning" (criterion and
    its facts, strategy, min_filters, ranking_seconds; or a pruned start's name and file), magnitude pruning its
    "magnitude_sparsity"."""

    pruning: dict[str, Any] | None = None
    magnitude_sparsity: float | None = None


@dataclass(frozen=True)
class RetrainSections:
    """What the retraining adds to the report (`steps.retrain_step`); all None when not retrained."""

    retrain_data: dict[str, Any] | None = None
    """What it trained on: data, fold, train_samples, val_frames."""
    distillation: dict[str, Any] | None = None
    """The base model as a teacher: weight and its facts (None: --distill 0)."""
    retraining: Retraining | None = None
    polish: Retraining | None = None
    """After a retraining with frames added, the one on the user's frames alone
    (`options.CompressOptions.polish_config`); None: none."""


@dataclass(frozen=True, kw_only=True)
class CompressReport:
    """What `compress_model` measured and wrote: one field per top-level key of NAME_pXX_report.json, in the
    file's order (`to_json`). A measured step is a `ModelStep` or a `TFLiteStep`; a refused format is a `RefusedFormat`.
    A section only some runs have (pruning, magnitude_sparsity, retrain_data, distillation, retraining, polish) is None
    when the run has none and is then not written; "quantized" is written either way (null: every format refused)."""

    base_model: str
    """The model that was compressed, its file as given."""
    method: str
    """The pruning method: l1 (filter surgery, whatever the criterion) or magnitude."""
    recipe: str
    """One line naming how the file was made (`methods.PruningMethod.recipe`); "" read back from a report older than
    it."""
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
    base: ModelStep
    """The unpruned model (Keras)."""
    pruning: dict[str, Any] | None = _if_any()
    """Filter surgery's criterion and its facts, strategy, min_filters (the floor used), ranking_seconds."""
    magnitude_sparsity: float | None = _if_any()
    """Magnitude pruning's fraction of zeroed weights (the parameter reduction of filter surgery at the rate)."""
    pruned_before_retraining: ModelStep
    """The pruned model before any retraining (Keras, no timing)."""
    retrain_data: dict[str, Any] | None = _if_any()
    """What the retraining trained on: data, fold, train_samples, val_frames (None: not retrained)."""
    distillation: dict[str, Any] | None = _if_any()
    """The base model as a teacher while retraining: weight and its facts (None: --distill 0)."""
    retraining: Retraining | None = _if_any()
    """How the retraining went (`retraining_report`); None: not retrained."""
    polish: Retraining | None = _if_any()
    """After a retraining with frames added (`compress --more-frames`), how the retraining on the user's frames alone
    went (`--polish-minutes`); None: none."""
    retrained: ModelStep
    """The retrained model as saved (Keras, NAME_pXX.keras)."""
    quantized: TFLiteStep | None
    """The first TFLite file written (the paper's float16 by default); None when every format was refused."""
    other_quantized: list[TFLiteStep] = field(default_factory=list)
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
    def tflite_files(self) -> list[TFLiteStep]:
        """The TFLite files written: "quantized" first, then "other_quantized"."""
        return [step for step in [self.quantized, *self.other_quantized] if step is not None]

    @property
    def added_frames(self) -> dict[str, Any] | None:
        """The frames `compress --more-frames` added to the retraining (`data.dataset.AddedFrames.to_json`), or None."""
        return (self.retrain_data or {}).get("added_frames")

    def to_json(self) -> dict[str, Any]:
        """The report as NAME_pXX_report.json holds it: the fields in order, `metadata`'s keys in its place, a
        section only some runs have left out when None.

        Returns:
            NAME_pXX_report.json's object: its sections in order, the metadata's keys among them.
        """
        report: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "metadata":
                report.update(value)
            elif f.name in ("refused", "other_quantized"):
                report[f.name] = [entry.to_json() for entry in value]
            elif isinstance(value, (ModelStep, TFLiteStep, Retraining)):
                report[f.name] = value.to_json()
            elif value is not None or not f.metadata.get("if_any"):
                report[f.name] = value
        return report

    @classmethod
    def from_json(cls, report: dict[str, Any]) -> CompressReport:
        """The report of a parsed NAME_pXX_report.json (to read a written one back, e.g. for its table). Keys that
        reports held before "recipe", "other_quantized" and "refused" existed read as "", [] and [] (one file,
        and a refused format ended those runs); a key without a field goes to `metadata`.

        Args:
            report: the parsed JSON object.
        Returns:
            The report; `to_json()` gives back every key it was read from.
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
        for name in ("retraining", "polish"):
            if values.get(name) is not None:
                values[name] = Retraining.from_json(values[name])
        for name in ("base", "pruned_before_retraining", "retrained"):
            values[name] = ModelStep.from_json(values[name])
        if values.get("quantized") is not None:
            values["quantized"] = TFLiteStep.from_json(values["quantized"])
        values["other_quantized"] = [TFLiteStep.from_json(step) for step in values.get("other_quantized") or []]
        values["refused"] = [RefusedFormat.from_json(entry) for entry in values.get("refused") or []]
        return cls(**values, metadata={k: v for k, v in report.items() if k not in names})


def _check_metadata(metadata: dict[str, Any] | None) -> None:
    """ValueError if a key of a report's further facts is one of its sections (it would overwrite it)."""
    clash = sorted(set(metadata or {}) & {f.name for f in fields(CompressReport)})
    if clash:
        raise ValueError(f"report metadata cannot hold {', '.join(clash)}: a section of the report")
