"""The units of a sweep, run the same way by every executor.

Two kinds of job, both identified by name:

    fold{K}_base   train fold K's unpruned model on the fold's training frames (or reuse
                   models/base_fold{K}.keras), measure it (Keras) on the fold's validation frames
    fold{K}_p{RR}  compress that model at rate RR% with `compress_model`: L1 filter pruning,
                   retraining, verified float16 TFLite export, Keras and TFLite measured on the
                   same validation frames (p00: the unpruned model exported, not retrained)

A job writes its model files under OUT/models/ and then, as its very last step, its record
OUT/jobs/NAME.json (atomically). A record on disk therefore means the job is finished; anything
else a job left behind (a half-trained checkpoint, a partial export) is redone or resumed on
the next run. `run_job` is a plain module-level function taking only picklable arguments, so a
local process pool and Ray can both ship it. Nothing here imports TensorFlow at module level.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Required, TypedDict

from fcnpose_tf import settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.progress import Reporter
from fcnpose_tf.records import MachineInfo, file_sha256, library_versions, machine_info, training_record
from fcnpose_tf.sweep.rates import DEFAULT_RATES_SPEC, parse_rates, rate_label, rate_percent, rate_tag

if TYPE_CHECKING:
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.training.train import FitConfig

RECORD_VERSION = 1
JOBS_DIR = "jobs"
MODELS_DIR = "models"

class ConfigKey(TypedDict, total=False):
    """The settings that change a job's results (KEY_FIELDS), as a job record's "config_key" holds them. A key a
    record predates is missing (`normalize_key` fills it in); a job that does not retrain has no retraining fields
    (`job_key`)."""

    data_sha256: str
    splits_sha256: str
    folds: int
    input_size: int
    epochs: int
    patience: int
    retrain_epochs: int
    retrain_patience: int
    batch_size: int
    learning_rate: float
    lr_patience: int
    positive_weight: float
    augment_copies: int
    seed: int
    threads: int
    importance: str
    importance_frames: int
    distill: float
    min_filters: int
    lr_schedule: str
    freeze: int
    max_minutes: float | None
    centroid: str


KEY_FIELDS = tuple(ConfigKey.__annotations__)
"""Settings that change a job's results: a results folder holds jobs of one value of each."""

KEY_DEFAULTS = {"lr_patience": 0, "importance": "l1", "importance_frames": settings.IMPORTANCE_FRAMES.default,
                "distill": 0.0, "min_filters": 0, "lr_schedule": "plateau", "freeze": 0, "max_minutes": None,
                "centroid": "plain"}
"""Key fields added after results folders existed, with the value older folders were made with."""

RETRAINING_FIELDS = ("retrain_epochs", "retrain_patience", "importance", "importance_frames", "distill", "min_filters",
                     "freeze")
"""Key fields that only matter to jobs that retrain (a rate above 0): a base job or the unpruned export
keeps its record when they change."""


def normalize_key(key: ConfigKey | None) -> ConfigKey | None:
    """A stored config key with the fields it predates filled in (so older folders still match)."""
    if not isinstance(key, dict):
        return key
    return {**{name: value for name, value in KEY_DEFAULTS.items() if name not in key}, **key}


def retrain_epochs_at(rate: float | None, default: int, by_rate: Any = ()) -> int:
    """The retraining budget of `rate`: its entry in `by_rate` ((rate, epochs) pairs), else `default`."""
    for r, epochs in by_rate or ():
        if rate is not None and rate_percent(float(r)) == rate_percent(rate):
            return int(epochs)
    return int(default)


def job_key(key: ConfigKey, rate: float | None, by_rate: Any = ()) -> ConfigKey:
    """What a job of `rate` (None: base job) must have been run with, from the sweep's `key`.

    The retraining budget is the rate's own (`by_rate` overrides the default); jobs that do not
    retrain (base, rate 0) leave the retraining fields out, so changing them keeps those jobs.
    """
    key = ConfigKey(**normalize_key(key))
    if rate is None or rate_percent(rate) == 0:
        for name in RETRAINING_FIELDS:
            key.pop(name, None)
    else:
        key["retrain_epochs"] = retrain_epochs_at(rate, key["retrain_epochs"], by_rate)
    return key


def record_matches(record: JobRecord | None, key: ConfigKey, by_rate: Any = ()) -> bool:
    """Whether a job record was made with the settings `key` (+ per-rate budgets) asks of its job."""
    if not isinstance(record, dict) or not isinstance(record.get("config_key"), dict):
        return False
    rate = None if record.get("kind") == "base" else float(record["rate"])
    # job_key of the stored key keeps its own budget and drops what the job does not depend on
    return job_key(record["config_key"], rate) == job_key(key, rate, by_rate)


SWEEP_FIXED = ("method", "strategy", "quantize", "calibration_frames", "augment", "qat_epochs", "qat_learning_rate",
               "start", "input_size", "cluster", "keep_best", "polish_minutes")
"""CompressOptions settings a sweep does not vary: filter surgery with independent ranking, the float16 and int8 files,
the paper's offline copies, compress's QAT fallback (CompressOptions' defaults), surgery on each fold's own base
model as the pruned start (the paper's), at that model's own input size (the sweep's --input-size), each map's
largest cluster (Algorithm 1), the epoch of the lowest validation loss kept (the paper's), the polish's minutes (a
sweep adds no frames, so nothing is polished). Every other one is the sweep's own."""


@dataclass(frozen=True)
class SweepConfig:
    """Everything a job needs, as plain values (picklable, JSON-ready but for the reporter).

    `data` and `out` must be paths every worker sees (absolute; on a Ray cluster a shared
    file system). `data_sha256` and `splits_sha256` identify the annotation file and its folds;
    `prepare_data` fills them in, and each job checks that it sees the same.
    """

    out: str
    data: str
    images: str | None = None
    keypoint_attr: str = "keypoint"
    min_visible: int | None = None
    skip_bad: bool = False
    split_seed: int | None = None
    """The splits' seed; None (the CLI without --split-seed): the stored splits', else 0, fixed by
    `driver.prepare_config` before any job runs."""
    folds: int = settings.FOLDS.field()
    rates: tuple[float, ...] = parse_rates(DEFAULT_RATES_SPEC)
    input_size: int = settings.INPUT_SIZE.field()
    epochs: int = settings.SWEEP_EPOCHS.field()
    patience: int = settings.PATIENCE.field()
    retrain_epochs: int = settings.RETRAIN_EPOCHS.field()
    retrain_epochs_by_rate: tuple[tuple[float, int], ...] = ()
    """(rate, epochs) pairs overriding `retrain_epochs` for those rates (`--retrain-epochs 10,0.6:0.9:0.1=40`):
    heavier pruning may need longer retraining to converge."""
    retrain_patience: int = settings.RETRAIN_PATIENCE.field()
    batch_size: int = settings.BATCH_SIZE.field()
    learning_rate: float = settings.LEARNING_RATE.field()
    lr_patience: int = settings.LR_PATIENCE.field()
    """Halve Adam's rate after this many epochs without a better validation loss (base training and
    retraining); 0 keeps it constant (the paper)."""
    positive_weight: float = settings.POSITIVE_WEIGHT.field()
    augment_copies: int = settings.AUGMENT_COPIES.field()
    seed: int = settings.SEED.field()
    importance: str = settings.IMPORTANCE.field()
    """How a rate job ranks the filters it removes (l1: the paper's)."""
    importance_frames: int = settings.IMPORTANCE_FRAMES.field()
    distill: float = settings.DISTILL.field()
    """Weight of the fold's base model's maps in a rate job's retraining loss (0: the paper's)."""
    min_filters: int = settings.MIN_FILTERS.field()
    """No pruned layer under this many filters, within the keep rule's parameter budget (0: the paper's widths)."""
    lr_schedule: str = settings.LR_SCHEDULE.field()
    freeze: int = settings.SWEEP_FREEZE.field()
    """conv1..convN kept fixed while a rate job retrains (base models start from random weights: every layer trains)."""
    max_minutes: float | None = settings.SWEEP_MAX_MINUTES.field()
    """Time budget of each base model's training (retraining is bounded by its epochs)."""
    centroid: str = settings.SWEEP_CENTROID.field()
    """Where in its cluster a keypoint is read when a job is measured (plain: the paper's Algorithm 1)."""
    threads: int = 1
    """Resolved by the command (`commands.sweep.resolve_threads`): never None here."""
    reporter: Reporter = field(default_factory=Reporter, compare=False, repr=False)
    """Where a job's lines and its training's progress go (a worker process gets it pickled with the config): bars on a
    terminal; `Reporter(quiet=True)` one line per epoch (logs, parallel workers); `progress.SILENT` nothing."""
    force: bool = False
    """Redo every job, retraining base models from scratch."""
    data_sha256: str = ""
    splits_sha256: str = ""

    def key(self) -> ConfigKey:
        """The result-affecting settings (KEY_FIELDS) that every job record carries."""
        return ConfigKey(**{name: getattr(self, name) for name in KEY_FIELDS})

    def job_key(self, job: "Job") -> ConfigKey:
        """The settings `job`'s record carries (its own retraining budget; none for jobs that do not retrain)."""
        return job_key(self.key(), job.rate, self.retrain_epochs_by_rate)

    def retrain_epochs_at(self, rate: float) -> int:
        return retrain_epochs_at(rate, self.retrain_epochs, self.retrain_epochs_by_rate)

    @classmethod
    def preset(cls, name: str, **values: Any) -> SweepConfig:
        """A config with preset `name`'s value (`fcnpose_tf.settings.PRESETS`) of every setting not in `values`."""
        return settings.from_preset(cls, name, **values)

    def fit_config(self) -> FitConfig:
        """How the base models are trained: every FitConfig setting the sweep's (random weights: no layer frozen,
        no teacher, the epoch of the lowest validation loss kept: the paper's)."""
        from fcnpose_tf.training.train import FitConfig

        return settings.carried(self, FitConfig, freeze=0, distill=0.0, keep_best=settings.TRAIN_KEEP_BEST.paper)

    def compress_options(self, job: Job) -> CompressOptions:
        """How a rate job compresses its fold's base model (the unpruned export, rate 0, is not retrained): every
        CompressOptions setting the sweep's, those of SWEEP_FIXED at CompressOptions' defaults."""
        from fcnpose_tf.compression.options import CompressOptions

        defaults = CompressOptions.preset(settings.DEFAULT_PRESET, rate=float(job.rate))
        fixed = {name: getattr(defaults, name) for name in SWEEP_FIXED}
        fixed["start"] = settings.PRUNED_START.paper  # surgery: the paper's protocol
        fixed["keep_best"] = settings.KEEP_BEST.paper  # the lowest validation loss, as the base models'
        return settings.carried(
            self, CompressOptions, renamed={"patience": "retrain_patience"}, **fixed, rate=float(job.rate),
            fold=job.fold, retrain_epochs=0 if job.rate == 0 else self.retrain_epochs_at(job.rate),
            distill=0.0 if job.rate == 0 else self.distill, max_minutes=None,
            total_minutes=None)  # rates compared at equal epochs

    def to_dict(self) -> dict[str, Any]:
        """The settings as JSON-ready values (all but the reporter)."""
        data = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "reporter"}
        data["rates"] = list(self.rates)
        data["retrain_epochs_by_rate"] = [list(pair) for pair in self.retrain_epochs_by_rate]
        return data

    def validate(self) -> None:
        """Raise UserError for settings no job could run with."""
        settings.validate_fields(self)
        settings.THREADS.validate(self.threads)
        for _, epochs in self.retrain_epochs_by_rate:
            settings.RETRAIN_EPOCHS.validate(epochs)
        if not self.rates:
            raise UserError("no pruning rates given")
        stray = [r for r, _ in self.retrain_epochs_by_rate
                 if rate_percent(r) not in {rate_percent(x) for x in self.rates}]
        if stray:
            raise UserError(f"--retrain-epochs gives a budget for {', '.join(rate_label(r) for r in stray)}, which "
                            f"--rates ({', '.join(rate_label(r) for r in self.rates)}) does not include")


@dataclass(frozen=True, order=True)
class Job:
    """One unit of work: fold K's base model (rate None) or its compression at one rate."""

    fold: int
    rate: float | None = None

    @property
    def is_base(self) -> bool:
        return self.rate is None

    @property
    def name(self) -> str:
        """File stem of the job's record: fold0_base, fold0_p70."""
        return f"fold{self.fold}_base" if self.is_base else f"fold{self.fold}_{rate_tag(self.rate)}"

    @property
    def label(self) -> str:
        """For progress lines: "fold 0 base model", "fold 0 rate 70%"."""
        if self.is_base:
            return f"fold {self.fold} base model"
        if self.rate == 0:
            return f"fold {self.fold} unpruned export"
        return f"fold {self.fold} rate {rate_label(self.rate)}"

    def base(self) -> Job:
        """The job this one depends on (itself for a base job)."""
        return Job(self.fold)


def plan_jobs(folds: int, rates: tuple[float, ...]) -> list[Job]:
    """Every job of a sweep, fold by fold: base first, then its rates in increasing order."""
    return [job for k in range(folds) for job in [Job(k)] + [Job(k, float(r)) for r in rates]]


class BaseTraining(TypedDict, total=False):
    """How a base job got its model (a base record's "training"): trained here (`reused` False; resumed from a
    checkpoint or not) or reused from OUT/models (`record`: whether it had a NAME_train.json to read these from)."""

    reused: Required[bool]
    resumed: bool
    record: bool
    epochs_run: int | None
    best_epoch: int | None
    best_val_loss: float | None
    seconds: float | None
    stopped_early: bool | None


class JobRecord(TypedDict, total=False):
    """OUT/jobs/NAME.json: what a finished job measured and wrote (`run_job`). It stays the JSON object it was read
    as: `--retime` edits its timings in place (`retime.retime_sweep`), so a record written by an older version keeps
    every key. A measured model is a `compression.report` step as written (`ModelStep.to_json`, `TFLiteStep.to_json`
    without "export" and "tflite_ops", kept in the compression's NAME_report.json)."""

    record_version: Required[int]
    """RECORD_VERSION."""
    job: Required[str]
    """`Job.name`: fold0_base, fold0_p70."""
    kind: Required[str]
    """"base" or "rate"."""
    fold: Required[int]
    rate: Required[float | None]
    """None for a base job."""
    config_key: Required[ConfigKey]
    """The settings the job ran with (`SweepConfig.job_key`)."""
    eval_frames: int
    """Validation frames of the fold every model was measured on."""
    training: BaseTraining
    """A base job's training (or reuse) of its model."""
    keras: dict[str, Any]
    """The Keras model measured: a base job's model, a rate job's retrained one (`ModelStep.to_json`)."""
    tflite: dict[str, Any]
    """A rate job's first TFLite file, the paper's float16 (`TFLiteStep.to_json`)."""
    tflite_int8: dict[str, Any]
    """A rate job's int8 file; another format's file is in its own `tflite_section`."""
    pruned_before_retraining: dict[str, Any]
    """The pruned model before retraining (`ModelStep.to_json`, no timing)."""
    base_remeasured: dict[str, Any]
    """{"timing"}: the fold's base model timed again by the compression."""
    retraining: dict[str, Any] | None
    """`compression.report.Retraining.to_json` (None: not retrained, rate 0)."""
    pruning: dict[str, Any] | None
    """The compression report's "pruning" (criterion, strategy, min_filters, ranking_seconds)."""
    distillation: dict[str, Any] | None
    """The compression report's "distillation" (None: --distill 0)."""
    verification: dict[str, Any] | None
    """The first TFLite file's comparison with Keras (`verify.ParityReport.to_dict`)."""
    files: dict[str, str]
    """The files the job wrote, relative to OUT, by `options.output_names` key (keras, tflite_fp16, report...)."""
    model_sha256: str
    """A base job's model file's SHA-256 (a rate job is redone when its base changes)."""
    base_model_sha256: str
    """The SHA-256 of the base model a rate job compressed."""
    base_training_record: dict[str, Any]
    """A base job's NAME_train.json, the keys tables need (data, split, train_samples, val_frames, config, epochs)."""
    seconds: float
    """Wall time of the job."""
    finished_utc: str
    machine: MachineInfo
    tensorflow_threads: dict[str, Any]
    """TensorFlow's intra- and inter-op thread counts as it reported them, and $TF_NUM_INTRAOP_THREADS."""
    versions: dict[str, str | None]
    """`records.library_versions`."""
    retimed: dict[str, Any]
    """Written by `--retime`: when, on which machine, with which threads and versions, how often, and the job's own
    timings ("original_timing")."""


def base_model_path(out: str | os.PathLike, fold: int) -> Path:
    """OUT/models/base_fold{K}.keras (the name `fcnpose-tf train --folds K --out OUT/models/base.keras` writes)."""
    return Path(out) / MODELS_DIR / f"base_fold{fold}.keras"


def job_path(out: str | os.PathLike, job: Job) -> Path:
    """OUT/jobs/NAME.json: the finished job's record."""
    return Path(out) / JOBS_DIR / f"{job.name}.json"


def read_record(path: Path) -> JobRecord | None:
    """A job record, or None when it is unreadable (a stray file; the job is then redone)."""
    try:
        record = json.loads(path.read_text("utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("record_version") == RECORD_VERSION else None


# ------------------------------------------------------------------------------------------
# Data identity (no TensorFlow)
# ------------------------------------------------------------------------------------------

def splits_sha256(dataset: Any, folds: int) -> str:
    """Fingerprint of the K folds' validation frames (by file name): same folds, same hash."""
    names = dataset.names
    parts = []
    for k in range(folds):
        _, val = dataset.split(k)
        parts.append(",".join(sorted(names[int(i)] for i in val)))
    return hashlib.sha256("\n".join(parts).encode("utf-8")).hexdigest()


def load_data(config: SweepConfig, *, write_splits: bool = False) -> Any:
    """The sweep's dataset with its K folds; UserError if it is not the one `config` was made for.

    Workers pass write_splits=False (the driver stored the splits before any job started; a
    node without them rebuilds the same folds from the seed).
    """
    from fcnpose_tf.data.dataset import load_dataset

    where = socket.gethostname()
    if not Path(config.data).exists():
        raise UserError(f"{config.data}: data not found on {where}; with several machines the data (and --out) "
                        "must be on a path every worker sees")
    dataset = load_dataset(config.data, config.images, attribute=config.keypoint_attr,
                           min_visible=config.min_visible, skip_bad=config.skip_bad, folds=config.folds,
                           split_seed=config.split_seed, write_splits=write_splits)
    if config.data_sha256 and file_sha256(dataset.via_path) != config.data_sha256:
        raise UserError(f"{dataset.via_path}: on {where} this annotation file differs from the one the sweep "
                        "started with")
    if config.splits_sha256 and splits_sha256(dataset, config.folds) != config.splits_sha256:
        raise UserError(f"{dataset.splits_path}: on {where} the folds differ from the sweep's")
    return dataset


# ------------------------------------------------------------------------------------------
# Running a job (imports TensorFlow)
# ------------------------------------------------------------------------------------------

def run_job(config: SweepConfig, job: Job) -> JobRecord:
    """Run one job, write its model files and (last) its record; return the record.

    Raises:
        UserError: data not visible or changed, a reused base model that does not fit the
            sweep, or anything `compress_model` refuses (e.g. an export failing verification).
    """
    import gc

    from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_threads

    start = time.perf_counter()
    import_tensorflow_quietly()  # in a worker process: without TensorFlow's start-up log lines, as the CLI does
    set_tensorflow_threads(config.threads)
    import tensorflow as tf

    tf_threads = {"intra_op": tf.config.threading.get_intra_op_parallelism_threads(),
                  "inter_op": tf.config.threading.get_inter_op_parallelism_threads(),
                  "env_TF_NUM_INTRAOP_THREADS": os.environ.get("TF_NUM_INTRAOP_THREADS")}
    dataset = load_data(config)
    try:
        body = _run_base(config, job, dataset) if job.is_base else _run_rate(config, job, dataset)
    finally:
        import tf_keras as keras

        keras.backend.clear_session()
        gc.collect()
    record: JobRecord = {"record_version": RECORD_VERSION, "job": job.name, "kind": "base" if job.is_base else "rate",
                         "fold": job.fold, "rate": job.rate, "config_key": config.job_key(job), **body,
                         "seconds": round(time.perf_counter() - start, 1),
                         "finished_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                         "machine": machine_info(config.threads), "tensorflow_threads": tf_threads,
                         "versions": library_versions()}
    from fcnpose_tf.fileio import write_json

    write_json(job_path(config.out, job), record, force=True)
    return record


def _relative(path: str | os.PathLike, out: str | os.PathLike) -> str:
    try:
        return str(Path(path).resolve().relative_to(Path(out).resolve()))
    except ValueError:
        return str(path)


def tflite_section(quantize: str) -> str:
    """A rate job's record section for a TFLite file other than the first: tflite_int8 (the first, the
    paper's float16, is "tflite")."""
    return f"tflite_{settings.QUANTIZE_FILE_TAGS[quantize]}"


def tflite_sections(record: JobRecord) -> list[str]:
    """The record's TFLite sections, the first file's ("tflite") first."""
    return [s for s in record if s == "tflite" or (s.startswith("tflite_") and isinstance(record[s], dict))]


def _strip(step: dict[str, Any]) -> dict[str, Any]:
    """A compress report step without what the tables never need (kept in the NAME_report.json)."""
    return {k: v for k, v in step.items() if k not in ("export", "tflite_ops")}


def _run_base(config: SweepConfig, job: Job, dataset: Any) -> dict[str, Any]:
    from fcnpose_tf.compression.costs import file_sizes, model_facts
    from fcnpose_tf.compression.report import ModelStep
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.training.train import run_paths, train_fold

    path = base_model_path(config.out, job.fold)
    _, val_idx = dataset.split(job.fold)
    checkpoint = run_paths(path)["ckpt_state"]
    if path.is_file() and not checkpoint.is_file() and not config.force:
        training = _check_reused_base(config, job, dataset, path)
        config.reporter.say(f"{job.label}: reusing {path}")
        model = load_model(path)
        config.reporter.say(f"{job.label}: evaluating on {len(val_idx)} validation frames")
        result = evaluate_predictor(KerasKeypointModel(model, path, num_threads=config.threads,
                                                       decoding=Decoding(centroid=config.centroid)), dataset, val_idx,
                                    dataset.schema)
        validation = result.measurement()
    else:
        resume = checkpoint.is_file() and not config.force
        trained = train_fold(dataset, job.fold, path, config.fit_config(), input_size=config.input_size,
                             augment_copies=config.augment_copies, resume=resume, force=config.force or not resume,
                             metadata={"data": config.data, "trained_by": "fcnpose-tf sweep"},
                             threads=config.threads, decoding=Decoding(centroid=config.centroid),
                             label=f"{job.label} ({path.name})", reporter=config.reporter)
        facts = trained.raw
        training: BaseTraining = {"reused": False, "resumed": resume, "epochs_run": facts["epochs_run"],
                                  "best_epoch": facts["best_epoch"], "best_val_loss": facts["best_val_loss"],
                                  "seconds": facts["train_seconds"], "stopped_early": facts["stopped_early"]}
        validation = trained.validation
        model = load_model(path)
    keras_step = ModelStep.of(model_facts(model), validation, file_sizes(model, path)).to_json()
    record = training_record(path)
    raw = record.raw if record is not None else {}
    return {"eval_frames": len(val_idx), "training": training, "keras": keras_step,
            "files": {"keras": _relative(path, config.out)}, "model_sha256": file_sha256(path),
            "base_training_record": {k: raw.get(k) for k in ("data", "split", "train_samples", "val_frames",
                                                             "config", "epochs_run", "best_epoch")}}


def _check_reused_base(config: SweepConfig, job: Job, dataset: Any, path: Path) -> BaseTraining:
    from fcnpose_tf.training.model import load_model

    model = load_model(path)
    size, maps = int(model.input_shape[1]), int(model.output_shape[-1])
    if size != config.input_size:
        raise UserError(f"{path}: a {size}x{size} model, but the sweep's --input-size is {config.input_size}; "
                        "use another --out, or --force to retrain it")
    if maps != dataset.schema.num_maps:
        raise UserError(f"{path}: {maps} output maps, but the data needs {dataset.schema.num_maps}")
    record = training_record(path)
    if record is None:
        config.reporter.say(f"warning: {path} has no training record (NAME_train.json); cannot check that it was "
                            f"trained on fold {job.fold}'s training frames only")
        return {"reused": True, "record": False}
    if record.data_sha256 not in (None, config.data_sha256) or record.fold != job.fold \
            or record.split_seed not in (None, config.split_seed) or record.folds not in (None, config.folds):
        split = record.split if record.split is not None else "another split"
        raise UserError(f"{path}: trained on {split} of {record.data}, not on fold {job.fold} of {config.folds} of "
                        f"{config.data} (its validation frames would leak into training); move it away or pass "
                        "--force to retrain")
    raw = record.raw
    return {"reused": True, "record": True, "epochs_run": raw.get("epochs_run"),
            "best_epoch": raw.get("best_epoch"), "best_val_loss": raw.get("best_val_loss"),
            "seconds": raw.get("train_seconds"), "stopped_early": raw.get("stopped_early")}


def _run_rate(config: SweepConfig, job: Job, dataset: Any) -> dict[str, Any]:
    from fcnpose_tf.compression.compress import compress_model

    base = base_model_path(config.out, job.fold)
    if not base.is_file():
        raise UserError(f"{base}: fold {job.fold}'s base model is missing (its base job must finish first)")
    _, val_idx = dataset.split(job.fold)
    base_sha256 = file_sha256(base)
    config.reporter.say(f"{job.label}: compressing {base.name}")
    report = compress_model(base, dataset, dataset, [int(i) for i in val_idx], Path(config.out) / MODELS_DIR,
                            config.compress_options(job).checked(base), force=True, reporter=config.reporter,
                            eval_description=f"{len(val_idx)} validation frames of fold {job.fold} of {config.folds}")
    if report.quantized is None:  # every format refused by its keypoint gate: the job fails, one line
        reasons = "; ".join(f"{entry.quantize}: {entry.reason}" for entry in report.refused)
        raise UserError(f"{job.label}: no TFLite file passed its keypoint gate ({reasons})")
    parity = report.quantized.parity
    return {"eval_frames": len(val_idx), "base_model_sha256": base_sha256,
            "keras": _strip(report.retrained.to_json()),
            "tflite": _strip(report.quantized.to_json()),
            **{tflite_section(step.quantize): _strip(step.to_json()) for step in report.other_quantized},
            "pruned_before_retraining": report.pruned_before_retraining.to_json(),
            "base_remeasured": {"timing": report.base.timing.to_json() if report.base.timing else None},
            "retraining": report.retraining.to_json() if report.retraining is not None else None,
            "pruning": report.pruning, "distillation": report.distillation,
            "verification": parity.to_dict() if parity is not None else None,
            "files": {k: _relative(v, config.out) for k, v in report.files.items()}}


@dataclass
class JobEvent:
    """What an executor reports about a job: started, done (with its record), failed or skipped."""

    kind: str
    job: Job
    record: JobRecord | None = None
    error: str | None = None
    details: dict[str, Any] = field(default_factory=dict)
