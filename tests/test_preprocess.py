"""Frame preprocessing: the two-step resize keeps keypoint coordinates exact and is used for every size."""

import os

import cv2
import numpy as np
import pytest

from fcnpose_tf.preprocess import box_reduce, keypoints_to_frame, keypoints_to_input, preprocess_frame, read_image


def _blob_frame(w, h, centre, sigma=6.0):
    """A smooth bright blob at a sub-pixel centre (pixel-centre convention) on a dark frame."""
    x = np.arange(w)[None, :] - centre[0]
    y = np.arange(h)[:, None] - centre[1]
    blob = 255.0 * np.exp(-(x ** 2 + y ** 2) / (2 * sigma ** 2))
    return np.repeat(np.round(blob).astype(np.uint8)[..., None], 3, axis=2)


def _centroid(image):
    v = image[..., 0].astype(np.float64)
    ys, xs = np.mgrid[:v.shape[0], :v.shape[1]]
    return np.array([(v * xs).sum() / v.sum(), (v * ys).sum() / v.sum()])


@pytest.mark.parametrize("w, h", [(640, 480), (1280, 720), (601, 457), (224, 224), (160, 120)])
def test_blob_centre_lands_where_keypoints_to_input_says(w, h):
    centre = np.array([0.37 * w + 0.3, 0.61 * h - 0.2])
    out = preprocess_frame(_blob_frame(w, h, centre, sigma=max(w, h) / 40), 64)
    assert out.shape == (64, 64, 3) and out.dtype == np.float32
    expected = keypoints_to_input(centre[None], (h, w), 64)[0]
    np.testing.assert_allclose(_centroid(out), expected, atol=0.05)
    np.testing.assert_allclose(keypoints_to_frame(expected[None], (h, w), 64)[0], centre, atol=1e-9)


def test_reduction_averages_instead_of_skipping_pixels():
    """A one-pixel checkerboard (sensor-noise-like detail) becomes flat grey, not an aliasing pattern."""
    board = (np.indices((480, 640)).sum(0) % 2 * 255).astype(np.uint8)
    small = preprocess_frame(np.repeat(board[..., None], 3, axis=2), 224)
    assert small.shape == (224, 224, 3)
    assert abs(float(small.mean()) - 0.5) < 1 / 255 and float(small.std()) < 2 / 255


def test_rgb_order_and_scale():
    frame = np.zeros((100, 100, 3), np.uint8)
    frame[..., 0] = 255  # blue in BGR
    out = preprocess_frame(frame, 32)
    np.testing.assert_allclose(out[..., 2], 1.0) and np.testing.assert_allclose(out[..., :2], 0.0)


def test_grey_or_broken_frames_are_user_errors():
    from fcnpose_tf.errors import UserError

    with pytest.raises(UserError, match="H x W x 3"):
        preprocess_frame(np.zeros((10, 10), np.uint8), 32)
    with pytest.raises(UserError, match="got None"):
        preprocess_frame(None, 32)


def test_speed_path_is_an_integer_box_filter_then_bit_exact_bilinear():
    """640x480 -> 224: a 2x2 box reduction to 320x240 (OpenCV's exact INTER_AREA path), then
    INTER_LINEAR_EXACT, whose integer rounding is the same on x86 and arm64 (plain INTER_LINEAR's is not)."""
    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    reduced = box_reduce(frame, 224)
    np.testing.assert_array_equal(reduced, cv2.resize(frame, (320, 240), interpolation=cv2.INTER_AREA))
    expected = cv2.resize(reduced, (224, 224), interpolation=cv2.INTER_LINEAR_EXACT)[..., ::-1]
    np.testing.assert_array_equal(preprocess_frame(frame, 224), expected * np.float32(1.0 / 255.0))


def test_output_buffer_is_filled_in_place():
    frame = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    buffer = np.full((224, 224, 3), -1, np.float32)
    assert preprocess_frame(frame, 224, out=buffer) is buffer
    np.testing.assert_array_equal(buffer, preprocess_frame(frame, 224))
    view = np.full((224, 224, 4), -1, np.float32)[..., :3]  # not contiguous: still filled
    assert preprocess_frame(frame, 224, out=view) is view
    np.testing.assert_array_equal(view, buffer)


def test_frame_already_at_input_size_is_only_scaled():
    frame = np.random.default_rng(2).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    np.testing.assert_array_equal(preprocess_frame(frame, 64), frame[..., ::-1] * np.float32(1.0 / 255.0))


def test_pixel_bytes_are_the_float_input_before_scaling_and_fill_a_buffer_in_place():
    """The int8 export's uint8 input (scale 1/255, zero point 0) takes these bytes as they are."""
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.preprocess import preprocess_frame_bytes

    frame = np.random.default_rng(3).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    pixels = preprocess_frame_bytes(frame, 224)
    assert pixels.dtype == np.uint8 and pixels.shape == (224, 224, 3)
    np.testing.assert_array_equal(pixels * np.float32(1.0 / 255.0), preprocess_frame(frame, 224))
    buffer = np.zeros((1, 224, 224, 3), np.uint8)  # as an interpreter's input tensor
    assert preprocess_frame_bytes(frame, 224, out=buffer[0]).base is buffer
    np.testing.assert_array_equal(buffer[0], pixels)
    with pytest.raises(UserError, match="C-contiguous 224 x 224 x 3 uint8 buffer"):
        preprocess_frame_bytes(frame, 224, out=np.zeros((224, 224, 3), np.float32))


@pytest.mark.parametrize("w, h, size, blocks", [(640, 480, 192, (320, 240)), (640, 480, 160, (160, 160)),
                                                (1280, 720, 192, (256, 240)), (601, 457, 64, (66, 65)),
                                                (100, 60, 64, (100, 60))])
def test_box_reduction_uses_blocks_that_divide_the_frame(w, h, size, blocks):
    """640 // 192 = 3 does not divide 640: the blocks are 2 x 2 (OpenCV's whole-block path), not a fractional 3.005.
    A prime side keeps the fractional factor (the bilinear step alone would skip pixels)."""
    frame = np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)
    reduced = box_reduce(frame, size)
    assert reduced.shape[1::-1] == blocks
    if (w, h) != blocks:
        np.testing.assert_array_equal(reduced, cv2.resize(frame, blocks, interpolation=cv2.INTER_AREA))


def test_read_image_gives_none_for_a_header_opencv_refuses_and_for_a_named_pipe(tmp_path):
    import struct
    import zlib

    ok, png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(png.tobytes())
    data[16:24] = struct.pack(">II", 40000, 40000)  # IHDR's width and height; its CRC recomputed below
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    (tmp_path / "huge.png").write_bytes(bytes(data))
    assert read_image(tmp_path / "huge.png") is None  # cv2.imdecode raises on it
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.png")
        assert read_image(tmp_path / "pipe.png") is None  # at once: no writer is waited for


def test_a_cut_off_or_damaged_png_reads_as_none_without_libpngs_own_line(tmp_path, capfd):
    """libpng prints `libpng error: ...` to descriptor 2 for a truncated or damaged PNG, ahead of the command's one `error:`
    line; the reader keeps it off (the None is what the caller reports)."""
    whole = tmp_path / "whole.png"
    cv2.imwrite(str(whole), (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8))
    cut = tmp_path / "cut.png"
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])
    damaged = bytearray(whole.read_bytes())
    damaged[len(damaged) // 2:len(damaged) // 2 + 64] = bytes(64)  # inside IDAT: its CRC no longer matches
    scrambled = tmp_path / "scrambled.png"  # whole, IEND and all: "libpng error: ..." as it decodes
    scrambled.write_bytes(damaged)
    capfd.readouterr()
    assert read_image(cut) is None and read_image(scrambled) is None and read_image(whole).shape == (64, 64, 3)
    assert capfd.readouterr().err == ""
