"""Re-measure a finished sweep's inference times on this machine, without retraining anything.

Timing figures taken while other work shares the cores (parallel jobs, a training next to
the sweep, a mixed Ray cluster) are inflated. `retime_sweep` runs, sequentially in this
process, exactly the measurements the jobs made — the same model files, the same validation
frames, the same warm-up and frame count, the same thread count — and replaces the timing
fields of every finished job record:

    base job   keras.timing                      models/base_fold{K}.keras, Keras direct call
    rate job   keras.timing                      models/base_fold{K}_p{RR}.keras
               tflite.timing                     models/base_fold{K}_p{RR}_fp16.tflite, LiteRT
               tflite_int8.timing                models/base_fold{K}_p{RR}_int8.tflite, LiteRT
               base_remeasured.timing            the fold's base model, as the compression measured it

The keypoint metrics of every measurement must come out identical to the recorded ones (same
files, same frames, deterministic forward passes); if any differs, nothing is written and the
error lists the differences. Otherwise each record gets a `retimed` entry (when, which machine,
thread settings, versions, and the job's original timings), models/*_report.json get the same
timings, sweep.json gets a run entry of kind "retime", and tables, plot, summary.md and
results.json are rebuilt.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from fcnpose_tf import progress
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import json_default, write_json
from fcnpose_tf.measurements import MeasurementJson
from fcnpose_tf.progress import Reporter
from fcnpose_tf.records import file_sha256, library_versions, machine_info
from fcnpose_tf.sweep import report as _report
from fcnpose_tf.sweep.jobs import (JOBS_DIR, JobRecord, SweepConfig, base_model_path, load_data, tflite_section,
                                   tflite_sections)

RETIME_KIND = "retime"


@dataclass
class RetimeOutcome:
    """What a retime did: the jobs re-measured, old and new FPS per (job, section), and the report."""

    jobs: list[str] = field(default_factory=list)
    changes: list[dict[str, Any]] = field(default_factory=list)
    """{"job", "section", "fps_before", "fps_after"} per timed section."""
    seconds: float = 0.0
    report: _report.SweepReport | None = None
    """The tables rebuilt at the end (None until then)."""


def config_from_sweep(out: str | Path, data: str | None = None) -> SweepConfig:
    """The SweepConfig stored in OUT/sweep.json (with `out` = the folder given, `data` overridable)."""
    doc = _report.read_sweep(out)["config"]
    names = {f.name for f in dataclasses.fields(SweepConfig)}
    values = {k: v for k, v in doc.items() if k in names}
    values["rates"] = tuple(float(r) for r in doc["rates"])
    values["out"] = str(Path(out).resolve())
    if data is not None:
        values["data"] = str(data)
    return SweepConfig(**values)


def _normalized(value: Any) -> Any:
    """As it reads back from a record (JSON round trip: numpy scalars become floats, tuples lists)."""
    return json.loads(json.dumps(value, allow_nan=False, default=json_default))


def _differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for key in sorted(set(old) | set(new), key=str):
            out += _differences(old.get(key), new.get(key), f"{prefix}.{key}" if prefix else str(key))
        return out
    return [] if old == new else [f"{prefix}: {old!r} -> {new!r}"]


def _measure(predictor: Any, dataset: Any, indices: list[int]) -> MeasurementJson:
    """The jobs' measurement: every frame scored once, timing over >= 50 frames after 5 warm-up frames."""
    from fcnpose_tf.training.evaluate import MIN_TIMED_FRAMES, WARMUP_FRAMES, evaluate_predictor

    result = evaluate_predictor(predictor, dataset, indices, dataset.schema, min_timed_frames=MIN_TIMED_FRAMES,
                                warmup=WARMUP_FRAMES)
    return _normalized(result.measurement().to_json())


def _checked_file(out: Path, relative: str | None, what: str, sha256: str | None = None) -> Path:
    if not relative:
        raise UserError(f"{what}: the job record names no file")
    path = out / relative
    if not path.is_file():
        raise UserError(f"{path}: {what} is missing; the job must be rerun (not retimed)")
    if sha256 and file_sha256(path) != sha256:
        raise UserError(f"{path}: {what} changed since the job measured it (SHA-256 differs); rerun the sweep")
    return path


def measure_job(config: SweepConfig, record: JobRecord, dataset: Any) -> dict[str, MeasurementJson]:
    """Re-run the job's measurements: {section: {"metrics", "timing"}} for each timed section it has, as JSON reads
    them back (the comparison with the record is on what it holds)."""
    from fcnpose_tf.postprocess import Decoding
    from fcnpose_tf.training.evaluate import KerasKeypointModel
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.runtime.estimator import KeypointModel

    out = Path(config.out)
    fold = int(record["fold"])
    _, val_idx = dataset.split(fold)
    indices = [int(i) for i in val_idx]
    if len(indices) != record.get("eval_frames"):
        raise UserError(f"{record['job']}: {len(indices)} validation frames now, {record.get('eval_frames')} when "
                        "the job ran")
    files = record.get("files") or {}
    measured: dict[str, MeasurementJson] = {}
    threads, decoding = config.threads, Decoding(centroid=config.centroid)

    def keras(path: Path) -> KerasKeypointModel:
        return KerasKeypointModel(load_model(path), path, num_threads=threads, decoding=decoding)

    if record["kind"] == "base":
        path = _checked_file(out, files.get("keras"), "the base model", record.get("model_sha256"))
        measured["keras"] = _measure(keras(path), dataset, indices)
        return measured
    base = base_model_path(out, fold)
    _checked_file(out, str(base.relative_to(out)), "the fold's base model", record.get("base_model_sha256"))
    if (record.get("base_remeasured") or {}).get("timing"):
        measured["base_remeasured"] = _measure(keras(base), dataset, indices)
    keras_path = _checked_file(out, files.get("keras"), "the compressed Keras model")
    measured["keras"] = _measure(keras(keras_path), dataset, indices)
    from fcnpose_tf.compression.options import tflite_key

    for section in tflite_sections(record):
        quantize = record[section].get("quantize")
        # records written before one file per format name the (float16) file "tflite"
        name = files.get(tflite_key(quantize)) if quantize else files.get("tflite")
        tflite_path = _checked_file(out, name, f"the {quantize or 'float16'} TFLite export")
        measured[section] = _measure(KeypointModel(tflite_path, num_threads=threads, decoding=decoding), dataset,
                                     indices)
    return measured


def _expected_metrics(config: SweepConfig, record: JobRecord, section: str) -> dict[str, Any] | None:
    """The metrics the job recorded for `section` (base_remeasured: from the compression's report file)."""
    if section != "base_remeasured":
        return (record.get(section) or {}).get("metrics")
    report_file = (record.get("files") or {}).get("report")
    try:
        return json.loads((Path(config.out) / report_file).read_text("utf-8"))["base"]["metrics"]
    except (TypeError, OSError, ValueError, KeyError):
        return None


def retime_sweep(out: str | Path, *, threads: int | None = None, data: str | None = None,
                 reporter: Reporter | None = None,
                 measure: Callable[[SweepConfig, JobRecord, Any], dict[str, MeasurementJson]] = measure_job,
                 ) -> RetimeOutcome:
    """Re-measure every finished job of the sweep in OUT on this machine, then rebuild the report.

    Args:
        out: the results folder.
        threads: must equal the sweep's thread count when given (timings are tied to it).
        data: where the sweep's data is on this machine (checked by SHA-256); default: as recorded.
        reporter: where progress lines go (default: the current reporter, `progress.current`).
        measure: the measurement function (tests pass a fake one).
    Returns:
        RetimeOutcome with the old and new FPS of every timed section.
    Raises:
        UserError: no sweep or no finished job in OUT, another thread count, data or model files
            that differ from the ones the jobs used, or metrics that do not come out identical
            (then nothing is written).
    """
    out = Path(out)
    log = progress.resolve(reporter).say
    config = config_from_sweep(out, data)
    if threads is not None and threads != config.threads:
        raise UserError(f"{out}: the sweep was timed with {config.threads} thread(s), so --retime measures with "
                        f"{config.threads} (got --threads {threads}); the thread count is part of its settings")
    sweep = _report.read_sweep(out)
    records = _report.collect(out, sweep["config"]).records
    if not records:
        raise UserError(f"{out}: no finished job to retime")
    dataset = load_data(config)

    tf_threads = _prepare_tensorflow(config.threads) if measure is measure_job else {}
    started_utc = datetime.now(timezone.utc).isoformat(timespec="seconds")
    start = time.perf_counter()
    log(f"Retiming {len(records)} finished job(s) of {out} sequentially on this machine, {config.threads} "
        f"thread(s); metrics must come out identical")
    new: dict[str, dict[str, MeasurementJson]] = {}
    mismatches: list[str] = []
    for count, record in enumerate(records, 1):
        job_start = time.perf_counter()
        try:
            measured = measure(config, record, dataset)
        finally:
            if tf_threads:
                import tf_keras as keras

                keras.backend.clear_session()
        for section, result in measured.items():
            expected = _expected_metrics(config, record, section)
            if expected is not None and _normalized(expected) != result["metrics"]:
                diffs = _differences(_normalized(expected), result["metrics"])
                mismatches.append(f"{record['job']} {section}: " + "; ".join(diffs[:5])
                                  + (f"; ... ({len(diffs)} differences)" if len(diffs) > 5 else ""))
        new[record["job"]] = measured
        log(f"retime: {count}/{len(records)} {record['job']} in {time.perf_counter() - job_start:.1f} s: "
            + ", ".join(f"{s} FPS {_fps(record.get(s))} -> {_fps(m)}" for s, m in measured.items()))
    if mismatches:
        raise UserError(f"{out}: --retime measured other metrics than the jobs recorded, so these are not the "
                        f"same measurements; nothing was written ({len(mismatches)} difference(s)):\n  "
                        + "\n  ".join(mismatches))

    seconds = time.perf_counter() - start
    machine = machine_info(config.threads)
    versions = library_versions()
    outcome = RetimeOutcome(seconds=seconds)
    for record in records:
        measured = new[record["job"]]
        previous = record.get("retimed") or {}
        original = previous.get("original_timing") or {s: (record.get(s) or {}).get("timing") for s in measured}
        for section, result in measured.items():
            outcome.changes.append({"job": record["job"], "section": section, "fps_before": _fps(record.get(section)),
                                    "fps_after": _fps(result)})
            record[section]["timing"] = result["timing"]
        record["retimed"] = {"utc": started_utc, "machine": machine, "tensorflow_threads": tf_threads,
                             "versions": versions, "count": int(previous.get("count", 0)) + 1,
                             "original_timing": original}
        write_json(out / JOBS_DIR / f"{record['job']}.json", record, force=True)
        _update_compress_report(out, record, measured)
        outcome.jobs.append(record["job"])

    sweep["runs"] = sweep.get("runs", []) + [{
        "kind": RETIME_KIND, "started_utc": started_utc, "seconds": round(seconds, 1), "threads": config.threads,
        "machine": machine, "jobs_retimed": list(outcome.jobs)}]
    write_json(out / _report.SWEEP_FILE, sweep, force=True)
    outcome.report = _report.write_report(out)
    log(f"retimed {len(outcome.jobs)} job(s) in {seconds / 60:.1f} min on {machine['hostname']} "
        f"({machine['cpu_model']}); metrics identical")
    return outcome


def _prepare_tensorflow(threads: int) -> dict[str, Any]:
    """Import TensorFlow quietly with the jobs' thread settings; return them as TensorFlow reports them."""
    from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_threads, tensorflow_threads

    import_tensorflow_quietly()
    set_tensorflow_threads(threads)
    return tensorflow_threads()


def _fps(step: dict[str, Any] | None) -> float | None:
    timing = (step or {}).get("timing") or {}
    return timing.get("fps")


def _update_compress_report(out: Path, record: JobRecord, measured: dict[str, MeasurementJson]) -> None:
    """Put the new timings into the job's models/NAME_report.json too (base, retrained, quantized). The file is
    edited as JSON, not read as a `CompressReport`: one written by an older version keeps every key as it was."""
    report_file = (record.get("files") or {}).get("report")
    if record["kind"] == "base" or not report_file:
        return
    path = out / report_file
    try:
        report = json.loads(path.read_text("utf-8"))
    except (OSError, ValueError):
        return
    for section, key in (("base_remeasured", "base"), ("keras", "retrained"), ("tflite", "quantized")):
        if section in measured and isinstance(report.get(key), dict):
            report[key]["timing"] = measured[section]["timing"]
    for step in report.get("other_quantized") or []:
        section = tflite_section(step.get("quantize"))
        if section in measured:
            step["timing"] = measured[section]["timing"]
    report["retimed"] = {k: v for k, v in record["retimed"].items() if k != "original_timing"}
    write_json(path, report, force=True)


__all__ = ["RetimeOutcome", "config_from_sweep", "measure_job", "retime_sweep"]
