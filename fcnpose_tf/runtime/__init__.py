"""The Raspberry Pi runtime: run an FCN-Pose .tflite on frames with numpy, OpenCV and LiteRT only.

Nothing in this package imports TensorFlow or Keras (a test runs it with them
made unimportable); `tf.lite` is only tried as the last interpreter fallback.

    from fcnpose_tf.runtime import KeypointModel, open_source
    model = KeypointModel("model.tflite", num_threads=4)
    with open_source("0") as frames:
        for frame in frames:
            pred = model.predict(frame.image)   # pred.keypoints (K x 2 frame px), pred.times

Modules: `interpreter` (backend fallbacks, model checks, params/MACs), `estimator`
(KeypointModel), `sources` (camera/video/images), `sinks` (JSONL/CSV/video,
overlay), `timing` (latency statistics, the FPS definition), `runner` (the
`run` loop), `bench` (the `bench` measurements). Attributes are loaded on
first use, so `import fcnpose_tf.runtime` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Backend": "interpreter", "ModelIO": "interpreter", "ModelStats": "interpreter", "TensorSpec": "interpreter",
    "find_backend": "interpreter", "load_interpreter": "interpreter", "inspect_io": "interpreter",
    "model_stats": "interpreter", "default_num_threads": "interpreter", "BACKENDS": "interpreter",
    "KeypointModel": "estimator", "Prediction": "estimator", "StageTimes": "estimator",
    "Frame": "sources", "FrameSource": "sources", "CameraSource": "sources", "VideoSource": "sources",
    "ImageSource": "sources", "LiveSource": "sources", "Picamera2Source": "sources", "open_source": "sources",
    "JsonlWriter": "sinks", "CsvWriter": "sinks", "VideoSink": "sinks", "open_record_writer": "sinks",
    "draw_overlay": "sinks", "frame_record": "sinks", "RollingFps": "sinks",
    "LatencyLog": "timing", "describe_ms": "timing", "FPS_DEFINITION": "timing",
    "run_stream": "runner", "RunSummary": "runner",
    "benchmark": "bench", "BenchReport": "bench", "synthetic_frame": "bench",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'fcnpose_tf.runtime' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"fcnpose_tf.runtime.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
