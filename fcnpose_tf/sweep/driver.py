"""Run a sweep: check the results folder, skip finished jobs, run the rest, rebuild the report.

    OUT/sweep.json      the configuration (result-affecting settings must match on a rerun)
                        and one entry per run (executor, threads, jobs, duration, outcome)
    OUT/jobs/*.json     one record per finished job (written by the job itself)
    OUT/models/         base_fold{K}.keras and every compressed model, TFLite and report

A rerun skips every job whose record matches the configuration (and, for a rate job, the
fold's current base model); a rate job whose base was retrained is redone.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fcnpose_tf import progress
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import write_json
from fcnpose_tf.progress import Reporter
from fcnpose_tf.records import file_sha256
from fcnpose_tf.sweep import report as _report
from fcnpose_tf.sweep.executors import Executor, JobFunction
from fcnpose_tf.sweep.jobs import (KEY_FIELDS, Job, JobEvent, JobRecord, SweepConfig, job_path, load_data,
                                   normalize_key, plan_jobs, read_record, record_matches, retrain_epochs_at,
                                   run_job, splits_sha256)
from fcnpose_tf.sweep.rates import rate_label


@dataclass
class SweepOutcome:
    """What a run did: jobs skipped as finished, run, failed (name -> error), and the report."""

    skipped: list[str] = field(default_factory=list)
    done: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    not_run: list[str] = field(default_factory=list)
    report: _report.SweepReport | None = None
    """The tables rebuilt at the end (None until then)."""
    seconds: float = 0.0


def prepare_config(config: SweepConfig) -> tuple[SweepConfig, int]:
    """Load the data once in the driver (storing its splits beside it), fingerprint data and folds.

    Returns the config with an absolute VIA path, the splits' seed (the stored one when none was asked) and both
    fingerprints, and the frame count.
    """
    dataset = load_data(dataclasses.replace(config, data_sha256="", splits_sha256=""), write_splits=True)
    for k in range(config.folds):
        dataset.split(k)  # UserError when there are too few frames for K folds
    config = dataclasses.replace(config, data=str(dataset.via_path.resolve()), split_seed=dataset.splits.seed,
                                 images=str(Path(config.images).resolve()) if config.images else None,
                                 out=str(Path(config.out).resolve()),
                                 data_sha256=file_sha256(dataset.via_path),
                                 splits_sha256=splits_sha256(dataset, config.folds))
    return config, len(dataset)


def _differences(old: dict[str, Any], config: SweepConfig) -> list[str]:
    """Settings of the stored sweep `old` (its config document) that `config` changes.

    The retraining budget is compared rate by rate, for the rates `old` ran: adding a rate with
    its own budget is not a change.
    """
    old_key, new = normalize_key({name: old.get(name) for name in KEY_FIELDS if name in old}), config.key()
    diffs = [f"{name} {old_key.get(name)!r} -> {new.get(name)!r}" for name in KEY_FIELDS
             if name != "retrain_epochs" and old_key.get(name) != new.get(name)]
    for rate in old.get("rates", ()):
        if float(rate) == 0:
            continue
        before = retrain_epochs_at(float(rate), old["retrain_epochs"], old.get("retrain_epochs_by_rate", ()))
        after = config.retrain_epochs_at(float(rate))
        if before != after:
            diffs.append(f"retrain_epochs at {rate_label(float(rate))} {before} -> {after}")
    return diffs


def finished_jobs(config: SweepConfig, jobs: list[Job]) -> set[str]:
    """Names of `jobs` whose records are valid for `config` (none when config.force)."""
    if config.force:
        return set()
    key = config.key()
    records = {job.name: read_record(job_path(config.out, job)) for job in jobs}
    done: set[str] = set()
    for job in jobs:
        rec = records[job.name]
        if not record_matches(rec, key, config.retrain_epochs_by_rate):
            continue
        if job.is_base:
            model = Path(config.out) / rec.get("files", {}).get("keras", "")
            if model.is_file() and file_sha256(model) == rec.get("model_sha256"):
                done.add(job.name)
        else:
            base = records.get(job.base().name) or read_record(job_path(config.out, job.base()))
            if base and job.base().name in done and rec.get("base_model_sha256") == base.get("model_sha256"):
                done.add(job.name)
    return done


def run_sweep(config: SweepConfig, executor: Executor, *, job_fn: JobFunction = run_job,
              reporter: Reporter | None = None) -> SweepOutcome:
    """Run every unfinished job of `config` on `executor`, then rebuild tables, plot and results.json.

    Args:
        config: the sweep; `prepare_config` is applied here (data fingerprints, absolute paths).
        executor: LocalExecutor or RayExecutor.
        job_fn: the job function (tests pass a fake one).
        reporter: where the sweep's own lines go (default: the current reporter, `progress.current`); the jobs' go
            to `config.reporter`.
    Returns:
        SweepOutcome; failed jobs do not raise (the others still run), see `failed`.
    Raises:
        UserError: bad settings, unusable data, or a results folder made with other settings
            (without config.force).
        KeyboardInterrupt: after the running jobs were stopped and the report of the finished
            ones written.
    """
    config.validate()
    log = progress.resolve(reporter).say
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    config, num_frames = prepare_config(config)
    sweep_path = out / _report.SWEEP_FILE
    runs: list[_report.RunEntry] = []
    rates = tuple(config.rates)
    if sweep_path.is_file():
        previous = _report.read_sweep(out)
        diffs = _differences(previous["config"], config)
        if diffs and not config.force:
            raise UserError(f"{out}: holds a sweep with other settings ({'; '.join(diffs)}); use another --out, "
                            "or pass --force to redo every job with the new settings")
        if not diffs:  # the same experiment: later runs may add rates
            runs = previous.get("runs", [])
            rates = tuple(sorted(set(rates) | {float(r) for r in previous["config"]["rates"]}))
    config_doc = {**config.to_dict(), "rates": list(rates), "num_frames": num_frames}
    config_doc.pop("force")

    jobs = plan_jobs(config.folds, tuple(config.rates))
    done_before = finished_jobs(config, jobs)
    outcome = SweepOutcome(skipped=[j.name for j in jobs if j.name in done_before])
    to_run = [j for j in jobs if j.name not in done_before]
    run_entry = _report.new_run_entry(executor.describe(), to_run)
    runs.append(run_entry)
    out.mkdir(parents=True, exist_ok=True)
    write_json(sweep_path, {"config": config_doc, "runs": runs}, force=True)

    log(f"Sweep into {out}: {config.folds} folds x rates {', '.join(rate_label(r) for r in config.rates)} "
        f"on {num_frames} frames of {config.data}, input {config.input_size}")
    if outcome.skipped:
        shown = ", ".join(outcome.skipped[:12]) + (", ..." if len(outcome.skipped) > 12 else "")
        log(f"skipping {len(outcome.skipped)} finished job(s): {shown}")
    desc = executor.describe()
    log(f"{len(to_run)} job(s) to run on the {desc['executor']} executor"
        + (f" ({desc['workers']} worker process(es))" if desc.get("workers", 1) > 1 else "")
        + (f" at {desc['address']}" if desc.get("address") else "")
        + f", {config.threads} thread(s) per job" if to_run else "nothing to run: every job is finished")

    start = time.perf_counter()
    total = len(to_run)

    def on_event(event: JobEvent) -> None:
        job = event.job
        count = len(outcome.done) + len(outcome.failed) + len(outcome.not_run) + 1
        if event.kind == "done":
            outcome.done.append(job.name)
            log(f"sweep: job {count}/{total} done: {job.label} in {_duration(event.record.get('seconds'))}; "
                f"{_brief(event.record)}")
        elif event.kind == "failed":
            outcome.failed[job.name] = event.error or "failed"
            log(f"sweep: job {count}/{total} FAILED: {job.label}: {event.error}")
            if event.details.get("traceback"):
                log(event.details["traceback"].rstrip())
        elif event.kind == "skipped":
            outcome.not_run.append(job.name)
            log(f"sweep: job {count}/{total} not run: {job.label} ({event.error})")
        elif event.kind == "started" and desc.get("workers", 1) > 1:
            log(f"sweep: {job.label} started")

    def finish(interrupted: bool) -> None:
        outcome.seconds = time.perf_counter() - start
        run_entry.update(seconds=round(outcome.seconds, 1), jobs_done=list(outcome.done),
                         jobs_failed=dict(outcome.failed), interrupted=interrupted, **executor.describe())
        write_json(sweep_path, {"config": config_doc, "runs": runs}, force=True)
        outcome.report = _report.write_report(out)

    try:
        if to_run:
            executor.run(job_fn, config, to_run, set(done_before), on_event)
    except BaseException as exc:
        try:  # keep what finished visible in the tables, without hiding why the run stopped
            finish(interrupted=isinstance(exc, KeyboardInterrupt))
        except Exception as report_error:  # noqa: BLE001
            log(f"warning: could not rebuild the report: {report_error}")
        if isinstance(exc, KeyboardInterrupt):
            log(f"interrupted: {len(outcome.skipped) + len(outcome.done)} of {len(jobs)} jobs are finished and "
                "saved; rerun the same command to continue")
        raise
    finish(interrupted=False)
    return outcome


def _duration(seconds: Any) -> str:
    if not isinstance(seconds, (int, float)):
        return "?"
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _brief(record: JobRecord) -> str:
    def part(name: str, section: str) -> str:
        step = record.get(section) or {}
        pck = (step.get("metrics") or {}).get("pck@0.5_bbox")
        fps = (step.get("timing") or {}).get("fps")
        return f"{name} PCK@0.5 {pck:.3f} at {fps:.1f} FPS" if pck is not None and fps else f"{name} -"

    return part("Keras", "keras") + ("" if record.get("kind") == "base" else "; " + part("TFLite", "tflite"))
