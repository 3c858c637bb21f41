"""`compress --more-frames`: frames of the user's camera labelled by their model, added to the retraining's training
split only, the time budgets grown for them."""

import json
from pathlib import Path

import numpy as np
import pytest

from fcnpose_tf import settings
from fcnpose_tf.compression.options import CompressOptions
from fcnpose_tf.compression.report import CompressReport
from fcnpose_tf.correction.pseudolabel import label_frames, project_frames, spread_indices
from fcnpose_tf.data.dataset import AddedFrames, load_dataset, with_training_frames
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema
from fcnpose_tf.runtime.estimator import Prediction, StageTimes
from test_runtime import write_video
from test_train_evaluate import make_via_folder
from weights import randomize


class _FixedPredictor:
    """Every frame's keypoints at fixed places, the last `missing` of them not found."""

    schema = UR5

    def __init__(self, missing: int = 0):
        self.missing = missing
        self.seen = 0

    def predict(self, image):
        self.seen += 1
        h, w = image.shape[:2]
        keypoints = np.c_[np.linspace(5, w - 5, 8), np.linspace(5, h - 5, 8)]
        if self.missing:
            keypoints[-self.missing:] = np.nan
        confidence = np.where(np.isnan(keypoints[:, 0]), 0.0, 9.0)
        return Prediction(keypoints, confidence, StageTimes(0.0, 0.0, 0.0), tuple(image.shape))


def test_frames_spread_evenly_over_the_source_first_and_last_among_them():
    picked = spread_indices(30, 12)
    assert len(picked) == 12 and min(picked) == 0 and max(picked) == 29
    assert max(np.diff(sorted(picked))) - min(np.diff(sorted(picked))) <= 1
    assert spread_indices(5, 12) == frozenset(range(5))  # fewer than asked: all of them
    assert spread_indices(None, 12) is None and spread_indices(0, 12) is None  # length unknown: the first 12


def test_the_budgets_grow_with_the_frames_and_lose_the_labelling_minutes():
    """192 training frames and 720 more: an epoch 4.75x as long, the default 10-minute retraining 47.5 and the
    15-minute total 62.5 with the polish's 10, less the 2 minutes labelling took; a budget the user gave keeps its
    value."""
    options = CompressOptions(rate=0.7)
    assert (options.max_minutes, options.total_minutes, options.polish_minutes) == (10.0, 15.0, 10.0)
    grown = options.with_added_frames(192, 720, spent_minutes=2.0)
    assert grown.max_minutes == pytest.approx(47.5) and grown.total_minutes == pytest.approx(60.5)
    given = options.with_added_frames(192, 720, 2.0, given={"max_minutes"})
    assert given.max_minutes == 10.0 and given.total_minutes == pytest.approx(23.0)
    unbounded = CompressOptions(rate=0.7, max_minutes=None, total_minutes=None).with_added_frames(192, 720, 2.0)
    assert (unbounded.max_minutes, unbounded.total_minutes) == (None, None)
    spent = options.with_added_frames(192, 0, spent_minutes=60.0)  # labelling took the whole budget: the least left
    assert spent.max_minutes == 10.0 and spent.total_minutes == settings.MIN_RETRAIN_MINUTES


def test_the_polish_gets_its_own_minutes_after_the_retraining():
    """With frames added, the total grows by the polish's 10 minutes too, and the retraining's share of a total
    leaves them for the polish; --polish-minutes 0 adds nothing."""
    options = CompressOptions(rate=0.7, polish_minutes=10.0)
    grown = options.with_added_frames(192, 720, spent_minutes=2.0)
    assert grown.max_minutes == pytest.approx(47.5) and grown.total_minutes == pytest.approx(60.5)
    # 3 minutes before the retraining, 6 kept for the steps after it, 10 for the polish: 41.5 of the 60.5 left
    assert grown.retraining_minutes(3.0, polish_minutes=10.0) == pytest.approx(41.5)
    assert grown.retraining_minutes(3.0) == pytest.approx(47.5)  # no polish: the retraining's whole budget
    unpolished = CompressOptions(rate=0.7, polish_minutes=0.0).with_added_frames(192, 720, spent_minutes=2.0)
    assert unpolished.total_minutes == pytest.approx(50.5)


@pytest.mark.parametrize("method, freeze, frozen", [("l1", 0, 2), ("l1", 4, 4), ("magnitude", 0, 0)])
def test_the_polish_is_the_retraining_at_a_tenth_of_its_learning_rate(method, freeze, frozen):
    options = CompressOptions(rate=0.7, method=method, freeze=freeze, learning_rate=3e-3, polish_minutes=7.0,
                              retrain_epochs=25, keep_best="keypoints")
    config = options.polish_config()
    assert config.learning_rate == pytest.approx(3e-4) and config.max_minutes == 7.0
    assert config.freeze == frozen  # conv1-2 fixed, as train fine-tunes; magnitude pruning retrains every weight
    assert (config.epochs, config.keep_best, config.seed) == (25, "keypoints", options.seed)
    assert settings.POLISH_MINUTES.default == 10.0


def test_the_user_s_own_frames_come_back_with_their_splits(tmp_path):
    from fcnpose_tf.data.dataset import own_frames

    dataset = load_dataset(make_via_folder(tmp_path / "user", n=20), folds=5)
    extra = load_dataset(make_via_folder(tmp_path / "more", n=6, seed=3), write_splits=False)
    own = own_frames(with_training_frames(dataset, extra, AddedFrames("clip.mp4", "arm.keras", 6, "6 frames")))
    assert own.added is None and own.samples == dataset.samples
    for fold in (None, *range(5)):
        assert all(np.array_equal(a, b) for a, b in zip(own.split(fold), dataset.split(fold)))
    assert own_frames(dataset) is dataset


def test_added_frames_train_every_split_and_validate_none(tmp_path):
    dataset = load_dataset(make_via_folder(tmp_path / "user", n=20), folds=5)
    extra = load_dataset(make_via_folder(tmp_path / "more", n=6, seed=3), write_splits=False)
    grown = with_training_frames(dataset, extra, AddedFrames("clip.mp4", "arm.keras", 6, "6 frames"))
    added = set(range(20, 26))
    assert len(grown) == 26 and grown.samples[20:] == extra.samples and grown.added.frames == 6
    for fold in (None, *range(5)):
        train, val = grown.split(fold)
        old_train, old_val = dataset.split(fold)
        assert np.array_equal(val, old_val)  # validation: the user's frames, as before
        assert set(train) == set(old_train) | added and np.all(np.diff(train) > 0)
    assert dataset.added is None and len(dataset) == 20  # the user's dataset itself unchanged


def test_another_schema_is_refused(tmp_path):
    from fcnpose_tf.data.via import ViaFrame, write_via_project

    dataset = load_dataset(make_via_folder(tmp_path / "user", n=6), write_splits=False)
    other = KeypointSchema("pendulum", ("pivot", "bob"), ((0, 1),))
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "cam_00.jpg").write_bytes((tmp_path / "user" / "images" / "cam_00.jpg").read_bytes())
    write_via_project(tmp_path / "other" / "p.json", [ViaFrame("cam_00.jpg", 96, 72, np.array([[5., 5.], [9., 9.]]))],
                      other)
    extra = load_dataset(tmp_path / "other" / "p.json", min_visible=1, write_splits=False)
    with pytest.raises(UserError, match="keypoint schema 'pendulum'.*differs"):
        with_training_frames(dataset, extra, AddedFrames("x", "y", 1, "z"))


def test_image_folder_frames_are_labelled_and_measured_frames_left_out(tmp_path):
    """Of 10 images (3 of them copies of the user's measured frames) 5 are asked for, evenly spread: the copies among
    them are left out, unlabelled; missing keypoints get no point; the frames are referenced where they are."""
    user = make_via_folder(tmp_path / "user", n=3)
    folder = make_via_folder(tmp_path / "more", n=10, seed=5) / "images"
    for i in (0, 4, 9):  # the same bytes under another name
        (folder / f"cam_{i:02d}.jpg").write_bytes((user / "images" / f"cam_{i % 3:02d}.jpg").read_bytes())
    predictor = _FixedPredictor(missing=2)
    labelled = label_frames(predictor, folder, tmp_path / "out" / "p.json", 5,
                            known_images=sorted((user / "images").iterdir()), labelled_by="arm.keras")
    picked = sorted(spread_indices(10, 5))
    assert picked == [0, 2, 4, 7, 9]
    assert (labelled.read, labelled.known, labelled.frames) == (5, 3, 2) and predictor.seen == 2
    assert (labelled.keypoints, labelled.not_found) == (12, 4)
    project = load_dataset(labelled.via_path, min_visible=1, write_splits=False)
    assert [s.image_path.name for s in project.samples] == ["cam_02.jpg", "cam_07.jpg"]
    assert all(s.image_path.parent.resolve() == folder.resolve() for s in project.samples)
    words = labelled.added(1, 4).description
    assert words.startswith(f"1 frames of {folder} (5 of its 10, evenly spread; left out: 3 frames of --data or "
                            "--test-data, 1 with fewer than 4 keypoints) labelled by arm.keras: 12 keypoints, 4 not found")


def test_a_video_s_frames_are_saved_beside_the_project(tmp_path):
    frames = [np.full((48, 64, 3), 10 * i, np.uint8) for i in range(9)]
    video = write_video(tmp_path / "clip.avi", frames)
    labelled = label_frames(_FixedPredictor(), video, tmp_path / "out" / "p.json", 3)
    assert (labelled.total, labelled.read, labelled.frames, labelled.keypoints) == (9, 3, 3, 24)
    saved = sorted(p.name for p in (tmp_path / "out" / "images").iterdir())
    assert saved == ["clip_000000.png", "clip_000004.png", "clip_000008.png"]
    assert len(load_dataset(labelled.via_path, write_splits=False)) == 3
    with pytest.raises(UserError, match="p.json: already exists; pass --force"):
        label_frames(_FixedPredictor(), video, tmp_path / "out" / "p.json", 3)
    again = label_frames(_FixedPredictor(missing=1), video, tmp_path / "out" / "p.json", 3, force=True)
    assert again.keypoints == 21


class _FailingPredictor(_FixedPredictor):
    """Fails on its `fail_at`-th frame, as a model, a full disk or a Ctrl-C may."""

    def __init__(self, fail_at: int):
        super().__init__()
        self.fail_at = fail_at

    def predict(self, image):
        if self.seen + 1 == self.fail_at:
            raise KeyboardInterrupt
        return super().predict(image)


def test_a_labelling_stopped_midway_leaves_no_frame_and_no_project(tmp_path):
    video = write_video(tmp_path / "clip.avi", [np.full((48, 64, 3), 10 * i, np.uint8) for i in range(9)])
    with pytest.raises(KeyboardInterrupt):
        label_frames(_FailingPredictor(fail_at=3), video, tmp_path / "out" / "p.json", 5)
    assert not (tmp_path / "out" / "p.json").exists() and not list((tmp_path / "out").glob("images/*"))


def test_nothing_to_add_is_an_error_naming_why(tmp_path):
    user = make_via_folder(tmp_path / "user", n=3)
    with pytest.raises(UserError, match="no frame to add \\(all 3 frames read are frames of --data or --test-data\\)"):
        label_frames(_FixedPredictor(), user / "images", tmp_path / "out" / "p.json", 5,
                     known_images=sorted((user / "images").iterdir()))
    labelled = label_frames(_FixedPredictor(missing=6), user / "images", tmp_path / "out" / "p.json", 5)
    with pytest.raises(UserError, match="in none of the 3 frames labelled did the model find 4 keypoints"):
        labelled.load(UR5, 4)


def test_a_project_s_frames_are_added_with_their_labels_as_they_are(tmp_path):
    """A VIA project (one --more-frames-via kept, then corrected): its labels unchanged, its frames that are the user's
    left out, a frame with too few keypoints dropped, the rest spread evenly to the count, no splits file written."""
    from fcnpose_tf.data.via import ViaFrame, write_via_project

    user = make_via_folder(tmp_path / "user", n=3)
    folder = make_via_folder(tmp_path / "more", n=11, seed=5)
    for i in (0, 9):  # the same bytes under another name
        (folder / "images" / f"cam_{i:02d}.jpg").write_bytes((user / "images" / f"cam_{i % 3:02d}.jpg").read_bytes())
    original = load_dataset(folder, write_splits=False)
    frames = [ViaFrame(s.filename, s.width, s.height, s.keypoints.copy()) for s in original.samples]
    frames[10].keypoints[3:] = np.nan  # corrected: the model's points past the third were wrong
    project = folder / "corrected.json"
    write_via_project(project, frames, UR5)
    (folder / "labels.json").unlink()
    extra, added = project_frames(project, UR5, 4, 5, known_images=sorted((user / "images").iterdir()))
    names = [s.filename for s in extra.samples]
    assert names == ["cam_01.jpg", "cam_03.jpg", "cam_05.jpg", "cam_06.jpg", "cam_08.jpg"]  # 5 of 8, evenly spread
    by_name = {s.filename: s.keypoints for s in original.samples}
    assert all(np.array_equal(s.keypoints, by_name[s.filename]) for s in extra.samples)
    assert added.labelled_by is None and added.frames == 5 and added.source == str(project)
    assert added.description.startswith(f"5 frames of {project} (5 of its 8, evenly spread; its labels as they are, "
                                        "40 keypoints; left out: 2 frames of --data or --test-data, 1 ")
    assert not list(folder.glob("*.splits.json"))
    with pytest.raises(UserError, match="no frame to add \\(all 2 of its frames are frames of --data"):
        write_via_project(project, frames[:1] + frames[9:10], UR5, force=True)
        project_frames(project, UR5, 4, 5, known_images=sorted((user / "images").iterdir()))


def _saturated_model(path: Path) -> Path:
    """A seeded 64 x 64 FCN-Pose whose every map is above the threshold everywhere: every keypoint found (at the
    map's centre), so every frame it labels is kept."""
    from fcnpose_tf.training.model import build_fcn_pose

    model = randomize(build_fcn_pose(input_size=64), seed=0)
    kernel, bias = model.get_layer("conv10").get_weights()
    model.get_layer("conv10").set_weights([kernel, np.full_like(bias, 5.0)])
    model.save(path)
    return path


@pytest.mark.slow  # one compress run with one retraining epoch: about 10 s of CPU
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_retrains_on_the_added_frames_and_says_so(cli_here, tmp_path):
    base = _saturated_model(tmp_path / "arm.keras")
    data = make_via_folder(tmp_path / "user", n=20)
    more = make_via_folder(tmp_path / "more", n=30, seed=3) / "images"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--more-frames", more,
                                   "--more-frames-count", "12", "--retrain-epochs", "1", "--quantize", "float16",
                                   "--out-dir", tmp_path / "out", "--threads", "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    said = stdout + err
    assert f"more frames: 12 frames of {more} (12 of its 30, evenly spread) labelled by {base}: 96 keypoints" in said
    assert "retraining on 16 + 12 frames, time budget 17.5 min of retraining" in said
    assert f"with 12 more frames of {more} labelled by {base}, then 1 epoch on your frames alone at learning rate " \
           "0.0003); measured on 4 validation frames" in said
    report = json.loads((tmp_path / "out" / "arm_p70_report.json").read_text())
    assert report["retrain_data"]["val_frames"] == 4  # the user's validation frames only
    assert report["retrain_data"]["added_frames"]["frames"] == 12
    assert report["options"]["max_minutes"] == pytest.approx(17.5)
    record = json.loads((tmp_path / "out" / "arm_p70_train.json").read_text())
    assert record["added_frames"] == report["retrain_data"]["added_frames"]
    assert not list(Path(tmp_path).glob("**/more_frames.json"))  # the labelled project was the run's own
    # the polish: the user's 16 frames alone, the retrained model the epoch to beat, its record the file's
    assert "then 10 min on the 16 alone" in said
    assert f"polish: up to 10 min more on the 16 training frames of {data / 'labels.json'} alone, learning rate " \
           "0.0003, conv1-2 fixed" in said
    polish = report["polish"]
    assert polish["kept_by"] == "keypoints" and polish["learning_rates"] == [pytest.approx(3e-4)]
    assert polish["epochs_run"] == 1 and isinstance(polish["start_kept"], bool)
    assert record["retraining_before_polish"] == report["retraining"] and record["config"]["freeze"] == 2
    assert record["start_val_keypoints"] is not None  # the retrained model scored as epoch 0
    assert CompressReport.from_json(report).to_json() == report
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "arm_p70.keras", "arm_p70_fp16.tflite", "arm_p70_loss.csv", "arm_p70_loss.png", "arm_p70_report.json",
        "arm_p70_train.json"]  # the retraining's own files went with their temporary folder


@pytest.mark.slow  # two compress runs with one retraining epoch each: about 20 s of CPU
@pytest.mark.usefixtures("few_timed_frames")
def test_kept_frames_are_looked_at_corrected_and_added_as_they_are(cli_here, tmp_path):
    """--more-frames-via keeps a video's labelled frames as a VIA project with its PNGs; passed back as --more-frames,
    the project's frames join the retraining with their labels as they are (no model labels them again)."""
    from fcnpose_tf.data.via import ViaFrame, write_via_project

    base = _saturated_model(tmp_path / "arm.keras")
    data = make_via_folder(tmp_path / "user", n=20)
    video = write_video(tmp_path / "cell.avi", [np.full((48, 64, 3), 8 * i, np.uint8) for i in range(30)])
    kept = tmp_path / "kept" / "more.json"
    common = ("compress", "--rate", "0.7", "--model", base, "--data", data, "--retrain-epochs", "1", "--quantize",
              "float16", "--threads", "1")
    status, stdout, err = cli_here(*common, "--more-frames", video, "--more-frames-via", kept, "--more-frames-count",
                                   "12", "--out-dir", tmp_path / "out")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert f"; kept in {kept} (look: `fcnpose-tf data inspect {kept} --out preview.png`" in stdout + err
    labelled = load_dataset(kept, write_splits=False)
    assert len(labelled) == 12 and len(list((kept.parent / "images").glob("cell_*.png"))) == 12
    corrected = [ViaFrame(s.filename, s.width, s.height, s.keypoints + 1.0) for s in labelled.samples[:10]]
    write_via_project(kept, corrected, UR5, force=True)  # a person's round: 2 frames deleted, every point moved
    status, stdout, err = cli_here(*common, "--more-frames", kept, "--out-dir", tmp_path / "again",
                                   "--polish-minutes", "0")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert f"with 10 more frames of {kept}, their labels as they are); measured on 4" in stdout
    report = json.loads((tmp_path / "again" / "arm_p70_report.json").read_text())
    added = report["retrain_data"]["added_frames"]
    assert (added["frames"], added["labelled_by"], added["source"]) == (10, None, str(kept))
    assert "polish" not in report and "polish:" not in stdout + err  # --polish-minutes 0: none
    assert "labelling frames" not in stdout + err


@pytest.mark.slow  # one compress run's labelling and data: a few seconds of CPU
def test_kept_frames_outlive_a_later_failure(cli_here, tmp_path, monkeypatch):
    """The labelling is minutes of work: a run that fails after it keeps the project (named on the error line) and
    removes its half-made output folder."""
    import fcnpose_tf.compression.compress as pipeline

    def fails(*args, **kwargs):
        raise UserError("retraining failed (a stand-in for a full disk)")

    monkeypatch.setattr(pipeline, "compress_model", fails)
    base = _saturated_model(tmp_path / "arm.keras")
    data = make_via_folder(tmp_path / "user", n=6)
    video = write_video(tmp_path / "cell.avi", [np.full((48, 64, 3), 8 * i, np.uint8) for i in range(9)])
    kept = tmp_path / "kept" / "more.json"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--more-frames", video,
                                   "--more-frames-via", kept, "--out-dir", tmp_path / "out", "--threads", "1")
    assert status == 2 and "retraining failed" in err, err[-2000:]
    assert "kept the files completed before it: " in err, err
    assert err.rstrip().endswith(f"{kept}, {kept.parent / 'images'}"), err
    assert len(load_dataset(kept, write_splits=False)) == 9 and not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra, message", [
    (("--more-frames", "0"), "--more-frames 0: a camera; --more-frames reads a video file or an image folder"),
    (("--more-frames-via", "{tmp}/k.json"), "--more-frames-via keeps the frames --more-frames labels"),
    (("--more-frames", "{more}", "--more-frames-via", "{tmp}/k.txt"), "--more-frames-via must be a .json file"),
    (("--more-frames", "{user}/labels.json", "--more-frames-via", "{tmp}/k.json"),
     "labels.json is a VIA project, whose labels are used as they are"),
    (("--more-frames", "{tmp}/missing.json"), "--more-frames {tmp}/missing.json: VIA project not found"),
    (("--more-frames", "{more}", "--more-frames-via", "{user}/labels.json"), "labels.json: already exists"),
    (("--more-frames", "nothere"), "nothere: no such file or folder"),
    (("--more-frames", "{more}", "--more-frames-count", "0"), "--more-frames-count must be at least 1, got 0"),
    (("--more-frames", "{more}", "--retrain-epochs", "0"), "--more-frames adds frames to the retraining"),
    (("--more-frames", "{more}", "--polish-minutes", "-1"), "--polish-minutes must be >= 0, got -1"),
    (("--more-frames", "{user}/images"), "no frame to add (all 6 frames read are frames of --data or --test-data)"),
])
def test_bad_more_frames_are_one_line_and_leave_nothing(cli_here, tmp_path, extra, message):
    base = _saturated_model(tmp_path / "arm.keras")
    user = make_via_folder(tmp_path / "user", n=6)
    more = make_via_folder(tmp_path / "more", n=3, seed=3) / "images"
    extra = [part.format(more=more, user=user, tmp=tmp_path) for part in extra]
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", user, *extra,
                                   "--out-dir", tmp_path / "out", "--threads", "1")
    assert status == 2 and message.format(tmp=tmp_path) in err, err[-2000:]
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob("k.*"))
