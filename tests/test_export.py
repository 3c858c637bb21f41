"""TFLite export: what the converter writes (inspected in the flatbuffer), parity with Keras, refusal."""

import numpy as np
import pytest
import tf_keras as keras

from fcnpose_tf.compression import export as export_module
from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.export import export_tflite, to_tflite, write_tflite
from fcnpose_tf.compression.verify import ExportVerificationError, _interpreter, run_tflite, verify_tflite
from fcnpose_tf.compression.tflite_file import inspect_tflite
from fcnpose_tf.training.model import build_fcn_pose
from fcnpose_tf.compression.prune import prune_model
from weights import randomize


def frames(size, n=2, seed=1):
    return np.random.default_rng(seed).random((n, size, size, 3), dtype=np.float32)


@pytest.fixture(scope="module")
def fcn64():
    return randomize(build_fcn_pose(input_size=64), seed=2)


@pytest.fixture(scope="module")
def fcn64_fp16(fcn64):
    return export_tflite(fcn64, "float16")


@pytest.fixture(scope="module")
def sizes224():
    """float32 / float16 / int8-weights exports of the full and the 70%-pruned FCN-Pose at 224."""
    full = randomize(build_fcn_pose(), seed=3)
    models = {"full": full, "p70": prune_model(full, 0.7)}
    # int8-weights: dynamic-range hybrid kernels also quantize activations on the fly, which on this
    # untrained network moves maps by up to ~0.05; the mode's default map_atol (0.2) allows it.
    return {(name, q): (model.count_params(), export_tflite(model, q))
            for name, model in models.items() for q in ("float32", "float16", "int8-weights")}


def blob_model(size=32, channel=0, name="blobs"):
    """A model with crisp maps: map k is ~1 where input channel `channel` is bright, else ~0.

    Three maps (two keypoints + skeleton) from a 1x1 convolution with large weights, so keypoints
    decode to the centroid of the bright square in the input.
    """
    inputs = keras.Input((size, size, 3), name="image")
    conv = keras.layers.Conv2D(3, 1, activation="sigmoid", name="maps")
    model = keras.Model(inputs, conv(inputs), name=name)
    kernel = np.zeros((1, 1, 3, 3), np.float32)
    kernel[0, 0, channel, :] = 40.0
    conv.set_weights([kernel, np.full(3, -20.0, np.float32)])
    return model


def blob_frames(size=32):
    x = np.zeros((2, size, size, 3), np.float32)
    x[0, 4:9, 6:10, 0] = 1.0  # channel 0: a blob centred at (7.5, 6)
    x[1, 20:23, 10:13, 0] = 1.0
    x[0, 20:25, 20:24, 1] = 1.0  # channel 1: somewhere else
    x[1, 2:5, 25:28, 1] = 1.0
    return x


# ------------------------------------------------------------------------------------------
# what the converter writes
# ------------------------------------------------------------------------------------------

def test_float16_stores_conv_weights_as_float16_feeding_dequantize(fcn64_fp16):
    info = inspect_tflite(fcn64_fp16.data)
    convs = info["convolutions"]
    assert len(convs) == 10 and all(c["op"] == "CONV_2D" for c in convs)
    for conv in convs:
        assert conv["stored_dtype"] == "FLOAT16" and conv["dequantized"] and conv["filter_dtype"] == "FLOAT32"
    # every stored float is float16 (the only other constants are RESIZE's int32 sizes)
    assert set(info["constant_dtypes"]) == {"FLOAT16", "INT32"}
    assert info["op_counts"]["DEQUANTIZE"] == info["constant_dtypes"]["FLOAT16"] == 20
    assert info["constant_dtypes"]["INT32"] == 4
    assert convs[0]["filter_shape"] == [128, 3, 3, 3] and convs[0]["stored_bytes"] == 128 * 27 * 2


def test_interface_is_static_float32_and_builtin_only(fcn64_fp16):
    info = inspect_tflite(fcn64_fp16.data)
    assert [(t["shape"], t["dtype"]) for t in info["inputs"]] == [([1, 64, 64, 3], "FLOAT32")]
    assert [(t["shape"], t["dtype"]) for t in info["outputs"]] == [([1, 64, 64, 9], "FLOAT32")]
    assert info["builtin_only"] and info["custom_ops"] == [] and info["flex_ops"] == []
    assert info["subgraphs"] == 1
    assert info["op_counts"] == {"CONV_2D": 10, "DEQUANTIZE": 20, "LOGISTIC": 1, "MAX_POOL_2D": 5,
                                 "RESIZE_NEAREST_NEIGHBOR": 4}
    assert fcn64_fp16.input_shape == (1, 64, 64, 3)


@pytest.mark.slow
def test_float32_has_no_dequantize_and_int8_weights_are_int8(sizes224):
    f32 = inspect_tflite(sizes224[("full", "float32")][1].data)
    assert "DEQUANTIZE" not in f32["op_counts"] and set(f32["constant_dtypes"]) == {"FLOAT32", "INT32"}
    i8 = inspect_tflite(sizes224[("full", "int8-weights")][1].data)
    for conv in i8["convolutions"]:
        # the converter quantizes kernels of at least 1024 weights (conv6 of FCN-Pose, 8 x 8 x 9, is smaller)
        big = np.prod(conv["filter_shape"]) >= 1024
        assert (conv["stored_dtype"], conv["dequantized"]) == ("INT8" if big else "FLOAT32", False), conv
    assert sum(c["stored_dtype"] == "INT8" for c in i8["convolutions"]) == 9
    assert i8["builtin_only"] and i8["inputs"][0]["dtype"] == "FLOAT32" and i8["outputs"][0]["dtype"] == "FLOAT32"


@pytest.mark.slow
@pytest.mark.parametrize("name,limit", [("full", 280_000), ("p70", 45_000)])
def test_sizes_at_224(sizes224, name, limit):
    params, fp16 = sizes224[(name, "float16")]
    assert (name, params) in {("full", 131_705), ("p70", 14_668)}
    assert fp16.size_bytes <= limit
    overhead = fp16.size_bytes - 2 * params  # 2 bytes per parameter plus the graph (~11 KB)
    assert 0 < overhead < 16_000
    f32 = sizes224[(name, "float32")][1].size_bytes
    assert 0 < f32 - 4 * params < 16_000
    assert sizes224[(name, "int8-weights")][1].size_bytes < fp16.size_bytes < f32


@pytest.mark.slow
def test_size_overhead_does_not_depend_on_widths(sizes224):
    overheads = [sizes224[(name, "float16")][1].size_bytes - 2 * sizes224[(name, "float16")][0]
                 for name in ("full", "p70")]
    assert abs(overheads[0] - overheads[1]) < 1_000, overheads


@pytest.mark.slow
def test_every_export_at_224_matches_keras(sizes224):
    for (name, quantize), (_, result) in sizes224.items():
        assert result.parity.max_abs_diff <= (0.1 if quantize == "int8-weights" else 1e-2), (name, quantize)
        assert result.parity.frames == 2 and result.convert_seconds > 0


@pytest.mark.slow
def test_verification_tolerance_is_per_mode(sizes224):
    for (name, quantize), (_, result) in sizes224.items():
        int8 = quantize == "int8-weights"
        assert (result.parity.map_atol, result.parity.keypoint_px) == ((0.2, 2.0) if int8 else (1e-2, 1.0))
    assert sizes224[("full", "int8-weights")][1].parity.max_abs_diff > 1e-2  # needs the looser check
    # an explicit tolerance still wins
    with pytest.raises(ExportVerificationError, match=r"max abs map difference .* > 0.001"):
        export_tflite(randomize(build_fcn_pose(input_size=64), seed=3), "int8-weights", map_atol=1e-3)


# ------------------------------------------------------------------------------------------
# parity with Keras
# ------------------------------------------------------------------------------------------

def test_parity_on_fresh_frames(fcn64, fcn64_fp16, tmp_path):
    from fcnpose_tf.runtime.interpreter import load_interpreter

    path = tmp_path / "fcn64_fp16.tflite"
    path.write_bytes(fcn64_fp16.data)
    interpreter, _ = load_interpreter(path, num_threads=1)  # the Pi-side loader, no TensorFlow involved
    x = frames(64, n=3, seed=7)  # not the frames the export was verified on
    got = run_tflite(interpreter, x)
    want = fcn64(x, training=False).numpy()
    assert got.shape == want.shape == (3, 64, 64, 9)
    assert np.abs(got - want).max() <= 1e-2
    assert 0 < fcn64_fp16.parity.max_abs_diff <= 1e-2  # float16 weights: close, not identical


def test_keypoints_compared_on_crisp_maps():
    model = blob_model()
    result = export_tflite(model, "float16", sample_frames=blob_frames())
    parity = result.parity
    assert parity.keypoints_compared == 4 and parity.keypoints_ambiguous == 0  # 2 frames x 2 keypoints
    assert parity.max_keypoint_px < 0.01
    assert result.to_dict()["parity"]["keypoints_compared"] == 4


def _constant_maps_model(bias):
    inputs = keras.Input((32, 32, 3))
    conv = keras.layers.Conv2D(3, 1, activation="sigmoid", kernel_initializer="zeros",
                               bias_initializer=keras.initializers.Constant(bias))
    return keras.Model(inputs, conv(inputs))


def test_maps_on_the_threshold_are_ambiguous_not_compared():
    # Keras maps are exactly sigmoid(0) = 0.5, the threshold itself: every keypoint is missing.
    keras_model = _constant_maps_model(0.0)
    assert export_tflite(keras_model, "float32").parity.keypoints_compared == 4  # exact copy: all compared
    # A "converted" model 2.5e-4 above it finds every keypoint (the whole map is active). Within
    # map_atol, and the Keras decoding itself flips at threshold - 2.5e-4: ambiguous, not an error.
    nudged = to_tflite(_constant_maps_model(1e-3), "float32")
    parity = verify_tflite(keras_model, nudged, frames(32))
    assert parity.keypoints_compared == 0 and parity.keypoints_ambiguous == 4
    assert parity.max_abs_diff == pytest.approx(2.5e-4, rel=1e-2)


def test_single_frame_and_variable_size_models():
    inputs = keras.Input((None, None, 3), name="image")
    model = randomize(keras.Model(inputs, keras.layers.Conv2D(3, 3, padding="same", activation="sigmoid")(inputs)))
    with pytest.raises(UserError, match="variable input size"):
        to_tflite(model)
    data = to_tflite(model, "float16", input_size=32, sample_frames=frames(32, 1)[0])
    assert inspect_tflite(data)["inputs"][0]["shape"] == [1, 32, 32, 3]


@pytest.mark.parametrize("kwargs,message", [
    ({"quantize": "int4"}, "quantize must be one of float32, float16, int8-weights"),
    ({"sample_frames": np.zeros((2, 32, 32, 3), np.float32)}, r"sample frames must be N x 64 x 64 x 3"),
    ({"sample_frames": np.full((1, 64, 64, 3), np.nan, np.float32)}, "NaN"),
    ({"num_samples": 0}, "num_samples"),
    ({"input_size": 32}, "takes 64 x 64 inputs"),
])
def test_bad_arguments(fcn64, kwargs, message):
    with pytest.raises(UserError, match=message):
        to_tflite(fcn64, **kwargs)


# ------------------------------------------------------------------------------------------
# a file that disagrees is refused and nothing is written
# ------------------------------------------------------------------------------------------

def _substitute(monkeypatch, data):
    """Make the converter return `data`, whatever it is given."""
    monkeypatch.setattr(export_module, "_convert", lambda model, quantize, shape, calibration=None: data)


def test_other_weights_are_refused_and_nothing_written(fcn64, tmp_path, monkeypatch):
    other = export_tflite(randomize(build_fcn_pose(input_size=64), seed=99), "float16").data
    _substitute(monkeypatch, other)
    target = tmp_path / "out" / "model.tflite"
    with pytest.raises(ExportVerificationError, match=r"max abs map difference .* > 0.01 at frame \d+, map \d+"):
        write_tflite(fcn64, target)
    assert not target.exists() and list(target.parent.iterdir()) == []


@pytest.mark.slow
def test_nan_output_is_refused(fcn64, tmp_path, monkeypatch):
    broken = randomize(build_fcn_pose(input_size=64), seed=2)
    kernel, bias = broken.get_layer("conv10").get_weights()
    broken.get_layer("conv10").set_weights([kernel, np.full_like(bias, np.nan)])
    _substitute(monkeypatch, export_module._convert(broken, "float32", (1, 64, 64, 3)))
    with pytest.raises(ExportVerificationError, match="NaN/infinite"):
        write_tflite(fcn64, tmp_path / "m.tflite")
    assert list(tmp_path.iterdir()) == []


def test_corrupt_bytes_are_refused(fcn64, fcn64_fp16, tmp_path, monkeypatch):
    data = bytearray(fcn64_fp16.data)
    _substitute(monkeypatch, bytes(data[: len(data) // 3]))  # truncated
    with pytest.raises(ExportVerificationError, match="does not load"):
        write_tflite(fcn64, tmp_path / "m.tflite")
    assert list(tmp_path.iterdir()) == []


def test_wrong_interface_is_refused(fcn64, monkeypatch):
    _substitute(monkeypatch, to_tflite(build_fcn_pose(input_size=32), "float32"))
    with pytest.raises(ExportVerificationError,
                       match=r"takes float32 \[1, 32, 32, 3\], expected float32 \[1, 64, 64, 3\]"):
        to_tflite(fcn64)


def test_keypoint_disagreement_is_named():
    from fcnpose_tf.keypoints import KeypointSchema
    from fcnpose_tf.training.model import with_schema

    keras_model = blob_model(channel=0)
    wrong = to_tflite(blob_model(channel=1), "float32", sample_frames=blob_frames())  # maps of the other blob
    with pytest.raises(ExportVerificationError,
                       match=r"decodes kp0 \(keypoint 0\) of frame 0 at \(21\.5, 22\.0\), the Keras model at "
                             r"\(7\.5, 6\.0\), \d+\.\d+ px > 1 px \(4 keypoint\(s\) disagree"):
        verify_tflite(keras_model, wrong, blob_frames(), map_atol=1.0)
    with_schema(keras_model, KeypointSchema.chain("gripper", ("finger L", "finger R")))  # the user's own names
    with pytest.raises(ExportVerificationError, match=r"decodes finger L \(keypoint 0\) of frame 0"):
        verify_tflite(keras_model, wrong, blob_frames(), map_atol=1.0)


def test_custom_and_flex_ops_are_seen_and_refused(fcn64, fcn64_fp16, monkeypatch):
    from ai_edge_litert import schema_py_generated as schema
    from ai_edge_litert.tools import flatbuffer_utils

    tree = schema.ModelT.InitFromPackedBuf(fcn64_fp16.data, 0)
    logistic = next(code for code in tree.operatorCodes
                    if max(code.builtinCode, code.deprecatedBuiltinCode) == schema.BuiltinOperator.LOGISTIC)
    logistic.builtinCode = logistic.deprecatedBuiltinCode = schema.BuiltinOperator.CUSTOM
    logistic.customCode = "FlexSigmoid"
    flex = bytes(flatbuffer_utils.convert_object_to_bytearray(tree))
    info = inspect_tflite(flex)
    assert info["flex_ops"] == ["FlexSigmoid"] and info["custom_ops"] == ["FlexSigmoid"]
    assert not info["builtin_only"] and "LOGISTIC" not in info["op_counts"]
    _substitute(monkeypatch, flex)
    with pytest.raises(ExportVerificationError, match="does not load"):
        to_tflite(fcn64)


# ------------------------------------------------------------------------------------------
# writing and inspecting files
# ------------------------------------------------------------------------------------------

def test_write_tflite_atomic_and_no_overwrite(tmp_path, monkeypatch):
    model = blob_model()
    path = tmp_path / "blobs_fp16.tflite"
    result = write_tflite(model, path, "float16", sample_frames=blob_frames())
    assert path.read_bytes() == result.data and inspect_tflite(path)["size_bytes"] == result.size_bytes

    def never(*args):
        raise AssertionError("converted although the file exists")

    monkeypatch.setattr(export_module, "_convert", never)
    with pytest.raises(UserError, match="already exists; pass --force"):
        write_tflite(model, path)  # fails before converting
    with pytest.raises(UserError, match=r"should end in \.tflite"):
        write_tflite(model, tmp_path / "m.h5")
    monkeypatch.undo()
    write_tflite(model, path, "float32", force=True)
    assert inspect_tflite(path)["constant_dtypes"] == {"FLOAT32": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blobs_fp16.tflite"]


def test_write_tflite_unwritable_folder(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match="cannot create output folder"):
        write_tflite(blob_model(), tmp_path / "file" / "m.tflite")


def test_inspect_rejects_what_is_not_tflite(tmp_path):
    with pytest.raises(UserError, match="not found"):
        inspect_tflite(tmp_path / "missing.tflite")
    (tmp_path / "x.tflite").write_bytes(b"PK\x03\x04 not a flatbuffer")
    with pytest.raises(UserError, match="not a TFLite flatbuffer"):
        inspect_tflite(tmp_path / "x.tflite")


# --------------------------------------------------------------------------------------------
# Full-integer int8
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fcn64_int8(fcn64):
    """The random-weight 64 x 64 FCN-Pose as full-integer int8 (interface and storage only: its maps
    are not keypoints, so the keypoint check is off here; the trained model's tests below use it)."""
    calibration = frames(64, n=8, seed=4)
    return export_tflite(fcn64, "int8", sample_frames=frames(64, n=16, seed=5), calibration_frames=calibration,
                         check_keypoints=False)


def test_int8_is_full_integer_with_a_pixel_byte_input(fcn64_int8):
    info = inspect_tflite(fcn64_int8.data)
    assert info["builtin_only"] and not info["flex_ops"]
    # every convolution consumes int8 weights stored as int8 (no DEQUANTIZE, no float kernel left)
    assert len(info["convolutions"]) == 10
    for conv in info["convolutions"]:
        assert conv["filter_dtype"] == conv["stored_dtype"] == "INT8" and not conv["dequantized"]
    assert "FLOAT32" not in info["tensor_dtypes"] and "FLOAT16" not in info["tensor_dtypes"]
    assert "DEQUANTIZE" not in info["op_counts"]
    (inp,), (out,) = info["inputs"], info["outputs"]
    assert inp["dtype"] == "UINT8" and inp["shape"] == [1, 64, 64, 3]
    assert out["dtype"] == "INT8" and out["shape"] == [1, 64, 64, 9]
    interpreter = _interpreter(fcn64_int8.data)
    scale, zero_point = interpreter.get_input_details()[0]["quantization"]
    assert scale == pytest.approx(1 / 255, rel=1e-7) and zero_point == 0
    assert interpreter.get_output_details()[0]["quantization"] == (pytest.approx(1 / 256), -128)  # the sigmoid's
    # the mode's graph rewrite: upsampling folded (measured faster for int8), and said so
    assert fcn64_int8.graph_rewrites and "DEPTH_TO_SPACE" in info["op_counts"]
    assert fcn64_int8.to_dict()["calibration_frames"] == 8


def test_int8_input_scale_is_pinned_whatever_the_calibration_range(fcn64):
    """Calibration frames that never reach black or white would give the uint8 input another scale;
    the exporter declares the input as pixel / 255 regardless, and the file still matches Keras."""
    dim = 0.25 + 0.5 * frames(64, n=8, seed=6)  # pixels in [0.25, 0.75)
    data = export_tflite(fcn64, "int8", sample_frames=dim[:1].repeat(16, 0), calibration_frames=dim,
                         check_keypoints=False).data
    scale, zero_point = _interpreter(data).get_input_details()[0]["quantization"]
    assert scale == pytest.approx(1 / 255, rel=1e-7) and zero_point == 0


@pytest.mark.parametrize("kwargs,message", [
    ({"sample_frames": frames(64, n=16)}, "int8 \\(full-integer\\) export needs real preprocessed frames"),
    ({"calibration_frames": frames(64, n=4)}, "int8 \\(full-integer\\) export needs real preprocessed frames"),
    ({"sample_frames": frames(64, n=15), "calibration_frames": frames(64, n=4)}, "at least 16 real frames"),
    ({"sample_frames": frames(64, n=16), "calibration_frames": frames(32, n=4)}, "calibration frames must be N x 64"),
])
def test_int8_needs_real_frames(fcn64, kwargs, message):
    with pytest.raises(UserError, match=message):
        export_tflite(fcn64, "int8", **kwargs)


def test_int8_file_with_a_float_interface_is_refused(fcn64, monkeypatch):
    """A file that would need float input is not what the runtime's int8 path feeds bytes to."""
    _substitute(monkeypatch, to_tflite(fcn64, "float32"))
    with pytest.raises(ExportVerificationError, match=r"takes float32 \[1, 64, 64, 3\], expected uint8 "
                                                      r"\(scale 1/255, zero point 0\)"):
        export_tflite(fcn64, "int8", sample_frames=frames(64, n=16), calibration_frames=frames(64, n=2),
                      check_keypoints=False)


@pytest.fixture(scope="module")
def trained_p70_frames():
    """The bundled trained 70% model and real synthetic frames: 16 to calibrate on, 16 to verify on."""
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.data.synth.frame import render_frame
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.preprocess import preprocess_frame

    model = load_model(models_dir() / "fcnpose_ur5_p70.keras")
    real = np.stack([preprocess_frame(render_frame(0, i)[0], 224) for i in range(32)])
    return model, real[:16], real[16:]


@pytest.mark.slow
def test_int8_of_the_trained_model_passes_the_keypoint_gate(trained_p70_frames, tmp_path):
    model, calibration, verification = trained_p70_frames
    export = write_tflite(model, tmp_path / "p70_int8.tflite", "int8", sample_frames=verification,
                          calibration_frames=calibration)
    parity = export.parity
    assert parity.frames == 16 and parity.keypoints_compared >= 0.9 * 16 * 8
    assert parity.keypoints_lost_or_gained == 0 and parity.min_keypoint_share == 0.95
    assert parity.keypoints_within_px >= 0.95 * parity.keypoints_compared and parity.keypoint_px == 2.0
    assert (tmp_path / "p70_int8.tflite").read_bytes() == export.data


@pytest.mark.slow
def test_int8_gate_refuses_a_broken_calibration_and_writes_nothing(trained_p70_frames, tmp_path):
    """Calibrated on black frames, the activation ranges are wrong for every real frame: keypoints are
    lost, the file is refused."""
    model, calibration, verification = trained_p70_frames
    path = tmp_path / "broken_int8.tflite"
    with pytest.raises(ExportVerificationError, match=r"lost or gained|keypoints within 2 px"):
        write_tflite(model, path, "int8", sample_frames=verification, calibration_frames=np.zeros_like(calibration))
    assert not path.exists()


def test_export_with_too_few_frames_for_int8_refuses_before_writing_anything(cli_here, tmp_path):
    """The 16-frame minimum of the int8 gate is known before any conversion: no float16 file first, then a failure."""
    from fcnpose_tf.training.model import build_fcn_pose
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "frames", n=6)
    model = tmp_path / "m.keras"
    build_fcn_pose(input_size=64).save(model)
    status, _, err = cli_here("export", model, "--data", data, "--quantize", "float16,int8", "--out-dir",
                              tmp_path / "out", "--threads", "1")
    assert status == 2, err
    assert err.strip().splitlines()[-1].startswith("error: int8 export is verified on keypoints of at least 16")
    assert not (tmp_path / "out").exists()


def test_export_without_data_calibrates_on_the_frames_the_model_was_trained_on(cli_here, tmp_path):
    """A user's model names its training frames in NAME_train.json: without --data, export takes those, not the
    bundled synthetic frames (someone else's arm). Here they are too few for int8, which says so at once."""
    import json

    from fcnpose_tf.records import file_sha256
    from fcnpose_tf.training.model import build_fcn_pose
    from test_train_evaluate import make_via_folder

    via = make_via_folder(tmp_path / "frames", n=6) / "labels.json"
    model = tmp_path / "m.keras"
    build_fcn_pose(input_size=64).save(model)
    (tmp_path / "m_train.json").write_text(json.dumps({"data": str(via), "data_sha256": file_sha256(via)}))
    status, out, err = cli_here("export", model, "--quantize", "float16,int8", "--out-dir", tmp_path / "out",
                                "--threads", "1")
    assert status == 2, err
    assert f"Data: {via}, the frames m.keras was trained on" in out
    assert err.strip().splitlines()[-1].startswith("error: int8 export is verified on keypoints of at least 16")
    assert f"{via} has 6" in err
    assert not (tmp_path / "out").exists()
