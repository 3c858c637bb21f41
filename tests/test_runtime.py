"""The Raspberry Pi runtime: interpreter loading and checks, KeypointModel, sources, sinks, timing, bench.

The main fixture is a tiny FCN-Pose (64 x 64 input, 3 filters per layer) with
hand-set weights, so its keypoints are known exactly: every conv passes each
RGB channel through unchanged (ReLU of a non-negative image), so the 64 x 64
maps are the channel maxima over 32 x 32 blocks (one per frame quadrant), and
conv10 turns them into clean, far-from-threshold maps:

    map 0 base      red present in the quadrant         map 4 wrist2  quadrant without any colour
    map 1 shoulder  green present                       map 5 wrist3  always on (whole frame)
    map 2 elbow     blue present                        map 6 flange  never on (missing)
    map 3 wrist1    red absent                          map 7 tool    green or blue present

Runtime (float16 .tflite through LiteRT) and training side (Keras + the same
preprocess + post-processing) must agree to 0.5 px, and both must give the
analytic block centres. Tests that prove the runtime needs no TensorFlow run
in a subprocess where tensorflow, tf_keras and keras cannot be imported.
"""

from __future__ import annotations

import json
from dataclasses import replace
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, schema_for_maps
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.runtime import bench as rbench
from fcnpose_tf.runtime import interpreter as rinterp
from fcnpose_tf.runtime import sources as rsources
from fcnpose_tf.runtime.estimator import KeypointModel, Prediction, StageTimes
from fcnpose_tf.runtime.runner import run_stream
from fcnpose_tf.runtime.sinks import (CsvWriter, JsonlWriter, RollingFps, VideoSink, draw_overlay,
                                      open_record_writer)
from fcnpose_tf.runtime.sources import Frame, ImageSource, VideoSource, open_source
from fcnpose_tf.runtime.timing import LatencyLog, describe_ms

SIZE = 64
QUADRANTS = {"tl": (0, 0), "tr": (1, 0), "br": (1, 1), "bl": (0, 1)}  # (column, row) of the 32 x 32 block
BLOCKED = ("tensorflow", "tf_keras", "keras")


# --------------------------------------------------------------------------------------------------
# fixtures: models and frames
# --------------------------------------------------------------------------------------------------

def _to_tflite(model) -> bytes:
    """float16 .tflite bytes: the project's verified exporter when present, else the plain converter."""
    try:
        from fcnpose_tf.compression.export import to_tflite
    except ImportError:
        to_tflite = None
    if to_tflite is not None:
        return to_tflite(model, "float16")
    return _convert_plain(model)


def _convert_plain(model) -> bytes:
    import tensorflow as tf

    converter = tf.lite.TFLiteConverter.from_keras_model(model)
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    converter.target_spec.supported_types = [tf.float16]
    return converter.convert()


def _structured_model():
    """The hand-set FCN-Pose described in the module docstring (tf_keras)."""
    from fcnpose_tf.training.model import build_fcn_pose

    model = build_fcn_pose((3,) * 9, input_size=SIZE)
    for i in range(1, 10):
        layer = model.get_layer(f"conv{i}")
        kernel = np.zeros(layer.kernel.shape, np.float32)
        for c in range(3):
            kernel[1, 1, c, c] = 1.0
        layer.set_weights([kernel, np.zeros(3, np.float32)])
    kernel = np.zeros((3, 3, 3, 9), np.float32)
    bias = np.zeros(9, np.float32)
    r, g, b = 0, 1, 2
    kernel[1, 1, r, 0], bias[0] = 20, -10          # red present
    kernel[1, 1, g, 1], bias[1] = 20, -10          # green present
    kernel[1, 1, b, 2], bias[2] = 20, -10          # blue present
    kernel[1, 1, r, 3], bias[3] = -20, 10          # red absent
    kernel[1, 1, :, 4], bias[4] = -20, 10          # no colour at all
    bias[5] = 10                                   # always on
    bias[6] = -10                                  # never on
    kernel[1, 1, g, 7] = kernel[1, 1, b, 7] = 20   # green or blue
    bias[7] = -10
    kernel[1, 1, r, 8], bias[8] = 20, -10          # skeleton map (ignored by post-processing)
    model.get_layer("conv10").set_weights([kernel, bias])
    return model


def quadrant_frame(width: int = 640, height: int = 480, red: str = "tl") -> np.ndarray:
    """Black BGR frame with a red patch in quadrant `red`, blue top-right, green bottom-right."""
    img = np.zeros((height, width, 3), np.uint8)

    def patch(quadrant, bgr):
        col, row = QUADRANTS[quadrant]
        x0, y0 = col * width // 2, row * height // 2
        img[y0 + height // 8: y0 + height * 3 // 8, x0 + width // 8: x0 + width * 3 // 8] = bgr

    patch("tr", (255, 0, 0))
    patch("br", (0, 255, 0))
    if red in ("tr", "br"):  # share the quadrant: red strip above the other colour
        col, row = QUADRANTS[red]
        x0, y0 = col * width // 2, row * height // 2
        img[y0 + 2: y0 + height // 16, x0 + width // 8: x0 + width * 3 // 8] = (0, 0, 255)
    else:
        patch(red, (0, 0, 255))
    return img


def block_centre(blocks, width: int, height: int) -> tuple[float, float]:
    """Frame-pixel centroid of a union of 32 x 32 map blocks given as (column, row) pairs."""
    xs = [c * 32 + 15.5 for c, _ in blocks]
    ys = [r * 32 + 15.5 for _, r in blocks]
    mx, my = float(np.mean(xs)), float(np.mean(ys))
    return (mx + 0.5) * width / SIZE - 0.5, (my + 0.5) * height / SIZE - 0.5


def expected_keypoints(width: int = 640, height: int = 480, red: str = "tl") -> np.ndarray:
    """The analytic keypoints of the structured model on quadrant_frame (NaN for flange)."""
    q = QUADRANTS
    has_red = {red}
    coloured = {"tr", "br", red}
    all_q = ["tl", "tr", "br", "bl"]
    sets = [
        [q[red]],
        [q["br"]],
        [q["tr"]],
        [q[k] for k in all_q if k not in has_red],
        [q[k] for k in all_q if k not in coloured],
        [q[k] for k in all_q],
        None,
        [q["tr"], q["br"]],
    ]
    out = np.full((8, 2), np.nan)
    for i, blocks in enumerate(sets):
        if blocks:
            out[i] = block_centre(blocks, width, height)
    return out


@pytest.fixture(scope="module")
def structured(tmp_path_factory):
    """(keras model, path of its float16 .tflite)."""
    model = _structured_model()
    path = tmp_path_factory.mktemp("models") / "structured_fp16.tflite"
    path.write_bytes(_to_tflite(model))
    return model, path


@pytest.fixture(scope="module")
def random_model(tmp_path_factory):
    """(keras model, .tflite path) of a random-weight FCN-Pose with the 70%-pruned widths, 64 x 64."""
    from fcnpose_tf.training.model import build_fcn_pose

    model = build_fcn_pose((39, 20, 10, 5, 3, 3, 5, 10, 20), input_size=SIZE)
    path = tmp_path_factory.mktemp("models") / "p70_fp16.tflite"
    path.write_bytes(_convert_plain(model))
    return model, path


@pytest.fixture(scope="module")
def bad_models(tmp_path_factory):
    """Valid .tflite files that are not FCN-Pose models, by name."""
    import tf_keras as keras

    folder = tmp_path_factory.mktemp("bad")
    models = {
        "vector_input": keras.Sequential([keras.Input((16,)), keras.layers.Dense(4)]),
        "grey_input": keras.Sequential([keras.Input((SIZE, SIZE, 1)), keras.layers.Conv2D(9, 3, padding="same")]),
        "one_map": keras.Sequential([keras.Input((SIZE, SIZE, 3)), keras.layers.Conv2D(1, 3, padding="same")]),
        "maps_not_input_size": keras.Sequential([keras.Input((SIZE, SIZE, 3)), keras.layers.MaxPooling2D(2),
                                                 keras.layers.Conv2D(9, 3, padding="same")]),
    }
    paths = {}
    for name, model in models.items():
        paths[name] = folder / f"{name}.tflite"
        paths[name].write_bytes(_convert_plain(model))
    return paths


def write_video(path: Path, frames, fps: float = 10.0) -> Path:
    fourcc = "MJPG" if path.suffix == ".avi" else "mp4v"
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()
    return path


RED_CYCLE = ("tl", "bl", "tr", "br")


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """A 12-frame 320x240 MJPG video; the red patch moves through the quadrants frame by frame."""
    frames = [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(12)]
    return write_video(tmp_path_factory.mktemp("video") / "clip.avi", frames)


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory) -> Path:
    """frame1.png .. frame10.png (natural order), mixed sizes, plus one unreadable .png."""
    folder = tmp_path_factory.mktemp("images")
    for i in (1, 2, 10):
        cv2.imwrite(str(folder / f"frame{i}.png"), quadrant_frame(320 + 32 * i, 240, RED_CYCLE[i % 4]))
    (folder / "frame5.png").write_bytes(b"not a png")
    (folder / "notes.txt").write_text("ignored")
    return folder


# --------------------------------------------------------------------------------------------------
# interpreter: backends, model checks, cost
# --------------------------------------------------------------------------------------------------

def test_backend_prefers_litert():
    backend = rinterp.find_backend()
    assert backend.name == "ai_edge_litert" and backend.skipped == ()
    assert backend.label.startswith("ai_edge_litert ")


def test_backend_falls_back_and_says_why(monkeypatch, structured):
    real = rinterp._import_backend

    def fake(name):
        if name in ("ai_edge_litert", "tflite_runtime"):
            raise ImportError(f"No module named '{name}'")
        return real(name)

    monkeypatch.setattr(rinterp, "_import_backend", fake)
    backend = rinterp.find_backend("auto")
    assert backend.name == "tensorflow"
    assert [s.split(":")[0] for s in backend.skipped] == ["ai_edge_litert", "tflite_runtime"]
    # the tf.lite fallback computes the same keypoints
    frame = quadrant_frame()
    with pytest.warns(UserWarning):  # tf.lite.Interpreter warns that it is deprecated
        tf_model = KeypointModel(structured[1], 1)
    assert tf_model.backend.name == "tensorflow"
    np.testing.assert_allclose(tf_model.predict(frame).keypoints, expected_keypoints(), atol=1e-6)


def test_no_backend_is_a_user_error(monkeypatch):
    def fail(name):
        raise ImportError("missing")

    monkeypatch.setattr(rinterp, "_import_backend", fail)
    with pytest.raises(UserError, match="pip install ai-edge-litert"):
        rinterp.find_backend()


def test_model_io_is_read_from_the_model(structured):
    model = KeypointModel(structured[1], num_threads=1)
    assert (model.view.shape, model.view.crop, model.num_maps) == ((SIZE, SIZE), None, 9)
    assert model.io.input.dtype == np.float32 and model.io.input.shape == (1, SIZE, SIZE, 3)
    assert model.schema is UR5
    assert model.num_threads == 1
    assert "64x64x3 float32 -> 64x64x9 float32" in model.describe()


def test_default_threads_is_all_cores(structured):
    model = KeypointModel(structured[1])
    assert model.num_threads == rinterp.default_num_threads() == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("widths", [(3,) * 9, (39, 20, 10, 5, 3, 3, 5, 10, 20)])
def test_params_and_macs_match_keras(widths, structured, random_model):
    from fcnpose_tf.training.model import describe

    keras_model, path = structured if widths == (3,) * 9 else random_model
    stats = KeypointModel(path, 1).stats()
    assert stats.params == keras_model.count_params()
    assert stats.macs == sum(r.macs for r in describe(keras_model))
    assert stats.conv_layers == 10
    assert stats.weight_dtypes == ("float16",)
    assert stats.size_bytes == path.stat().st_size


def test_missing_corrupt_and_foreign_files(tmp_path, structured):
    with pytest.raises(UserError, match="model file not found"):
        KeypointModel(tmp_path / "nope.tflite")
    data = structured[1].read_bytes()
    truncated = tmp_path / "truncated.tflite"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match="cannot be loaded as a TFLite model"):
        KeypointModel(truncated)
    keras_file = tmp_path / "model.tflite"
    keras_file.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    with pytest.raises(UserError, match="not a TFLite model"):
        KeypointModel(keras_file)
    with pytest.raises(UserError, match="not a file"):
        KeypointModel(tmp_path)


@pytest.mark.parametrize("name, message", [
    ("vector_input", r"input shape \[1, 16\], expected \[1, H, W, 3\]"),
    ("grey_input", r"input shape \[1, 64, 64, 1\]"),
    ("one_map", r"output shape \[1, 64, 64, 1\], expected \[1, H, W, C\] maps with C >= 2"),
    ("maps_not_input_size", "output maps 32x32 differ from the 64x64 input"),
])
def test_non_fcn_pose_models_are_refused(bad_models, name, message):
    with pytest.raises(UserError, match=message):
        KeypointModel(bad_models[name])


def test_bad_threads_and_threshold(structured):
    with pytest.raises(UserError, match="threads"):
        KeypointModel(structured[1], num_threads=0)
    with pytest.raises(UserError, match="threshold"):
        KeypointModel(structured[1], decoding=Decoding(threshold=1.0))


def test_generic_schema_for_other_map_counts():
    schema = schema_for_maps(5)
    assert schema.keypoints == ("kp0", "kp1", "kp2", "kp3") and schema.edges == ((0, 1), (1, 2), (2, 3))
    assert schema_for_maps(9) is UR5


# --------------------------------------------------------------------------------------------------
# KeypointModel: the frame path, parity with the training side
# --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("width, height, red", [(640, 480, "tl"), (333, 517, "bl"), (64, 64, "br")])
def test_keypoints_are_the_analytic_block_centres(structured, width, height, red):
    model = KeypointModel(structured[1], 1)
    pred = model.predict(quadrant_frame(width, height, red))
    np.testing.assert_allclose(pred.keypoints, expected_keypoints(width, height, red), atol=1e-9)
    assert pred.found.tolist() == [True] * 6 + [False, True]
    assert pred.confidence[6] == 0 and pred.confidence[5] == SIZE * SIZE  # pixel counts of the clusters
    assert pred.frame_shape == (height, width, 3)
    t = pred.times
    assert t.preprocess_ms > 0 and t.invoke_ms > 0 and t.postprocess_ms > 0
    assert t.total_ms == pytest.approx(t.preprocess_ms + t.invoke_ms + t.postprocess_ms)


def test_runtime_matches_training_side_path(structured, random_model):
    """One frame through LiteRT float16 vs Keras + preprocess_frame + maps_to_keypoints + keypoints_to_frame."""
    from fcnpose_tf.postprocess import maps_to_keypoints
    from fcnpose_tf.preprocess import keypoints_to_frame, preprocess_frame

    frame = quadrant_frame(640, 480, "bl")
    keras_model, path = structured
    x = preprocess_frame(frame, SIZE)[None]
    keras_maps = keras_model.predict(x, verbose=0)[0]
    kp, conf = maps_to_keypoints(keras_maps, 0.5)
    kp = keypoints_to_frame(kp, frame.shape, SIZE)
    runtime = KeypointModel(path, 1)
    pred = runtime.predict(frame)
    assert np.array_equal(np.isnan(pred.keypoints), np.isnan(kp))
    np.testing.assert_allclose(pred.keypoints, kp, atol=0.5)
    np.testing.assert_array_equal(pred.confidence, conf)
    np.testing.assert_allclose(runtime.predict_maps(frame), keras_maps, atol=1e-3)
    # a random-weight model: the float16 interpreter's maps follow Keras' closely on a natural-ish frame
    keras_model, path = random_model
    frame = rbench.synthetic_frame(640, 480, seed=3)
    keras_maps = keras_model.predict(preprocess_frame(frame, SIZE)[None], verbose=0)[0]
    np.testing.assert_allclose(KeypointModel(path, 2).predict_maps(frame), keras_maps, atol=1e-2)


def test_keras_and_litert_predictors_share_one_frame_path(tmp_path, random_model):
    """The same float32-exported model behind both predictors: one predict, the same keypoints and maps."""
    from fcnpose_tf.training.evaluate import KerasKeypointModel
    from fcnpose_tf.compression.export import to_tflite
    from fcnpose_tf.runtime.estimator import KeypointPredictor

    model = _structured_model()
    path = tmp_path / "structured_fp32.tflite"
    path.write_bytes(to_tflite(model, "float32"))
    keras_predictor, litert = KerasKeypointModel(model, num_threads=1), KeypointModel(path, 1)
    assert isinstance(keras_predictor, KeypointPredictor) and isinstance(litert, KeypointPredictor)
    assert type(keras_predictor).predict is type(litert).predict is KeypointPredictor.predict
    assert keras_predictor.backend_label == "tf_keras (direct call)"
    assert litert.backend_label == litert.backend.label and litert.backend.name in litert.backend_label
    for width, height, red in [(640, 480, "tl"), (333, 517, "br")]:
        frame = quadrant_frame(width, height, red)
        a, b = keras_predictor.predict(frame), litert.predict(frame)
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        np.testing.assert_array_equal(a.keypoints, litert.predict(frame).keypoints)
        np.testing.assert_allclose(a.keypoints, expected_keypoints(width, height, red), atol=1e-9)
        np.testing.assert_array_equal(a.confidence, b.confidence)
        assert a.confidence.dtype == b.confidence.dtype == np.float64 and a.frame_shape == b.frame_shape
        assert min(a.times.preprocess_ms, a.times.invoke_ms, a.times.postprocess_ms) > 0
    # random weights (maps away from 0/1): the two forward passes agree to float32 rounding
    model = random_model[0]
    path = tmp_path / "random_fp32.tflite"
    path.write_bytes(to_tflite(model, "float32"))
    keras_predictor, litert = KerasKeypointModel(model, num_threads=1), KeypointModel(path, 1)
    frame = rbench.synthetic_frame(320, 240, seed=5)
    for predictor in (keras_predictor, litert):
        predictor.set_input(frame)
        predictor.invoke()
    np.testing.assert_allclose(keras_predictor.read_maps(), litert.read_maps(), atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["uint8", "int8"])
def test_fully_quantized_models_are_fed_and_read_through_their_scales(tmp_path, dtype):
    """Integer input/output (full-integer quantization): the frame is quantized, the maps dequantized."""
    import tensorflow as tf

    from fcnpose_tf.training.model import describe
    from fcnpose_tf.preprocess import preprocess_frame

    keras_model = _structured_model()

    def representative():
        for red in RED_CYCLE:
            yield [preprocess_frame(quadrant_frame(640, 480, red), SIZE)[None]]

    converter = tf.lite.TFLiteConverter.from_keras_model(keras_model)
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    converter.representative_dataset = representative
    converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
    converter.inference_input_type = converter.inference_output_type = getattr(tf, dtype)
    path = tmp_path / f"{dtype}.tflite"
    path.write_bytes(converter.convert())
    model = KeypointModel(path, 1)
    assert model.io.input.dtype == np.dtype(dtype) and model.io.input.quantized and model.io.output.quantized
    for red in RED_CYCLE:
        pred = model.predict(quadrant_frame(640, 480, red))
        np.testing.assert_allclose(pred.keypoints, expected_keypoints(640, 480, red), atol=1e-9)
    stats = model.stats()
    assert "int8" in stats.weight_dtypes
    assert stats.params == keras_model.count_params() and stats.macs == sum(r.macs for r in describe(keras_model))


def test_predict_reuses_buffers_and_leaves_interpreter_usable(structured):
    model = KeypointModel(structured[1], 1)
    frames = [quadrant_frame(640, 480, r) for r in RED_CYCLE]
    for _ in range(3):  # no "reference to internal data" error across calls; results independent
        for red, frame in zip(RED_CYCLE, frames):
            np.testing.assert_allclose(model.predict(frame).keypoints, expected_keypoints(640, 480, red), atol=1e-9)
    maps = model.read_maps(copy=True)
    model.invoke()  # a copy does not pin the interpreter's buffer
    assert maps.shape == (SIZE, SIZE, 9)


def test_records_use_null_for_missing(structured):
    pred = KeypointModel(structured[1], 1).predict(quadrant_frame())
    records = pred.records(UR5)
    assert [r["name"] for r in records] == list(UR5.keypoints)
    assert records[6] == {"name": "flange", "x": None, "y": None, "confidence": 0}
    assert records[0] == {"name": "base", "x": 159.5, "y": 119.5, "confidence": 1024}


# --------------------------------------------------------------------------------------------------
# sources
# --------------------------------------------------------------------------------------------------

def test_video_source_reads_all_frames(clip):
    with open_source(str(clip)) as src:
        assert isinstance(src, VideoSource) and src.fps == pytest.approx(10.0) and src.frame_count == 12
        frames = list(src)
    assert [f.index for f in frames] == list(range(12))
    assert frames[0].image.shape == (240, 320, 3) and frames[0].image.flags.c_contiguous
    assert frames[3].media_time_s == pytest.approx(0.3, abs=1e-6)
    assert src.end_reason == "end of video (12 frames)"


def test_truncated_video_ends_cleanly_with_a_message(tmp_path):
    frames = [rbench.synthetic_frame(320, 240, seed=i) for i in range(30)]
    full = write_video(tmp_path / "full.avi", frames)
    cut = tmp_path / "cut.avi"
    data = full.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    messages = []
    src = open_source(cut, warn=messages.append)
    n = sum(1 for _ in src)
    src.close()
    assert 0 < n < 30
    assert f"ended after {n} of 30 frames" in src.end_reason and messages


def test_image_folder_natural_order_and_skip(image_dir):
    messages = []
    with open_source(image_dir, warn=messages.append) as src:
        assert isinstance(src, ImageSource)
        frames = list(src)
    names = [Path(f.name).name for f in frames]
    assert names == ["frame1.png", "frame2.png", "frame10.png"]
    assert src.skipped == 1 and messages == [f"skipped {image_dir / 'frame5.png'}: not a readable image"]
    assert src.end_reason == "end of the images (3 read, 1 unreadable)"  # all gone through, not stopped early


def test_single_image_and_errors(tmp_path, image_dir):
    with open_source(image_dir / "frame2.png") as src:
        assert [Path(f.name).name for f in src] == ["frame2.png"]
    (tmp_path / "empty").mkdir()
    cases = [(tmp_path / "missing.mp4", "no such file or folder"), (tmp_path / "empty", "has no images"),
             (image_dir / "frame5.png", "cannot be read as an image"),
             (image_dir / "notes.txt", "cannot be opened as a video"),
             ("/dev/video987", "no such camera device"), ("97", "camera 97: cannot be opened")]
    for spec, message in cases:
        with pytest.raises(UserError, match=message):
            open_source(spec)


class FakeCapture:
    """Stands in for cv2.VideoCapture: frames every `period` s, numbered in pixel [0, 0]; fails after `fail_after`."""

    def __init__(self, device, period=0.002, fail_after=None):
        self.period, self.fail_after, self.n = period, fail_after, 0
        self.released = False

    def isOpened(self):
        return True

    def set(self, prop, value):
        return True

    def get(self, prop):
        return 30.0 if prop == cv2.CAP_PROP_FPS else 0.0

    def read(self):
        time.sleep(self.period)
        if self.fail_after is not None and self.n >= self.fail_after:
            return False, None
        self.n += 1
        img = np.zeros((4, 4, 3), np.uint8)
        img[0, 0, 0] = self.n % 256
        return True, img

    def release(self):
        self.released = True


def test_camera_keeps_only_the_newest_frame(monkeypatch):
    monkeypatch.setattr(rsources.cv2, "VideoCapture", lambda device: FakeCapture(device))
    src = open_source("0")
    assert isinstance(src, rsources.CameraSource) and src.fps == 30.0
    seen = []
    for frame in src:
        seen.append(frame.index)
        time.sleep(0.02)  # a slow model: ~10 frames arrive meanwhile
        if len(seen) == 8:
            break
    src.close()
    assert seen == sorted(seen) and len(set(seen)) == 8
    gaps = np.diff(seen)
    assert gaps.min() >= 1 and gaps.mean() > 3  # stale frames were dropped, not queued
    assert src.dropped == seen[-1] + 1 - len(seen)
    assert src._cap.released and not src._thread.is_alive()


def test_camera_that_disappears_ends_the_run(monkeypatch):
    monkeypatch.setattr(rsources.cv2, "VideoCapture", lambda device: FakeCapture(device, fail_after=5))
    messages = []
    src = rsources.CameraSource(0, warn=messages.append, stall_timeout_s=0.2)
    frames = list(src)
    src.close()
    assert 1 <= len(frames) <= 5
    assert "stopped delivering frames" in src.end_reason and messages


def test_camera_that_never_opens(monkeypatch):
    class Closed(FakeCapture):
        def isOpened(self):
            return False

    monkeypatch.setattr(rsources.cv2, "VideoCapture", lambda device: Closed(device))
    with pytest.raises(UserError, match="/dev/video0: cannot be opened"):
        rsources.CameraSource("/dev/video0")


def test_camera_runs_report_capture_to_keypoints_latency(monkeypatch, structured, clip):
    monkeypatch.setattr(rsources.cv2, "VideoCapture", lambda device: FakeCapture(device, period=0.01))
    model = KeypointModel(structured[1], 1)
    src = open_source("0")
    try:
        summary = run_stream(model, src, max_frames=5)
    finally:
        src.close()
    latency = np.array(summary.capture_to_keypoints_ms)
    model_ms = summary.latency.values("end_to_end")
    assert len(latency) == 5 and (latency < 5000).all()
    assert (latency >= model_ms - 1.0).all()  # from capture: at least the frame's own model time
    assert "Latency: capture to keypoints written" in summary.report(model, src)
    monkeypatch.undo()  # the clip is read by OpenCV itself
    video = open_source(clip)  # a file's timestamps are read times, not capture times: no such line
    summary = run_stream(model, video, max_frames=3)
    video.close()
    assert len(summary.capture_to_keypoints_ms) == 0 and "Latency:" not in summary.report(model, video)


# --------------------------------------------------------------------------------------------------
# sinks and the loop
# --------------------------------------------------------------------------------------------------

def _prediction(found=True) -> Prediction:
    kp = np.array([[10.0 * i + 5, 20.0] for i in range(8)])
    if not found:
        kp[2] = np.nan
    conf = np.arange(8, dtype=np.float64) * (1 if found else 1)
    return Prediction(kp, conf, StageTimes(1.0, 2.0, 0.5), (100, 200, 3))


def _frame(i=0) -> Frame:
    return Frame(i, np.zeros((100, 200, 3), np.uint8), 1700000000.0 + i, "cam")


def test_jsonl_flushes_every_frame_and_refuses_overwrite(tmp_path):
    path = tmp_path / "k.jsonl"
    writer = JsonlWriter(path, UR5)
    writer.write(_frame(0), _prediction())
    writer.write(_frame(1), _prediction(found=False))
    lines = path.read_text().splitlines()  # read while still open: already on disk
    assert len(lines) == 2
    rec = json.loads(lines[1])
    assert list(rec) == ["frame", "timestamp", "source", "width", "height", "latency_ms", "keypoints"]
    assert rec["frame"] == 1 and rec["width"] == 200 and rec["height"] == 100
    assert rec["latency_ms"] == {"preprocess": 1.0, "invoke": 2.0, "postprocess": 0.5}
    assert rec["keypoints"][2] == {"name": "elbow", "x": None, "y": None, "confidence": 2}
    writer.close()
    with pytest.raises(UserError, match="already exists"):
        JsonlWriter(path, UR5)
    before = path.read_text()
    JsonlWriter(path, UR5, force=True).close()  # no record written: the earlier file is not replaced
    assert path.read_text() == before
    replacing = JsonlWriter(path, UR5, force=True)
    replacing.write(_frame(7), _prediction())
    assert path.read_text() == before  # replaced only when the new records are closed
    replacing.close()
    assert [json.loads(line)["frame"] for line in path.read_text().splitlines()] == [7]
    assert [p.name for p in tmp_path.iterdir()] == ["k.jsonl"]  # no temporary left beside it


def test_csv_columns_and_missing_cells(tmp_path):
    import csv

    path = tmp_path / "k.csv"
    with open_record_writer(path, UR5) as writer:
        assert isinstance(writer, CsvWriter)
        writer.write(_frame(0), _prediction(found=False))
        assert len(path.read_text().splitlines()) == 2  # header + the flushed row
    rows = list(csv.DictReader(path.open()))
    assert rows[0]["elbow_x"] == "" and rows[0]["base_x"] == "5.0" and rows[0]["tool_confidence"] == "7"
    assert rows[0]["invoke_ms"] == "2.0"
    with pytest.raises(UserError, match="use .jsonl or .csv"):
        open_record_writer(tmp_path / "k.txt", UR5)


def test_overlay_draws_keypoints_skeleton_and_fps():
    img = np.zeros((480, 640, 3), np.uint8)
    pred = Prediction(np.array([[100.0, 300.0], [400.0, 300.0]] + [[np.nan, np.nan]] * 6), np.ones(8),
                      StageTimes(1, 1, 1), img.shape)
    out = draw_overlay(img, pred, UR5, fps=12.3)
    assert img.max() == 0  # copy by default
    assert out[300, 100].any() and out[300, 400].any() and out[300, 250].any()  # points and the edge between
    assert out[5:25, 5:60].any()  # FPS box top-left
    assert not out[100, 500].any()  # nothing else drawn
    bare = draw_overlay(img, pred, UR5, fps=None)
    assert not bare[5:25, 5:60].any()
    boxed = draw_overlay(img, replace(pred, crop=(50, 200, 500, 200)), UR5, fps=None)  # the crop it read, outlined
    assert boxed[200, 300].any() and boxed[399, 300].any() and boxed[250, 50].any() and boxed[250, 549].any()
    assert not boxed[100, 500].any() and not boxed[250, 300].any()


def test_rolling_fps_averages_recent_frames():
    fps = RollingFps(window=3)
    for ms in (100.0, 10.0, 10.0, 10.0):
        fps.add(ms)
    assert fps.fps == pytest.approx(100.0)  # the 100 ms frame has left the window
    assert np.isnan(RollingFps().fps)


def test_latency_log_statistics():
    log = LatencyLog([StageTimes(1.0, float(i), 0.5) for i in range(1, 101)])
    s = log.summary()
    assert len(log) == 100
    assert s["invoke"]["median"] == pytest.approx(50.5) and s["invoke"]["p95"] == pytest.approx(95.05)
    assert s["end_to_end"]["mean"] == pytest.approx(50.5 + 1.5)
    assert log.fps()["end_to_end"] == pytest.approx(1000 / 52.0)
    assert describe_ms([])["mean"] != describe_ms([])["mean"]  # NaN
    assert "end-to-end" in log.table()


def test_stage_summary_is_mean_sample_std_and_median():
    """The one summary of per-frame times: std is the sample std (ddof=1), as numpy computes it."""
    values = np.random.default_rng(0).gamma(2.0, 3.0, 57)
    summary = describe_ms(values)
    assert summary["mean"] == pytest.approx(np.mean(values), rel=1e-12)
    assert summary["std"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
    assert summary["std"] != pytest.approx(np.std(values), rel=1e-6)  # not the population std
    assert summary["median"] == pytest.approx(np.median(values), rel=1e-12)
    assert describe_ms([4.0])["std"] == 0.0
    log = LatencyLog(StageTimes(0.5, float(v), 0.25) for v in values)
    assert log.summary()["invoke"]["std"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
    assert log.summary()["end_to_end"]["std"] == pytest.approx(np.std(values + 0.75, ddof=1), rel=1e-9)


def test_video_sink_appears_only_when_closed(tmp_path):
    path = tmp_path / "out.mp4"
    sink = VideoSink(path, fps=5)
    sink.write(np.zeros((48, 64, 3), np.uint8))
    sink.write(np.zeros((100, 100, 3), np.uint8))  # another size: resized to the first
    assert not path.exists()
    assert sink.close() == path
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600
    cap = cv2.VideoCapture(str(path))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2 and int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 64
    cap.release()
    assert list(tmp_path.iterdir()) == [path]
    with pytest.raises(UserError, match="already exists"):
        VideoSink(path)
    with pytest.raises(UserError, match="unknown video type"):
        VideoSink(tmp_path / "x.gif")


def test_run_stream_writes_each_frame_and_keeps_them_on_a_crash(structured, clip, tmp_path):
    model = KeypointModel(structured[1], 1)
    path = tmp_path / "k.jsonl"
    writer = JsonlWriter(path, model.schema)

    def crash(frame, prediction):
        if frame.index == 4:
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        run_stream(model, open_source(clip), [writer], on_frame=crash)
    records = [json.loads(line) for line in path.read_text().splitlines()]
    assert [r["frame"] for r in records] == [0, 1, 2, 3, 4]  # written before the crash
    writer.close()


def test_run_stream_summary_and_ctrl_c(structured, clip, tmp_path):
    model = KeypointModel(structured[1], 1)

    def interrupt(frame, prediction):
        if frame.index == 2:
            raise KeyboardInterrupt

    src = open_source(clip)
    summary = run_stream(model, src, on_frame=interrupt)
    assert summary.end_reason == "interrupted (Ctrl-C)" and summary.frames == 2
    src = open_source(clip)
    summary = run_stream(model, src, max_frames=5)
    assert summary.frames == 5 and len(summary.latency) == 5 and "max-frames 5" in summary.end_reason
    report = summary.report(model, src)
    assert "end-to-end" in report and "invoke-only" in report and "1 thread;" in report


# --------------------------------------------------------------------------------------------------
# bench
# --------------------------------------------------------------------------------------------------

def test_benchmark_report_and_json(random_model):
    keras_model, path = random_model
    report = rbench.benchmark(path, threads=(1, 2), frames=6, warmup=1)
    assert [r.threads for r in report.results] == [1, 2] and all(r.ok for r in report.results)
    d = report.to_dict()
    assert d["params"] == keras_model.count_params() and d["size_bytes"] == path.stat().st_size
    assert d["input_shape"] == [SIZE, SIZE, 3] and d["output_shape"] == [SIZE, SIZE, 9]
    r0 = d["results"][0]
    for key in ("invoke_latency_ms", "end_to_end_latency_ms", "preprocess_latency_ms", "postprocess_latency_ms"):
        assert set(r0[key]) == {"mean", "std", "median", "p95", "min", "max"} and r0[key]["median"] > 0
    e2e = r0["end_to_end_latency_ms"]["mean"]
    assert e2e > r0["preprocess_latency_ms"]["mean"] + r0["postprocess_latency_ms"]["mean"]  # + its invoke
    assert r0["fps_end_to_end"] == pytest.approx(1000 / e2e, rel=1e-3)
    json.dumps(d, allow_nan=False)
    text = report.report()
    assert "FPS invoke" in text and f"{keras_model.count_params():,} parameters" in text
    assert "Fewer than 50 timed frames" in text


def test_thread_list_parsing():
    import argparse

    from fcnpose_tf.settings import thread_counts

    assert thread_counts("1, 2,4,2") == (1, 2, 4)
    for bad in ("0", "a", "1,,2", "-1"):
        with pytest.raises(argparse.ArgumentTypeError):
            thread_counts(bad)
    assert rbench.default_thread_counts(4) == (1, 2, 4)
    assert rbench.default_thread_counts(6) == (1, 2, 4, 6)
    assert rbench.default_thread_counts(1) == (1,)


def test_synthetic_frame_is_deterministic():
    a, b = rbench.synthetic_frame(seed=1), rbench.synthetic_frame(seed=1)
    assert a.shape == (480, 640, 3) and a.dtype == np.uint8 and np.array_equal(a, b)
    assert not np.array_equal(a, rbench.synthetic_frame(seed=2))


# --------------------------------------------------------------------------------------------------
# without TensorFlow: the `pi` extra is enough
# --------------------------------------------------------------------------------------------------

BLOCKER = f'''
import sys
_BLOCKED = {BLOCKED!r}

class _NoTensorFlow:
    """Make TensorFlow and Keras unimportable, as on a Raspberry Pi with only the `pi` extra."""
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in _BLOCKED:
            raise ImportError(f"No module named {{name!r}} (blocked: Pi environment test)")
        return None

sys.meta_path.insert(0, _NoTensorFlow())
'''


@pytest.fixture(scope="module")
def no_tf_env(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("no_tf")
    (folder / "sitecustomize.py").write_text(BLOCKER)
    pythonpath = os.pathsep.join([str(folder)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
    return dict(os.environ, PYTHONPATH=pythonpath, TF_CPP_MIN_LOG_LEVEL="2")


def _py(env, *args, cwd=None, timeout=PROCESS_TIMEOUT):
    return subprocess.run([sys.executable, *map(str, args)], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def test_runtime_modules_import_without_tensorflow(no_tf_env):
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        for blocked in ("tensorflow", "tf_keras", "keras"):
            try:
                importlib.import_module(blocked)
            except ImportError:
                pass
            else:
                raise SystemExit(f"{blocked} should be blocked")
        import fcnpose_tf.runtime as rt
        names = [m.name for m in pkgutil.iter_modules(rt.__path__, "fcnpose_tf.runtime.")]
        for name in names + ["fcnpose_tf.commands.run", "fcnpose_tf.commands.bench", "fcnpose_tf.commands.predict",
                             "fcnpose_tf.correction.prelabel", "fcnpose_tf.training.evaluate", "fcnpose_tf.cli"]:
            importlib.import_module(name)
        for attr in rt.__all__:
            getattr(rt, attr)
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("tensorflow", "tf_keras", "keras"))
        print(len(names), leaked)
    """)
    result = _py(no_tf_env, "-c", code)
    assert result.returncode == 0, result.stderr
    count, leaked = result.stdout.split(" ", 1)
    assert int(count) >= 7 and leaked.strip() == "[]"


def test_run_and_bench_work_without_tensorflow(no_tf_env, structured, random_model, clip, image_dir, tmp_path):
    model = structured[1]
    result = _py(no_tf_env, "-m", "fcnpose_tf", "run", model, "--source", clip, "--threads", "1",
                 "--out", "k.jsonl", "--out", "k.csv", "--save-video", "overlay.mp4", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "ai_edge_litert" in result.stdout and "end of video (12 frames)" in result.stdout
    assert "FPS:" in result.stdout and "p95 (ms)" in result.stdout
    records = [json.loads(line) for line in (tmp_path / "k.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in records] == list(range(12))
    for r in records:
        red = RED_CYCLE[r["frame"] % 4]
        kp = {k["name"]: k for k in r["keypoints"]}
        assert list(kp) == list(UR5.keypoints)
        exp = expected_keypoints(320, 240, red)
        assert (kp["base"]["x"], kp["base"]["y"]) == pytest.approx(tuple(exp[0]), abs=0.01)
        assert (kp["shoulder"]["x"], kp["shoulder"]["y"]) == pytest.approx(tuple(exp[1]), abs=0.01)
        assert kp["flange"]["x"] is None and kp["flange"]["y"] is None
        assert r["source"] == str(clip) and r["width"] == 320
    assert len((tmp_path / "k.csv").read_text().splitlines()) == 13
    cap = cv2.VideoCapture(str(tmp_path / "overlay.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    cap.release()

    result = _py(no_tf_env, "-m", "fcnpose_tf", "run", model, "--source", image_dir, "--out", "img.jsonl",
                 cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "skipped" in result.stderr and "frame5.png" in result.stderr
    records = [json.loads(line) for line in (tmp_path / "img.jsonl").read_text().splitlines()]
    assert [Path(r["source"]).name for r in records] == ["frame1.png", "frame2.png", "frame10.png"]
    for r in records:
        i = int(Path(r["source"]).stem[5:])
        exp = expected_keypoints(320 + 32 * i, 240, RED_CYCLE[i % 4])
        assert (r["keypoints"][0]["x"], r["keypoints"][0]["y"]) == pytest.approx(tuple(exp[0]), abs=0.01)

    result = _py(no_tf_env, "-m", "fcnpose_tf", "bench", random_model[1], "--threads", "1,2", "--frames", "5",
                 "--warmup", "1", "--json", "bench.json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "FPS invoke" in result.stdout and "ai_edge_litert" in result.stdout
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["backend"] == "ai_edge_litert" and [r["threads"] for r in data["results"]] == [1, 2]
    assert data["params"] == random_model[0].count_params()


def test_bundled_int8_file_takes_pixel_bytes_and_thresholds_its_maps_as_integers():
    """The full-integer file: preprocessing writes the resized RGB bytes into its uint8 input, and the
    keypoints decoded from its raw int8 maps equal those of its dequantized maps, on real frames."""
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.data.synth.frame import render_frame
    from fcnpose_tf.postprocess import decode
    from fcnpose_tf.preprocess import preprocess_frame_bytes

    model = KeypointModel(models_dir() / "fcnpose_ur5_p70_int8.tflite", 1)
    assert model.io.input.holds_pixel_bytes and model.io.output.dtype == np.int8
    assert model.stats().params == 14611  # the folded file counts as the 70 % network (compress --min-filters 15)
    found = 0
    for index in range(4):
        frame = render_frame(1, index)[0]
        pred = model.predict(frame)
        np.testing.assert_array_equal(model.interpreter.get_tensor(model.io.input.index)[0],
                                      preprocess_frame_bytes(frame, 224))
        keypoints, confidence = decode(model.read_maps(), frame.shape, model.decoding.threshold)
        np.testing.assert_array_equal(pred.keypoints, keypoints)
        np.testing.assert_array_equal(pred.confidence, confidence)
        found += int(pred.found.sum())
    assert found >= 30  # a trained model on frames like its training data: keypoints, not an empty check


def test_frame_path_does_not_recompute_the_tensor_specs(monkeypatch):
    """`holds_pixel_bytes` (np.isclose) and `quantized` are asked on every frame; computed once per model,
    they cost the int8 file's preprocessing ~0.07 ms less per frame (docs/runtime.md, "Frame path")."""
    from fcnpose_tf.bundled import models_dir

    model = KeypointModel(models_dir() / "fcnpose_ur5_p70_int8.tflite", 1)
    frame = quadrant_frame(640, 480, RED_CYCLE[0])
    expected = model.predict(frame)
    calls = []
    monkeypatch.setattr(np, "isclose", lambda *a, **k: calls.append(a) or True)
    for _ in range(3):
        pred = model.predict(frame)
        np.testing.assert_array_equal(pred.keypoints, expected.keypoints)
    assert calls == []
    assert {"holds_pixel_bytes", "quantized"} <= model.io.input.__dict__.keys()  # cached on the spec
    assert "quantized" in model.io.output.__dict__


def test_evaluate_of_a_tflite_file_works_without_tensorflow(no_tf_env, structured, tmp_path):
    from test_via import write_dataset

    via, _ = write_dataset(tmp_path / "frames", n=4, size=(64, 48))
    result = _py(no_tf_env, "-m", "fcnpose_tf", "evaluate", structured[1], "--data", via, "--threads", "1",
                 "--worst", "2", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "all 4 frames" in result.stdout and "pck@0.5_bbox" in result.stdout and "Worst 2 frames" in result.stdout
    result = _py(no_tf_env, "-m", "fcnpose_tf", "evaluate", tmp_path / "m.keras", "--data", via, cwd=tmp_path)
    assert result.returncode == 2 and "this command needs TensorFlow" in result.stderr  # a .keras does
