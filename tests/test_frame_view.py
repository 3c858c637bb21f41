"""A model's frame view (a workspace crop and an H x W input): exact keypoint mapping, carried in every model
file, read by the Pi runtime without TensorFlow."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.errors import UserError
from fcnpose_tf.preprocess import FrameView, keypoints_to_frame, keypoints_to_input, preprocess_frame
from test_preprocess import _blob_frame, _centroid
from test_runtime import no_tf_env  # noqa: F401 - fixture
from weights import randomize

VIEW = FrameView(64, 96, crop=(200, 90, 360, 240), frame_size=(640, 480))


@pytest.mark.parametrize("frame_wh", [(640, 480), (1280, 960)])
def test_a_blob_lands_where_the_crop_mapping_says_and_maps_back_exactly(frame_wh):
    w, h = frame_wh
    centre = np.array([0.55 * w + 0.3, 0.41 * h - 0.2])
    frame = _blob_frame(w, h, centre, sigma=w / 60)
    out = preprocess_frame(frame, VIEW)
    assert out.shape == (64, 96, 3)
    expected = keypoints_to_input(centre[None], frame.shape, VIEW)[0]
    np.testing.assert_allclose(_centroid(out), expected, atol=0.05)
    np.testing.assert_allclose(keypoints_to_frame(expected[None], frame.shape, VIEW)[0], centre, atol=1e-9)


def test_the_box_scales_with_the_frame_and_a_point_outside_the_crop_lands_outside_the_input():
    assert VIEW.box((480, 640, 3)) == (200, 90, 360, 240)
    assert VIEW.box((960, 1280)) == (400, 180, 720, 480)
    outside = keypoints_to_input(np.array([[100.0, 100.0], [600.0, 400.0]]), (480, 640), VIEW)
    assert outside[0, 0] < 0 and outside[1, 0] > 96 and outside[1, 1] > 64
    whole = FrameView(64, 96)
    assert whole.box((480, 640)) == (0, 0, 640, 480) and whole.cropped(np.zeros((4, 5, 3))).shape == (4, 5, 3)


def test_views_round_trip_as_json_and_bad_ones_are_refused():
    assert FrameView.from_json(json.loads(json.dumps(VIEW.to_json()))) == VIEW
    assert FrameView.of(224) == FrameView(224, 224) and FrameView.of((224, 288)).shape == (224, 288)
    with pytest.raises(UserError, match="inside its 640 x 480 frame"):
        FrameView(64, 96, crop=(500, 0, 200, 100), frame_size=(640, 480))
    with pytest.raises(UserError, match="frame size"):
        FrameView(64, 96, crop=(0, 0, 10, 10))
    with pytest.raises(UserError, match="not a frame view"):
        FrameView.from_json({"input_height": 64})
    assert "crop x 200-559, y 90-329 of 640x480" in VIEW.describe()


def test_target_maps_and_training_rows_are_h_by_w():
    from fcnpose_tf.data.masks import make_target_maps
    from fcnpose_tf.keypoints import UR5

    kps = np.full((UR5.num_keypoints, 2), np.nan)
    kps[0] = (90.0, 10.0)  # near the right edge of a 96-wide map, where a square S = 64 map would clip it
    maps = make_target_maps(kps, (64, 96), UR5)
    assert maps.shape == (64, 96, UR5.num_maps) and maps[10, 90, 0] == 1 and maps[10, 60, 0] == 0


@pytest.mark.parametrize("suffix", [".keras", ".h5"])
def test_the_view_is_saved_inside_the_model_file_and_kept_by_resizing(tmp_path, suffix):
    from fcnpose_tf.training.model import at_input_size, build_fcn_pose, load_model, save_for_inference, view_of

    model = build_fcn_pose(input_size=VIEW)
    assert model.input_shape == (None, 64, 96, 3) and view_of(model) == VIEW
    save_for_inference(model, tmp_path / f"m{suffix}")
    loaded = load_model(tmp_path / f"m{suffix}")
    assert view_of(loaded) == VIEW
    assert view_of(at_input_size(loaded, (96, 128))) == VIEW.with_input(96, 128)
    plain = build_fcn_pose(input_size=(64, 96))
    save_for_inference(plain, tmp_path / f"plain{suffix}")
    assert view_of(load_model(tmp_path / f"plain{suffix}")) == FrameView(64, 96)


def _frames(n=4, seed=0):
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n):
        frame = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), (0, 0), 9)
        frames.append(np.ascontiguousarray(frame))
    return frames


@pytest.fixture(scope="module")
def cropped_tflite(tmp_path_factory):
    from fcnpose_tf.compression.export import write_tflite
    from fcnpose_tf.training.model import build_fcn_pose, save_for_inference

    folder = tmp_path_factory.mktemp("cropped")
    model = randomize(build_fcn_pose(input_size=VIEW), seed=3)
    samples = np.stack([preprocess_frame(f, VIEW) for f in _frames()])
    write_tflite(model, folder / "m.tflite", "float32", sample_frames=samples)
    save_for_inference(model, folder / "m.keras")
    return folder


def test_the_tflite_carries_its_view_in_its_metadata(cropped_tflite):
    from fcnpose_tf.compression.tflite_file import inspect_tflite
    from fcnpose_tf.runtime.tflite_metadata import VIEW_METADATA, read_metadata

    stored = read_metadata(cropped_tflite / "m.tflite")
    assert FrameView.from_json(json.loads(stored[VIEW_METADATA])) == VIEW
    # the hand-read entries are the schema's own
    schema_read = inspect_tflite(cropped_tflite / "m.tflite")["metadata"]
    assert set(schema_read) == set(stored) and schema_read[VIEW_METADATA] == stored[VIEW_METADATA].decode()
    with pytest.raises(ValueError, match="not a TFLite FlatBuffer"):
        read_metadata(b"\x10\x00\x00\x00short")


def test_the_pi_runtime_reads_the_crop_without_tensorflow_and_agrees_with_keras(no_tf_env, cropped_tflite,
                                                                                tmp_path):
    from fcnpose_tf.training.evaluate import KerasKeypointModel

    frames = _frames()
    for i, frame in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), frame)
    keras_model = KerasKeypointModel(cropped_tflite / "m.keras", num_threads=1)
    expected = [keras_model.predict(f).keypoints for f in frames]
    code = (
        "import json, sys, cv2\n"
        "from fcnpose_tf.runtime.estimator import KeypointModel\n"
        f"m = KeypointModel({str(cropped_tflite / 'm.tflite')!r}, num_threads=1)\n"
        f"out = [m.predict(cv2.imread({str(tmp_path)!r} + f'/f{{i}}.png')).keypoints.tolist() for i in range({len(frames)})]\n"
        "print(json.dumps({'view': m.view.to_json(), 'kps': out, "
        "'tf': [k for k in sys.modules if k.split('.')[0] in ('tensorflow', 'tf_keras', 'keras')]}))\n")
    result = subprocess.run([sys.executable, "-c", code], env=no_tf_env, capture_output=True, text=True,
                            timeout=PROCESS_TIMEOUT)
    assert result.returncode == 0, result.stderr
    answer = json.loads(result.stdout.strip().splitlines()[-1])
    assert answer["tf"] == [] and FrameView.from_json(answer["view"]) == VIEW
    got = np.array(answer["kps"], np.float64)
    want = np.stack(expected)
    assert np.isfinite(want).sum() >= 8  # the random model finds keypoints to compare
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    found = np.isfinite(want)
    assert np.abs(got[found] - want[found]).max() <= 0.5
    # and every keypoint lies inside the crop: the model cannot see beyond it
    x, y, w, h = VIEW.crop
    points = want.reshape(-1, 2)[np.isfinite(want.reshape(-1, 2)).all(axis=1)]
    assert (points[:, 0] >= x - 0.5).all() and (points[:, 0] <= x + w - 0.5).all()
    assert (points[:, 1] >= y - 0.5).all() and (points[:, 1] <= y + h - 0.5).all()


def test_a_keypoint_outside_the_crop_is_missing_in_the_training_sample():
    frame = np.zeros((480, 640, 3), np.uint8)
    kps = np.array([[250.0, 100.0], [100.0, 100.0], [np.nan, np.nan], [559.5, 329.5]])
    crop, moved = VIEW.crop_sample(frame, kps)
    assert crop.shape == (240, 360, 3) and crop.flags.c_contiguous
    np.testing.assert_allclose(moved[0], [50.0, 10.0])
    assert np.isnan(moved[1]).all() and np.isnan(moved[2]).all()  # outside the crop; missing already
    np.testing.assert_allclose(moved[3], [359.5, 239.5])  # the last pixel's outer edge is still inside


def test_keypoints_at_an_inner_border_of_the_crop_are_flagged_and_the_frames_own_edge_is_not():
    from fcnpose_tf.runtime.estimator import Prediction, StageTimes

    times = StageTimes(0.0, 0.0, 0.0)
    crop = (200, 0, 360, 480)  # the crop spans the frame's height: its top and bottom are the frame's
    kps = np.array([[203.0, 200.0], [556.0, 200.0], [380.0, 2.0], [380.0, 477.0], [380.0, 200.0], [np.nan, np.nan]])
    edge = Prediction(kps, np.ones(6), times, (480, 640, 3), crop).at_crop_edge()
    assert edge.tolist() == [True, True, False, False, False, False]
    assert not Prediction(kps, np.ones(6), times, (480, 640, 3)).at_crop_edge().any()  # no crop, no edge


def test_no_keypoint_of_the_frames_a_workspace_crop_was_set_on_is_at_its_edge():
    """The crop's edge means a keypoint beyond every training keypoint: the workspace crop holds the training
    keypoints with a margin, so none of them is flagged. At a share of 0.10 a fixed camera's base, which never moves,
    flagged 298 of the new cell's 300 test frames."""
    from fcnpose_tf.data.arm_size import workspace_box
    from fcnpose_tf.runtime.estimator import Prediction, StageTimes

    rng = np.random.default_rng(0)
    for trial in range(20):
        lo = rng.uniform([20, 20], [300, 200])
        hi = lo + rng.uniform([40, 40], [320, 260])
        frames = [rng.uniform(lo, hi, size=(8, 2)) for _ in range(12)]
        crop = workspace_box([(k, 640, 480) for k in frames])
        flagged = [Prediction(k, np.ones(8), StageTimes(0.0, 0.0, 0.0), (480, 640, 3), crop).at_crop_edge()
                   for k in frames]
        assert not np.any(flagged), (trial, crop)


def test_the_run_summary_says_to_retrain_only_when_a_frame_had_a_keypoint_at_the_crop_edge(cropped_tflite):
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.runtime.runner import RunSummary
    from fcnpose_tf.runtime.sources import ImageSource

    model = KeypointModel(cropped_tflite / "m.tflite", num_threads=1)
    for flagged, advised in ((0, False), (3, True)):
        report = RunSummary(crop_edge_frames=flagged).report(model, ImageSource([], "frames"))
        crop = next(line for line in report.splitlines() if line.startswith("Crop:"))
        assert f"{flagged} of 0 frames had a keypoint at its edge" in crop and ("retrain" in crop) == advised, crop


def test_the_run_summary_counts_the_keypoints_not_found_per_keypoint():
    """An arm past a crop shows mostly as keypoints not found (12 of 13 such frames on the held-out fixed camera, the
    edge flag 1): the summary counts the frames missing one and names the keypoints missed most."""
    from fcnpose_tf.keypoints import UR5
    from fcnpose_tf.runtime.runner import RunSummary

    summary = RunSummary(frames=4)
    nan = [np.nan, np.nan]
    for missing in ((), (7,), (7, 2), ()):
        summary.count_missed(np.array([nan if k in missing else [1.0, 2.0] for k in range(8)]))
    assert summary.missed_frames == 2 and summary.missed_by_keypoint == [0, 0, 1, 0, 0, 0, 0, 2]
    found = summary._found(UR5.keypoints)
    assert found.startswith("Found:   every keypoint in 2 of 4 frames; not found: tool in 2, elbow in 1"), found
    assert RunSummary(frames=3)._found(UR5.keypoints) == "Found:   every keypoint in every frame"


def test_frames_of_another_aspect_than_the_crops_are_warned_about_once_per_size(cropped_tflite, caplog):
    from fcnpose_tf.runtime.estimator import KeypointModel

    assert VIEW.aspect_note((480, 640, 3)) is None and VIEW.aspect_note((960, 1280)) is None  # the same mode, scaled
    assert VIEW.aspect_note((479, 640)) is None and FrameView(64, 96).aspect_note((720, 1280)) is None
    note = VIEW.aspect_note((720, 1280, 3))
    assert note.startswith("frames of 1280x720 are not of the aspect of the 640x480 frames the model's crop was set "
                           "on (1.78 against 1.33)")
    model = KeypointModel(cropped_tflite / "m.tflite", num_threads=1)
    with caplog.at_level("WARNING", logger="fcnpose_tf.runtime.estimator"):
        for shape in ((480, 640, 3), (960, 1280, 3), (720, 1280, 3), (720, 1280, 3), (360, 640, 3)):
            model.predict(np.zeros(shape, np.uint8))
    assert [r.getMessage() for r in caplog.records] == [f"m.tflite: {note}", f"m.tflite: {VIEW.aspect_note((360, 640))}"]


def test_bench_draws_its_synthetic_frame_at_the_crops_frame_size(tmp_path, capsys, caplog):
    """A crop set on 1280x720 frames: bench's synthetic frame is 1280x720 (no warning about its own frame's aspect);
    --frame-size still wins; a whole-frame model keeps 640x480."""
    from fcnpose_tf.cli import main
    from fcnpose_tf.compression.export import write_tflite
    from fcnpose_tf.runtime.bench import crop_frame_size
    from fcnpose_tf.training.model import build_fcn_pose

    wide = FrameView(64, 96, crop=(300, 100, 600, 400), frame_size=(1280, 720))
    path = tmp_path / "wide.tflite"
    write_tflite(randomize(build_fcn_pose(input_size=wide), seed=1), path, "float32")
    assert crop_frame_size(path) == (1280, 720) and crop_frame_size(tmp_path / "missing.tflite") == (640, 480)
    with caplog.at_level("WARNING", logger="fcnpose_tf.runtime.estimator"):
        assert main(["bench", str(path), "--threads", "1", "--frames", "2", "--warmup", "0"]) == 0
        assert "frame: synthetic 1280x720" in capsys.readouterr().out and not caplog.records
        assert main(["bench", str(path), "--threads", "1", "--frames", "2", "--warmup", "0", "--frame-size",
                     "640x480"]) == 0
        assert "frame: synthetic 640x480" in capsys.readouterr().out
    assert any("not of the aspect" in r.getMessage() for r in caplog.records)
    # several models whose crops were set on frames of other sizes: each gets its own frames' synthetic frame
    caplog.clear()
    tall = FrameView(96, 64, crop=(40, 200, 400, 600), frame_size=(480, 960))
    write_tflite(randomize(build_fcn_pose(input_size=tall), seed=1), tmp_path / "tall.tflite", "float32")
    with caplog.at_level("WARNING", logger="fcnpose_tf.runtime.estimator"):
        assert main(["bench", str(path), str(tmp_path / "tall.tflite"), "--threads", "1", "--frames", "2", "--warmup",
                     "0"]) == 0
    out = capsys.readouterr().out
    assert "frame: synthetic 1280x720" in out and "frame: synthetic 480x960" in out and not caplog.records
