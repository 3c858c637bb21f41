"""Training, resuming, evaluation and their CLI errors on a small, non-synthetic VIA dataset built on the fly."""

import io
import json
from dataclasses import fields
from pathlib import Path

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.via import ViaFrame, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from fcnpose_tf.progress import SILENT
from fcnpose_tf.records import training_record


def make_via_folder(folder, n=10, size=(96, 72), seed=0, schema=UR5, suffix=".jpg"):
    """Frames of any size with coloured dots at the keypoints (a user's VIA export of `schema`, not synthetic)."""
    rng = np.random.default_rng(seed)
    (folder / "images").mkdir(parents=True)
    w, h = size
    frames = []
    for i in range(n):
        img = np.full((h, w, 3), 40, np.uint8)
        kps = np.c_[rng.uniform(8, w - 9, schema.num_keypoints), rng.uniform(8, h - 9, schema.num_keypoints)]
        for k, (x, y) in enumerate(kps):
            cv2.circle(img, (int(round(x)), int(round(y))), 3, (30 * k, 255 - 30 * k, 200), -1)
        cv2.imwrite(str(folder / "images" / f"cam_{i:02d}{suffix}"), img)
        frames.append(ViaFrame(f"cam_{i:02d}{suffix}", w, h, kps))
    write_via_project(folder / "labels.json", frames, schema)
    return folder


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 64x64 FCN-Pose trained 2 epochs by the CLI on a small VIA folder (shared by the tests below).

    In this process (`fcnpose_tf.cli.main`, as the `cli_here` fixture runs it), its validation timed on a few frames.
    """
    import contextlib
    import io

    from conftest import cut_timed_frames
    from fcnpose_tf.cli import main

    root = tmp_path_factory.mktemp("train")
    data = make_via_folder(root / "frames")
    out = root / "models" / "arm.keras"
    stdout, stderr = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        cut_timed_frames(patch)
        status = main(["train", "--data", str(data), "--out", str(out), "--epochs", "2", "--input-size", "64",
                       "--augment", "paper", "--augment-copies", "1", "--quiet"])
    assert status == 0, stdout.getvalue() + stderr.getvalue()
    return data, out, stdout.getvalue()


@pytest.mark.slow
def test_train_writes_model_curves_and_record(trained):
    data, out, stdout = trained
    stem = out.with_suffix("")
    assert out.is_file() and not out.with_suffix(".ckpt").exists()
    rows = (stem.parent / f"{stem.name}_loss.csv").read_text().splitlines()
    assert rows[0] == "epoch,loss,val_loss" and len(rows) == 3
    png = cv2.imread(str(stem.parent / f"{stem.name}_loss.png"))
    assert png is not None and png.shape[0] > 100
    record = json.loads((stem.parent / f"{stem.name}_train.json").read_text())
    assert record["epochs_run"] == 2 and record["train_samples"] == 16 and record["val_frames"] == 2
    assert "pck@0.5_bbox" in record["validation"]["metrics"]
    assert record["init"] == "generalist"  # the default start, by its name: its path is this machine's
    # the default network from the generalist: FCN-Pose with its skip, said and recorded
    assert record["architecture"] == record["architecture_auto"] == "fcn-pose-skip"
    assert "Architecture: fcn-pose-skip (fine-tuning the generalist" in stdout
    typed = training_record(out)  # every field read from what train wrote, with its type (fold: the hold-out split)
    assert [f.name for f in fields(typed) if getattr(typed, f.name) is None] == ["images", "fold"]  # no --images
    assert typed.data_absolute == str(Path(record["data"]).resolve())  # found from any folder (export, compress)
    assert typed.keypoints == tuple(UR5.keypoints) and typed.positive_weight == record["config"]["positive_weight"]
    assert (typed.data_sha256, typed.split, typed.folds, typed.input_size) == \
        (record["data_sha256"], record["split"], record["folds"], record["input_size"])
    assert "16 samples (8 frames + 1 augmented copies each)" in stdout
    assert "PCK normalised by max(bbox w, h)" in stdout


@pytest.mark.slow
def test_existing_model_needs_force(trained, cli_here):
    data, out, _ = trained
    before = out.read_bytes()
    status, _, err = cli_here("train", "--data", data, "--out", out, "--epochs", "1", "--input-size", "64")
    assert status == 2 and "already exists; pass --force" in err
    assert out.read_bytes() == before


@pytest.mark.slow
def test_evaluate_picks_validation_frames_of_own_data_and_all_of_other(trained, cli_here, tmp_path, monkeypatch):
    from conftest import cut_timed_frames

    data, out, _ = trained
    status, stdout, err = cli_here("evaluate", out, "--data", data, "--json", tmp_path / "r.json", "--threads", "1")
    assert status == 0, err
    assert "validation frames of the hold-out 80/20 split (2 frames)" in stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["timing"]["frames_timed"] >= 50 and report["timing"]["threads"] == 1
    assert set(report["metrics"]) >= {"pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox", "epe_px", "pck_auc_0-20px"}
    assert report["decoding"] == {"threshold": 0.5, "fallback": None, "centroid": "weighted", "cluster": "largest"}
    assert "Decoding: Algorithm 1 (largest cluster above 0.5, its centroid weighted by (p - 0.5)^2)" in stdout
    cut_timed_frames(monkeypatch)  # the runs below check what is scored and said, not what is timed
    status, stdout, err = cli_here("evaluate", out, "--data", data, "--json", tmp_path / "w.json", "--threads", "1",
                                   "--centroid", "plain")
    assert status == 0, err
    assert "Decoding: Algorithm 1 (largest cluster above 0.5, its centroid)" in stdout
    assert json.loads((tmp_path / "w.json").read_text())["decoding"]["centroid"] == "plain"
    status, stdout, err = cli_here("evaluate", out, "--data", data, "--json", tmp_path / "c.json", "--threads", "1",
                                   "--cluster", "chain")
    assert status == 0, err
    assert "Decoding: clusters above 0.5 chained along the arm" in stdout
    assert json.loads((tmp_path / "c.json").read_text())["decoding"]["cluster"] == "chain"
    status, _, err = cli_here("evaluate", out, "--data", data, "--cluster", "best")
    assert status == 2 and "--cluster" in err and "chain" in err
    other = make_via_folder(tmp_path / "other", n=4, seed=5)
    status, stdout, err = cli_here("evaluate", out, "--data", other)
    assert status == 0, err
    assert "all 4 frames" in stdout


@pytest.mark.slow
def test_evaluate_errors(trained, cli_here, tmp_path):
    from fcnpose_tf.training.model import build_fcn_pose

    data, out, _ = trained
    status, _, err = cli_here("evaluate", tmp_path / "nope.keras", "--data", data)
    assert status == 2 and "nope.keras: model file not found" in err
    wrong = tmp_path / "five.keras"
    build_fcn_pose(input_size=64, num_maps=5).save(wrong)
    status, _, err = cli_here("evaluate", wrong, "--data", data)  # in-process: a defect raises here
    assert status == 2 and "5 output maps" in err and "Traceback" not in err
    empty = tmp_path / "empty"
    empty.mkdir()
    write_via_project(empty / "labels.json", [], UR5)
    status, _, err = cli_here("evaluate", out, "--data", empty)
    assert status == 2 and "no usable frames" in err
    status, _, err = cli_here("evaluate", out, "--data", tmp_path / "missing")
    assert status == 2 and "not found" in err


@pytest.mark.slow
@pytest.mark.parametrize("keep_best", ["loss", "keypoints"])
def test_interrupted_training_resumes(tmp_path, monkeypatch, keep_best):
    """A run stopped after its first epoch resumes where it stopped, keeping its epoch by the same rule."""
    from conftest import stop_after_first_epoch
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    out = tmp_path / "m.keras"
    config = train.FitConfig(epochs=3, patience=5, batch_size=4, keep_best=keep_best)
    scored = train.ValidationKeypoints.of(va)
    stop_after_first_epoch(monkeypatch)
    with pytest.raises(UserError, match="interrupted after 1 complete epochs; continue with --resume"):
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, reporter=SILENT,
                  val_keypoints=scored)
    state = json.loads((tmp_path / "m.ckpt" / "state.json").read_text())
    assert state["epoch"] == 1 and not out.exists() and state["keep_best"] == keep_best
    with pytest.raises(UserError, match="pass --resume to continue it or --force"):
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, reporter=SILENT,
                  val_keypoints=scored)
    monkeypatch.undo()
    result = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, resume=True,
                       reporter=SILENT, val_keypoints=scored)
    assert result.epochs_run == 3 and [h["epoch"] for h in result.history] == [1, 2, 3]
    assert out.is_file() and not (tmp_path / "m.ckpt").exists()
    # the rule it started with, every epoch: the keypoints' score in each row and the kept one's in the result
    assert all(("val_mean_pck" in h) == (keep_best == "keypoints") for h in result.history)
    assert (result.best_keypoints is not None) == (keep_best == "keypoints")


def test_an_interrupted_run_that_cannot_resume_says_what_to_do_and_leaves_no_checkpoint(tmp_path, monkeypatch):
    """compress retrains through fit(resumable=False): Ctrl-C names the epochs done and says to run the command
    again, not to pass a --resume compress does not have."""
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    original = train._CheckpointAndStop.on_epoch_end

    def interrupt_after_first(self, epoch, logs=None):
        original(self, epoch, logs)
        raise KeyboardInterrupt

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", interrupt_after_first)
    with pytest.raises(UserError) as info:
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), tmp_path / "m_p70.keras",
                  train.FitConfig(epochs=3, batch_size=4), reporter=SILENT, resumable=False)
    assert str(info.value) == ("stopped after 1 of 3 epochs; this run cannot be resumed (its checkpoint is removed): "
                               "run the same command again to start it over")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_a_stop_after_the_last_epoch_of_a_run_that_cannot_resume_leaves_no_checkpoint(tmp_path, monkeypatch):
    """A SIGTERM while compress writes its retrained model left the checkpoint, and the next compress then asked
    for a --resume it does not have; a checkpoint a SIGKILL left is removed by the next such run."""
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    out = tmp_path / "m_p70.keras"

    def stopped_while_saving(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(train, "save_for_inference", stopped_while_saving)
        with pytest.raises(UserError, match="stopped after 1 of 1 epochs; this run cannot be resumed"):
            train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out,
                      train.FitConfig(epochs=1, batch_size=4), reporter=SILENT, resumable=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    stale = train.run_paths(out)["ckpt_dir"]  # as a SIGKILL leaves it
    stale.mkdir()
    for name in ("ckpt_state", "ckpt_model"):
        train.run_paths(out)[name].write_text("{}")
    train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, train.FitConfig(epochs=1, batch_size=4),
              reporter=SILENT, resumable=False)
    assert out.is_file() and not stale.exists()


def test_a_loss_that_becomes_nan_stops_training_keeps_the_best_epoch_or_writes_nothing(tmp_path, monkeypatch):
    """A learning rate far too high makes the loss NaN: training stops at that epoch (the weights are lost), the best
    epoch before it is the model written and the record names the epoch; with no epoch before it, one error line
    and no file."""
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    original = train._CheckpointAndStop.on_epoch_end
    nan_from = {"epoch": 1}

    def diverging(self, epoch, logs=None):
        if epoch >= nan_from["epoch"]:
            logs = {**logs, "loss": float("nan"), "val_loss": float("nan")}
        original(self, epoch, logs)

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", diverging)
    out = tmp_path / "m.keras"
    result = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out,
                       train.FitConfig(epochs=4, patience=5, batch_size=4), reporter=SILENT)
    assert result.epochs_run == 1 and result.best_epoch == 1 and [h["epoch"] for h in result.history] == [1]
    assert out.is_file() and not (tmp_path / "m.ckpt").exists()
    assert json.loads((tmp_path / "m_train.json").read_text())["diverged_at_epoch"] == 2
    nan_from["epoch"] = 0
    with pytest.raises(UserError, match=r"^the loss became NaN or infinite in epoch 1 \(learning rate 0.001: try a "
                                        r"lower --learning-rate\); no epoch before it to keep: .*n.keras not written$"):
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), tmp_path / "n.keras",
                  train.FitConfig(epochs=4, patience=5, batch_size=4), reporter=SILENT)
    assert not (tmp_path / "n.keras").exists() and not (tmp_path / "n.ckpt").exists()


def test_validation_keypoints_score_the_maps_as_the_files_read_them(tmp_path):
    """`ValidationKeypoints.score`: maps drawn at the true keypoints score a mean PCK of 1 and a sub-pixel EPE; the
    same maps shifted by 3 pixels lose PCK@0.05 and gain 3 px of EPE; empty maps find nothing (EPE None)."""
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.train import ValidationKeypoints

    ds = load_dataset(make_via_folder(tmp_path / "d", n=10))
    _, va = fold_data(ds, None, 64, 0)
    images, maps = va.arrays()
    truth = ValidationKeypoints.of(va)
    assert truth.keypoints.shape == (len(images), UR5.num_keypoints, 2) and truth.names == tuple(UR5.keypoints)

    class Maps:  # a model whose output is given
        def __init__(self, out):
            self.out = out

        def predict(self, inputs, batch_size, verbose):
            assert len(inputs) == len(self.out)
            return self.out

    exact = truth.score(Maps(maps), images, 4)
    assert exact["mean_pck"] == 1.0 and exact["pck_fine"] == 1.0 and exact["epe_px"] < 1.0
    shifted = truth.score(Maps(np.roll(maps, 3, axis=2)), images, 4)
    assert shifted["pck_fine"] < 1.0 and 2.0 < shifted["epe_px"] < 4.0 and shifted["mean_pck"] < 1.0
    assert truth.score(Maps(np.zeros_like(maps)), images, 4) == {"mean_pck": 0.0, "pck_fine": 0.0, "epe_px": None}


def test_the_better_score_is_the_higher_mean_pck_then_the_lower_epe():
    from fcnpose_tf.training.train import better_score

    score = {"mean_pck": 0.9, "pck_fine": 0.8, "epe_px": 5.0}
    assert better_score(score, None)
    assert better_score(score, {**score, "mean_pck": 0.89, "epe_px": 1.0})
    assert not better_score(score, {**score, "mean_pck": 0.91, "epe_px": 9.0})
    assert better_score(score, {**score, "epe_px": 5.5}) and not better_score(score, {**score, "epe_px": 4.5})
    assert not better_score(score, score)  # a tie keeps the earlier epoch
    assert better_score(score, {**score, "epe_px": None}) and not better_score({**score, "epe_px": None}, score)


def test_keep_best_keypoints_keeps_the_epoch_whose_keypoints_score_best(tmp_path, monkeypatch):
    """keep_best "keypoints": the kept epoch is the best-scoring one whatever the loss did, patience waits on the
    score, and the record, the loss CSV and the progress lines say what chose it; without the validation keypoints
    `fit` refuses before any work. A trained start is epoch 0's candidate by its score too."""
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.progress import Reporter
    from fcnpose_tf.training import train
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    scores = iter([0.2, 0.6, 0.5, 0.4, 0.3, 0.1])  # epochs 1-4 (the run stops after 2 without a better score)
    monkeypatch.setattr(train.ValidationKeypoints, "score", lambda self, model, inputs, batch_size: {
        "mean_pck": next(scores), "pck_fine": 0.5, "epe_px": 3.0})
    config = train.FitConfig(epochs=6, patience=2, batch_size=4, keep_best="keypoints", lr_patience=0)
    with pytest.raises(ValueError, match="pass val_keypoints"):
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), tmp_path / "x.keras", config,
                  reporter=SILENT)
    log = io.StringIO()
    out = tmp_path / "m.keras"
    result = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config,
                       reporter=Reporter(quiet=True, stream=log), val_keypoints=train.ValidationKeypoints.of(va))
    assert (result.epochs_run, result.best_epoch, result.stopped_early) == (4, 2, True)
    assert result.best_keypoints == {"mean_pck": 0.6, "pck_fine": 0.5, "epe_px": 3.0}
    assert result.best_val_loss == result.history[1]["val_loss"]  # the kept epoch's loss, whichever is lowest
    record = json.loads((tmp_path / "m_train.json").read_text())
    assert (record["kept_by"], record["best_val_keypoints"]["mean_pck"], record["config"]["keep_best"]) == \
        ("keypoints", 0.6, "keypoints")
    csv = (tmp_path / "m_loss.csv").read_text().splitlines()
    assert csv[0] == "epoch,loss,val_loss,val_mean_pck,val_pck_fine,val_epe_px" and csv[2].endswith(",0.6,0.5,3")
    assert "best validation keypoints at epoch 2 (mean PCK 0.600, PCK@0.05 0.500, EPE 3.00 input px)" in log.getvalue()
    scores = iter([0.7, 0.6, 0.5, 0.4])  # the start (epoch 0) scores best: it is the model written
    start = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), tmp_path / "s.keras", config,
                      reporter=SILENT, val_keypoints=train.ValidationKeypoints.of(va), start_is_candidate=True)
    assert (start.best_epoch, start.epochs_run, start.best_keypoints["mean_pck"]) == (0, 2, 0.7)


def test_weighted_bce_equals_keras_bce_at_weight_one_and_weights_discs():
    import tensorflow as tf
    import tf_keras as keras

    from fcnpose_tf.training.train import KeypointBinaryCrossentropy

    rng = np.random.default_rng(0)
    y = (rng.random((2, 8, 8, 3)) > 0.8).astype(np.float32)
    p = rng.uniform(0.01, 0.99, (2, 8, 8, 3)).astype(np.float32)
    plain = float(keras.losses.BinaryCrossentropy()(y, p))
    assert float(KeypointBinaryCrossentropy(1.0)(y, p)) == pytest.approx(plain, rel=1e-5)
    w = 5.0
    ref = -(w * y * np.log(p) + (1 - y) * np.log(1 - p))
    ref[..., -1] = -(y[..., -1] * np.log(p[..., -1]) + (1 - y[..., -1]) * np.log(1 - p[..., -1]))
    assert float(KeypointBinaryCrossentropy(w)(tf.constant(y), tf.constant(p))) == pytest.approx(ref.mean(), rel=1e-5)


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_fine_tune_from_a_model_and_reject_a_mismatched_one(trained, cli_here, tmp_path):
    from fcnpose_tf.training.model import architecture_of, build_fcn_pose, load_model, save_for_inference

    data, trained_out, _ = trained
    skip_start = load_model(trained_out)  # train's default network from the generalist
    assert architecture_of(skip_start) == "fcn-pose-skip"
    plain = build_fcn_pose(input_size=64)
    for layer in plain.layers:
        if layer.weights:
            layer.set_weights(skip_start.get_layer(layer.name).get_weights())
    save_for_inference(plain, tmp_path / "plain.keras")
    out = _poor_start(tmp_path / "plain.keras", tmp_path / "poor_start.keras")
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "ft.keras", "--epochs", "1",
                                   "--input-size", "64", "--augment-copies", "0", "--init", out, "--quiet")
    assert status == 0, err
    record = json.loads((tmp_path / "ft_train.json").read_text())
    assert record["best_epoch"] == 1 and record["best_val_loss"] < record["start_val_loss"]
    assert record["init"] == str(out) and record["config"]["freeze"] == 2  # a trained start keeps conv1..2
    assert record["config"]["learning_rate"] == 1e-3 and record["architecture"] == "fcn-pose"  # its own network
    assert "Recipe: conv1-2 fixed, learning rate 0.001 (fcn-pose, a trained start, paper augmentation" in stdout
    assert record["config"]["positive_weight"] == 8.0  # and draws tighter discs than training from scratch
    assert record["augment"] == "paper" and record["augment_auto"]["chose"] == "paper"  # one fixed "camera"
    assert "Augmentation: auto -> paper (one fixed camera" in stdout
    assert "Keypoint weight: 8 (fine-tuning a trained model on the paper's copies" in stdout
    start, tuned = load_model(out), load_model(tmp_path / "ft.keras")
    for name, kept in (("conv1", True), ("conv2", True), ("conv3", False), ("conv10", False)):
        same = all(np.array_equal(a, b) for a, b in zip(start.get_layer(name).get_weights(),
                                                          tuned.get_layer(name).get_weights()))
        assert same == kept, name
    assert all(layer.trainable for layer in tuned.layers)  # the written model is a plain FCN-Pose
    assert record["augment_copies"] == 0  # as given
    # an fcn-pose-skip start on one fixed camera keeps conv1 and trains the rest at 3e-3 (settings.train_recipe), on
    # 4 copies of each frame (settings.train_augment_copies)
    skip_out = _poor_start(trained_out, tmp_path / "poor_skip.keras")
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "fts.keras", "--epochs", "1",
                                   "--input-size", "64", "--init", skip_out, "--quiet")
    assert status == 0, err
    fts = json.loads((tmp_path / "fts_train.json").read_text())
    assert (fts["config"]["freeze"], fts["config"]["learning_rate"], fts["architecture"]) == (1, 3e-3, "fcn-pose-skip")
    assert "Recipe: conv1 fixed, learning rate 0.003 (fcn-pose-skip" in stdout
    assert fts["augment_copies"] == 4 and "Augmented copies: 4 a frame (fine-tuning an fcn-pose-skip network on " \
        "one fixed camera; --augment-copies sets it)" in stdout
    start_model, tuned_skip = load_model(skip_out), load_model(tmp_path / "fts.keras")
    assert np.array_equal(start_model.get_layer("conv1").get_weights()[0],
                          tuned_skip.get_layer("conv1").get_weights()[0])
    assert not np.array_equal(start_model.get_layer("conv2").get_weights()[0],
                              tuned_skip.get_layer("conv2").get_weights()[0])
    # the convolutions do not depend on the input size: a 64x64 model starts a 96x96 run
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "ft0.keras", "--epochs", "1",
                                   "--input-size", "96", "--augment-copies", "0", "--augment", "paper", "--init", out,
                                   "--freeze", "0", "--positive-weight", "20", "--quiet")
    assert status == 0, err
    ft0 = json.loads((tmp_path / "ft0_train.json").read_text())
    assert ft0["config"]["positive_weight"] == 20.0
    assert "start_as_saved" not in ft0  # a size the user asked for is kept: the 64x64 start is no candidate
    tuned = load_model(tmp_path / "ft0.keras")
    assert tuned.input_shape[1:3] == (96, 96)
    assert not np.array_equal(start.get_layer("conv1").get_weights()[0], tuned.get_layer("conv1").get_weights()[0])
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "bad.keras", "--init", out, "--freeze", "10")
    assert status == 2 and "error: frozen layers must be 0 to 9" in err
    # a model of another keypoint schema is refused before any training, saying how to start from scratch

    other = tmp_path / "other_arm.keras"
    save_for_inference(build_fcn_pose(input_size=64, num_maps=5), other)
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "bad.keras", "--epochs", "1",
                              "--input-size", "64", "--init", other)
    assert status == 2 and "pass --init none to train from scratch" in err
    assert not (tmp_path / "bad.keras").exists()


def _poor_start(model_path, path):
    """`model_path`'s model with its maps pushed towards 1 everywhere (conv10's bias +3): the first epoch of
    training beats it on any frames, so what fine-tuning changed is in the saved model."""
    from fcnpose_tf.training.model import load_model, save_for_inference

    model = load_model(model_path)
    kernel, bias = model.get_layer("conv10").get_weights()
    model.get_layer("conv10").set_weights([kernel, bias + 3.0])
    save_for_inference(model, path)
    return path


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_a_start_no_epoch_beats_is_the_model_written(trained, cli_here, tmp_path):
    data, out, _ = trained
    # a rate of 5 wrecks the last layer in one step: no epoch comes near the start's validation loss
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "kept.keras", "--epochs", "2",
                                   "--input-size", "64", "--augment-copies", "0", "--init", out, "--freeze", "9",
                                   "--learning-rate", "5", "--quiet")
    assert status == 0, err
    assert "at epoch 0 of 2 (the starting model: no epoch improved on it)" in stdout
    record = json.loads((tmp_path / "kept_train.json").read_text())
    assert record["best_epoch"] == 0 and record["best_val_loss"] == record["start_val_loss"]
    header, *rows = (tmp_path / "kept_loss.csv").read_text().splitlines()
    assert header == "epoch,loss,val_loss" and len(rows) == 2
    assert all(float(row.split(",")[2]) > record["start_val_loss"] for row in rows)
    from fcnpose_tf.training.model import load_model

    start, kept = load_model(out), load_model(tmp_path / "kept.keras")
    assert all(np.array_equal(a, b) for a, b in zip(start.get_weights(), kept.get_weights()))
    assert cv2.imread(str(tmp_path / "kept_loss.png")) is not None


def _run_epoch_callback(tmp_path, learning_rate, val_losses, seconds=0.0, **schedule):
    """`fit`'s per-epoch callback on a one-layer model fed these validation losses, `seconds` of training already
    behind it; its state afterwards."""
    import tf_keras as keras

    from fcnpose_tf.training.train import _CheckpointAndStop, compile_for_training, run_paths

    model = keras.Sequential([keras.Input((4, 4, 3)), keras.layers.Conv2D(9, 1, activation="sigmoid")])
    compile_for_training(model, learning_rate)
    paths = run_paths(tmp_path / "m.keras")
    paths["ckpt_dir"].mkdir()
    state = {"epoch": 0, "best_val_loss": float("inf"), "best_epoch": 0, "wait": 0, "stopped_early": False,
             "history": [], "seconds": seconds}
    callback = _CheckpointAndStop(paths, state, patience=10, **schedule)
    callback.set_model(model)
    for epoch, val_loss in enumerate(val_losses):
        callback.on_epoch_begin(epoch)
        callback.on_epoch_end(epoch, {"loss": 1.0, "val_loss": val_loss})
    return state


def test_learning_rate_halves_after_lr_patience_epochs_without_improvement(tmp_path):
    """--lr-patience N: the rate halves after N epochs with no better validation loss, again after N more."""
    state = _run_epoch_callback(tmp_path, 1e-3, [1.0, 0.5, 0.6, 0.7, 0.8, 0.9, 0.4, 0.45], lr_patience=2)
    rates = [round(row["lr"], 8) for row in state["history"]]
    # epochs 3-4 no better than 0.5 -> halve after epoch 4; epochs 5-6 -> halve again; 0.4 improves
    assert rates == [1e-3, 1e-3, 1e-3, 1e-3, 5e-4, 5e-4, 2.5e-4, 2.5e-4]
    assert state["best_epoch"] == 7


def test_cosine_schedule_sets_every_epochs_rate_and_refuses_plateau_halving_too(tmp_path):
    """--lr-schedule cosine: epoch e of E trains at 1e-5 + (lr - 1e-5)(1 + cos(pi e / E)) / 2 whatever the
    validation loss does (no time budget); combined with --lr-patience it is refused before any work."""
    import math

    from fcnpose_tf.training.train import FitConfig, cosine_rate

    expected = [1e-5 + (2e-3 - 1e-5) * (1 + math.cos(math.pi * e / 4)) / 2 for e in range(4)]
    assert [cosine_rate(e / 4, 2e-3) for e in range(4)] == pytest.approx(expected, rel=1e-12)
    assert expected[0] == pytest.approx(2e-3) and expected[2] == pytest.approx((2e-3 + 1e-5) / 2)
    state = _run_epoch_callback(tmp_path, 2e-3, [1.0, 1.5, 2.0, 0.5],  # stale epochs change nothing
                                rate_of_progress=lambda p: cosine_rate(p, learning_rate=2e-3), epochs=4)
    assert [row["lr"] for row in state["history"]] == pytest.approx(expected, rel=1e-6)  # float32 variable
    FitConfig(lr_schedule="cosine").validate()
    with pytest.raises(UserError, match="--lr-schedule cosine sets every epoch's learning rate itself"):
        FitConfig(lr_schedule="cosine", lr_patience=4).validate()
    with pytest.raises(UserError, match="learning-rate schedule must be one of plateau, cosine"):
        FitConfig(lr_schedule="step").validate()


def test_cosine_follows_whichever_budget_ends_first(tmp_path):
    """With a time budget the cosine's progress is the larger of the epochs' and the minutes' share: `train`'s
    500-epoch, 30-minute budget ends by time, so the rate reaches its floor with the minutes."""
    import math

    from fcnpose_tf.training.train import budget_progress, cosine_rate

    assert budget_progress(2, 4, seconds=10.0, max_seconds=None) == 0.5
    assert budget_progress(2, 500, seconds=1350.0, max_seconds=1800.0) == 0.75  # time ends first
    assert budget_progress(3, 4, seconds=60.0, max_seconds=1800.0) == 0.75      # epochs end first
    assert cosine_rate(1.0, 1e-3) == pytest.approx(1e-5) and cosine_rate(1.7, 1e-3) == pytest.approx(1e-5)
    assert cosine_rate(-0.1, 1e-3) == pytest.approx(1e-3)
    # 45 of 60 seconds spent when the first epoch of 500 begins: the rate of progress 0.75
    state = _run_epoch_callback(tmp_path, 1e-3, [1.0], seconds=45.0, max_minutes=1.0, epochs=500,
                                rate_of_progress=lambda p: cosine_rate(p, learning_rate=1e-3))
    expected = 1e-5 + (1e-3 - 1e-5) * (1 + math.cos(math.pi * 0.75)) / 2
    later = 1e-5 + (1e-3 - 1e-5) * (1 + math.cos(math.pi * (45.0 + 5.0) / 60.0)) / 2  # the test's own seconds add
    assert later * (1 - 1e-6) <= state["history"][0]["lr"] <= expected * (1 + 1e-6)


def test_loss_label_names_the_weighting():
    from fcnpose_tf.training.train import loss_name

    assert loss_name(1.0) == "binary cross-entropy"
    assert loss_name(20.0) == "binary cross-entropy, keypoint pixels weighted 20"


def test_evaluate_timing_uses_the_runtime_summary_with_sample_std():
    """evaluate_predictor's "± std" is the sample std (ddof=1) of the per-frame stage times."""
    from types import SimpleNamespace

    from fcnpose_tf.training.evaluate import evaluate_predictor, format_timing
    from fcnpose_tf.runtime.estimator import Prediction, StageTimes

    invoke = np.random.default_rng(1).uniform(5.0, 9.0, 60)
    truth = np.array([[10.0 + k, 20.0] for k in range(UR5.num_keypoints)])

    class Fake:
        num_maps, num_threads, backend_label = UR5.num_maps, 1, "fake backend"
        calls = 0

        def predict(self, frame):
            ms = invoke[max(Fake.calls - 2, 0)]  # after 2 warm-up frames, invoke[0], invoke[1], ...
            Fake.calls += 1
            return Prediction(truth, np.ones(len(truth)), StageTimes(1.0, float(ms), 0.5), frame.shape)

    dataset = SimpleNamespace(load_image=lambda i: np.zeros((48, 64, 3), np.uint8),
                              samples=[SimpleNamespace(keypoints=truth)] * 3)
    result = evaluate_predictor(Fake(), dataset, [0, 1, 2], UR5, min_timed_frames=60, warmup=2)
    timing = result.timing
    assert timing.frames_timed == 60 and timing.backend == "fake backend"
    assert timing.to_json()["inference_ms"] == {"mean": round(float(np.mean(invoke)), 4),
                                                "std": round(float(np.std(invoke, ddof=1)), 4),
                                                "median": round(float(np.median(invoke)), 4)}
    assert timing.total_ms.std == round(float(np.std(invoke + 1.5, ddof=1)), 4)
    assert timing.fps == round(1000 / float(np.mean(invoke + 1.5)), 2)
    assert result.metrics.pck[0.5] == 1.0
    assert "fake backend" in format_timing(timing)


def test_time_budget_ends_training_after_the_epoch_that_reaches_it(tmp_path):
    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    out = tmp_path / "m.keras"
    config = train.FitConfig(epochs=5, patience=5, batch_size=4, max_minutes=1e-6)
    result = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, reporter=SILENT)
    assert result.epochs_run == 1 and not result.stopped_early and result.stopped_by_time_budget
    record = json.loads((tmp_path / "m_train.json").read_text())
    assert record["stopped_by_time_budget"] is True and record["config"]["max_minutes"] == 1e-6
    last = train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), tmp_path / "one.keras",
                     train.FitConfig(epochs=1, patience=5, batch_size=4, max_minutes=1e-6), reporter=SILENT)
    assert last.epochs_run == 1 and not last.stopped_by_time_budget  # reached by the last epoch: it stopped nothing
    with pytest.raises(UserError, match="time budget must be a positive number of minutes"):
        train.FitConfig(max_minutes=0).validate()


def test_frozen_layers_keep_their_weights_and_the_saved_model_matches_the_trained_one(tmp_path):
    """fit with freeze=2: conv1..2 unchanged; the file holds each layer's trained weights (frozen ones sort last)."""
    from fcnpose_tf.training.model import build_fcn_pose, load_model
    from fcnpose_tf.training.train import FitConfig, fit

    rng = np.random.default_rng(0)
    images = rng.random((8, 32, 32, 3), dtype=np.float32)
    maps = (rng.random((8, 32, 32, 9)) > 0.9).astype(np.float32)
    model = build_fcn_pose(input_size=32)
    before = {layer.name: [w.copy() for w in layer.get_weights()] for layer in model.layers}
    import tensorflow as tf

    batches = tf.data.Dataset.from_tensor_slices((images, maps)).batch(4)
    fit(model, batches, (images[:4], maps[:4]), tmp_path / "m.keras",
        FitConfig(epochs=2, batch_size=4, freeze=2), reporter=SILENT)
    saved = load_model(tmp_path / "m.keras")
    for layer in model.layers:
        for trained, written in zip(layer.get_weights(), saved.get_layer(layer.name).get_weights()):
            np.testing.assert_array_equal(trained, written)
        changed = any(not np.array_equal(a, b) for a, b in zip(before[layer.name], layer.get_weights()))
        if layer.name in ("conv1", "conv2"):
            assert not changed
        elif layer.weights:
            assert changed, layer.name
    with pytest.raises(UserError, match="nothing to train"):
        from fcnpose_tf.training.train import freeze_first_convolutions

        freeze_first_convolutions(build_fcn_pose(input_size=32), 10)


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_evaluate_names_the_worst_frames_and_draws_them(trained, cli_here, tmp_path):
    data, out, _ = trained
    other = make_via_folder(tmp_path / "other", n=5, seed=6)
    pictures = tmp_path / "worst"
    status, stdout, err = cli_here("evaluate", out, "--data", other, "--worst", "3", "--pictures", pictures,
                                   "--json", tmp_path / "r.json")
    assert status == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    rows = report["worst_frames"]
    assert [f["frame"] for f in report["per_frame"]] == sorted(p.name for p in (other / "images").iterdir())
    assert all(len(f["errors_px"]) == 8 and set(f["missed"]) <= set(UR5.keypoints) for f in report["per_frame"])
    assert [r["rank"] for r in rows] == [1, 2, 3]
    assert [r["score"] for r in rows] == sorted((r["score"] for r in rows), reverse=True)
    names = {p.name for p in (other / "images").iterdir()}
    assert all(r["frame"] in names and r["frame"] in stdout for r in rows)
    assert "Worst 3 frames" in stdout and f"Pictures: {pictures} (3 PNG and contact_sheet.png)" in stdout
    drawn = sorted(p.name for p in pictures.iterdir() if p.name != "contact_sheet.png")
    assert drawn == [f"{r['rank']:02d}_{Path(r['frame']).stem}.png" for r in rows]
    assert cv2.imread(str(pictures / drawn[0])).shape[2] == 3
    sheet = cv2.imread(str(pictures / "contact_sheet.png"))
    assert sheet.shape[1] == 3 * (320 + 4)  # three tiles of 320 px, each framed by 2 px
    status, _, err = cli_here("evaluate", out, "--data", other, "--pictures", pictures)  # before any work
    assert status == 2 and "already holds files; pass --force" in err
    status, _, err = cli_here("evaluate", out, "--data", other, "--worst", "0", "--pictures", tmp_path / "p2")
    assert status == 2 and "--pictures draws the --worst frames" in err


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_train_adds_the_skip_to_its_start_and_compress_prunes_it(trained, cli_here, tmp_path):
    """--architecture fcn-pose-skip fine-tunes a plain start with the skip added (recorded in NAME_train.json); the
    skip model fine-tunes again with its own architecture by default, and compress prunes it by graph surgery (conv9
    and skip2 one group), retrains it with its skip and exports it verified against Keras."""
    from fcnpose_tf.training.model import SKIP_LAYERS, architecture_of, conv_widths, load_model

    data, start, _ = trained
    skip = tmp_path / "skip.keras"
    status, stdout, err = cli_here("train", "--data", data, "--out", skip, "--epochs", "1", "--input-size", "64",
                                   "--augment-copies", "0", "--init", start, "--architecture", "fcn-pose-skip",
                                   "--quiet")
    assert status == 0, err
    record = json.loads((tmp_path / "skip_train.json").read_text())
    assert record["architecture"] == "fcn-pose-skip" and record["start_val_loss"] > 0
    model = load_model(skip)
    assert architecture_of(model) == "fcn-pose-skip" and all(model.get_layer(name) for name in SKIP_LAYERS)
    again = tmp_path / "again.keras"
    status, stdout, err = cli_here("train", "--data", data, "--out", again, "--epochs", "1", "--input-size", "64",
                                   "--augment-copies", "0", "--init", skip, "--quiet")
    assert status == 0, err
    assert json.loads((tmp_path / "again_train.json").read_text())["architecture"] == "fcn-pose-skip"
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "plain.keras", "--epochs", "1",
                              "--input-size", "64", "--init", skip, "--architecture", "fcn-pose")
    assert status == 2 and "would drop its trained skip" in err
    status, _, err = cli_here("compress", "--model", skip, "--data", data, "--rate", "0.5", "--retrain-epochs", "1",
                              "--quantize", "float16", "--threads", "1", "--out-dir", tmp_path / "c")
    assert status == 0, err
    report = json.loads((tmp_path / "c" / "skip_p50_report.json").read_text())
    pruned = load_model(tmp_path / "c" / "skip_p50.keras")
    assert architecture_of(pruned) == "fcn-pose-skip" and report["retrained"]["widths"] == list(conv_widths(pruned))
    assert pruned.get_layer("skip2").filters == pruned.get_layer("conv9").filters == conv_widths(pruned)[8] < 64
    assert report["retrained"]["params"] == pruned.count_params() < 135_865 // 2
    assert (tmp_path / "c" / "skip_p50_fp16.tflite").is_file() and report["quantized"]["quantize"] == "float16"
