"""`train --input-size auto`: the arm's size in the frames, the input side chosen from it, and how train records it."""

import json

import numpy as np
import pytest

from fcnpose_tf import settings
from fcnpose_tf.data.arm_size import (AUTO_MAX_INPUT_SIZE, AUTO_MIN_INPUT_SIZE, MIN_ARM_INPUT_PX, arm_span,
                                      choose_input_size)
from fcnpose_tf.data.via import ViaFrame, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5


def _box(x0, y0, w, h):
    """Eight keypoints whose bounding box is (x0, y0, w, h)."""
    return np.array([[x0, y0], [x0 + w, y0 + h]] + [[x0 + w / 2, y0 + h / 2]] * 6, float)


def test_arm_span_is_the_median_of_the_larger_side_against_the_frame():
    frames = [(_box(10, 10, 320, 120), 640, 480),   # 0.5 of the width, 0.25 of the height -> 0.5
              (_box(0, 0, 64, 240), 640, 480),      # 0.1 / 0.5 -> 0.5
              (_box(0, 0, 64, 48), 640, 480)]       # 0.1
    assert arm_span(frames) == pytest.approx(0.5)
    # missing keypoints do not count; a frame with fewer than two visible ones has no box and is skipped
    partly = _box(0, 0, 320, 240)
    partly[0] = np.nan  # the box shrinks to the remaining points
    single = np.full((8, 2), np.nan)
    single[3] = (5, 5)
    assert arm_span([(partly, 640, 480), (single, 640, 480)]) == pytest.approx(160 / 640)
    assert arm_span([(single, 640, 480)]) == 0.0 and arm_span([]) == 0.0


@pytest.mark.parametrize("span, size", [
    (1.0, 224), (MIN_ARM_INPUT_PX / 224, 224),   # the arm spans 140 px at 224 already
    (0.62, 256), (0.53, 288), (0.50, 288),        # the random-view proxies (0.50-0.54)
    (0.388, 384),                                 # the held-out fixed camera's wide lens
    (0.2, 384), (0.0, 224)])                      # too small for any size: the largest; unknown: the default
def test_choose_input_size(span, size):
    assert choose_input_size(span) == size


def test_the_choice_is_the_smallest_size_reaching_the_wanted_pixels():
    for span in np.linspace(0.01, 1.0, 200):
        size = choose_input_size(float(span))
        assert AUTO_MIN_INPUT_SIZE <= size <= AUTO_MAX_INPUT_SIZE and size % settings.INPUT_SIZE_MULTIPLE == 0
        if size < AUTO_MAX_INPUT_SIZE:
            assert span * size >= MIN_ARM_INPUT_PX
        if size > AUTO_MIN_INPUT_SIZE:
            assert span * (size - settings.INPUT_SIZE_MULTIPLE) < MIN_ARM_INPUT_PX


@pytest.mark.parametrize("span, start_size, size", [
    (0.40, 384, 384), (0.40, 352, 352),   # the arm spans 140 px at the start's size too: the start's size is kept
    (0.40, 320, 352),                     # 128 px at 320: too few, the smallest size that reaches 140
    (0.50, 224, 288), (1.0, 224, 224),    # a bundled start (224) changes nothing
    (0.9, 416, 224), (0.9, 300, 224),     # a size auto never chooses (too large, not a multiple of 32) is not kept
    (0.0, 384, 224)])                     # unknown span: the default, whatever the start
def test_choose_input_size_keeps_the_start_size_where_the_arm_is_large_enough(span, start_size, size):
    assert choose_input_size(span, start_size) == size


def test_a_bundled_start_never_changes_the_choice():
    for span in np.linspace(0.01, 1.0, 200):
        assert choose_input_size(float(span), AUTO_MIN_INPUT_SIZE) == choose_input_size(float(span))


def test_train_takes_auto_or_a_multiple_of_32_and_the_paper_keeps_224():
    setting = settings.TRAIN_INPUT_SIZE
    assert setting.default == "auto" and setting.default_in("paper") == 224
    assert setting.parse("auto") == "auto" and setting.parse(" Auto ") == "auto" and setting.parse("320") == 320
    assert setting.validate("auto") == "auto" and setting.validate(384) == 384
    for bad in (100, 0, -32, "big", 2.5, True):
        with pytest.raises(UserError, match="input size must be auto or a positive multiple of 32"):
            setting.validate(bad)
    # everywhere else the input size stays a number
    with pytest.raises(UserError, match="input size must be a positive multiple of 32"):
        settings.INPUT_SIZE.validate("auto")


def _small_arm_project(folder, span, n=6, size=(640, 480)):
    (folder / "images").mkdir(parents=True)
    import cv2

    w, h = size
    frames = []
    for i in range(n):
        cv2.imwrite(str(folder / "images" / f"f{i}.png"), np.zeros((h, w, 3), np.uint8))
        frames.append(ViaFrame(f"f{i}.png", w, h, _box(20 + i, 30, span * w, span * h * 0.5)))
    write_via_project(folder / "labels.json", frames, UR5)
    return folder / "labels.json"


def _frames(via_path):
    from fcnpose_tf.data.via import read_via

    return read_via(via_path).frames


def test_resolve_input_size_reads_the_frames_and_says_why(tmp_path, capsys):
    from fcnpose_tf.training.train import resolve_input_size

    size, record = resolve_input_size(_frames(_small_arm_project(tmp_path / "wide", 0.39)))
    assert size == 384 and record == {"arm_span": 0.39, "min_arm_input_px": MIN_ARM_INPUT_PX, "chose": 384}
    out = capsys.readouterr().out
    assert "Input size: auto -> 384 (the arm's keypoint box spans 0.39 of the median frame: 150 input pixels" in out
    assert "--input-size 224 runs 2.9x faster" in out
    size, _ = resolve_input_size(_frames(_small_arm_project(tmp_path / "close", 0.8)))
    assert size == 224 and "faster" not in capsys.readouterr().out
    # a start trained at 384 on this camera stays at 384 where the arm spans 140 px there (352 would do)
    size, record = resolve_input_size(_frames(_small_arm_project(tmp_path / "next", 0.42)), start_size=384)
    assert size == 384 and record["start_input_size"] == 384 and record["chose"] == 384
    out = capsys.readouterr().out
    assert "auto -> 384" in out and "the starting model's own size, kept: the smallest size reaching them is 352" in out


@pytest.mark.slow
def test_train_auto_records_the_choice(cli, tmp_path):
    from fcnpose_tf.training.model import load_model

    data = _small_arm_project(tmp_path / "frames", 0.9)
    out = tmp_path / "m.keras"
    common = ["--data", data, "--out", out, "--init", "none", "--augment", "paper", "--augment-copies", "0",
              "--batch-size", "4", "--threads", "1", "--quiet"]
    proc = cli("train", *common, "--epochs", "1")
    assert proc.returncode == 0, proc.stderr
    assert "Input size: auto -> 224 (the arm's keypoint box spans 0.90 of the median frame" in proc.stdout
    record = json.loads((tmp_path / "m_train.json").read_text())
    assert record["input_size"] == 224 and record["input_size_auto"]["chose"] == 224
    assert load_model(out).input_shape[1:3] == (224, 224)
    # a next round from a model trained at 256 stays at 256: the arm spans 140 px there too
    first, second = tmp_path / "r1.keras", tmp_path / "r2.keras"
    proc = cli("train", *common[:2], "--out", first, *common[4:], "--epochs", "1", "--input-size", "256")
    assert proc.returncode == 0, proc.stderr
    common[5] = first
    proc = cli("train", *common[:2], "--out", second, *common[4:], "--epochs", "1")
    assert proc.returncode == 0, proc.stderr
    assert "Input size: auto -> 256" in proc.stdout and "the smallest size reaching them is 224" in proc.stdout
    record = json.loads((tmp_path / "r2_train.json").read_text())
    assert record["input_size"] == 256 and record["input_size_auto"]["start_input_size"] == 256
    assert load_model(second).input_shape[1:3] == (256, 256)
