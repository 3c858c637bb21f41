"""`train --input-size auto`: where the arm is and how large, the view chosen from it (a fixed camera's workspace
crop at its own aspect, the fewest input pixels up to the cap), and how train records it."""

import json

import numpy as np
import pytest

from fcnpose_tf import settings
from fcnpose_tf.data.arm_size import (AUTO_MAX_INPUT_PIXELS, MIN_ARM_INPUT_PX, WORKSPACE_MARGIN, arm_input_px,
                                      _holds, aspect_inputs, choose_view, fit_aspect, workspace_box)
from fcnpose_tf.data.via import ViaFrame, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from fcnpose_tf.metrics import FCN_POSE_P70_WIDTHS, fcn_pose_macs
from fcnpose_tf.preprocess import FrameView


def _box(x0, y0, w, h):
    """Eight keypoints whose bounding box is (x0, y0, w, h)."""
    return np.array([[x0, y0], [x0 + w, y0 + h]] + [[x0 + w / 2, y0 + h / 2]] * 6, float)


def test_the_workspace_holds_every_keypoint_with_its_margin_inside_the_frame():
    frames = [(_box(100, 50, 100, 200), 640, 480), (_box(300, 100, 100, 200), 640, 480)]
    x, y, w, h = workspace_box(frames)
    grow = WORKSPACE_MARGIN * np.array([300, 250])  # the union box is 100..400 x 50..300
    assert x == int(np.floor(100 - grow[0])) and y == int(np.floor(50 - grow[1]))
    assert x + w - 1 == int(np.ceil(400 + grow[0])) and y + h - 1 == int(np.ceil(300 + grow[1]))
    edge = workspace_box([(_box(0, 0, 639, 479), 640, 480)])
    assert edge == (0, 0, 640, 480)
    assert workspace_box([(_box(0, 0, 10, 10), 640, 480), (_box(0, 0, 10, 10), 320, 360)]) is None  # two aspects


def test_frames_of_one_aspect_at_two_sizes_share_one_workspace_in_the_larger_frames_pixels():
    # one camera at 640 x 480 and 1280 x 960: the same arm box, stated in each frame's pixels
    small = [(_box(200 + 8 * i, 150 + 4 * i, 80, 160), 640, 480) for i in range(6)]
    large = [((k + 0.5) * 2 - 0.5, 1280, 960) for k, _, _ in small]
    mixed = small[::2] + large[1::2]
    assert workspace_box(mixed) == workspace_box(large)
    view = choose_view(mixed, fixed_camera=True)
    assert view.crop is not None and view.frame_size == (1280, 960) and view == choose_view(large, fixed_camera=True)
    assert view.box((480, 640, 3)) == tuple(round(v / 2) for v in view.crop)  # the crop follows the frame's size


def test_fit_aspect_grows_one_axis_about_the_centre_and_stays_in_the_frame():
    assert fit_aspect((100, 100, 200, 200), 1.5, (640, 480)) == (50, 100, 300, 200)
    assert fit_aspect((0, 100, 200, 100), 1.0, (640, 480)) == (0, 50, 200, 200)
    assert fit_aspect((500, 0, 140, 480), 2.0, (640, 480))[::2] == (0, 640)  # as wide as the frame allows
    for shape in aspect_inputs(4 / 3):
        assert shape[0] % 32 == 0 and shape[1] % 32 == 0
    assert (224, 288) in aspect_inputs(4 / 3) and (224, 224) in aspect_inputs(1.0)


def test_crop_sides_grow_to_whole_reduction_blocks_inside_the_frame():
    from fcnpose_tf.data.arm_size import block_friendly
    from fcnpose_tf.preprocess import block_factor

    box = block_friendly((38, 1, 547, 479), (224, 256), (640, 480))
    assert box == (38, 0, 548, 480) and 548 % block_factor(548, 256) == 0 and 480 % block_factor(480, 224) == 0
    assert block_friendly((0, 0, 640, 479), (224, 256), (640, 480)) == (0, 0, 640, 480)
    assert block_friendly((100, 100, 300, 200), (224, 256), (640, 480)) == (100, 100, 300, 200)  # factor 1: as is
    assert block_friendly((635, 0, 5, 9), (2, 2), (640, 480))[0] + 6 <= 640  # grown and moved inside


def test_a_fixed_camera_gets_its_workspace_at_its_aspect_and_views_that_vary_the_whole_frame():
    # an arm 80 x 160 px moving inside a 160 x 200 workspace of 640 x 480 frames
    frames = [(_box(200 + 8 * i, 150 + 4 * i, 80, 160), 640, 480) for i in range(11)]
    view = choose_view(frames, fixed_camera=True)
    assert view.crop is not None and view.frame_size == (640, 480)
    x, y, w, h = view.crop
    assert abs(w / h - view.width / view.height) < 0.02  # square pixels
    assert arm_input_px(frames, view) >= MIN_ARM_INPUT_PX and view.height * view.width <= AUTO_MAX_INPUT_PIXELS
    # the fewest pixels that reach it: the next smaller input of that aspect does not
    smaller = [s for s in aspect_inputs(w / h) if s[0] * s[1] < view.height * view.width]
    if smaller:
        assert arm_input_px(frames, FrameView(*smaller[-1], fit_aspect(workspace_box(frames), smaller[-1][1] /
                                                                       smaller[-1][0], (640, 480)), (640, 480))) \
            < MIN_ARM_INPUT_PX
    whole = choose_view(frames, fixed_camera=False)
    assert whole.crop is None and whole.height * whole.width > view.height * view.width


def test_an_arm_too_small_for_the_cap_gets_the_most_pixels_within_it():
    frames = [(_box(10 + 40 * i, 10 + 40 * i, 60, 60), 640, 480) for i in range(10)]  # a workspace of 420 x 420
    view = choose_view(frames, fixed_camera=True)
    assert view.shape == (224, 224) and view.crop is not None  # 256 x 256 is past the cap
    assert arm_input_px(frames, view) < MIN_ARM_INPUT_PX
    assert fcn_pose_macs(view.shape) <= 1.91e9 and fcn_pose_macs(view.shape, FCN_POSE_P70_WIDTHS) <= 160e6


def test_a_workspace_wider_than_any_input_gets_a_crop_at_the_widest_input(capsys):
    from fcnpose_tf.data.arm_size import resolve_view

    # a 2000 x 300 camera whose arm sweeps a 1700 x 250 workspace (6.8 : 1; the widest input is 384 x 128's 3 : 1)
    frames = [ViaFrame(f"f{i}.png", 2000, 300, _box(150 + 170 * i, 25, 170, 250)) for i in range(10)]
    view = resolve_view(frames, "auto", "auto", fixed_camera=True).chose
    assert view.shape == (128, 384) and view.crop is not None and view.frame_size == (2000, 300)
    assert "frames of several" not in capsys.readouterr().out  # they are of one size
    assert aspect_inputs(6.8) == aspect_inputs(3.0) and aspect_inputs(0.05) == aspect_inputs(1 / 3)


@pytest.mark.parametrize("span, side", [(1.0, 224), (0.625, 224), (0.53, 288), (0.39, 384), (0.1, 384)])
def test_views_that_vary_keep_the_square_side_measured_there(span, side):
    frames = [(_box(5 + i, 5, span * 640, span * 480 * 0.5), 640, 480) for i in range(5)]
    assert choose_view(frames, fixed_camera=False) == FrameView(side, side)


def test_a_start_view_is_kept_only_while_it_holds_the_frames():
    frames = [(_box(200 + 8 * i, 150 + 4 * i, 80, 160), 640, 480) for i in range(11)]
    start = FrameView(256, 256, (160, 110, 260, 260), (640, 480))  # holds x 200-360, y 150-350
    assert arm_input_px(frames, start) >= MIN_ARM_INPUT_PX
    assert choose_view(frames, True, start=start) == start
    moved = frames + [(_box(600, 10, 30, 30), 640, 480)]  # a keypoint outside the start's crop
    assert choose_view(moved, True, start=start) != start
    # a whole-frame start (the bundled generalist's 224 x 224) does not replace a fixed camera's workspace crop
    large = [(_box(150 + 4 * i, 40, 200, 400), 640, 480) for i in range(5)]
    assert arm_input_px(large, FrameView(288, 288)) >= MIN_ARM_INPUT_PX
    assert choose_view(large, True, start=FrameView(288, 288)).crop is not None
    assert choose_view(large, False, start=FrameView(288, 288)) == FrameView(288, 288)  # views that vary: kept
    # frames of another aspect (a 16:9 camera mode after 640x480): the start's crop, stretched, holds them and gives
    # the arm its pixels, but its pixels are no longer square: the frames' own workspace is chosen instead
    wide = [(_box(400 + 4 * i, 200, 300, 200), 1280, 720) for i in range(5)]
    assert _holds(start, wide) and arm_input_px(wide, start) >= MIN_ARM_INPUT_PX
    chosen = choose_view(wide, True, start=start)
    assert chosen != start and chosen.frame_size == (1280, 720)
    assert choose_view([(k * 2, 1280, 960) for k, _, _ in frames], True, start=start) == start  # 4:3 at 2x: kept


def test_train_takes_auto_s_or_hxw_and_the_paper_keeps_224_over_the_whole_frame():
    setting = settings.TRAIN_INPUT_SIZE
    assert setting.default == "auto" and setting.default_in("paper") == 224
    assert settings.TRAIN_CROP.default == "auto" and settings.TRAIN_CROP.default_in("paper") == "none"
    assert setting.parse("auto") == "auto" and setting.parse(" Auto ") == "auto" and setting.parse("320") == 320
    assert setting.parse("224x288") == (224, 288) and setting.validate((224, 288)) == (224, 288)
    assert setting.validate("auto") == "auto" and setting.validate(384) == 384
    for bad in (100, 0, -32, "big", 2.5, True, (224, 100)):
        with pytest.raises(UserError, match="input size must be auto, S or HxW"):
            setting.validate(bad)
    with pytest.raises(UserError, match="input size must be a positive multiple of 32"):
        settings.INPUT_SIZE.validate("auto")


def _project(folder, boxes, size=(640, 480)):
    (folder / "images").mkdir(parents=True)
    import cv2

    w, h = size
    frames = []
    for i, box in enumerate(boxes):
        cv2.imwrite(str(folder / "images" / f"f{i}.png"), np.full((h, w, 3), 90, np.uint8))
        frames.append(ViaFrame(f"f{i}.png", w, h, _box(*box)))
    write_via_project(folder / "labels.json", frames, UR5)
    return folder / "labels.json"


def test_resolve_view_says_what_it_chose_and_what_it_costs(tmp_path, capsys):
    from fcnpose_tf.data.arm_size import resolve_view
    from fcnpose_tf.data.via import read_via

    frames = read_via(_project(tmp_path / "cell", [(200 + 8 * i, 150 + 4 * i, 80, 160) for i in range(11)])).frames
    choice = resolve_view(frames, "auto", "auto", fixed_camera=True)
    view, record = choice.chose, choice.to_json()
    out = capsys.readouterr().out
    assert view.crop is not None and record["chose"] == view.to_json() and record["fixed_camera"] is True
    assert list(record) == ["arm_input_px", "min_arm_input_px", "crop", "fixed_camera", "chose", "macs"]  # as written
    assert f"View: {view.describe()} (its workspace: one fixed camera)" in out
    assert f"{fcn_pose_macs(view.shape) / 1e9:.2f} G multiply-adds a frame unpruned" in out
    none = resolve_view(frames, "auto", "none", fixed_camera=True).chose
    assert none.crop is None
    given = resolve_view(frames, (224, 288), "auto", fixed_camera=True).chose  # a given size: the whole frame
    assert given == FrameView(224, 288)
    given = resolve_view(frames, (224, 288), "workspace", fixed_camera=True).chose
    assert given.shape == (224, 288) and given.crop is not None
    x, y, w, h = given.crop
    assert abs(w / h - 288 / 224) < 0.02


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_train_auto_records_the_view_and_the_model_carries_its_crop(cli_here, tmp_path):
    from fcnpose_tf.training.model import load_model, view_of

    data = _project(tmp_path / "frames", [(200 + 8 * i, 150 + 4 * i, 60, 120) for i in range(6)])
    out = tmp_path / "m.keras"
    common = ["--data", data, "--out", out, "--init", "none", "--augment", "paper", "--augment-copies", "0",
              "--batch-size", "4", "--threads", "1", "--quiet", "--epochs", "1"]
    status, out_text, err = cli_here("train", *common)
    assert status == 0, err
    assert "View: " in out_text and "(its workspace: one fixed camera)" in out_text
    record = json.loads((tmp_path / "m_train.json").read_text())
    view = FrameView.from_json(record["view"])
    assert view.crop is not None and record["view_auto"]["chose"] == record["view"]
    assert view_of(load_model(out)) == view
    # a next round from that model keeps its view: its crop holds the frames and the arm spans enough there
    second = tmp_path / "r2.keras"
    status, out_text, err = cli_here("train", *common[:2], "--out", second, "--init", str(out), *common[6:])
    assert status == 0, err
    assert "the starting model's own view, kept" in out_text
    assert view_of(load_model(second)) == view
