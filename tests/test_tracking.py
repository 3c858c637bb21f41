"""The crop that follows the arm on video (`runtime.tracking`): its box, what the wrapped model reads, `run --track`.

The model is test_runtime's hand-set FCN-Pose (its keypoints are the centres of coloured quadrants), so what the
tracker must give is known: frame n read over `follow_box` of frame n-1's keypoints is the same model on that crop,
moved back by the crop's corner.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from fcnpose_tf.cli import main
from fcnpose_tf.runtime.estimator import KeypointModel
from fcnpose_tf.runtime.runner import run_stream
from fcnpose_tf.runtime.sources import open_source
from fcnpose_tf.runtime.tracking import CROP_SIDE_STEP, TrackingCrop, follow_box
from test_runtime import RED_CYCLE, quadrant_frame, write_video


@pytest.fixture(scope="module")
def model_path(tmp_path_factory, structured_tflite):
    path = tmp_path_factory.mktemp("tracking") / "structured.tflite"
    path.write_bytes(structured_tflite)
    return path


def test_the_box_holds_the_keypoints_with_their_margin_at_the_inputs_aspect_inside_the_frame():
    keypoints = np.array([[300.0, 200.0], [340.0, 260.0], [np.nan, np.nan], [320.0, 230.0], [310.0, 250.0]])
    x, y, w, h = follow_box(keypoints, (480, 640, 3), (224, 288), margin=0.25)
    assert w % CROP_SIDE_STEP == 0 and h % CROP_SIDE_STEP == 0
    assert abs(w / h - 288 / 224) < 0.03  # the input's aspect, to the rounding of its sides
    assert w >= 288 and h >= 224  # never smaller than the input: no upsampled crop
    assert 0 <= x and x + w <= 640 and 0 <= y and y + h <= 480
    assert x <= 300 - 0.25 * 41 and x + w >= 340 + 0.25 * 41 and y <= 200 - 0.25 * 61 and y + h >= 260 + 0.25 * 61
    big = np.array([[20.0, 100.0], [600.0, 120.0], [300.0, 110.0], [310.0, 115.0]])
    assert follow_box(big, (480, 640, 3), (224, 224), margin=0.0) is None  # a square that holds it is not in the frame
    assert follow_box(big, (480, 640, 3), (224, 288), margin=0.0) == (18, 0, 584, 452)  # 4:3 fits, moved inside
    x, y, w, h = follow_box(big, (480, 640, 3), (224, 288), margin=0.25)  # its margin does not fit: the largest crop
    assert (w, h) == (620, 480) and x <= 20 and x + w >= 601  # of the input's aspect that fits, the box still in it
    near_edge = np.array([[630.0, 470.0], [600.0, 440.0], [620.0, 450.0], [610.0, 460.0]])
    x, y, w, h = follow_box(near_edge, (480, 640, 3), (64, 64))
    assert x + w == 640 and y + h == 480  # moved inside the frame, the keypoints still held
    assert follow_box(near_edge[:3], (480, 640, 3), (64, 64)) is None  # fewer than 4 found: nothing to follow
    assert follow_box(near_edge[:3], (480, 640, 3), (64, 64), min_found=3) is not None
    assert follow_box(np.array([[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]]), (3, 3, 3), (64, 64)) is None


def test_a_square_box_is_square_and_its_side_whole_steps():
    keypoints = np.array([[100.0, 100.0], [181.0, 140.0], [150.0, 120.0], [120.0, 130.0]])
    x, y, w, h = follow_box(keypoints, (480, 640, 3), (64, 64), margin=0.0)
    assert w == h == 84  # 82 px (the box's 81 plus its last pixel) rounded up to whole steps of 4
    assert (x, y) == (99, 78)  # centred on the box's centre (140.5, 120)


def test_each_frame_is_the_model_on_the_previous_frames_box_moved_back(model_path):
    model = KeypointModel(model_path, num_threads=1)
    reference = KeypointModel(model_path, num_threads=1)
    tracked = TrackingCrop(model, margin=0.1)  # the quadrants' keypoints span half the frame: a square 0.6 of it
    frames = [quadrant_frame(640, 480, red) for red in RED_CYCLE]
    first = tracked.predict(frames[0])
    np.testing.assert_array_equal(first.keypoints, reference.predict(frames[0]).keypoints)  # its own view
    assert first.crop is None and tracked.whole_view_frames == 1
    previous = first
    for frame in frames[1:]:
        box = follow_box(previous.keypoints, frame.shape, model.view.shape, margin=0.1)
        assert box is not None
        x, y, w, h = box
        prediction = tracked.predict(frame)
        expected = reference.predict(np.ascontiguousarray(frame[y:y + h, x:x + w])).keypoints + (x, y)
        np.testing.assert_allclose(prediction.keypoints, expected, atol=1e-9)
        assert prediction.crop == box
        previous = prediction
    assert tracked.frames == 4 and tracked.whole_view_frames == 1
    assert model.view == tracked.own_view  # the wrapped model keeps its own view between frames


def test_a_frame_that_loses_the_arm_or_changes_size_sends_the_next_back_to_the_whole_view(model_path):
    tracked = TrackingCrop(KeypointModel(model_path, num_threads=1), margin=0.1)
    tracked.predict(quadrant_frame(640, 480))
    black = np.zeros((480, 640, 3), np.uint8)  # 3 keypoints found (wrist1-3 read "no colour"): fewer than 4
    assert tracked.predict(black).crop is not None  # read over the box the first frame gave
    assert tracked.predict(quadrant_frame(640, 480)).crop is None  # the arm was lost: the whole view again
    assert tracked.predict(quadrant_frame(320, 240)).crop is None  # another frame size: the whole view
    assert tracked.predict(quadrant_frame(320, 240)).crop is not None
    tracked.warmup((240, 320, 3))  # a warm-up starts the tracking afresh
    assert tracked.predict(quadrant_frame(320, 240)).crop is None
    assert tracked.whole_view_frames == 4 and tracked.frames == 6
    with pytest.raises(ValueError):
        TrackingCrop(tracked.model, margin=-0.1)


def test_run_stream_tracks_sequentially_and_says_how_frames_were_read(model_path, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    import cv2

    for i, red in enumerate(RED_CYCLE * 2):
        cv2.imwrite(str(folder / f"f{i:02d}.png"), quadrant_frame(320, 240, red))
    tracked = TrackingCrop(KeypointModel(model_path, num_threads=1), margin=0.1)
    source = open_source(str(folder))
    try:
        summary = run_stream(tracked, source, pipelined=True)
        report = summary.report(tracked, source)
    finally:
        source.close()
    assert not summary.pipelined and summary.frames == 8
    whole = tracked.whole_view_frames  # the first frame, and any after a crop that held fewer than 4 keypoints
    assert 1 <= whole < 8 and tracked.frames == 8
    assert (f"Tracking: {8 - whole} of 8 frames read over the previous frame's keypoint box, {whole} over the "
            "model's own view") in report
    assert "a crop following the arm" in report


def test_run_track_on_a_video(capsys, tmp_path, model_path):
    # 300 x 240: the quadrants' keypoint box with the default margin (a square 0.75 of 300 wide) fits its height
    video = write_video(tmp_path / "clip.avi", [quadrant_frame(300, 240, RED_CYCLE[i % 4]) for i in range(6)])
    records_path = tmp_path / "k.jsonl"
    code = main(["run", str(model_path), "--source", str(video), "--track", "--out", str(records_path), "--threads", "1"])
    out_text, err = capsys.readouterr()
    assert code == 0, err
    records = [json.loads(line) for line in records_path.read_text().splitlines()]
    assert len(records) == 6
    assert "crop_xywh" not in records[0] and all("crop_xywh" in r for r in records[1:])  # the boxes it read
    assert "a crop following the arm" in err
    assert "frames read over the previous frame's keypoint box" in out_text and "sequential" in out_text
