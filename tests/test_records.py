"""The training record (NAME_train.json) read as a `TrainingRecord`: its fields from a full record, an older
one, and files that are no record at all."""

import json

import pytest

from fcnpose_tf.records import TrainingRecord, lineage, training_record

KEYPOINTS = ["base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3", "flange", "tool"]


def written_by_train(**changes):
    """A NAME_train.json as `fcnpose-tf train` writes it (the shape of a real one, trimmed)."""
    record = {
        "data": "nc_train/ur5_synth.json",
        "data_sha256": "ea46fb790d1a6f6b6848ba811933ba411c254351b06e2984b8d205dfc66246aa",
        "num_frames": 240, "split": "fold 2 of 5", "fold": 2, "folds": 5, "split_seed": 0, "input_size": 288,
        "augment": "paper", "augment_copies": 2, "train_samples": 576, "val_frames": 48,
        "schema": {"name": "ur5", "keypoints": KEYPOINTS, "edges": [[i, i + 1] for i in range(7)]},
        "init": "generalist",
        "config": {"epochs": 500, "patience": 12, "batch_size": 8, "learning_rate": 0.001, "seed": 0,
                   "positive_weight": 8.0, "lr_patience": 4, "lr_schedule": "plateau", "freeze": 2, "distill": 0.0},
        "epochs_run": 31, "best_epoch": 19, "best_val_loss": 0.0123, "train_seconds": 1500.2, "stopped_early": True,
        "validation": {"metrics": {"pck@0.5_bbox": 0.97}, "timing": {}},
    }
    record.update(changes)
    return record


def test_a_full_record_reads_into_its_fields():
    raw = written_by_train()
    record = TrainingRecord.from_json(raw)
    assert record == TrainingRecord(data="nc_train/ur5_synth.json", data_sha256=raw["data_sha256"], fold=2, folds=5,
                                    split="fold 2 of 5", split_seed=0, keypoints=tuple(KEYPOINTS),
                                    positive_weight=8.0, input_size=288, augment="paper", augment_copies=2,
                                    init="generalist", raw=raw)
    assert record.raw is raw and record.raw["epochs_run"] == 31  # the rest of the file, by key
    assert isinstance(record.keypoints, tuple) and isinstance(record.positive_weight, float)
    with pytest.raises(AttributeError):
        record.fold = 3  # frozen
    hash(record)  # the raw dict is left out of the hash


def test_the_hold_out_split_has_no_fold():
    record = TrainingRecord.from_json(written_by_train(split="hold-out 80/20", fold=None))
    assert record.fold is None and record.folds == 5 and record.split == "hold-out 80/20"


def test_the_fields_are_the_keys_train_writes():
    """Each field reads the key (or nested key) `train` writes under that name, unchanged."""
    raw = written_by_train()
    record = TrainingRecord.from_json(raw)
    for name in ("data", "data_sha256", "fold", "folds", "split", "split_seed", "input_size", "augment",
                 "augment_copies", "init"):
        assert getattr(record, name) == raw[name], name
    assert list(record.keypoints) == raw["schema"]["keypoints"]
    assert record.positive_weight == raw["config"]["positive_weight"]


def test_a_start_train_kept_unchanged_is_told_apart_from_a_trained_one():
    """start_kept: no epoch beat the start (best epoch 0), or the start as saved measured better; never for a random
    start (no init)."""
    assert not TrainingRecord.from_json(written_by_train()).start_kept  # best epoch 19
    assert TrainingRecord.from_json(written_by_train(best_epoch=0)).start_kept
    assert TrainingRecord.from_json(written_by_train(start_as_saved={"chose": "start", "start_mean_pck": 0.82})
                                    ).start_kept
    assert not TrainingRecord.from_json(written_by_train(start_as_saved={"chose": "trained"})).start_kept
    assert not TrainingRecord.from_json(written_by_train(best_epoch=0, init=None)).start_kept
    assert not TrainingRecord.from_json(written_by_train(best_epoch="0", start_as_saved="start")).start_kept


def test_an_older_record_reads_its_missing_keys_as_none():
    """Records from before a key existed, or a compressed model's (no split, folds, schema...)."""
    raw = {"data": "labels.json", "config": {"epochs": 10}, "epochs_run": 10}
    record = TrainingRecord.from_json(raw)
    assert record == TrainingRecord(data="labels.json", raw=raw)
    assert None is record.data_sha256 is record.fold is record.folds is record.split is record.split_seed
    assert None is record.keypoints is record.positive_weight is record.input_size
    assert TrainingRecord.from_json({}) == TrainingRecord()


def test_values_of_another_type_read_as_none():
    record = TrainingRecord.from_json(written_by_train(
        fold="2", folds=True, data_sha256=123, schema=["base"], config={"positive_weight": "8"}, input_size=None))
    assert None is record.fold is record.folds is record.data_sha256 is record.keypoints
    assert None is record.positive_weight is record.input_size
    assert TrainingRecord.from_json(written_by_train(schema={"keypoints": ["base", 1]})).keypoints is None
    assert TrainingRecord.from_json(written_by_train(config=None)).positive_weight is None
    assert TrainingRecord.from_json(written_by_train(config={"positive_weight": 20})).positive_weight == 20.0


@pytest.mark.parametrize("value", [[], [1, 2], "text", 3, None])
def test_from_json_refuses_what_is_no_json_object(value):
    with pytest.raises(TypeError):
        TrainingRecord.from_json(value)


def test_training_record_reads_the_file_beside_the_model_and_its_derivatives(tmp_path):
    (tmp_path / "m_train.json").write_text(json.dumps(written_by_train()))
    for model in ("m.keras", "m_fp16.tflite", "m_int8.tflite", "m_p70.keras", "m_p5.keras"):
        record = training_record(tmp_path / model)
        assert isinstance(record, TrainingRecord) and record.fold == 2 and record.keypoints == tuple(KEYPOINTS)
    assert training_record(tmp_path / "other.keras") is None  # none beside it
    for other in ("m_best.keras", "m_v2.keras", "m_p700.keras"):  # another model named like it: not its record
        assert training_record(tmp_path / other) is None, other


@pytest.mark.parametrize("text", ["", "{not json", "[1, 2, 3]", '"a string"', "42", "null", "\xff\xfe"])
def test_training_record_is_none_for_a_file_that_is_no_record(tmp_path, text):
    (tmp_path / "m_train.json").write_text(text, encoding="latin-1")
    assert training_record(tmp_path / "m.keras") is None



def test_a_record_that_is_no_regular_file_is_no_record_and_no_wait(tmp_path):
    import os
    import threading

    from fcnpose_tf.records import recorded_schema

    (tmp_path / "m_train.json").mkdir()
    (tmp_path / "loop_train.json").symlink_to("loop_train.json")
    os.mkfifo(tmp_path / "pipe_train.json")  # opened for reading, it would wait for a writer: a hung `run`
    found = {}
    reader = threading.Thread(target=lambda: found.update(
        (name, (recorded_schema(tmp_path / name), training_record(tmp_path / name)))
        for name in ("m.keras", "loop_fp16.tflite", "pipe.keras")), daemon=True)
    reader.start()
    reader.join(timeout=10)
    if reader.is_alive():
        try:  # let the waiting reader go: a writer that closes at once
            os.close(os.open(tmp_path / "pipe_train.json", os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass
    assert found == dict.fromkeys(("m.keras", "loop_fp16.tflite", "pipe.keras"), (None, None))

def test_lineage_follows_each_records_init_back_to_a_bundled_start(tmp_path):
    """round2 was trained from round1 (a path), round1 from the generalist: round2's lineage names both, nearest first;
    a random start, a model without a record and a loop end it."""
    (tmp_path / "round1_train.json").write_text(json.dumps(written_by_train(init="generalist")))
    (tmp_path / "round1.keras").write_bytes(b"")
    (tmp_path / "round2_train.json").write_text(json.dumps(written_by_train(init=str(tmp_path / "round1.keras"))))
    assert lineage(tmp_path / "round2.keras") == [str(tmp_path / "round1.keras"), "generalist"]
    assert lineage(tmp_path / "round1.keras") == ["generalist"]
    assert lineage(tmp_path / "round2.keras", kept_only=True) == []  # both rounds changed their start's weights
    (tmp_path / "round1_train.json").write_text(json.dumps(written_by_train(init="generalist", best_epoch=0)))
    assert lineage(tmp_path / "round2.keras", kept_only=True) == []  # round 2 did
    (tmp_path / "round2_train.json").write_text(json.dumps(written_by_train(
        init=str(tmp_path / "round1.keras"), start_as_saved={"chose": "start"})))
    assert lineage(tmp_path / "round2.keras", kept_only=True) == [str(tmp_path / "round1.keras"), "generalist"]
    assert lineage(tmp_path / "none.keras") == []
    (tmp_path / "scratch_train.json").write_text(json.dumps(written_by_train(init=None)))
    assert lineage(tmp_path / "scratch.keras") == []
    (tmp_path / "gone_train.json").write_text(json.dumps(written_by_train(init=str(tmp_path / "deleted.keras"))))
    assert lineage(tmp_path / "gone.keras") == [str(tmp_path / "deleted.keras")]
    for name, parent in (("a", "b"), ("b", "a")):  # a loop of two records
        (tmp_path / f"{name}.keras").write_bytes(b"")
        (tmp_path / f"{name}_train.json").write_text(json.dumps(written_by_train(init=str(tmp_path / f"{parent}.keras"))))
    assert lineage(tmp_path / "a.keras") == [str(tmp_path / "b.keras"), str(tmp_path / "a.keras")]


def test_every_bundled_record_and_report_reads_unchanged():
    """The files a previous version wrote and the wheel ships (saved_models/) read as they are: each training record
    as a `TrainingRecord` with its schema and split, the compress report back to the same JSON and its table."""
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.compression.report import CompressReport
    from fcnpose_tf.compression.summary import report_table

    folder = models_dir()
    records = sorted(folder.glob("*_train.json"))
    assert len(records) >= 4
    for path in records:
        record = training_record(path.with_name(path.name.replace("_train.json", ".keras")))
        assert record is not None and record.data_sha256 and record.raw["epochs_run"] >= 1, path.name
        if "pruned_from" in record.raw:  # compress's retraining record: the rate and widths' origin
            assert record.raw["rate"] == 0.7 and record.positive_weight, path.name
        else:  # train's: the schema and the split
            assert record.keypoints == tuple(KEYPOINTS) and record.split, path.name
    reports = sorted(folder.glob("*_report.json"))
    assert reports
    for path in reports:
        written = json.loads(path.read_text())
        report = CompressReport.from_json(written)
        assert report.to_json() == written, path.name
        assert "float16 TFLite" in report_table(report), path.name


def test_the_frames_a_model_was_trained_on_are_found_from_any_folder_or_refused(tmp_path, monkeypatch):
    """`export`/`compress` without --data: the annotation file and images folder `train` recorded, found from any
    current folder; a user's model whose recorded frames are gone is refused, never given the synthetic frames."""
    from fcnpose_tf.data import synthcache
    from fcnpose_tf.data.args import default_data
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.records import file_sha256

    project = tmp_path / "project"
    project.mkdir()
    via = project / "labels.json"
    via.write_text("{}")
    models = tmp_path / "models"
    models.mkdir()
    record = {"data": "project/labels.json", "data_sha256": file_sha256(via), "data_absolute": str(via),
              "images": str(tmp_path / "photos")}
    (models / "arm_train.json").write_text(json.dumps(record))
    said = []
    monkeypatch.chdir(models)  # not the folder train ran in: the path as given does not resolve here
    assert default_data(models / "arm_int8.tflite", say=said.append) == (via, tmp_path / "photos")
    assert default_data(models / "arm.keras", tmp_path / "mine", say=said.append) == (via, tmp_path / "mine")
    assert said[0] == f"Data: {via}, the frames arm_int8.tflite was trained on (its training record)"
    via.write_text("{ }")  # changed since
    with pytest.raises(UserError, match="not there or has changed; give them with --data"):
        default_data(models / "arm.keras", say=said.append)
    monkeypatch.setattr(synthcache, "default_training_data", lambda: tmp_path / "synth.json")
    assert default_data(models / "other.keras", say=said.append) == (tmp_path / "synth.json", None)  # no record
    assert "no training record names the frames other.keras was trained on" in said[-1]


def test_evaluating_a_model_without_a_record_on_frames_with_stored_splits_says_its_training_frames_may_be_among_them(
        tmp_path):
    """An exported file copied away from NAME_train.json is measured on every frame; when the frames have stored
    splits (something was trained on them), the description says its training frames may be among them."""
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.training.evaluate import choose_frames
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=6)
    first = load_dataset(data)  # splits created now: a set nothing was trained on yet
    assert choose_frames(first, tmp_path / "m_fp16.tflite", "auto", None)[1] == "all 6 frames"
    indices, described = choose_frames(load_dataset(data), tmp_path / "m_fp16.tflite", "auto", None)
    assert indices == list(range(6)) and described.startswith("all 6 frames; no training record beside m_fp16.tflite")
    # a record of another annotation file (the same frames saved again in VIA: other bytes) says so too
    (tmp_path / "m_train.json").write_text(json.dumps({"data_sha256": "0" * 64, "fold": None}))
    described = choose_frames(load_dataset(data), tmp_path / "m_fp16.tflite", "auto", None)[1]
    assert described.startswith("all 6 frames; m_fp16.tflite's training record names another annotation file")
