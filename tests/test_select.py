"""predict --select: each strategy on a constructed case whose answer is known, the spread rule, and the CLI."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fcnpose_tf.data.via import read_via
from fcnpose_tf.preprocess import FrameView
from fcnpose_tf.runtime.sources import Frame
from fcnpose_tf.correction.selection import (FrameRecord, FrameScores, default_min_gap, flip_back, pick_spread, pick_uniform,
                                          zoom_out)
from test_predict import BUNDLED_P70
from test_run_bench_cli import _one_line_error, _run
from test_runtime import RED_CYCLE, quadrant_frame, write_video

K = 8


def _records(tracks: np.ndarray, confidence: np.ndarray | None = None) -> list[FrameRecord]:
    conf = np.full(tracks.shape[:2], 100.0) if confidence is None else confidence
    return [FrameRecord(t, tracks[t], conf[t], (48, 64, 3)) for t in range(len(tracks))]


def _scores(strategy: str, records) -> FrameScores:
    scores = FrameScores(strategy, predictor=object())
    scores.records = list(records)
    return scores


def _smooth_tracks(n: int = 40) -> np.ndarray:
    """K keypoints moving fast but smoothly (a sine, up to 6 px per frame)."""
    t = np.arange(n)[:, None]
    x = 30 + 20 * np.sin(t / 5.0 + np.arange(K)[None] * 0.3)
    y = 20 + 10 * np.cos(t / 7.0 + np.arange(K)[None] * 0.2)
    return np.stack([x, y], axis=2)


def test_uniform_spreads_evenly_and_respects_the_gap():
    indices = list(range(100))
    assert [indices[i] for i in pick_uniform(indices, 5, 1)] == [0, 25, 49, 74, 99]
    assert [indices[i] for i in pick_uniform(indices, 5, 30)] == [0, 33, 66, 99]  # only 4 fit 30 apart
    every_third = list(range(0, 30, 3))  # --every 3: the source indices of the processed frames
    assert [every_third[i] for i in pick_uniform(every_third, 3, 10)] == [0, 12, 27]
    assert pick_uniform(indices, 200, 1) == indices


def test_uncertain_picks_missing_and_low_confidence_keypoints():
    tracks = _smooth_tracks(30)
    conf = np.full((30, K), 100.0)
    conf[4, 2] = 10.0  # one keypoint at a tenth of its usual confidence: 0.9
    tracks[17, 5] = np.nan  # one keypoint missing: 1.0
    conf[17, 5] = 0.0
    conf[25, :] = 80.0  # every keypoint slightly low: 8 x 0.2 = 1.6
    scores = _scores("uncertain", _records(tracks, conf))
    np.testing.assert_allclose(scores.scores()[[4, 17, 25, 0]], [0.9, 1.0, 1.6, 0.0])
    assert [r.index for r in scores.pick(3, 1)] == [4, 17, 25]
    assert [r.index for r in scores.pick(2, 1)] == [17, 25]


def test_jump_finds_one_frame_off_its_track_not_fast_smooth_motion():
    tracks = _smooth_tracks(40)
    tracks[12, 3] += (15.0, -9.0)  # one keypoint off its track in frame 12
    tracks[30, 6] = np.nan  # a missing keypoint is not a jump
    scores = _scores("jump", _records(tracks))
    values = scores.scores()
    assert values.argmax() == 12 and values[12] == pytest.approx(np.hypot(15, 9), rel=0.05)
    assert values[[11, 13]].max() < values[12] and np.delete(values, [11, 12, 13]).max() < 1.0
    picks = [r.index for r in scores.pick(2, 5)]
    assert picks[0] == 12 or picks[1] == 12
    assert all(abs(p - 12) >= 5 or p == 12 for p in picks)  # its neighbours (half its score) are within the gap


class DotFinder:
    """A stand-in model: keypoint k is the brightest pixel of channel k % 3 (first in raster order on a tie),
    so it follows a flip or a zoom exactly unless two pixels tie."""

    schema = None

    def predict(self, image):
        kps = np.full((K, 2), np.nan)
        for k in range(K):
            channel = image[..., k % 3]
            if channel.max() > 0:
                y, x = np.unravel_index(int(channel.argmax()), channel.shape)
                kps[k] = (x, y)
        return SimpleNamespace(keypoints=kps, confidence=np.full(K, 50.0))


def test_disagree_picks_the_frame_whose_keypoints_move_when_flipped_or_zoomed():
    finder = DotFinder()
    scores = FrameScores("disagree", finder)
    for t in range(6):
        image = np.zeros((48, 64, 3), np.uint8)
        image[10 + t, 8 + 5 * t] = 255  # one dot per channel: every view agrees
        if t == 4:
            image[10 + t, 50] = 255  # a second, equally bright dot: the flipped view finds the other one
        frame = Frame(t, image, 0.0, "f")
        scores.add(frame, finder.predict(image))
    values = scores.scores()
    assert values.argmax() == 4 and values[4] == pytest.approx(50 - (8 + 5 * 4))
    assert np.delete(values, 4).max() == 0.0
    assert [r.index for r in scores.pick(1, 1)] == [4]


class CropDotFinder(DotFinder):
    """`DotFinder` reading only its view's crop of a frame, as a model with a workspace crop does."""

    def __init__(self, view: FrameView):
        self.view = view

    def predict(self, image):
        x, y, w, h = self.view.box(image.shape)
        found = DotFinder.predict(self, image[y:y + h, x:x + w])
        return SimpleNamespace(keypoints=found.keypoints + (x, y), confidence=found.confidence)


def test_disagree_flips_and_zooms_out_the_crop_a_model_reads_not_the_whole_frame():
    finder = CropDotFinder(FrameView(48, 64, (0, 0, 64, 48), (128, 48)))  # the workspace: the frame's left half
    scores = FrameScores("disagree", finder)
    image = np.zeros((48, 128, 3), np.uint8)
    image[10, 20] = 255
    scores.add(Frame(0, image, 0.0, "f"), finder.predict(image))
    flipped, zoomed = scores.records[0].views
    np.testing.assert_allclose(flipped, np.tile([20.0, 10.0], (K, 1)))  # the whole frame flipped: outside the crop
    np.testing.assert_allclose(zoomed, np.tile([20.0, 10.0], (K, 1)))
    assert scores.scores()[0] == 0.0 and finder.view.crop == (0, 0, 64, 48)  # every view agrees; the view restored


def test_views_map_back_to_the_frame():
    kps = np.array([[0.0, 3.0], [63.0, 5.0]])
    np.testing.assert_allclose(flip_back(kps, 64), [[63.0, 3.0], [0.0, 5.0]])
    canvas, (dx, dy) = zoom_out(np.ones((48, 64, 3), np.uint8))
    assert canvas.shape == (60, 80, 3) and (dx, dy) == (8, 6) and canvas[6, 8].all() and not canvas[5, 7].any()


def test_picks_are_spread_and_ties_go_to_the_earlier_frame():
    scores = np.array([5.0, 5.0, 4.0, 1.0, 3.0, 0.0])
    assert pick_spread(scores, [0, 1, 2, 3, 4, 5], 3, 1) == [0, 1, 2]
    assert pick_spread(scores, [0, 1, 2, 3, 4, 5], 3, 2) == [0, 2, 4]
    assert pick_spread(scores, [0, 10, 20, 30, 40, 50], 2, 30) == [0, 4]  # frames 10, 20 are within 30 of frame 0


def test_default_gap_is_one_second_of_video_or_one_image():
    assert default_min_gap(25.0, "video") == 25 and default_min_gap(None, "video") == 30
    assert default_min_gap(None, "images") == 1


@pytest.fixture(scope="module")
def clip12(tmp_path_factory) -> Path:
    """12 frames at 10 FPS, the red patch moving through the quadrants."""
    frames = [quadrant_frame(160, 120, RED_CYCLE[i % 4]) for i in range(12)]
    return write_video(tmp_path_factory.mktemp("video") / "clip.avi", frames, fps=10.0)


def test_predict_select_writes_only_the_picked_video_frames(capsys, tmp_path, clip12):
    via = tmp_path / "round2" / "pre.json"
    code, out, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via, "--select", "3",
                          "--threads", 1)
    assert code == 0, err
    assert "Selected 2 of 12 processed frames by uniform, at least 10 frame(s) apart (only 2 fit" in out
    assert out.split("Selected")[1].splitlines()[0].endswith(": frame 0, frame 11")  # a video's frames by number
    saved = sorted(p.name for p in (via.parent / "images").iterdir())
    assert saved == ["clip_000000.png", "clip_000011.png"]  # one second apart at 10 FPS: the ends
    assert [f.filename for f in read_via(via, min_visible=0).frames] == saved

    via2 = tmp_path / "round3" / "pre.json"
    code, out, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via2, "--select", "3",
                          "--min-gap", "4", "--by", "jump", "--threads", 1)
    assert code == 0, err
    picks = sorted(int(p.stem.split("_")[1]) for p in (via2.parent / "images").iterdir())
    assert len(picks) == 3 and min(np.diff(picks)) >= 4
    assert len(json.loads(via2.read_text())["_via_img_metadata"]) == 3


def _stills(folder: Path, count: int) -> Path:
    """`count` PNG frames f00.png, f01.png ... of the quadrant patch in turn (RED_CYCLE), in a new `folder`."""
    import cv2

    folder.mkdir()
    for i in range(count):
        cv2.imwrite(str(folder / f"f{i:02d}.png"), quadrant_frame(160, 120, RED_CYCLE[i % 4]))
    return folder


def test_predict_select_on_images_by_disagree_references_the_picked_images(capsys, tmp_path):
    folder = _stills(tmp_path / "frames", 5)
    via = tmp_path / "pre.json"
    code, out, err = _run(capsys, "predict", BUNDLED_P70, "--source", folder, "--via", via, "--select", "2",
                          "--by", "disagree", "--threads", 1)
    assert code == 0, err
    assert "each frame predicted 3 times" in err and "Selected 2 of 5 processed frames by disagree" in out
    assert "--by jump scores how far" not in err
    code, _, err = _run(capsys, "predict", BUNDLED_P70, "--source", folder, "--via", tmp_path / "jump.json",
                        "--select", "2", "--by", "jump", "--threads", 1)
    assert code == 0 and "note: --by jump scores how far the keypoints moved" in err  # a folder is no video
    frames = read_via(via, min_visible=0).frames
    assert len(frames) == 2 and all(f.image_path.parent.resolve() == folder.resolve() for f in frames)
    picked = out.split("Selected")[1].splitlines()[0].split(": ", 1)[1]
    assert sorted(name.split(" ")[0] for name in picked.split(", ")) == sorted(f.filename for f in frames)
    assert not (tmp_path / "images").exists()


def test_more_picks_than_a_contact_sheet_are_named_by_the_highest_scores(capsys, tmp_path):
    """--select 13 of 14 stills: the line names the 12 highest-scoring picks, highest first, and where the other one
    is, not every pick (200 picks were one line of 6,000 characters)."""
    folder = _stills(tmp_path / "stills", 14)
    via = tmp_path / "pre.json"
    code, out, err = _run(capsys, "predict", BUNDLED_P70, "--source", folder, "--via", via, "--select", "13",
                          "--by", "uncertain", "--threads", 1)
    assert code == 0, err
    line = out.split("Selected")[1].splitlines()[0]
    named, rest = line.split("the 12 highest-scoring: ")[1].split("; the other 1 in ")
    scores = [float(pick.rsplit("(", 1)[1].rstrip(")")) for pick in named.split(", ")]
    assert len(scores) == 12 and scores == sorted(scores, reverse=True)
    assert rest == str(via) and len(read_via(via, min_visible=0).frames) == 13


def test_select_options_are_checked_before_the_model_loads(capsys, tmp_path, clip12):
    via = tmp_path / "pre.json"
    code, _, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via, "--by", "jump")
    _one_line_error(code, err, "--by and --min-gap choose frames for --select N")
    code, _, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via, "--select", "0")
    _one_line_error(code, err, "--select must be at least 1")
    code, _, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via, "--select", "2",
                        "--smooth")
    _one_line_error(code, err, "--smooth and --select do not go together")
    assert not via.exists()


def test_a_stopped_selection_writes_the_picks_of_the_frames_scored_and_exits_143(capsys, tmp_path, clip12,
                                                                                  monkeypatch):
    import os
    import signal

    from fcnpose_tf.correction import selection

    original = selection.FrameScores.add

    def add_then_stop(self, frame, prediction):
        original(self, frame, prediction)
        if len(self.records) == 6:
            os.kill(os.getpid(), signal.SIGTERM)  # held back until the frame is counted, then ends the scoring

    monkeypatch.setattr(selection.FrameScores, "add", add_then_stop)
    via = tmp_path / "pre.json"
    code, out, err = _run(capsys, "predict", BUNDLED_P70, "--source", clip12, "--via", via, "--select", "2",
                          "--min-gap", "3", "--threads", 1)
    assert code == 143, err
    assert "Selected 2 of 6 processed frames by uniform" in out and err.strip().splitlines()[-1].startswith(
        "terminated (SIGTERM)")
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == ["clip_000000.png", "clip_000005.png"]
