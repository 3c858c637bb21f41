"""`fcnpose-tf sweep`: rate specs, tables and plot from saved jobs, resumability, executors, smoke sweeps.

The fast tests use a fake job function (no TensorFlow) that writes records shaped like the real
ones; the smoke tests run real tiny sweeps (64x64, 1 epoch) on the local executor and on a Ray head
of 2 CPUs started for this module (`ray_head`).
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from conftest import PROCESS_TIMEOUT, run_cli_few_timed
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import write_json
from fcnpose_tf.progress import SILENT, Reporter
from fcnpose_tf.sweep import Job, LocalExecutor, RayExecutor, SweepConfig, parse_rates, run_sweep, write_report
from fcnpose_tf.sweep.executors import thread_env
from fcnpose_tf.records import file_sha256
from fcnpose_tf.sweep.jobs import base_model_path, job_path, plan_jobs
from fcnpose_tf.sweep.rates import parse_per_rate_epochs, rate_label, rate_tag

# ------------------------------------------------------------------------------------------
# Rate specifications
# ------------------------------------------------------------------------------------------


def test_range_gives_exactly_nine_rates_without_float_drift():
    rates = parse_rates("0.1:0.9:0.1")
    assert rates == (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    assert [repr(r) for r in rates] == ["0.1", "0.2", "0.3", "0.4", "0.5", "0.6", "0.7", "0.8", "0.9"]
    assert [rate_tag(r) for r in rates] == [f"p{10 * i}" for i in range(1, 10)]


@pytest.mark.parametrize("spec, expected", [
    ("0.5,0.7", (0.5, 0.7)),
    (" 0.7 , 0.5 ,0.7", (0.5, 0.7)),
    ("full,0.5", (0.0, 0.5)),
    ("0,0.05", (0.0, 0.05)),
    ("0:0.2:0.1", (0.0, 0.1, 0.2)),
    ("0.1:0.85:0.1", (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)),
    ("0.5:0.5:0.1", (0.5,)),
    ("0.9,0.1:0.3:0.1", (0.1, 0.2, 0.3, 0.9)),
    ("0.01:0.99:0.01", tuple(i / 100 for i in range(1, 100))),
])
def test_rate_specs(spec, expected):
    assert parse_rates(spec) == expected


@pytest.mark.parametrize("spec, message", [
    ("", "--rates is empty"),
    ("0.5,,0.7", "empty item"),
    ("abc", "'abc' is not a number"),
    ("1.0", "outside [0, 1)"),
    ("70", "write 0.7 for 70%"),
    ("-0.1", "outside [0, 1)"),
    ("nan", "not a finite number"),
    ("0.125", "not a whole percentage"),
    ("0.1:0.9", "must be START:STOP:STEP"),
    ("0.1:0.9:0", "step of '0.1:0.9:0' must be positive"),
    ("0.9:0.1:0.1", "starts above its stop"),
    ("0.1:0.9:0.015", "not a whole percentage"),
    ("0.1:1.5:0.1", "outside [0, 1)"),
])
def test_bad_rate_specs_are_user_errors(spec, message):
    with pytest.raises(UserError, match=None) as info:
        parse_rates(spec)
    assert message in str(info.value)


@pytest.mark.parametrize("spec, expected", [
    ("25", (25, ())),
    (" 10 , 0.6:0.9:0.1=40 ", (10, ((0.6, 40), (0.7, 40), (0.8, 40), (0.9, 40)))),
    ("0.7=30,10,0.5=20", (10, ((0.5, 20), (0.7, 30)))),
    ("0", (0, ())),
])
def test_per_rate_retraining_budgets(spec, expected):
    assert parse_per_rate_epochs(spec) == expected


@pytest.mark.parametrize("spec, message", [
    ("x", "'x' is not a whole number of epochs"),
    ("10,12", "two default epoch counts"),
    ("0.6=40", "no default epoch count"),
    ("10,0.6=-1", "epochs must be >= 0"),
    ("10,0.6=4,0.6:0.7:0.1=5", "rate 60% is given 4 and 5 epochs"),
    ("10,1.5=4", "--retrain-epochs '1.5': rate 1.5 is outside [0, 1)"),
])
def test_bad_per_rate_retraining_budgets(spec, message):
    with pytest.raises(UserError) as info:
        parse_per_rate_epochs(spec)
    assert message in str(info.value)


def test_job_names_and_labels():
    assert Job(3).name == "fold3_base" and Job(3).is_base
    assert Job(0, 0.7).name == "fold0_p70" and Job(1, 0.05).name == "fold1_p05" and Job(2, 0.0).name == "fold2_p00"
    assert Job(0, 0.7).base() == Job(0)
    assert rate_label(0.0) == rate_label(None) == "full" and rate_label(0.7) == "70%"
    assert [j.name for j in plan_jobs(2, (0.5, 0.7))] == ["fold0_base", "fold0_p50", "fold0_p70",
                                                          "fold1_base", "fold1_p50", "fold1_p70"]


# ------------------------------------------------------------------------------------------
# Fake job records: the paper's figures, per fold a little apart
# ------------------------------------------------------------------------------------------

PAPER = {  # rate: (PCK@0.5, Keras FPS, params, TFLite FPS)
    0.0: (0.997, 11.7, 131705, 27.0), 0.1: (0.998, 11.1, 110237, 30.0), 0.3: (0.991, 13.7, 68014, 45.0),
    0.5: (0.985, 27.8, 35185, 70.0), 0.7: (0.980, 41.9, 14668, 110.0), 0.9: (0.284, 61.9, 2480, 200.0)}


def _step(pck: float, fps: float, params: int, tflite: bool = False) -> dict:
    metrics = {"pck@0.5_bbox": pck, "pck@0.2_bbox": pck * 0.9, "pck@0.05_bbox": pck * 0.5, "epe_px": 40 * (1 - pck) + 2}
    timing = {"inference_ms": {"mean": 900 / fps, "std": 0.1, "median": 900 / fps}, "fps": fps,
              "fps_inference_only": fps * 1.1, "threads": 2, "total_ms": {"mean": 1000 / fps}}
    step = {"params": params, "macs": params * 4000, "flops": params * 8000, "metrics": metrics, "timing": timing}
    if tflite:
        step["tflite_size_bytes"] = params * 2 + 9000
    else:
        step.update(h5_size_bytes=params * 4 + 50000, keras_size_bytes=params * 4 + 60000)
    return step


def fake_record(config: SweepConfig, job: Job, offset: float = 0.0) -> dict:
    """A job record shaped like run_job's, with the paper's numbers shifted by `offset`."""
    rate = 0.0 if job.is_base else job.rate
    pck, fps, params, tfl_fps = PAPER.get(rate, (0.95, 20.0, 50000, 60.0))
    record = {"record_version": 1, "job": job.name, "kind": "base" if job.is_base else "rate", "fold": job.fold,
              "rate": job.rate, "config_key": config.job_key(job), "eval_frames": 5, "seconds": 1.5,
              "machine": {"hostname": "h", "cpu_model": "Test CPU", "cpu_cores": 2, "threads": config.threads},
              "keras": _step(min(1.0, pck + offset), fps * (1 + offset), params)}
    if job.is_base:
        record["training"] = {"epochs_run": 3, "seconds": 60.0}
    else:
        record["tflite"] = _step(min(1.0, pck + offset - 0.002), tfl_fps * (1 + offset), params, tflite=True)
        record["pruned_before_retraining"] = {"metrics": {"pck@0.5_bbox": pck / 2}}
    return record


def fake_job(config: SweepConfig, job: Job) -> dict:
    """A stand-in for run_job: obeys the same contract (files first, record last), no TensorFlow.

    FAKE_FAIL names jobs to fail; a rate job refuses to run before its base model exists.
    """
    if job.name in os.environ.get("FAKE_FAIL", "").split(","):
        raise UserError(f"{job.name}: made to fail")
    base = base_model_path(config.out, job.fold)
    if job.is_base:
        base.parent.mkdir(parents=True, exist_ok=True)
        base.write_bytes(b"model of fold %d" % job.fold)
    elif not base.is_file():
        raise UserError(f"{base}: missing (ran before its base)")
    time.sleep(float(os.environ.get("FAKE_SLEEP", "0")))
    record = fake_record(config, job, offset=0.01 * job.fold)
    record["files"] = {"keras": f"models/{base.name}"}
    record["worker"] = {"pid": os.getpid(), "TF_NUM_INTRAOP_THREADS": os.environ.get("TF_NUM_INTRAOP_THREADS")}
    if job.is_base:
        record["model_sha256"] = file_sha256(base)
    else:
        record["base_model_sha256"] = file_sha256(base)
    write_json(job_path(config.out, job), record, force=True)
    return record


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    from test_train_evaluate import make_via_folder

    return make_via_folder(tmp_path_factory.mktemp("sweepdata") / "frames", n=10)


@pytest.fixture(scope="module")
def smoke_frames(tmp_path_factory):
    """Frames for real sweeps: 20, so each fold's int8 export has the 16 real frames its keypoint gate needs."""
    from test_train_evaluate import make_via_folder

    return make_via_folder(tmp_path_factory.mktemp("smokedata") / "frames", n=20)


def _config(out, data, rates="0.5,0.7", folds=2, **kwargs) -> SweepConfig:
    settings = {"input_size": 64, "epochs": 1, "retrain_epochs": 1, "threads": 1, **kwargs}
    return SweepConfig(out=str(out), data=str(data), rates=parse_rates(rates), folds=folds, **settings)


# ------------------------------------------------------------------------------------------
# Tables, plot and results.json from saved jobs
# ------------------------------------------------------------------------------------------


def test_report_from_saved_jobs_has_every_table_plot_and_results(tmp_path, frames):
    import cv2

    config = _config(tmp_path / "res", frames, rates="full,0.1,0.3,0.5,0.7,0.9", folds=2)
    said = Reporter(stream=io.StringIO())
    outcome = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=said)
    lines = said.stream.getvalue().splitlines()
    assert len(outcome.done) == 14 and not outcome.failed and not outcome.skipped
    out = tmp_path / "res"
    for name in ("folds", "pruning", "requirements", "quantization"):
        assert (out / "tables" / f"{name}.md").is_file() and (out / "tables" / f"{name}.csv").is_file()

    # Folds 0 and 1 differ by offset 0.01: PCK@0.5 of the bases 0.997 and 1.0 (capped) -> mean 0.9985
    folds = list(csv.DictReader(io.StringIO((out / "tables" / "folds.csv").read_text())))
    assert [r["fold"] for r in folds] == ["0", "1", "mean", "std"]
    assert float(folds[2]["pck@0.5_bbox"]) == pytest.approx(0.9985)
    assert float(folds[3]["pck@0.5_bbox"]) == pytest.approx(0.0015)

    pruning = list(csv.DictReader(io.StringIO((out / "tables" / "pruning.csv").read_text())))
    assert [float(r["rate"]) for r in pruning] == [0.0, 0.1, 0.3, 0.5, 0.7, 0.9]
    row70 = pruning[4]
    assert row70["params"] == "14668" and row70["folds"] == "2"
    assert float(row70["pck@0.5_bbox_mean"]) == pytest.approx(0.985) and \
        float(row70["pck@0.5_bbox_std"]) == pytest.approx(0.005)
    fps70 = (41.9 + 41.9 * 1.01) / 2
    assert float(row70["fps_mean"]) == pytest.approx(fps70, rel=1e-5)
    assert float(row70["speedup"]) == pytest.approx(fps70 / ((11.7 + 11.7 * 1.01) / 2), rel=1e-4)
    md = (out / "tables" / "pruning.md").read_text()
    assert "| 70%  |" in md and "0.985 ± 0.005" in md and "14,668" in md

    req = list(csv.DictReader(io.StringIO((out / "tables" / "requirements.csv").read_text())))
    assert req[0]["params"] == "131705" and float(req[0]["params_fraction"]) == 1.0
    assert float(req[-1]["h5_size_mb"]) == pytest.approx((2480 * 4 + 50000) / 1e6)
    assert float(req[-1]["flops_millions"]) == pytest.approx(2 * float(req[-1]["macs_millions"]))

    quant = list(csv.DictReader(io.StringIO((out / "tables" / "quantization.csv").read_text())))
    assert [float(r["rate"]) for r in quant] == [0.0, 0.1, 0.3, 0.5, 0.7, 0.9]  # "full" = the rate-0 export
    assert float(quant[4]["pck@0.5_bbox_delta_vs_keras_mean"]) == pytest.approx(-0.002)
    assert "+0.000" not in (out / "tables" / "quantization.md").read_text().split("| 70%")[1].split("\n")[0]

    results = json.loads((out / "results.json").read_text())
    assert results["complete"] and results["missing_jobs"] == [] and len(results["jobs"]) == 14
    assert results["machine"]["cpu_model"] and results["machine"]["cpu_cores"] >= 1 and results["threads"] == 1
    for lib in ("tensorflow", "tf_keras", "ai_edge_litert", "numpy", "opencv", "fcnpose_tf"):
        assert lib in results["versions"]
    assert set(results["tables"]) == {"folds", "pruning", "requirements", "quantization"}
    assert results["tables"]["pruning"]["rows"][4]["pck@0.5_bbox"]["mean"] == pytest.approx(0.985)
    assert results["runs"][0]["executor"] == "local" and results["runs"][0]["jobs_done"]

    summary = (out / "summary.md").read_text()
    for title in ("5-Folds Desktop", "Pruning Results", "Requirements", "Pruning and Quantization", "Definitions"):
        assert title in summary
    assert "(complete)" in summary and "![PCK@0.5 vs FPS](pck_vs_fps.png)" in summary

    image = cv2.imread(str(out / "pck_vs_fps.png"))
    assert image is not None and image.shape[0] > 400 and image.shape[1] > 600 and image.std() > 10
    assert any("sweep: job 14/14 done" in line for line in lines)


def test_partial_results_show_fold_counts_and_missing_jobs(tmp_path, frames):
    config = _config(tmp_path / "res", frames)
    run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    out = tmp_path / "res"
    (out / "jobs" / "fold1_p70.json").unlink()
    other = fake_record(SweepConfig(**{**config.to_dict(), "rates": (0.5,), "epochs": 99}), Job(0, 0.5))
    write_json(out / "jobs" / "fold0_p90.json", {**other, "job": "fold0_p90", "rate": 0.9})  # another config
    result = write_report(out)
    pruning = {r["rate"]: r for r in result.tables["pruning"].records()}
    assert pruning[0.7]["folds"] == 1 and pruning[0.5]["folds"] == 2 and 0.9 not in pruning
    assert pruning[0.7]["pck@0.5_bbox"]["n"] == 1
    assert "0.980 ±" not in (out / "tables" / "pruning.md").read_text().split("| 70%")[1].split("\n")[0]
    results = json.loads((out / "results.json").read_text())
    assert results["missing_jobs"] == ["fold1_p70"] and not results["complete"]
    assert results["ignored_job_files"] == ["fold0_p90.json"]
    assert "1 missing (fold1_p70)" in (out / "summary.md").read_text()


def test_report_only_needs_a_sweep(tmp_path):
    with pytest.raises(UserError, match="holds no sweep"):
        write_report(tmp_path)


@pytest.mark.parametrize("text, message", [
    ("[" * 400 + "]" * 400, "nested more than 64 levels deep"),
    ('{"config": {"rates": ' + "[" * 300 + "]" * 300 + "}}", "nested more than 64 levels deep"),
    ('{"config": {}}', "no configuration with a list of rates"),
    ("[1, 2]", "no configuration with a list of rates"),
])
def test_report_only_refuses_a_broken_sweep_file_in_one_line(tmp_path, text, message):
    (tmp_path / "sweep.json").write_text(text)
    with pytest.raises(UserError, match=message):
        write_report(tmp_path)


def test_report_modules_import_no_tensorflow_or_ray():
    code = ("import sys, fcnpose_tf.sweep, fcnpose_tf.sweep.report, fcnpose_tf.commands.sweep; "
            "bad = [m for m in ('tensorflow', 'tf_keras', 'ray', 'matplotlib') if m in sys.modules]; "
            "assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 0, proc.stderr


# ------------------------------------------------------------------------------------------
# Resuming, failures, settings checks, executors (fake jobs)
# ------------------------------------------------------------------------------------------


def test_rerun_skips_finished_jobs_and_redoes_rates_of_a_changed_base(tmp_path, frames):
    config = _config(tmp_path / "res", frames)
    first = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert len(first.done) == 6
    said = Reporter(stream=io.StringIO())
    again = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=said)
    lines = said.stream.getvalue().splitlines()
    assert again.done == [] and len(again.skipped) == 6
    assert any("skipping 6 finished job(s)" in s for s in lines) and any("nothing to run" in s for s in lines)

    # A job lost (e.g. interrupted) is redone; a base model replaced invalidates its fold's rate jobs
    (tmp_path / "res" / "jobs" / "fold0_p70.json").unlink()
    base_model_path(config.out, 1).write_bytes(b"retrained elsewhere")
    third = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert sorted(third.done) == ["fold0_p70", "fold1_base", "fold1_p50", "fold1_p70"]

    # More rates later: only the new jobs run, and sweep.json keeps every rate
    fourth = run_sweep(_config(tmp_path / "res", frames, rates="0.9"), LocalExecutor(), job_fn=fake_job,
                       reporter=SILENT)
    assert sorted(fourth.done) == ["fold0_p90", "fold1_p90"]
    assert json.loads((tmp_path / "res" / "sweep.json").read_text())["config"]["rates"] == [0.5, 0.7, 0.9]
    assert len(json.loads((tmp_path / "res" / "sweep.json").read_text())["runs"]) == 4


def test_failed_base_skips_its_rates_and_the_rest_still_runs(tmp_path, frames, monkeypatch):
    monkeypatch.setenv("FAKE_FAIL", "fold0_base,fold1_p50")
    outcome = run_sweep(_config(tmp_path / "res", frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert set(outcome.failed) == {"fold0_base", "fold1_p50"} and "made to fail" in outcome.failed["fold0_base"]
    assert sorted(outcome.not_run) == ["fold0_p50", "fold0_p70"]
    assert sorted(outcome.done) == ["fold1_base", "fold1_p70"]
    monkeypatch.delenv("FAKE_FAIL")
    retry = run_sweep(_config(tmp_path / "res", frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert sorted(retry.done) == ["fold0_base", "fold0_p50", "fold0_p70", "fold1_p50"]


def test_other_settings_in_the_same_folder_are_refused_unless_forced(tmp_path, frames):
    run_sweep(_config(tmp_path / "res", frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    changed = _config(tmp_path / "res", frames, epochs=5)
    with pytest.raises(UserError, match=r"other settings \(epochs 1 -> 5\).*--force"):
        run_sweep(changed, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    forced = SweepConfig(**{**changed.to_dict(), "rates": changed.rates, "force": True})
    outcome = run_sweep(forced, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert len(outcome.done) == 6 and json.loads((tmp_path / "res" / "sweep.json").read_text())["config"]["epochs"] == 5


def test_per_rate_retraining_budget_is_each_jobs_own_setting(tmp_path, frames):
    out = tmp_path / "res"
    config = _config(out, frames, retrain_epochs=1, retrain_epochs_by_rate=((0.7, 3),))
    assert (config.retrain_epochs_at(0.5), config.retrain_epochs_at(0.7)) == (1, 3)
    run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    keys = {p.stem: json.loads(p.read_text())["config_key"] for p in (out / "jobs").glob("*.json")}
    assert keys["fold0_p50"]["retrain_epochs"] == 1 and keys["fold1_p70"]["retrain_epochs"] == 3
    assert "retrain_epochs" not in keys["fold0_base"]  # a base model does not depend on retraining
    assert "retraining up to 1 epoch (3 at 70%)" in (out / "summary.md").read_text()
    assert json.loads((out / "sweep.json").read_text())["config"]["retrain_epochs_by_rate"] == [[0.7, 3]]
    again = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert again.done == [] and len(again.skipped) == 6

    # The same folder refuses another budget for a rate it ran; adding a rate with its own budget is fine
    with pytest.raises(UserError, match=r"other settings \(retrain_epochs at 70% 3 -> 1\)"):
        run_sweep(_config(out, frames, retrain_epochs=1), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    more = run_sweep(_config(out, frames, rates="0.7,0.9", retrain_epochs=1, retrain_epochs_by_rate=((0.7, 3), (0.9, 5))),
                     LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert sorted(more.done) == ["fold0_p90", "fold1_p90"]

    # Longer retraining for some rates in a new folder that reuses the base models and the other rates' jobs
    longer = tmp_path / "longer"
    for sub in ("jobs", "models"):
        (longer / sub).mkdir(parents=True)
    for name in ("fold0_base", "fold1_base", "fold0_p50", "fold1_p50"):
        shutil.copy(out / "jobs" / f"{name}.json", longer / "jobs")
    for model in (out / "models").glob("base_fold*.keras"):
        shutil.copy(model, longer / "models")
    redo = run_sweep(_config(longer, frames, retrain_epochs=1, retrain_epochs_by_rate=((0.7, 8),)), LocalExecutor(),
                     job_fn=fake_job, reporter=SILENT)
    assert sorted(redo.done) == ["fold0_p70", "fold1_p70"] and len(redo.skipped) == 4
    assert json.loads((longer / "jobs" / "fold0_p70.json").read_text())["config_key"]["retrain_epochs"] == 8

    with pytest.raises(UserError, match=r"budget for 80%, which --rates \(50%, 70%\) does not include"):
        _config(out, frames, retrain_epochs_by_rate=((0.8, 3),)).validate()


def test_lr_patience_is_a_result_setting_and_folders_older_than_it_still_match(tmp_path, frames):
    out = tmp_path / "res"
    run_sweep(_config(out, frames, lr_patience=4), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    records = [json.loads(p.read_text()) for p in (out / "jobs").glob("*.json")]
    assert {r["config_key"]["lr_patience"] for r in records} == {4}
    assert "halved after 4 epochs without a better validation loss" in (out / "summary.md").read_text()
    with pytest.raises(UserError, match=r"other settings \(lr_patience 4 -> 0\)"):
        run_sweep(_config(out, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)

    # A folder written before lr_patience existed: no such key anywhere; it means 0 (constant rate)
    old = tmp_path / "old"
    run_sweep(_config(old, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    sweep = json.loads((old / "sweep.json").read_text())
    del sweep["config"]["lr_patience"]
    write_json(old / "sweep.json", sweep, force=True)
    for path in (old / "jobs").glob("*.json"):
        record = json.loads(path.read_text())
        del record["config_key"]["lr_patience"]
        write_json(path, record, force=True)
    assert len(write_report(old).results.records) == 6
    again = run_sweep(_config(old, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert again.done == [] and len(again.skipped) == 6
    with pytest.raises(UserError, match=r"lr_patience 0 -> 2"):
        run_sweep(_config(old, frames, lr_patience=2), LocalExecutor(), job_fn=fake_job, reporter=SILENT)


def test_importance_distillation_and_floor_reach_rate_jobs_and_older_folders_still_match(tmp_path, frames):
    from test_compress import recipe_of

    out = tmp_path / "res"
    config = _config(out, frames, rates="full,0.7", importance="taylor", importance_frames=32, distill=0.5,
                     min_filters=12)
    options = config.compress_options(Job(0, 0.7))
    assert (options.importance, options.importance_frames, options.distill) == ("taylor", 32, 0.5)
    assert options.min_filters == 12 and "no layer under 12 filters" in recipe_of(options)
    assert config.compress_options(Job(0, 0.0)).distill == 0.0  # the unpruned export is not retrained
    run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    keys = {p.stem: json.loads(p.read_text())["config_key"] for p in (out / "jobs").glob("*.json")}
    assert (keys["fold0_p70"]["importance"], keys["fold0_p70"]["distill"], keys["fold0_p70"]["min_filters"]) == \
        ("taylor", 0.5, 12)
    assert "importance" not in keys["fold0_base"] and "distill" not in keys["fold1_p00"]  # they do not retrain
    assert "min_filters" not in keys["fold0_base"]
    summary = (out / "summary.md").read_text()
    assert "ranked by first-order Taylor on 32 training frames" in summary and "teacher weight 0.5" in summary
    assert "filter pruning with no layer under 12 filters" in summary
    with pytest.raises(UserError, match=r"other settings \(distill 0.5 -> 0.0\)"):
        run_sweep(_config(out, frames, rates="full,0.7", importance="taylor", importance_frames=32, min_filters=12),
                  LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    with pytest.raises(UserError, match=r"other settings \(min_filters 12 -> 8\)"):
        run_sweep(_config(out, frames, rates="full,0.7", importance="taylor", importance_frames=32, distill=0.5,
                          min_filters=8), LocalExecutor(), job_fn=fake_job, reporter=SILENT)

    # A folder written before criteria and distillation existed: the paper's L1 norm and no teacher
    old = tmp_path / "old"
    run_sweep(_config(old, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    sweep = json.loads((old / "sweep.json").read_text())
    for name in ("importance", "importance_frames", "distill", "min_filters"):
        del sweep["config"][name]
    write_json(old / "sweep.json", sweep, force=True)
    for path in (old / "jobs").glob("*.json"):
        record = json.loads(path.read_text())
        for name in ("importance", "importance_frames", "distill", "min_filters"):
            record["config_key"].pop(name, None)
        write_json(path, record, force=True)
    again = run_sweep(_config(old, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert again.done == [] and len(again.skipped) == 6
    assert "keeping n - floor(n·rate) filters per layer ranked by L1 norm (output layer untouched)" in \
        (old / "summary.md").read_text()


def _fake_measure(factor: float, spoil: str | None = None):
    """A stand-in for retime.measure_job: the recorded metrics, FPS times `factor` (metrics of `spoil` changed)."""
    def measure(config, record, dataset):
        sections = ["keras"] if record["kind"] == "base" else ["keras", "tflite"]
        out = {}
        for section in sections:
            metrics = json.loads(json.dumps(record[section]["metrics"]))
            if record["job"] == spoil:
                metrics["pck@0.5_bbox"] -= 0.01
            timing = {**record[section]["timing"], "fps": round(record[section]["timing"]["fps"] * factor, 2),
                      "frames_timed": 55}
            out[section] = {"metrics": metrics, "timing": timing}
        return out
    return measure


@pytest.mark.slow
def test_retime_replaces_timings_keeps_metrics_and_rebuilds_the_report(tmp_path, frames):
    from fcnpose_tf.sweep.retime import retime_sweep

    out = tmp_path / "res"
    config = _config(out, frames)
    run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    before = {p.name: json.loads(p.read_text()) for p in (out / "jobs").glob("*.json")}
    fps_before = {r["rate"]: r["fps"]["mean"] for r in json.loads((out / "results.json").read_text())[
        "tables"]["quantization"]["rows"]}

    # Metrics that differ: loud failure naming the job, and nothing written
    raw = {p.name: p.read_bytes() for p in (out / "jobs").glob("*.json")}
    with pytest.raises(UserError, match=r"fold1_p70 keras: pck@0.5_bbox: .*nothing was written|nothing was written"
                       ) as info:
        retime_sweep(out, measure=_fake_measure(2.0, spoil="fold1_p70"), reporter=SILENT)
    assert "fold1_p70 keras: pck@0.5_bbox" in str(info.value) and "fold1_p70 tflite" in str(info.value)
    assert {p.name: p.read_bytes() for p in (out / "jobs").glob("*.json")} == raw
    with pytest.raises(UserError, match="timed with 1 thread"):
        retime_sweep(out, threads=2, measure=_fake_measure(2.0), reporter=SILENT)

    # A copied folder (trained on a cluster, timed elsewhere) is retimed where it is; the original is untouched
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    assert len(retime_sweep(copy, measure=_fake_measure(3.0), reporter=SILENT).jobs) == 6
    assert {p.name: p.read_bytes() for p in (out / "jobs").glob("*.json")} == raw
    assert json.loads((copy / "jobs" / "fold0_base.json").read_text())["retimed"]["count"] == 1

    said = Reporter(stream=io.StringIO())
    outcome = retime_sweep(out, measure=_fake_measure(2.0), reporter=said)
    lines = said.stream.getvalue().splitlines()
    assert len(outcome.jobs) == 6 and any("metrics identical" in s for s in lines)
    for path in (out / "jobs").glob("*.json"):
        record, old = json.loads(path.read_text()), before[path.name]
        for section in ("keras", "tflite"):
            if section in old:
                assert record[section]["metrics"] == old[section]["metrics"]
                assert record[section]["timing"]["fps"] == pytest.approx(old[section]["timing"]["fps"] * 2, abs=0.01)
                assert record["retimed"]["original_timing"][section] == old[section]["timing"]
        assert record["retimed"]["machine"]["cpu_model"] and record["retimed"]["utc"] and record["retimed"]["count"] == 1
        assert record["config_key"] == old["config_key"] and record["seconds"] == old["seconds"]
    results = json.loads((out / "results.json").read_text())
    fps_after = {r["rate"]: r["fps"]["mean"] for r in results["tables"]["quantization"]["rows"]}
    assert fps_after[0.7] == pytest.approx(2 * fps_before[0.7], rel=1e-3)
    assert results["timing_source"]["retimed_jobs"] == 6 == results["timing_source"]["jobs"]
    assert results["runs"][-1]["kind"] == "retime" and len(results["runs"][-1]["jobs_retimed"]) == 6
    summary = (out / "summary.md").read_text()
    assert "re-measured with `--retime` for every job" in summary

    # A second retime keeps the jobs' own timings as the original; the sweep still skips every job
    retime_sweep(out, measure=_fake_measure(1.5), reporter=SILENT)
    record = json.loads((out / "jobs" / "fold0_p50.json").read_text())
    assert record["retimed"]["count"] == 2
    assert record["retimed"]["original_timing"]["keras"] == before["fold0_p50.json"]["keras"]["timing"]
    again = run_sweep(config, LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    assert again.done == [] and len(again.skipped) == 6


def test_retime_needs_finished_jobs(tmp_path, frames):
    from fcnpose_tf.sweep.retime import retime_sweep

    with pytest.raises(UserError, match="holds no sweep"):
        retime_sweep(tmp_path / "none", measure=_fake_measure(2.0))
    out = tmp_path / "res"
    run_sweep(_config(out, frames), LocalExecutor(), job_fn=fake_job, reporter=SILENT)
    for path in (out / "jobs").glob("*.json"):
        path.unlink()
    with pytest.raises(UserError, match="no finished job to retime"):
        retime_sweep(out, measure=_fake_measure(2.0))


def test_too_few_frames_for_the_folds(tmp_path):
    from test_train_evaluate import make_via_folder

    frames = make_via_folder(tmp_path / "frames", n=10)
    with pytest.raises(UserError, match="too few frames for 11 folds"):
        run_sweep(_config(tmp_path / "res", frames, folds=11), LocalExecutor(), job_fn=fake_job, reporter=SILENT)


def test_process_pool_limits_threads_and_keeps_bases_before_rates(tmp_path, monkeypatch):
    from test_train_evaluate import make_via_folder

    monkeypatch.setenv("FAKE_SLEEP", "0.3")
    config = _config(tmp_path / "res", make_via_folder(tmp_path / "frames", n=10), folds=3, threads=1)
    outcome = run_sweep(config, LocalExecutor(workers=2, threads=1), job_fn=fake_job, reporter=SILENT)
    assert len(outcome.done) == 9 and not outcome.failed  # a rate job before its base would have failed
    records = [json.loads(p.read_text()) for p in (tmp_path / "res" / "jobs").glob("*.json")]
    assert {r["worker"]["TF_NUM_INTRAOP_THREADS"] for r in records} == {"1"}
    assert len({r["worker"]["pid"] for r in records}) == 2 and os.getpid() not in {r["worker"]["pid"] for r in records}


def test_ray_missing_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(UserError, match=r"pip install 'fcnpose-tf\[ray\]'"):
        RayExecutor(num_cpus=1).run(fake_job, None, [Job(0)], set(), lambda e: None)


@pytest.mark.parametrize("argv, message", [
    (["--executor", "ray", "--workers", "2"], "--workers is for the local executor"),
    (["--address", "auto"], "are for --executor ray"),
    (["--executor", "ray", "--address", "auto", "--num-cpus", "2"], "--num-cpus sizes a local Ray instance"),
    (["--executor", "ray", "--num-cpus", "1", "--threads", "2"], "no task could ever be scheduled"),
    (["--workers", "0"], "--workers must be at least 1"),
])
def test_executor_option_combinations(argv, message):
    from fcnpose_tf.cli import build_parser
    from fcnpose_tf.commands.sweep import make_executor, resolve_threads

    args = build_parser().parse_args(["sweep", *argv])
    with pytest.raises(UserError) as info:
        make_executor(args, resolve_threads(args))
    assert message in str(info.value)


# ------------------------------------------------------------------------------------------
# Real smoke sweeps (TensorFlow): local executor, then a local Ray instance
# ------------------------------------------------------------------------------------------

SMOKE = ["--rates", "0.5,0.7", "--folds", "2", "--epochs", "1", "--retrain-epochs", "1", "--input-size", "64",
         "--lr-patience", "3", "--quiet"]


def _check_smoke_outputs(out: Path, threads: int) -> None:
    for name in ("summary.md", "pck_vs_fps.png", "results.json", "sweep.json"):
        assert (out / name).is_file(), name
    for name in ("folds", "pruning", "requirements", "quantization"):
        assert (out / "tables" / f"{name}.md").is_file() and (out / "tables" / f"{name}.csv").is_file()
    assert sorted(p.name for p in (out / "jobs").iterdir()) == [
        "fold0_base.json", "fold0_p50.json", "fold0_p70.json", "fold1_base.json", "fold1_p50.json", "fold1_p70.json"]
    for k in (0, 1):
        assert (out / "models" / f"base_fold{k}.keras").is_file()
        assert (out / "models" / f"base_fold{k}_p70_fp16.tflite").is_file()
        assert (out / "models" / f"base_fold{k}_p70_int8.tflite").is_file()
    results = json.loads((out / "results.json").read_text())
    assert results["complete"] and len(results["jobs"]) == 6
    rows = {r["rate"]: r for r in results["tables"]["requirements"]["rows"]}
    assert rows[0.0]["params"] == 131705 and rows[0.5]["params"] == 35185 and rows[0.7]["params"] == 14668
    quant = {(r["rate"], r["quantize"]): r for r in results["tables"]["quantization"]["rows"]}
    assert [key for key in quant if key[0] == 0.7] == [(0.7, "float16"), (0.7, "int8")]  # a row per file
    for key in ((0.7, "float16"), (0.7, "int8")):
        assert quant[key]["folds"] == 2 and quant[key]["fps"]["mean"] > 0 and quant[key]["tflite_size_mb"] < 0.07
    assert results["config"]["lr_patience"] == 3  # reached both trainings' FitConfig:
    for k in (0, 1):
        assert json.loads((out / "models" / f"base_fold{k}_train.json").read_text())["config"]["lr_patience"] == 3
        assert json.loads((out / "models" / f"base_fold{k}_p70_train.json").read_text())["config"]["lr_patience"] == 3
    for job in results["jobs"]:
        assert job["machine"]["threads"] == threads and job["tensorflow_threads"]["intra_op"] == threads
        for section in [job["keras"]] if job["kind"] == "base" else [job["tflite"], job["tflite_int8"]]:
            assert section["timing"]["threads"] == threads and section["metrics"]["num_frames"] == 10


def _sweep_cli(*args, cwd, env=None):
    """`python -m fcnpose_tf ARGS` in a fresh process (the sweep sets TensorFlow's threads before it starts), its
    evaluations timing a few frames (`cli_few_timed.py`): no test here asserts a timing beyond its presence."""
    return run_cli_few_timed(*args, cwd=cwd, env=env)


@pytest.fixture(scope="module")
def smoke_sweep(tmp_path_factory, smoke_frames):
    """A real sweep on the local executor, 1 thread per job (not TensorFlow's default on any machine), run once:
    each smoke test works on its own copy of the results folder."""
    out = tmp_path_factory.mktemp("smokesweep") / "res"
    proc = _sweep_cli("sweep", "--data", smoke_frames, "--out", out, *SMOKE, "--threads", "1", cwd=out.parent)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc


@pytest.mark.slow
def test_smoke_sweep_local_then_rerun_skips(tmp_path, smoke_frames, smoke_sweep, cli_here):
    frames = smoke_frames
    first, proc = smoke_sweep
    out = tmp_path / "res"
    shutil.copytree(first, out)  # copy2: the files' modification times too
    _check_smoke_outputs(out, threads=1)
    assert "Pruning results, Keras" in proc.stdout and "14,668" in proc.stdout
    assert "frames at 64x64" not in proc.stdout + proc.stderr  # --quiet: no progress bars in logs
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "models").iterdir()}
    jobs = {p.name: p.read_bytes() for p in (out / "jobs").iterdir()}
    record = json.loads(jobs["fold0_p70.json"])
    assert record["pruning"]["importance"] == "l1" and record["distillation"] is None  # the paper's recipe

    status, stdout, err = cli_here("sweep", "--data", frames, "--out", out, *SMOKE, "--threads", "1")  # nothing runs
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "skipping 6 finished job(s)" in stdout and "nothing to run" in stdout
    assert {p.name: p.stat().st_mtime_ns for p in (out / "models").iterdir()} == stamps
    assert {p.name: p.read_bytes() for p in (out / "jobs").iterdir()} == jobs

    status, _, err = cli_here("sweep", "--data", frames, "--out", out, *SMOKE, "--threads", "2")
    assert status == 2 and "threads 1 -> 2" in err

    # --retime: the same measurements from the saved files; identical metrics, new timings, same models (a new
    # process: it sets TensorFlow's threads, which this one fixed when it first ran a model)
    retime = _sweep_cli("sweep", "--out", out, "--retime", cwd=tmp_path)
    assert retime.returncode == 0, retime.stdout[-3000:] + retime.stderr[-3000:]
    assert "metrics identical" in retime.stdout and "FPS before" in retime.stdout
    assert {p.name: p.stat().st_mtime_ns for p in (out / "models").iterdir() if p.suffix != ".json"} == \
        {k: v for k, v in stamps.items() if not k.endswith(".json")}
    for name, raw in jobs.items():
        old, new = json.loads(raw), json.loads((out / "jobs" / name).read_text())
        for section in ("keras", "tflite", "tflite_int8"):
            if section in old:
                assert new[section]["metrics"] == old[section]["metrics"]
                assert new[section]["timing"]["threads"] == 1
                assert new[section]["timing"]["total_ms"] != old[section]["timing"]["total_ms"]
        assert new["retimed"]["tensorflow_threads"]["intra_op"] == 1
    report = json.loads((out / "models" / "base_fold0_p70_report.json").read_text())
    job = json.loads((out / "jobs" / "fold0_p70.json").read_text())
    assert report["quantized"]["timing"] == job["tflite"]["timing"]
    assert report["other_quantized"][0]["timing"] == job["tflite_int8"]["timing"]
    assert "re-measured with `--retime` for every job" in (out / "summary.md").read_text()
    moved = tmp_path / "moved"
    out.rename(moved)
    status, stdout, _ = cli_here("sweep", "--out", moved, "--report-only")
    assert status == 0 and f"wrote {moved / 'summary.md'}" in stdout


RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled", "RAY_NUM_REDIS_GET_RETRIES": "1800"}
"""The environment of the Ray head and of its drivers: no usage report, no token (a token in ~/.ray turns on token
authentication for `ray start` alone, and a driver without it is refused), 30 minutes (not 20 s) for a driver to
reach a slow GCS."""

RAY_START = """
import sys, time

import ray._private.services as services
from ray.scripts.scripts import main


def patient(get_node):
    # ray start gives the raylet a fixed 30 s to register with the GCS (Ray 2.60, ray/_private/node.py), asking
    # get_node until then: each call here asks for up to 30 minutes instead (a loaded machine can take minutes)
    def get_node_patiently(*args, **kwargs):
        deadline = time.monotonic() + 1800
        while True:
            try:
                return get_node(*args, **kwargs)
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
    return get_node_patiently


if hasattr(services, "get_node"):  # another Ray may register its raylet otherwise: then its own limit applies
    services.get_node = patient(services.get_node)
sys.argv[0] = "ray"
main()
"""
"""`ray start ARGS` (`python -c RAY_START ARGS`) without the fixed limit on the raylet's registration."""


def _free_ports(count: int) -> list[int]:
    """`count` distinct TCP ports free on this machine now (each bound to port 0, then released)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind(("", 0))
        return [sock.getsockname()[1] for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def _stop_ray_head(head: subprocess.Popen, temp: str) -> None:
    """SIGTERM to `ray start --block`, which stops every process it started; anything of its group left is killed."""
    head.terminate()
    try:
        head.wait(timeout=300)
    except subprocess.TimeoutExpired:
        head.kill()
        head.wait()
    try:
        os.killpg(head.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    shutil.rmtree(temp, ignore_errors=True)


def _start_ray_head(log: Path) -> tuple[subprocess.Popen, str, str]:
    """One `ray start --head --block` (RAY_START), its output in `log`; (process, temp folder, address) once Ray says
    it started, or the process ended (a failed start)."""
    gcs, grpc, listen, metrics, runtime_env, node_manager, objects, dashboard, client = _free_ports(9)
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths must fit in 107 bytes
    command = [sys.executable, "-c", RAY_START, "start", "--head", "--block", "--port", gcs, "--num-cpus", 2,
               "--object-store-memory", 256 * 2**20, "--include-dashboard", "false", "--disable-usage-stats",
               "--temp-dir", temp, "--dashboard-agent-grpc-port", grpc, "--dashboard-agent-listen-port", listen,
               "--metrics-export-port", metrics, "--runtime-env-agent-port", runtime_env,
               "--node-manager-port", node_manager, "--object-manager-port", objects, "--dashboard-port", dashboard,
               "--ray-client-server-port", client]
    path = os.pathsep.join([str(Path(__file__).parent), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = dict(os.environ, **RAY_ENV, PYTHONPATH=path, RAY_enable_worker_prestart="0",
               RAY_prestart_worker_first_driver="0", RAY_worker_niceness="0",
               RAY_agent_register_timeout_ms=str(30 * 60 * 1000), RAY_worker_register_timeout_seconds=str(30 * 60))
    with open(log, "w") as out:
        head = subprocess.Popen([str(a) for a in command], stdout=out, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True)
    deadline = time.monotonic() + 30 * 60  # generous: the wait ends as soon as Ray says it started
    while "Ray runtime started" not in log.read_text() and head.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    return head, temp, f"127.0.0.1:{gcs}"


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory):
    """A Ray head of 2 CPUs on this machine, started once for the module's Ray tests (`ray start --head --block`);
    its address ("127.0.0.1:PORT").

    Ray 2.60's own limits on a start are fixed and short, and a loaded machine exceeds them: the raylet waits 15 s for
    an agent's port file when the agent picks its port (ray-project/ray#65983; `ray.init` of a local instance cannot
    give those ports), and `ray start` 30 s for the raylet to register. So every port is given (nothing waits for a
    port file), the registration is asked for up to 30 minutes (RAY_START), the limits Ray reads from its environment
    are long (their cost is only on failure), and a start that fails anyway is tried again (3 times, new ports).
    Workers run at normal priority (Ray's default is nice 15: a loaded machine starves them), and no worker starts
    before a task needs one (every task of a sweep has a runtime_env of its own); they import this folder's modules
    (tasks of fake jobs). SIGTERM ends `ray start` and every process it started.
    """
    pytest.importorskip("ray")
    logs = tmp_path_factory.mktemp("rayhead")
    for attempt in range(3):
        log = logs / f"ray_start_{attempt}.txt"
        head, temp, address = _start_ray_head(log)
        if head.poll() is None and "Ray runtime started" in log.read_text():
            break
        _stop_ray_head(head, temp)
    else:
        pytest.fail(f"no Ray head started in 3 attempts; the last said:\n{log.read_text()[-5000:]}")
    try:
        yield address
    finally:
        _stop_ray_head(head, temp)


def meeting_job(config: SweepConfig, job: Job) -> dict:
    """`fake_job` once another job of the same kind (base or rate) has started too: it waits for that job's mark in
    OUT/started, so it returns only when two tasks ran at once (after 10 minutes alone it fails instead)."""
    started = Path(config.out) / "started"
    started.mkdir(exist_ok=True)
    kind = "base" if job.is_base else "rate"
    (started / f"{kind}_{job.name}").touch()
    deadline = time.monotonic() + 600  # only a failure waits this long
    while len(list(started.glob(f"{kind}_*"))) < 2:
        if time.monotonic() > deadline:
            raise UserError(f"{job.name}: no other {kind} job ran beside it")
        time.sleep(0.05)
    return fake_job(config, job)


@pytest.mark.slow
def test_ray_tasks_run_at_once_on_workers_and_bases_before_their_rates(tmp_path, frames, ray_head, monkeypatch):
    """Both bases at once on 2 CPUs, then the rates two at a time (each waits for another: see meeting_job), in
    worker processes with the thread caps of the tasks' runtime_env; a rate job before its base would fail."""
    for name, value in RAY_ENV.items():
        monkeypatch.setenv(name, value)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}  # ray.init sets them
    try:
        outcome = run_sweep(_config(tmp_path / "res", frames), RayExecutor(address=ray_head, threads=1),
                            job_fn=meeting_job, reporter=SILENT)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert sorted(outcome.done) == ["fold0_base", "fold0_p50", "fold0_p70", "fold1_base", "fold1_p50", "fold1_p70"]
    assert not outcome.failed
    records = [json.loads(p.read_text()) for p in (tmp_path / "res" / "jobs").glob("*.json")]
    assert {r["worker"]["TF_NUM_INTRAOP_THREADS"] for r in records} == {"1"}
    pids = {r["worker"]["pid"] for r in records}
    assert len(pids) >= 2 and os.getpid() not in pids
    results = json.loads((tmp_path / "res" / "results.json").read_text())
    assert results["complete"] and results["runs"][-1]["executor"] == "ray"
    assert results["runs"][-1]["cluster"] == {"cpus": 2, "nodes": 1}


def test_a_local_ray_instance_is_sized_by_num_cpus_and_shut_down(monkeypatch):
    """--num-cpus: `ray.init` of a local instance of that many CPUs, no dashboard, a small object store; the run is
    described with the instance's CPUs; Ray is shut down after the jobs (a stand-in for ray: the real one runs on the
    module's head, `ray_head`)."""
    import types

    calls = []
    ref = object()
    fake = types.SimpleNamespace(
        init=lambda **kwargs: calls.append(("init", kwargs)), cluster_resources=lambda: {"CPU": 3.0},
        nodes=lambda: [{"Alive": True}, {"Alive": False}], shutdown=lambda: calls.append(("shutdown", {})),
        remote=lambda fn: types.SimpleNamespace(options=lambda **options: types.SimpleNamespace(
            remote=lambda *args: calls.append(("remote", options)) or ref)),
        wait=lambda pending, num_returns: ([pending[0]], pending[1:]), get=lambda r: {"job": "fold0_base"})
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setitem(sys.modules, "ray.exceptions", types.SimpleNamespace(RayError=RuntimeError,
                                                                             RayTaskError=RuntimeError))
    executor, events = RayExecutor(num_cpus=3, threads=1), []
    executor.run(fake_job, None, [Job(0)], set(), events.append)
    init = calls[0][1]
    assert calls[0][0] == "init" and init["num_cpus"] == 3 and init["include_dashboard"] is False
    assert init["object_store_memory"] == 256 * 2**20 and "address" not in init
    assert calls[1] == ("remote", {"num_cpus": 1, "max_retries": 1,
                                   "runtime_env": {"env_vars": thread_env(1)}})
    assert calls[-1] == ("shutdown", {}) and [e.kind for e in events] == ["submitted", "done"]
    assert executor.describe()["cluster"] == {"cpus": 3.0, "nodes": 1} and executor.describe()["num_cpus"] == 3


@pytest.mark.slow
def test_smoke_sweep_on_a_ray_cluster(tmp_path, smoke_frames, smoke_sweep, ray_head, cli, cli_here):
    """A real job as a Ray task on the module's head (`--address`): fold 1's 70% job in a folder whose other jobs the
    local executor finished; it compresses and exports in a Ray worker with 1 thread and writes the same record as
    a local run. (Tasks at once on the workers, a base before its rates, the thread caps of the tasks' environment:
    test_ray_tasks_run_at_once_on_workers_and_bases_before_their_rates, with fake jobs on the same head.)"""
    frames = smoke_frames
    out = tmp_path / "res"
    shutil.copytree(smoke_sweep[0], out)
    for path in [out / "jobs" / "fold1_p70.json", *(out / "models").glob("base_fold1_p70*")]:
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    proc = cli("sweep", "--data", frames, "--out", out, *SMOKE, "--executor", "ray", "--address", ray_head,
               "--threads", "1", env=RAY_ENV)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "skipping 5 finished job(s): fold0_base, fold0_p50, fold0_p70, fold1_base, fold1_p50" in proc.stdout
    _check_smoke_outputs(out, threads=1)
    results = json.loads((out / "results.json").read_text())
    assert results["runs"][-1]["executor"] == "ray" and results["runs"][-1]["cluster"]["cpus"] == 2
    assert results["runs"][-1]["address"] == ray_head and results["runs"][-1]["jobs_done"] == ["fold1_p70"]
    record = json.loads((out / "jobs" / "fold1_p70.json").read_text())
    assert record["tensorflow_threads"]["env_TF_NUM_INTRAOP_THREADS"] == "1"  # the task's runtime_env
    local = json.loads((smoke_sweep[0] / "jobs" / "fold1_p70.json").read_text())
    assert sorted(record) == sorted(local) and record["config_key"] == local["config_key"]
    assert record["base_model_sha256"] == local["base_model_sha256"]
    status, stdout, _ = cli_here("sweep", "--data", frames, "--out", out, *SMOKE, "--executor", "ray", "--num-cpus",
                                 "2", "--threads", "1")  # every job finished: no Ray instance is started
    assert status == 0 and "skipping 6 finished job(s)" in stdout


def test_a_rate_job_whose_every_format_is_refused_fails_with_one_line(tmp_path, monkeypatch):
    """compress finishes with every format refused (its report's quantized None): the job is a clean failure."""
    import types

    import fcnpose_tf.compression.compress
    from fcnpose_tf.compression.report import CompressReport, RefusedFormat
    from fcnpose_tf.sweep import jobs

    base = jobs.base_model_path(tmp_path, 0)
    base.parent.mkdir(parents=True)
    base.write_bytes(b"not read")
    report = CompressReport(base_model=str(base), method="l1", recipe="", options={}, evaluation_frames="",
                            pck_normalisation="", threads=None, base={}, pruned_before_retraining={}, retrained={},
                            quantized=None, files={}, seconds=0.0, refused=[RefusedFormat("float16", "keypoint 3 lost"),
                                                                            RefusedFormat("int8", "2.5 px > 2 px")])
    monkeypatch.setattr(fcnpose_tf.compression.compress, "compress_model", lambda *a, **k: report)
    options = types.SimpleNamespace(checked=lambda base: None)
    config = types.SimpleNamespace(out=tmp_path, folds=2, reporter=SILENT, compress_options=lambda job: options)
    dataset = types.SimpleNamespace(split=lambda fold: ([0, 1], [2, 3]))
    with pytest.raises(UserError, match=r"no TFLite file passed its keypoint gate \(float16: keypoint 3 lost; int8"):
        jobs._run_rate(config, jobs.Job(0, 0.7), dataset)
