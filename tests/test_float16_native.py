"""The float16-native format (the Pi 5 file): float16 weights plus the reduced-precision metadata that lets
XNNPACK compute in float16 on ARMv8.2 cores; gated and run like the float16 file everywhere else."""

from __future__ import annotations

import numpy as np

from fcnpose_tf.compression.export import to_tflite

from fcnpose_tf.compression.tflite_file import inspect_tflite
from fcnpose_tf.training.model import build_fcn_pose
from fcnpose_tf.settings import QUANTIZE, QUANTIZE_FILE_TAGS
from test_runtime import RED_CYCLE, _structured_model, quadrant_frame


def test_float16_native_carries_float16_accumulation_metadata_and_float16_weights():
    model = build_fcn_pose((3,) * 9, input_size=64)
    plain, native = inspect_tflite(to_tflite(model, "float16")), inspect_tflite(to_tflite(model, "float16-native"))
    # The converter's encoding: float16 inference with float32 (plain) or float16 (native) accumulation.
    # XNNPACK takes float16 only from the second (both inference and accumulation in float16).
    assert plain["metadata"]["reduced_precision_support"] == "fp16accfp32"
    assert native["metadata"]["reduced_precision_support"] == "fp16accfp16"
    assert native["constant_dtypes"] == plain["constant_dtypes"] and "FLOAT16" in native["constant_dtypes"]
    assert native["inputs"][0]["dtype"] == "FLOAT32" and native["builtin_only"]


def test_float16_native_runs_in_the_runtime_with_the_float16_files_keypoints(tmp_path):
    """Where the CPU has no float16 arithmetic (this x86 host, a Pi 4) both files compute in float32."""
    from fcnpose_tf.runtime.estimator import KeypointModel

    keras_model = _structured_model()
    paths = {}
    for mode in ("float16", "float16-native"):
        paths[mode] = tmp_path / f"m_{QUANTIZE_FILE_TAGS[mode]}.tflite"
        paths[mode].write_bytes(to_tflite(keras_model, mode))  # the export gate ran inside to_tflite
    assert paths["float16-native"].name == "m_fp16native.tflite"
    models = {mode: KeypointModel(path, 1) for mode, path in paths.items()}
    for red in RED_CYCLE:
        frame = quadrant_frame(160, 120, red)
        a, b = (models[m].predict(frame) for m in ("float16", "float16-native"))
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        assert a.found.sum() >= 6


def test_compress_and_export_accept_the_format_by_name():
    assert QUANTIZE.parse("float16,float16-native") == ("float16", "float16-native")
    assert QUANTIZE.default == ("float16", "int8")  # not written unless asked for
