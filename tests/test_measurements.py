"""Typed measurements read every report and record file written before them, and write them back key for key."""

from __future__ import annotations

import json

import pytest

from fcnpose_tf.bundled import models_dir
from fcnpose_tf.measurements import KeypointMetrics, Measurement, SequenceReport, Timing

BUNDLED = sorted(models_dir().glob("*.json"))


def _measured(value, path=""):
    """(where, object) of every object in a parsed file that holds "metrics" (a measurement)."""
    if isinstance(value, dict):
        if isinstance(value.get("metrics"), dict) and "per_keypoint" in value["metrics"]:
            yield path, value
        for key, inner in value.items():
            yield from _measured(inner, f"{path}.{key}")
    elif isinstance(value, list):
        for i, inner in enumerate(value):
            yield from _measured(inner, f"{path}[{i}]")


def test_the_bundled_files_hold_measurements():
    names = {path.name for path in BUNDLED}
    assert {"fcnpose_ur5_p70_report.json", "fcnpose_ur5_train.json", "fcnpose_ur5_heldout.json"} <= names
    assert sum(1 for path in BUNDLED for _ in _measured(json.loads(path.read_text()))) >= 8


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.name)
def test_every_bundled_measurement_reads_and_writes_back_key_for_key(path):
    for where, entry in _measured(json.loads(path.read_text())):
        measurement = Measurement.from_json(entry)
        written = measurement.to_json()
        assert json.dumps(written) == json.dumps({k: entry[k] for k in ("metrics", "timing") if k in entry}), where
        assert Measurement.from_json(json.loads(json.dumps(written))) == measurement


def test_typed_access_matches_the_keys():
    entry = json.loads((models_dir() / "fcnpose_ur5_heldout.json").read_text())
    metrics, timing = KeypointMetrics.from_json(entry["metrics"]), Timing.from_json(entry["timing"])
    assert metrics.pck[0.5] == entry["metrics"]["pck@0.5_bbox"] and metrics.pck_auc == entry["metrics"]["pck_auc_0-20px"]
    assert list(metrics.pck) == [0.5, 0.2, 0.05] and metrics.max_px == 20.0
    assert metrics.per_keypoint["tool"].epe_px == entry["metrics"]["per_keypoint"]["tool"]["epe_px"]
    assert timing.inference_ms.mean == entry["timing"]["inference_ms"]["mean"] and timing.fps == entry["timing"]["fps"]
    assert Measurement.from_json({"metrics": entry["metrics"]}).timing is None
    with pytest.raises(TypeError):
        KeypointMetrics.from_json([])


def test_a_sequence_report_round_trips():
    raw = {"jitter_px": 1.2, "lag_frames": 0.5, "epe_px": 3.0, "pck@0.05_bbox": 0.8, "missing_fraction": 0.0}
    report = {"fps": 30.0, "definitions": "d", "raw": raw,
              "smoothing": {"filter": "one-euro", "min_cutoff_hz": 1.0, "beta": 0.1, "d_cutoff_hz": 1.0,
                            "max_coast_frames": 3}, "smoothed": {**raw, "jitter_px": 0.4}}
    assert json.dumps(SequenceReport.from_json(report).to_json()) == json.dumps(report)
    plain = {"fps": 30.0, "definitions": "d", "raw": raw}
    assert SequenceReport.from_json(plain).to_json() == plain


@pytest.mark.parametrize("path", sorted(models_dir().glob("*_report.json")), ids=lambda p: p.name)
def test_a_bundled_compress_report_reads_typed_and_writes_back_byte_for_byte(path):
    from fcnpose_tf.compression.report import CompressReport, ModelStep, TFLiteStep
    from fcnpose_tf.compression.summary import report_table

    text = path.read_text()
    report = CompressReport.from_json(json.loads(text))
    assert isinstance(report.base, ModelStep) and isinstance(report.quantized, TFLiteStep)
    assert all(isinstance(step, TFLiteStep) for step in report.other_quantized)
    assert json.dumps(report.to_json()) == json.dumps(json.loads(text))
    assert report.quantized.parity.keypoints_compared > 0 and report.base.timing.threads == report.threads
    assert report.quantized.parity.to_dict() == json.loads(text)["quantized"]["export"]["parity"]
    assert f"{report.quantized.metrics.pck[0.05]:.3f}" in report_table(report)


@pytest.mark.parametrize("path", sorted(models_dir().glob("*_train.json")), ids=lambda p: p.name)
def test_a_bundled_training_record_reads_its_validation_typed(path):
    from fcnpose_tf.records import TrainingRecord

    raw = json.loads(path.read_text())
    record = TrainingRecord.from_json(raw)
    if "validation" not in raw:  # a compressed model's record: its report holds the measurements
        assert record.validation is None
        return
    assert record.validation.to_json() == raw["validation"]
    assert record.validation.metrics.pck[0.5] == raw["validation"]["metrics"]["pck@0.5_bbox"]
