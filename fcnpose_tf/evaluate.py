"""Evaluate a .keras or .tflite FCN-Pose on dataset frames: keypoint metrics, inference time and FPS.

Both formats go through the same frame path: `preprocess_frame`, the model's
forward pass, `maps_to_keypoints`, then keypoints back to frame pixels; the
metrics compare with the ground truth in original frame pixels. Timing follows
docs (GUIDE section 4): after warm-up, mean and std over at least 50 frames;
FPS = 1 / (preprocess + inference + post-processing), with the invoke-only
rate beside it and the thread count stated.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.metrics import keypoint_report
from fcnpose_tf.postprocess import maps_to_keypoints
from fcnpose_tf.records import file_sha256, training_record
from fcnpose_tf.preprocess import keypoints_to_frame, preprocess_frame
from fcnpose_tf.runtime.estimator import Prediction, StageTimes

MIN_TIMED_FRAMES = 50
WARMUP_FRAMES = 5


def choose_frames(dataset: Any, model_path: str | os.PathLike, split: str, fold: int | None
                  ) -> tuple[list[int], str]:
    """Frame indices to evaluate and a description of them.

    split "val": the validation part of the hold-out split (or of `fold`); "all": every frame;
    "auto": the validation part if the model was trained on this very annotation file (its
    NAME_train.json records the file's SHA-256), otherwise every frame (an unseen dataset).
    """
    if split == "auto":
        record = training_record(model_path) or {}
        if record.get("data_sha256") == file_sha256(dataset.via_path):
            split = "val"
            if fold is None:
                fold = record.get("fold")
        else:
            split = "all"
    if split == "all":
        return list(range(len(dataset))), f"all {len(dataset)} frames"
    _, val = dataset.split(fold)
    name = "hold-out 80/20" if fold is None else f"fold {fold}"
    return [int(i) for i in val], f"validation frames of the {name} split ({len(val)} frames)"


class KerasKeypointModel:
    """A tf_keras FCN-Pose with the same `predict(frame) -> Prediction` interface as the LiteRT runtime.

    The forward pass is the model called directly on one frame (`model(x, training=False)`),
    the way a Keras user runs it; that is the "Keras" figure in reports.
    """

    def __init__(self, model: Any, path: str | os.PathLike | None = None, threshold: float = 0.5,
                 num_threads: int | None = None):
        import tf_keras as keras

        if isinstance(model, (str, os.PathLike)):
            from fcnpose_tf.model import load_model

            path, model = model, load_model(model)
        shape = model.input_shape
        if len(shape) != 4 or shape[1] != shape[2] or shape[3] != 3 or len(model.output_shape) != 4:
            raise UserError(f"{path or model.name}: not an FCN-Pose model (input {shape}, output "
                            f"{model.output_shape}); expected S x S x 3 in, S x S x C maps out")
        self.model: keras.Model = model
        self.path = Path(path) if path else None
        self.threshold = threshold
        self.num_threads = num_threads
        self.input_size = int(shape[1])
        self.num_maps = int(model.output_shape[-1])
        self.backend_label = "tf_keras (direct call)"
        self._x = np.empty((1, self.input_size, self.input_size, 3), np.float32)

    def predict_maps(self, frame_bgr: np.ndarray) -> np.ndarray:
        preprocess_frame(frame_bgr, self.input_size, out=self._x[0])
        return self.model(self._x, training=False).numpy()[0]

    def predict(self, frame_bgr: np.ndarray) -> Prediction:
        t0 = time.perf_counter()
        preprocess_frame(frame_bgr, self.input_size, out=self._x[0])
        t1 = time.perf_counter()
        maps = self.model(self._x, training=False).numpy()[0]
        t2 = time.perf_counter()
        kps, conf = maps_to_keypoints(maps, self.threshold)
        kps = keypoints_to_frame(kps, frame_bgr.shape, maps.shape[0])
        t3 = time.perf_counter()
        return Prediction(kps, conf, StageTimes((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3),
                          frame_bgr.shape)


def open_model(path: str | os.PathLike, threads: int | None = None, threshold: float = 0.5):
    """A predictor for a .keras/.h5 (tf_keras) or .tflite (LiteRT) file, by its extension."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: model file not found")
    if path.suffix == ".tflite":
        from fcnpose_tf.runtime.estimator import KeypointModel

        model = KeypointModel(path, num_threads=threads, threshold=threshold)
        model.backend_label = model.backend.label if hasattr(model.backend, "label") else str(model.backend)
        return model
    if path.suffix in (".keras", ".h5"):
        from fcnpose_tf.tfsetup import set_tensorflow_threads

        set_tensorflow_threads(threads)
        return KerasKeypointModel(path, path, threshold, threads)
    raise UserError(f"{path}: unknown model format; expected .keras, .h5 or .tflite")


def _mean_std(values: Sequence[float]) -> dict[str, float]:
    arr = np.asarray(values, np.float64)
    return {"mean": round(float(arr.mean()), 4), "std": round(float(arr.std()), 4),
            "median": round(float(np.median(arr)), 4)}


def evaluate_predictor(predictor: Any, dataset: Any, indices: Sequence[int], schema: KeypointSchema,
                       min_timed_frames: int = MIN_TIMED_FRAMES, warmup: int = WARMUP_FRAMES,
                       progress: bool = False) -> dict[str, Any]:
    """Run a predictor over dataset frames; keypoint metrics plus timing, as a JSON-ready dict.

    Every frame in `indices` is scored once; timing covers those frames and, if there are fewer
    than `min_timed_frames`, cycles through them again (timing only) to reach that count.
    """
    indices = [int(i) for i in indices]
    if not indices:
        raise UserError("no frames to evaluate (the chosen split is empty)")
    if getattr(predictor, "num_maps", schema.num_maps) != schema.num_maps:
        raise UserError(f"the model has {predictor.num_maps} output maps but the dataset's schema "
                        f"{schema.name!r} needs {schema.num_maps} ({schema.num_keypoints} keypoints + skeleton)")
    frames = {i: dataset.load_image(i) for i in indices}
    for _ in range(warmup):
        predictor.predict(frames[indices[0]])
    pred = np.full((len(indices), schema.num_keypoints, 2), np.nan)
    gt = np.stack([dataset.samples[i].keypoints for i in indices])
    times: list[StageTimes] = []
    iterator = range(max(len(indices), min_timed_frames))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="evaluating", unit="frame", leave=False)
    for step in iterator:
        j = step % len(indices)
        result = predictor.predict(frames[indices[j]])
        times.append(result.times)
        if step < len(indices):
            pred[j] = result.keypoints
    total = [t.total_ms for t in times]
    invoke = [t.invoke_ms for t in times]
    timing = {
        "threads": predictor.num_threads,
        "backend": getattr(predictor, "backend_label", ""),
        "frames_timed": len(times),
        "preprocess_ms": _mean_std([t.preprocess_ms for t in times]),
        "inference_ms": _mean_std(invoke),
        "postprocess_ms": _mean_std([t.postprocess_ms for t in times]),
        "total_ms": _mean_std(total),
        "fps": round(1000.0 / float(np.mean(total)), 2),
        "fps_inference_only": round(1000.0 / float(np.mean(invoke)), 2),
    }
    return {"metrics": keypoint_report(pred, gt, schema.keypoints), "timing": timing,
            "predictions": pred, "ground_truth": gt}


def format_timing(timing: dict[str, Any]) -> str:
    """One paragraph stating inference time, FPS and the thread count."""
    return (f"inference {timing['inference_ms']['mean']:.2f} ± {timing['inference_ms']['std']:.2f} ms/frame, "
            f"end to end {timing['total_ms']['mean']:.2f} ± {timing['total_ms']['std']:.2f} ms "
            f"(preprocess {timing['preprocess_ms']['mean']:.2f}, postprocess {timing['postprocess_ms']['mean']:.2f}); "
            f"FPS {timing['fps']:.1f} end to end, {timing['fps_inference_only']:.1f} inference only; "
            f"{timing['threads'] if timing['threads'] is not None else 'default'} thread(s), "
            f"{timing['backend']}, {timing['frames_timed']} frames after warm-up")
