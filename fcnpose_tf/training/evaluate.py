"""Evaluate a .keras or .tflite FCN-Pose on dataset frames: keypoint metrics, inference time and FPS.

Both formats are `runtime.estimator.KeypointPredictor`s and go through the same frame path:
`preprocess_frame`, the model's forward pass, then `postprocess.decode` (keypoints in frame
pixels); the metrics compare with the ground truth in original frame pixels. Timing follows
docs/training.md (metric definitions): after warm-up, mean and sample std over at least 50
frames; FPS = 1 / (preprocess + inference + post-processing), with the invoke-only rate beside
it and the thread count stated.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema, keypoint_difference
from fcnpose_tf.measurements import Evaluation, SequenceReport, StageTiming, Timing, TrackScores
from fcnpose_tf.metrics import keypoint_report
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.preprocess import preprocess_frame
from fcnpose_tf.records import file_sha256, training_record
from fcnpose_tf.runtime.estimator import KeypointPredictor
from fcnpose_tf.runtime.timing import LatencyLog, fps_from_ms

MIN_TIMED_FRAMES = 50
WARMUP_FRAMES = 5


def choose_frames(dataset: Any, model_path: str | os.PathLike, split: str, fold: int | None
                  ) -> tuple[list[int], str]:
    """Frame indices to evaluate and a description of them.

    Args:
        dataset: a loaded dataset with its splits.
        model_path: the model to evaluate (its NAME_train.json tells whether it was trained on this data).
        split: "val": the validation part of the hold-out split (or of `fold`); "all": every frame; "auto": the
            validation part if the model was trained on this very annotation file (its NAME_train.json records the
            file's SHA-256), otherwise every frame (an unseen dataset).
        fold: the fold whose validation frames "val" takes (None: the hold-out split).
    Returns:
        (indices, e.g. "validation frames of the hold-out 80/20 split (20 frames)").
    """
    unknown = ""
    if split == "auto":
        record = training_record(model_path)
        if record is not None and record.data_sha256 == file_sha256(dataset.via_path):
            split = "val"
            if fold is None:
                fold = record.fold
        else:
            split = "all"
            if dataset.splits_status == "loaded":  # frames some model was trained on, maybe this one
                why = (f"no training record beside {Path(model_path).name} says which frames it was trained on"
                       if record is None else f"{Path(model_path).name}'s training record names another annotation "
                       "file (another SHA-256: edited, or saved again in VIA?)")
                unknown = (f"; {why}: if these are its frames, its training frames are among them (--split val takes "
                           "the validation frames)")
    if split == "all":
        return list(range(len(dataset))), f"all {len(dataset)} frames{unknown}"
    _, val = dataset.split(fold)
    name = "hold-out 80/20" if fold is None else f"fold {fold}"
    return [int(i) for i in val], f"validation frames of the {name} split ({len(val)} frames)"


class KerasKeypointModel(KeypointPredictor):
    """A tf_keras FCN-Pose behind the runtime's predictor protocol (`KeypointPredictor`).

    The forward pass is the model called directly on one frame (`model(x, training=False)`),
    the way a Keras user runs it; that is the "Keras" figure in reports. Preprocessing,
    decoding and timing are the runtime's own.

    Args:
        model: a tf_keras FCN-Pose, or the path of a .keras/.h5 file to load.
        path: the model's file, for descriptions and errors (taken from `model` when it is a path).
        num_threads: stated in descriptions and timing records (None: the default); TensorFlow's threads are set
            by the caller (`tfsetup.set_tensorflow_threads`).
        decoding: how maps become keypoints (`postprocess.Decoding`); default the commands' (settings).
    Raises:
        UserError: a model whose input size is not fixed, or not H x W x 3 in and H x W x C maps out.
    """

    backend_label = "tf_keras (direct call)"

    def __init__(self, model: Any, path: str | os.PathLike | None = None, num_threads: int | None = None,
                 decoding: Decoding | None = None):
        if isinstance(model, (str, os.PathLike)):
            from fcnpose_tf.training.model import load_model

            path, model = model, load_model(model)
        from fcnpose_tf.training.model import check_fixed_input, given_schema, schema_of, view_of

        check_fixed_input(model, path)
        shape = model.input_shape
        if len(shape) != 4 or shape[3] != 3 or len(model.output_shape) != 4 \
                or tuple(model.output_shape[1:3]) != tuple(shape[1:3]):
            raise UserError(f"{path or model.name}: not an FCN-Pose model (input {shape}, output "
                            f"{model.output_shape}); expected H x W x 3 in, H x W x C maps out")
        self.model = model
        self.path = Path(path) if path else None
        self.decoding = decoding if decoding is not None else Decoding()
        self.num_threads = num_threads
        self.view = view_of(model)
        self.num_maps = int(model.output_shape[-1])
        self.schema = schema_of(model)
        self.names_keypoints = given_schema(model) is not None
        self._x = np.empty((1, *self.view.shape, 3), np.float32)
        self._maps: np.ndarray | None = None

    def set_input(self, frame_bgr: np.ndarray) -> None:
        """Preprocess a frame into the model's one-frame input batch (the training preprocessing).

        Args:
            frame_bgr: H x W x 3 uint8, any size.
        """
        preprocess_frame(frame_bgr, self.view, out=self._x[0])

    def invoke(self) -> None:
        """Call the model on the current input (its maps as a numpy array)."""
        self._maps = self.model(self._x, training=False).numpy()[0]

    def read_maps(self, copy: bool = True) -> np.ndarray:
        """The output maps of the last invoke.

        Args:
            copy: False returns the array the next invoke replaces (not overwrites).
        Returns:
            M x M x C float32 probabilities.
        Raises:
            RuntimeError: no invoke yet.
        """
        if self._maps is None:
            raise RuntimeError("read_maps before any invoke")
        return self._maps.copy() if copy else self._maps


def open_model(path: str | os.PathLike, threads: int | None = None, decoding: Decoding | None = None):
    """A predictor for a model file, by its extension.

    Args:
        path: a .keras/.h5 (tf_keras) or .tflite (LiteRT) file.
        threads: threads of its forward pass (None: all cores).
        decoding: how keypoints are read from its maps (`postprocess.Decoding`; default the commands').
    Returns:
        A `KerasKeypointModel` or a `runtime.estimator.KeypointModel`.
    Raises:
        UserError: another extension, or no such file.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: model file not found")
    if path.suffix == ".tflite":
        from fcnpose_tf.runtime.estimator import KeypointModel

        return KeypointModel(path, num_threads=threads, decoding=decoding)
    if path.suffix in (".keras", ".h5"):
        from fcnpose_tf.training.tfsetup import set_tensorflow_threads

        set_tensorflow_threads(threads)
        return KerasKeypointModel(path, path, threads, decoding)
    raise UserError(f"{path}: unknown model format; expected .keras, .h5 or .tflite")


def _by_name(predictor: KeypointPredictor, schema: KeypointSchema) -> list[int] | None:
    """The model's map for each of the data's keypoints when the model names the same keypoints in another order;
    None when it names them in the data's order or names none (`KeypointPredictor.names_keypoints`).

    Raises:
        UserError: the model names other keypoints than the data's.
    """
    if not getattr(predictor, "names_keypoints", False) or predictor.schema.keypoints == schema.keypoints:
        return None
    own = predictor.schema.keypoints
    if set(own) != set(schema.keypoints):
        name = predictor.path.name if getattr(predictor, "path", None) else "the model"
        raise UserError(f"{name}: trained for {', '.join(own)}, but the data's schema {schema.name!r} has "
                        f"{', '.join(schema.keypoints)} ({keypoint_difference(own, schema.keypoints, name)}); "
                        "evaluate it on frames of its own keypoints")
    return [own.index(name) for name in schema.keypoints]


def evaluate_predictor(predictor: KeypointPredictor, dataset: Any, indices: Sequence[int], schema: KeypointSchema,
                       min_timed_frames: int = MIN_TIMED_FRAMES, warmup: int = WARMUP_FRAMES,
                       progress: bool = False) -> Evaluation:
    """Run a predictor over dataset frames; keypoint metrics plus timing, with the keypoints compared.

    Every frame in `indices` is scored once; timing covers those frames and, if there are fewer
    than `min_timed_frames`, cycles through them again (timing only) to reach that count.
    Each stage's time is summarised by `runtime.timing.describe_ms` (mean, sample std, median;
    rounded to 4 decimals); FPS by `runtime.timing.fps_from_ms`.

    Args:
        predictor: the model ready to run (`KerasKeypointModel`, `runtime.estimator.KeypointModel`).
        dataset: a loaded dataset.
        indices: the frames to score.
        schema: the keypoints the maps stand for.
        min_timed_frames: frames timed at least.
        warmup: untimed frames first.
        progress: show a progress bar or lines (the current reporter).
    Returns:
        Metrics, timing, and the predicted and ground-truth keypoints.
    Raises:
        UserError: no frames, or a model whose maps do not fit the schema: another number, or other keypoint names
            (a model that names the same keypoints in another order is read by name).
    """
    indices = [int(i) for i in indices]
    if not indices:
        raise UserError("no frames to evaluate (the chosen split is empty)")
    if getattr(predictor, "num_maps", schema.num_maps) != schema.num_maps:
        raise UserError(f"the model has {predictor.num_maps} output maps but the dataset's schema "
                        f"{schema.name!r} needs {schema.num_maps} ({schema.num_keypoints} keypoints + skeleton)")
    order = _by_name(predictor, schema)
    frames = {i: dataset.load_image(i) for i in indices}
    for _ in range(warmup):
        predictor.predict(frames[indices[0]])
    pred = np.full((len(indices), schema.num_keypoints, 2), np.nan)
    gt = np.stack([dataset.samples[i].keypoints for i in indices])
    log = LatencyLog()
    iterator = range(max(len(indices), min_timed_frames))
    if progress:
        from fcnpose_tf import progress as reporting

        iterator = reporting.current().progress(iterator, "evaluating")
    for step in iterator:
        j = step % len(indices)
        result = predictor.predict(frames[indices[j]])
        log.add(result.times)
        if step < len(indices):
            pred[j] = result.keypoints if order is None else result.keypoints[order]
    summary = log.summary()

    def stage(name: str) -> StageTiming:
        return StageTiming(**{k: round(summary[name][k], 4) for k in ("mean", "std", "median")})

    timing = Timing(threads=predictor.num_threads, backend=predictor.backend_label, frames_timed=len(log),
                    preprocess_ms=stage("preprocess"), inference_ms=stage("invoke"),
                    postprocess_ms=stage("postprocess"), total_ms=stage("end_to_end"),
                    fps=round(fps_from_ms(summary["end_to_end"]["mean"]), 2),
                    fps_inference_only=round(fps_from_ms(summary["invoke"]["mean"]), 2))
    return Evaluation(keypoint_report(pred, gt, schema.keypoints), timing, predictions=pred, ground_truth=gt)


def format_timing(timing: Timing) -> str:
    """One paragraph stating inference time, FPS and the thread count.

    Args:
        timing: a measurement's timing.
    Returns:
        The paragraph.
    """
    return (f"inference {timing.inference_ms.mean:.2f} ± {timing.inference_ms.std:.2f} ms/frame, "
            f"end to end {timing.total_ms.mean:.2f} ± {timing.total_ms.std:.2f} ms "
            f"(preprocess {timing.preprocess_ms.mean:.2f}, postprocess {timing.postprocess_ms.mean:.2f}); "
            f"FPS {timing.fps:.1f} end to end, {timing.fps_inference_only:.1f} inference only; "
            f"{timing.threads if timing.threads is not None else 'default'} thread(s), "
            f"{timing.backend}, {timing.frames_timed} frames after warm-up")


def sequence_report(pred: np.ndarray, gt: np.ndarray, fps: float, smooth: Any = None,
                    names: Sequence[str] = (), frame_shape: tuple[int, ...] | None = None) -> SequenceReport:
    """Jitter and lag of a video's tracks, and with `smooth` the same for the smoothed tracks beside their PCK and EPE.

    Args:
        pred: N x K x 2 predicted keypoints of the frames in order (NaN: missing).
        gt: N x K x 2 ground-truth keypoints.
        fps: the video's frame rate.
        smooth: One-Euro parameters (`smoothing`), or None for the raw tracks only.
        names: keypoint names, in map order (`metrics.keypoint_report`).
        frame_shape: (height, width) of the video's frames, for the smoothing (`smoothing.KeypointSmoother`).
    Returns:
        The report (`evaluate --sequence`).
    """
    from fcnpose_tf.metrics import SEQUENCE_DEFINITIONS, jitter_px, lag_frames
    from fcnpose_tf.smoothing import smooth_track

    def describe(p: np.ndarray) -> TrackScores:
        report = keypoint_report(p, gt, names)
        finite = lambda v: round(v, 3) if np.isfinite(v) else None  # noqa: E731 - strict JSON
        return TrackScores(jitter_px=finite(jitter_px(p, gt)), lag_frames=finite(lag_frames(p, gt)),
                           epe_px=report.epe_px, pck_fine=report.pck[0.05], missing_fraction=report.missing_fraction)

    if smooth is None:
        return SequenceReport(fps, SEQUENCE_DEFINITIONS, describe(pred))
    smoothing = {"filter": "one-euro", "min_cutoff_hz": smooth.min_cutoff_hz, "beta": smooth.beta,
                 "d_cutoff_hz": smooth.d_cutoff_hz, "max_coast_frames": smooth.max_coast}
    return SequenceReport(fps, SEQUENCE_DEFINITIONS, describe(pred), smoothing, describe(smooth_track(pred, fps, smooth, frame_shape)))


def format_sequence(report: SequenceReport) -> str:
    """Lines stating jitter, lag, EPE and PCK@0.05 of the raw (and smoothed) tracks, with the definitions.

    Args:
        report: `sequence_report`'s.
    Returns:
        The lines, joined.
    """
    lines = [f"Sequence at {report.fps:g} FPS ({report.definitions})"]
    for key, r in (("raw", report.raw), ("smoothed", report.smoothed)):
        if r is not None:
            lines.append(f"  {key:8s} jitter {_num(r.jitter_px)} px, lag {_num(r.lag_frames)} frames, "
                         f"EPE {_num(r.epe_px)} px, PCK@0.05 {_num(r.pck_fine, 3)}, "
                         f"missing {_num(r.missing_fraction, 3)}")
    if report.smoothing is not None:
        s = report.smoothing
        lines.append(f"  smoothing: One-Euro, min cut-off {s['min_cutoff_hz']:g} Hz, beta {s['beta']:g}, "
                     f"coasting {s['max_coast_frames']} frames")
    return "\n".join(lines)


def _num(value: Any, decimals: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{decimals}f}"
