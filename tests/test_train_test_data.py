"""train --test-data (a fixed test set measured at the start and the end of every training) and a training
stopped before its first epoch ends (nothing to resume, nothing left behind)."""

import io
import json

import cv2
import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from fcnpose_tf.progress import SILENT
from tests.test_train_evaluate import make_via_folder


@pytest.mark.slow
@pytest.mark.parametrize("trained_start", [True, False])
def test_stopped_before_the_first_epoch_leaves_no_checkpoint_and_does_not_suggest_resume(
        tmp_path, monkeypatch, trained_start):
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    out = tmp_path / "m.keras"
    config = train.FitConfig(epochs=2, patience=5, batch_size=4)

    def stop_in_first_epoch(self, epoch, logs=None):  # Ctrl-C or SIGTERM (the handler raises the same) mid-epoch
        raise KeyboardInterrupt

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", stop_in_first_epoch)
    with pytest.raises(UserError) as info:
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, reporter=SILENT,
                  start_is_candidate=trained_start)
    assert "before the first epoch ended" in str(info.value) and "--resume" not in str(info.value)
    assert not (tmp_path / "m.ckpt").exists() and not out.exists()
    with pytest.raises(UserError, match="no checkpoint to resume from"):
        train.check_checkpoint(out, resume=True, force=False)
    train.check_checkpoint(out, resume=False, force=False)  # a plain rerun is not refused


def test_the_test_line_compares_start_and_end_and_says_when_the_end_is_worse():
    from fcnpose_tf.training.train import FixedTestSetRecord, format_test_set_line as line_of

    def format_test_set_line(test):
        return line_of(FixedTestSetRecord.from_json(test))

    start = {"pck@0.5_bbox": 0.9, "pck@0.2_bbox": 0.8, "pck@0.05_bbox": 0.3, "epe_px": 4.0, "missing_fraction": 0.0}
    better = {**start, "pck@0.05_bbox": 0.4, "epe_px": 3.5}
    worse = {**start, "pck@0.5_bbox": 0.85, "epe_px": 5.25}
    test = {"data": "t.json", "data_sha256": "0" * 64, "num_frames": 12, "definitions": "d",
            "start_model": "generalist"}
    line = format_test_set_line({**test, "start": start, "end": better})
    assert "\n" not in line and line.startswith("Test set t.json (12 frames): PCK@0.5 0.900 -> 0.900")
    assert "PCK@0.05 0.300 -> 0.400" in line and "EPE 4.00 -> 3.50 px" in line
    assert line.endswith("(start: generalist); no figure worse than the start")
    assert format_test_set_line({**test, "start": start, "end": worse}).endswith(
        "; WORSE than the start in PCK@0.5, EPE")
    more_missing = {**better, "missing_fraction": 0.019}  # tripled from 0.006 in a user's round 2
    assert format_test_set_line({**test, "start": {**start, "missing_fraction": 0.006}, "end": more_missing}).endswith(
        "; WORSE than the start in missing")
    assert format_test_set_line({**test, "start": start, "end": {**better, "epe_px": 4.004}}).endswith(
        "no figure worse than the start")  # 4.00 -> 4.00 as printed
    none = format_test_set_line({**test, "start_model": None, "start": None, "end": better})
    assert "EPE 3.50 px" in none and none.endswith("no starting model to compare (--init none: random weights)")


def test_a_bundled_test_set_record_reads_typed_and_writes_back_key_for_key():
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.training.train import FixedTestSetRecord

    entries = [record["test"] for path in sorted(models_dir().glob("**/*_train.json"))
               if "test" in (record := json.loads(path.read_text()))]
    assert entries
    for entry in entries:
        typed = FixedTestSetRecord.from_json(entry)
        assert json.dumps(typed.to_json()) == json.dumps(entry)
        assert typed.end.pck[0.5] == entry["end"]["pck@0.5_bbox"] and typed.start_model == entry["start_model"]


TRAIN = ("--epochs", "1", "--input-size", "64", "--augment", "paper", "--augment-copies", "0", "--batch-size", "4",
         "--quiet", "--threads", "1")


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_train_measures_the_start_and_every_fold_on_the_fixed_test_set(tmp_path, cli_here):
    data = make_via_folder(tmp_path / "frames", n=8, size=(64, 64))
    test = make_via_folder(tmp_path / "test", n=3, size=(64, 64), seed=7)
    out = tmp_path / "models" / "arm.keras"
    status, stdout, err = cli_here("train", "--data", data, "--out", out, "--test-data", test, "--init", "workcell",
                                   *TRAIN)
    assert status == 0, stdout + err
    record = json.loads((tmp_path / "models" / "arm_train.json").read_text())["test"]
    assert record["data"] == str(test / "labels.json") and record["num_frames"] == 3
    assert record["start_model"] == "workcell"
    for key in ("start", "end"):
        figures = record[key]
        assert {"pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox", "epe_px", "missing_fraction"} <= set(figures)
        assert list(figures["per_keypoint"]) == list(UR5.keypoints)
        assert figures["num_frames"] == 3
    line = next(line for line in stdout.splitlines() if line.startswith("Test set "))
    assert "(3 frames): PCK@0.5 " in line and " -> " in line and "(start: workcell)" in line
    assert not (test / "labels.splits.json").exists()  # the test set's folder is only read

    out2 = tmp_path / "models" / "scratch.keras"
    status, stdout, err = cli_here("train", "--data", data, "--out", out2, "--test-data", test, "--init", "none",
                                   "--folds", "2", "--resplit", *TRAIN)
    assert status == 0, stdout + err
    for fold in (0, 1):
        record = json.loads((tmp_path / "models" / f"scratch_fold{fold}_train.json").read_text())["test"]
        assert record["start"] is None and record["start_model"] is None and record["end"]["num_frames"] == 3
    lines = [line for line in stdout.splitlines() if "Test set " in line]
    assert any(line.startswith("fold 1: Test set ") for line in lines)
    assert all("no starting model to compare (--init none" in line for line in lines)
    # stopped before fold 1 began: --resume keeps fold 0 (read from its record) and trains fold 1
    fold0 = (tmp_path / "models" / "scratch_fold0.keras").read_bytes()
    for path in (tmp_path / "models").glob("scratch_fold1*"):
        path.unlink()
    again = ("train", "--data", data, "--out", out2, "--test-data", test, "--init", "none", "--folds", "2", *TRAIN)
    status, stdout, err = cli_here(*again, "--resume")
    assert status == 0, stdout + err
    assert "scratch_fold0.keras: fold 0 was finished before (its record)" in stdout
    assert (tmp_path / "models" / "scratch_fold1.keras").is_file()
    assert (tmp_path / "models" / "scratch_fold0.keras").read_bytes() == fold0
    assert "pck@0.5" in stdout.lower() and "mean" in stdout.lower()  # the folds' summary, both folds in it
    status, _, err = cli_here(*again, "--resume")
    assert status == 2 and "all 2 folds of" in err and "nothing to resume" in err


@pytest.mark.slow
def test_a_test_set_that_shares_frames_or_differs_in_schema_is_refused_before_training(tmp_path, cli_here):
    from fcnpose_tf.data.via import ViaFrame, write_via_project
    from fcnpose_tf.keypoints import KeypointSchema

    data = make_via_folder(tmp_path / "frames", n=6, size=(64, 64))
    out = tmp_path / "m.keras"
    status, _, err = cli_here("train", "--data", data, "--out", out, "--test-data", data / "labels.json", *TRAIN)
    assert status == 2 and "6 of its 6 frames are also frames of --data" in err
    assert "never trained on" in err and len(err.strip().splitlines()) == 1
    import shutil  # the same frames copied under another folder and names: still the training frames

    copy = tmp_path / "copy"
    shutil.copytree(data, copy, ignore=shutil.ignore_patterns("*.splits.json"))
    project = json.loads((copy / "labels.json").read_text())
    for i, meta in enumerate(project["_via_img_metadata"].values()):
        (copy / "images" / meta["filename"]).rename(copy / "images" / f"x_{meta['filename']}")
        meta["filename"] = f"x_{meta['filename']}"
        if i % 2:  # the decoded JPEG saved as a PNG: other bytes, the same pixels
            image_path = copy / "images" / meta["filename"]
            assert cv2.imwrite(str(image_path.with_suffix(".png")), cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED))
            image_path.unlink()
            meta["filename"] = image_path.with_suffix(".png").name
    project["_via_img_metadata"] = {f"{m['filename']}-1": m for m in project["_via_img_metadata"].values()}
    (copy / "labels.json").write_text(json.dumps(project))
    status, _, err = cli_here("train", "--data", data, "--out", out, "--test-data", copy / "labels.json", *TRAIN)
    assert status == 2 and "6 of its 6 frames are also frames of --data" in err, err
    other = KeypointSchema.chain("arm3", ("base", "elbow", "tip"))
    write_via_project(tmp_path / "frames" / "images" / "arm3.json",
                      [ViaFrame("cam_00.jpg", 64, 64, np.full((3, 2), 20.0))], other)
    status, _, err = cli_here("train", "--data", data, "--out", out, "--test-data",
                              tmp_path / "frames" / "images" / "arm3.json", "--min-visible", "1", *TRAIN)
    assert status == 2 and "keypoint schema 'arm3'" in err
    assert not out.exists() and not (tmp_path / "m.ckpt").exists()
    # compress measures on --test-data under the same rule, before any work
    status, _, err = cli_here("compress", "--rate", "0.7", "--model", "workcell", "--data", data, "--test-data", copy / "labels.json",
                              "--out-dir", tmp_path / "c", "--quantize", "float16", "--threads", "1")
    assert status == 2 and "6 of its 6 frames are also frames of --data" in err, err
    assert not (tmp_path / "c").exists()


def test_a_test_set_whose_images_lie_elsewhere_is_read_with_test_images(tmp_path, cli_here):
    data = make_via_folder(tmp_path / "frames", n=6, size=(64, 64))
    test = make_via_folder(tmp_path / "test", n=3, size=(64, 64), seed=7)
    labels = tmp_path / "labels_apart" / "test.json"  # the VIA file in one folder, its images in another
    labels.parent.mkdir()
    (test / "labels.json").rename(labels)
    out = tmp_path / "m.keras"
    status, _, err = cli_here("train", "--data", data, "--out", out, "--test-data", labels, *TRAIN)
    assert status == 2 and "pass --test-images DIR" in err  # the hint names the option of the data it is about
    status, stdout, err = cli_here("train", "--data", data, "--out", out, "--test-data", labels, "--test-images",
                                   test / "images", "--init", "none", *TRAIN)
    assert status == 0, stdout + err
    assert json.loads((tmp_path / "m_train.json").read_text())["test"]["num_frames"] == 3


def test_a_start_that_is_no_keypoint_model_and_a_single_frame_are_refused_in_one_line(tmp_path, cli_here):
    import tf_keras as keras

    dense = tmp_path / "dense.keras"
    keras.Sequential([keras.Input((64, 64, 3)), keras.layers.Flatten(), keras.layers.Dense(4)]).save(dense)
    data = make_via_folder(tmp_path / "frames", n=6, size=(64, 64))
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "a.keras", "--init", dense, *TRAIN)
    assert status == 2 and err.strip().splitlines()[-1].startswith(f"error: {dense}: not a keypoint-map model")
    one = make_via_folder(tmp_path / "one", n=1, size=(64, 64))
    status, _, err = cli_here("train", "--data", one, "--out", tmp_path / "b.keras", *TRAIN)
    assert status == 2 and "1 usable frame; training needs at least 2" in err.strip().splitlines()[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dense.keras", "frames", "one"]


def _synth_frames(folder, n, seed):
    from fcnpose_tf.data.synth import generate

    generate(folder, n=n, seed=seed, width=160, height=120, workers=1, progress=False)
    return folder


def test_a_start_whose_crop_was_set_on_frames_of_another_aspect_is_not_weighed(tmp_path):
    """A 16:9 camera mode's crop on 4:3 frames is stretched: kept, the model would warn on every frame it reads, so
    the start as saved is not a candidate (as `choose_view` does not keep its view)."""
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.progress import Reporter
    from fcnpose_tf.training.model import build_fcn_pose, save_for_inference, with_view
    from fcnpose_tf.training.train import keep_start_if_better

    data = load_dataset(_synth_frames(tmp_path / "frames", 6, seed=5))  # 160 x 120 frames
    _, val_idx = data.split(None)
    start = tmp_path / "wide_start.keras"
    save_for_inference(with_view(build_fcn_pose(input_size=64), FrameView(64, 64, (100, 20, 180, 180), (640, 360))),
                       start)
    said = io.StringIO()
    assert keep_start_if_better(start, data, val_idx, None, tmp_path / "trained.keras", FrameView(64, 64),
                                reporter=Reporter(stream=said)) is None
    assert "not weighed" in said.getvalue() and "640x360" in said.getvalue(), said.getvalue()


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_the_start_as_saved_is_a_candidate_when_training_ran_at_another_size(tmp_path):
    """A start pretrained at 224 that scores higher on the validation frames than the model trained at another
    size is the model written, at its own size; one that scores lower leaves the trained model alone."""
    from fcnpose_tf.bundled import resolve_model
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.training.model import build_fcn_pose, load_model, save_for_inference
    from types import SimpleNamespace

    from fcnpose_tf.measurements import KeypointMetrics
    from fcnpose_tf.training.train import keep_start_if_better

    data = load_dataset(_synth_frames(tmp_path / "frames", 6, seed=5))
    _, val_idx = data.split(None)
    start = resolve_model("workcell")
    trained_path = tmp_path / "trained.keras"
    save_for_inference(build_fcn_pose(input_size=64), trained_path)

    def trained_scoring(value):
        return SimpleNamespace(metrics=KeypointMetrics(pck={0.5: value, 0.2: value, 0.05: value}, max_px=20.0,
                                                       pck_auc=None, epe_px=None, epe_median_px=None,
                                                       missing_fraction=None))

    from fcnpose_tf.preprocess import FrameView

    entry, _, report = keep_start_if_better(start, data, val_idx, trained_scoring(1.0), trained_path, FrameView(64, 64),
                                            reporter=SILENT)
    assert entry["chose"] == "trained" and entry["input_size"] == 224 and entry["trained_mean_pck"] == 1.0
    assert load_model(trained_path).input_shape[1] == 64  # untouched
    entry, predictor, report = keep_start_if_better(start, data, val_idx, trained_scoring(0.0), trained_path,
                                                    FrameView(64, 64), reporter=SILENT)
    assert entry["chose"] == "start" and entry["start_mean_pck"] > 0 and predictor.view == FrameView(224, 224)
    kept, bundled = load_model(trained_path), load_model(start)
    assert kept.input_shape[1] == 224
    assert all(np.array_equal(a, b) for a, b in zip(kept.get_weights(), bundled.get_weights()))
    assert keep_start_if_better(start, data, val_idx, trained_scoring(1.0), trained_path, FrameView(224, 224),
                                reporter=SILENT) is None  # same size: fit's epoch 0 already was this candidate


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_train_at_the_size_auto_chose_also_weighs_the_start_at_its_own_size(tmp_path, cli_here):
    from fcnpose_tf.training.model import build_fcn_pose, load_model, save_for_inference

    data = _synth_frames(tmp_path / "frames", 6, seed=5)
    start = tmp_path / "start64.keras"
    save_for_inference(build_fcn_pose(input_size=64), start)
    out = tmp_path / "arm.keras"
    status, stdout, err = cli_here("train", "--data", data, "--out", out, "--init", start, "--epochs", "1", "--augment",
                                   "paper", "--augment-copies", "0", "--batch-size", "4", "--quiet", "--threads", "1")
    assert status == 0, stdout + err
    record = json.loads((tmp_path / "arm_train.json").read_text())
    chosen = record["view_auto"]["chose"]
    entry = record["start_as_saved"]
    assert chosen["input_height"] >= 128 and entry["input_size"] == 64 and entry["trained_view"] == chosen
    assert entry["chose"] in ("start", "trained")
    assert record["view"] == (entry["view"] if entry["chose"] == "start" else chosen)
    assert list(load_model(out).input_shape[1:3]) == [record["view"]["input_height"], record["view"]["input_width"]]
    assert f"on the same {record['val_frames']} validation frames" in stdout


def test_keypoint_names_spelt_another_way_are_pointed_out(tmp_path, cli_here):
    from fcnpose_tf.data.via import ViaFrame, write_via_project
    from fcnpose_tf.keypoints import UR5, KeypointSchema, spelling_hint

    names = ("base", "shoulder", "elbow", "wrist_1", "wrist_2", "Wrist-3", "flange", "tool")
    assert spelling_hint(names) == ("did you mean wrist1, wrist2, wrist3? The keypoint names differ from UR5's only in "
                                    "spelling (wrist_1 for wrist1, wrist_2 for wrist2, Wrist-3 for wrist3): rename "
                                    "them in the VIA file's keypoint options and points")
    assert spelling_hint(UR5.keypoints) is None and spelling_hint(("a", "b")) is None
    data = make_via_folder(tmp_path / "frames", n=6, size=(64, 64))
    project = data / "labels.json"
    frames = [ViaFrame(f.filename, 64, 64, f.keypoints) for f in __import__("fcnpose_tf.data.via", fromlist=["x"])
              .read_via(project).frames]
    project.unlink()
    write_via_project(project, frames, KeypointSchema.chain("mine", names))
    status, out, err = cli_here("data", "inspect", data)
    assert status == 0, err
    assert "note: did you mean wrist1, wrist2, wrist3?" in out
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "m.keras", *TRAIN)
    assert status == 2 and "did you mean wrist1, wrist2, wrist3? The keypoint names differ from" in err
