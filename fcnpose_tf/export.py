"""TFLite export with post-training quantization, verified by running the converted file.

A tf_keras model is converted with a static 1 x H x W x C float32 input (through a concrete
function with a fixed input signature, with the model passed as the trackable object so the
converter sees its variables), built-in ops only, and one of three weight formats:

    float32        no optimisation (the reference, largest file)
    float16        weights stored as float16, dequantized to float32 when the model is loaded
                   (the paper's choice: about half the size, same accuracy)
    int8-weights   dynamic-range quantization: weights stored as int8 with a scale per output
                   channel; convolutions run as hybrid kernels that quantize their inputs on the
                   fly (smallest file; big enough kernels only, small ones stay float32)

Before conversion, `fcnpose_tf.inference_graph.fold_upsampling` may rewrite the network exactly
(each nearest UpSampling2D + Conv2D pair computed at low resolution, then DEPTH_TO_SPACE), which
makes the file run faster; see `export_tflite`'s ``fold_upsampling``.

The converted model is never trusted: it is loaded in the LiteRT interpreter, run on sample
frames, and its maps are compared with the Keras model's (max abs difference) and decoded into
keypoints with the same post-processing the runtime uses. A model that disagrees raises
`ExportVerificationError` and `write_tflite` writes nothing. (Converting through
``from_concrete_functions`` without the trackable object can silently drop the weights and give a
~19 KB file whose output is NaN; this check is what catches that kind of failure.)

`inspect_tflite` reads a .tflite flatbuffer (with the schema that ships in ai_edge_litert) and
reports its interface, operators and tensor types, so tests and reports can check how weights
are stored without matching strings. It needs neither TensorFlow nor an interpreter.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError

if TYPE_CHECKING:  # TensorFlow is imported only when converting
    import tf_keras as keras

QUANTIZE_MODES = ("float32", "float16", "int8-weights")
DEFAULT_QUANTIZE = "float16"
MAP_ATOL = 1e-2
KEYPOINT_PX = 1.0
# Per-mode defaults of the verification (export_tflite's map_atol / keypoint_px = None).
# float32 and float16 are measured far inside 1e-2 and 1 px (float16 weights: max |diff| 0.0036
# and compared keypoints within 0.11 px on 16 frames of the trained bundled models). Dynamic-range
# int8 also quantizes every layer's input on the fly: on 32 frames the trained full / 70% models'
# maps move by up to 0.11 / 0.10 (0.14 / 0.11 with fold_upsampling; per-frame maximum median
# 0.04-0.06), and compared keypoints by median 0.13-0.18 px, p95 0.5-0.9 px, at most 1.4 px when
# the winning cluster stays the same. So int8-weights gets 0.2 and 2 px; a keypoint whose winning
# cluster changes (seen for 2 of 114 keypoints of the 70% model) still fails, as it should: the
# file then decodes differently.
MAP_ATOL_BY_MODE = {"float32": 1e-2, "float16": 1e-2, "int8-weights": 0.2}
KEYPOINT_PX_BY_MODE = {"float32": 1.0, "float16": 1.0, "int8-weights": 2.0}
DEFAULT_SAMPLES = 2
# Default of export_tflite / to_tflite `fold_upsampling`. Off: folding makes the 70% model's forward
# pass ~1.35x faster here but stores f*f phase kernels, so its float16 file grows from 40,304 to
# 103,276 bytes (the paper's size column, and compress's 45 KB bound for the 70% model, are about the
# plain network). The runtime counts a folded file's parameters and MACs as the original network's.
FOLD_UPSAMPLING = False
# Map values within this much of the threshold are "on the threshold": which side they fall on is
# arbitrary for maps only this accurate, so keypoints resting on such pixels are not compared.
THRESHOLD_MARGIN = 1e-2


class ExportVerificationError(UserError):
    """A converted model disagrees with its Keras model (or does not load); nothing was written."""


@dataclass(frozen=True)
class ParityReport:
    """How a converted model compares with its Keras model on the sample frames.

    Attributes:
        frames: sample frames run through both models.
        max_abs_diff: largest |tflite - keras| over all maps and pixels.
        map_atol: the allowed max_abs_diff.
        keypoints_compared: keypoints (frames x keypoint maps) whose positions were compared.
        keypoints_ambiguous: keypoints not compared because the Keras model's own decoding moves
            when the threshold shifts by min(max_abs_diff, 0.01) (a map hovering at the
            threshold); a faithful conversion may legitimately decode those differently.
        max_keypoint_px: largest distance between compared keypoints found by both (0 if none).
        keypoint_px: the allowed keypoint distance in map pixels.
        threshold: the map threshold used for decoding.
    """

    frames: int
    max_abs_diff: float
    map_atol: float
    keypoints_compared: int
    keypoints_ambiguous: int
    max_keypoint_px: float
    keypoint_px: float
    threshold: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, stable keys (pixel distances in map pixels)."""
        return asdict(self)


@dataclass(frozen=True)
class TFLiteExport:
    """A verified TFLite model and what it took to make it.

    Attributes:
        data: the .tflite flatbuffer.
        quantize: "float32", "float16" or "int8-weights".
        input_shape: the static input shape, (1, H, W, C).
        convert_seconds: time spent in the TFLite converter.
        verify_seconds: time spent loading and comparing the converted model.
        parity: the comparison with the Keras model.
        graph_rewrites: the exact rewrites applied before conversion (`fold_upsampling`), one line
            each, e.g. "up4 + conv10 -> conv10 at 1/4 size + depth_to_space(4)"; empty if none.
    """

    data: bytes
    quantize: str
    input_shape: tuple[int, ...]
    convert_seconds: float
    verify_seconds: float
    parity: ParityReport
    graph_rewrites: tuple[str, ...] = ()

    @property
    def size_bytes(self) -> int:
        return len(self.data)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (without the bytes)."""
        return {"quantize": self.quantize, "input_shape": list(self.input_shape), "size_bytes": self.size_bytes,
                "convert_seconds": round(self.convert_seconds, 3), "verify_seconds": round(self.verify_seconds, 3),
                "parity": self.parity.to_dict(), "graph_rewrites": list(self.graph_rewrites)}


# --------------------------------------------------------------------------------------------
# Conversion
# --------------------------------------------------------------------------------------------

def _check_quantize(quantize: str) -> str:
    if quantize not in QUANTIZE_MODES:
        raise UserError(f"quantize must be one of {', '.join(QUANTIZE_MODES)}, got {quantize!r}")
    return quantize


def _static_input_shape(model: keras.Model, input_size: int | tuple[int, int] | None) -> tuple[int, int, int, int]:
    if len(getattr(model, "inputs", None) or []) != 1 or len(model.outputs) != 1:
        raise UserError(f"model {getattr(model, 'name', model)!r}: export needs a built model with one input "
                        "and one output")
    shape = tuple(model.inputs[0].shape)
    if len(shape) != 4:
        raise UserError(f"model {model.name}: expected an image input (batch, H, W, C), got shape {shape}")
    _, h, w, c = shape
    if input_size is not None:
        size = (input_size, input_size) if isinstance(input_size, int) else tuple(input_size)
        if len(size) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 1 for s in size):
            raise UserError(f"input_size must be a positive int or (height, width), got {input_size!r}")
        if (h is not None and h != size[0]) or (w is not None and w != size[1]):
            raise UserError(f"model {model.name} takes {h} x {w} inputs, not {size[0]} x {size[1]}")
        h, w = size
    if h is None or w is None or c is None:
        raise UserError(f"model {model.name} has a variable input size {shape[1:]}; give input_size "
                        "to export it with a static shape")
    return 1, int(h), int(w), int(c)


def _convert(model: keras.Model, quantize: str, input_shape: tuple[int, ...]) -> bytes:
    import tensorflow as tf

    name = model.inputs[0].name.split(":")[0] or "image"
    forward = tf.function(lambda x: model(x, training=False),
                          input_signature=[tf.TensorSpec(input_shape, tf.float32, name=name)])
    # The model as trackable object: the converter then freezes the model's own variables
    # (without it, they can be garbage-collected away and the file holds no weights).
    converter = tf.lite.TFLiteConverter.from_concrete_functions([forward.get_concrete_function()], model)
    converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS]
    if quantize == "float16":
        converter.optimizations = [tf.lite.Optimize.DEFAULT]
        converter.target_spec.supported_types = [tf.float16]
    elif quantize == "int8-weights":
        converter.optimizations = [tf.lite.Optimize.DEFAULT]  # no representative data: dynamic range
    try:
        return bytes(converter.convert())
    except Exception as exc:  # ConverterError and friends: an op without a built-in kernel, ...
        detail = str(exc).strip().splitlines()
        raise UserError(f"TFLite conversion of model {model.name} ({quantize}) failed: "
                        f"{type(exc).__name__}: {detail[0] if detail else 'no detail'}") from exc


def export_tflite(model: keras.Model, quantize: str = DEFAULT_QUANTIZE, *, sample_frames: np.ndarray | None = None,
                  num_samples: int = DEFAULT_SAMPLES, seed: int = 0, input_size: int | tuple[int, int] | None = None,
                  map_atol: float | None = None, keypoint_px: float | None = None, threshold: float = 0.5,
                  check_keypoints: bool = True, num_threads: int | None = None,
                  fold_upsampling: bool = FOLD_UPSAMPLING) -> TFLiteExport:
    """Convert a tf_keras model to TFLite and verify the result by running it.

    Same as `to_tflite`, but returns the bytes together with the conversion time, the parity
    report and the graph rewrites (for `compress` reports).

    Returns:
        A `TFLiteExport`.
    Raises:
        UserError: for a bad argument or a conversion that fails.
        ExportVerificationError: if the converted model does not load or disagrees with Keras.
    """
    _check_quantize(quantize)
    map_atol = MAP_ATOL_BY_MODE[quantize] if map_atol is None else map_atol
    keypoint_px = KEYPOINT_PX_BY_MODE[quantize] if keypoint_px is None else keypoint_px
    input_shape = _static_input_shape(model, input_size)
    frames = _sample_frames(sample_frames, input_shape, num_samples, seed)
    start = time.perf_counter()
    graph, rewrites = _inference_graph(model) if fold_upsampling else (model, ())
    data = _convert(graph, quantize, input_shape)
    convert_seconds = time.perf_counter() - start
    start = time.perf_counter()
    # Always against the original model: the rewrite is checked together with the conversion.
    parity = verify_tflite(model, data, frames, map_atol=map_atol, keypoint_px=keypoint_px, threshold=threshold,
                           check_keypoints=check_keypoints, num_threads=num_threads, label=quantize)
    return TFLiteExport(data, quantize, input_shape, convert_seconds, time.perf_counter() - start, parity,
                        rewrites)


def _inference_graph(model: keras.Model) -> tuple[keras.Model, tuple[str, ...]]:
    """The model with its upsampling folded (and what was folded), or the model itself when its
    structure is not one `fold_upsampling` can rewrite (e.g. branches): folding only saves time."""
    from fcnpose_tf.inference_graph import UnsupportedGraphError, describe_folds, fold_upsampling

    try:
        rewrites = tuple(describe_folds(model))
        return (fold_upsampling(model) if rewrites else model), rewrites
    except UnsupportedGraphError:
        return model, ()


def to_tflite(model: keras.Model, quantize: str = DEFAULT_QUANTIZE, *, sample_frames: np.ndarray | None = None,
              num_samples: int = DEFAULT_SAMPLES, seed: int = 0, input_size: int | tuple[int, int] | None = None,
              map_atol: float | None = None, keypoint_px: float | None = None, threshold: float = 0.5,
              check_keypoints: bool = True, num_threads: int | None = None,
              fold_upsampling: bool = FOLD_UPSAMPLING) -> bytes:
    """Convert a tf_keras model to a verified TFLite flatbuffer.

    The converted model has a static ``1 x H x W x C`` float32 input and a float32 output, uses
    built-in TFLite ops only, and stores its weights as `quantize` says. Before it is returned it
    is loaded in the LiteRT interpreter and run on the sample frames: every map must be within
    `map_atol` (max abs) of the Keras model's, and the keypoints decoded from the maps
    (`fcnpose_tf.postprocess.maps_to_keypoints`) within `keypoint_px` map pixels.

    Args:
        model: a built tf_keras model (e.g. FCN-Pose, pruned or not) with one image input.
        quantize: ``"float16"`` (weights stored as float16; the paper's choice), ``"float32"``
            (no quantization) or ``"int8-weights"`` (dynamic-range int8 weights).
        sample_frames: preprocessed frames (N x H x W x C or H x W x C float, as the model takes
            them, e.g. from `fcnpose_tf.preprocess.preprocess_frame`) to compare on. Real frames
            make the keypoint check meaningful; if None, `num_samples` seeded random images in
            [0, 1) are used.
        num_samples: random frames to use when `sample_frames` is None.
        seed: seed of the random frames.
        input_size: H (or (H, W)) for a model whose input size is not fixed.
        map_atol: largest allowed |tflite - keras| over the maps; None: the mode's default
            (`MAP_ATOL_BY_MODE`: 1e-2 for float32 and float16, 0.2 for int8-weights, whose
            on-the-fly activation quantization moves trained FCN-Pose maps by up to ~0.14).
        keypoint_px: largest allowed distance between decoded keypoints, in map pixels; None: the
            mode's default (`KEYPOINT_PX_BY_MODE`: 1 px, 2 px for int8-weights, where trained
            models' keypoints move by up to 1.4 px, median 0.15 px).
        threshold: map threshold for decoding keypoints.
        check_keypoints: decode and compare keypoints (needs C >= 2 output maps, skeleton last).
        num_threads: interpreter threads for the check (None: the interpreter's default).
        fold_upsampling: convert `fcnpose_tf.inference_graph.fold_upsampling(model)` instead of
            `model` (exact; each nearest UpSampling2D + 'same' Conv2D pair becomes a low-resolution
            Conv2D + DEPTH_TO_SPACE, which XNNPACK runs faster; the file holds f*f times larger
            kernels for those layers). A model whose structure cannot be folded (branches, several
            inputs, ...) is converted as it is. Verification is always against `model`.
            Default `FOLD_UPSAMPLING` (off for now: the runtime's parameter count would report
            the folded kernels' size; docs/runtime.md has the speed figures).
    Returns:
        The .tflite flatbuffer as bytes.
    Raises:
        UserError: for a bad argument (unknown quantize, wrong frame shape) or a failed conversion.
        ExportVerificationError: if the converted model does not load, has the wrong interface,
            or disagrees with the Keras model; the message says by how much and where.
    Example:
        >>> from fcnpose_tf.model import build_fcn_pose
        >>> data = to_tflite(build_fcn_pose(input_size=64), "float16")
        >>> inspect_tflite(data)["inputs"][0]["shape"]
        [1, 64, 64, 3]
    """
    return export_tflite(model, quantize, sample_frames=sample_frames, num_samples=num_samples, seed=seed,
                         input_size=input_size, map_atol=map_atol, keypoint_px=keypoint_px, threshold=threshold,
                         check_keypoints=check_keypoints, num_threads=num_threads,
                         fold_upsampling=fold_upsampling).data


def write_tflite(model: keras.Model, path: str | os.PathLike, quantize: str = DEFAULT_QUANTIZE, *,
                 force: bool = False, **options: Any) -> TFLiteExport:
    """Convert, verify, and only then write the .tflite file atomically.

    The output path is checked before converting (an existing file without `force`, or a folder
    that cannot be written, fails fast), and the file appears only once verification passed:
    a model that disagrees leaves nothing behind.

    Args:
        model: a built tf_keras model.
        path: the .tflite file to write.
        quantize: ``"float16"``, ``"float32"`` or ``"int8-weights"``.
        force: replace an existing file.
        **options: passed to `export_tflite` (sample_frames, map_atol, ...).
    Returns:
        The `TFLiteExport` that was written (size, timings, parity).
    Raises:
        UserError: if the path exists (without force) or cannot be written, or conversion fails.
        ExportVerificationError: if the converted model disagrees with Keras (nothing written).
    Example:
        >>> export = write_tflite(model, "saved_models/fcn_pose_p70_fp16.tflite")  # doctest: +SKIP
    """
    path = Path(path)
    if path.suffix != ".tflite":
        raise UserError(f"{path}: a TFLite model file should end in .tflite")
    _check_quantize(quantize)
    fileio.check_writable(path, force)
    export = export_tflite(model, quantize, **options)
    fileio.write_bytes(path, export.data, force)
    return export


# --------------------------------------------------------------------------------------------
# Verification
# --------------------------------------------------------------------------------------------

def _sample_frames(frames: np.ndarray | None, input_shape: tuple[int, ...], num_samples: int,
                   seed: int) -> np.ndarray:
    if frames is None:
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
            raise UserError(f"num_samples must be a positive integer, got {num_samples!r}")
        return np.random.default_rng(seed).random((num_samples, *input_shape[1:]), dtype=np.float32)
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[1:] != tuple(input_shape[1:]) or len(frames) == 0:
        raise UserError(f"sample frames must be N x {' x '.join(map(str, input_shape[1:]))} (the model's input), "
                        f"got shape {np.shape(frames)}")
    if not np.isfinite(frames).all():
        raise UserError("sample frames contain NaN or infinite values")
    return frames


def _interpreter(data: bytes, num_threads: int | None = None):
    """An allocated interpreter for flatbuffer bytes, from the runtime's backend order (LiteRT first)."""
    from fcnpose_tf.nativelog import native_stderr_captured
    from fcnpose_tf.runtime.interpreter import find_backend

    kwargs: dict[str, Any] = {"num_threads": num_threads} if num_threads else {}
    with native_stderr_captured():  # LiteRT's `INFO: Created ... XNNPACK delegate`, as `load_interpreter` does
        interpreter = find_backend().interpreter_class(model_content=bytes(data), **kwargs)
        interpreter.allocate_tensors()
    return interpreter


def run_tflite(interpreter, frames: np.ndarray) -> np.ndarray:
    """Run a batch-1 interpreter on each frame (N x H x W x C); returns the stacked N x ... outputs."""
    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    results = []
    for frame in frames:
        interpreter.set_tensor(inp["index"], np.ascontiguousarray(frame[None], dtype=inp["dtype"]))
        interpreter.invoke()
        results.append(interpreter.get_tensor(out["index"])[0].copy())
    return np.stack(results)


def verify_tflite(model: keras.Model, tflite: bytes, frames: np.ndarray, *, map_atol: float = MAP_ATOL,
                  keypoint_px: float = KEYPOINT_PX, threshold: float = 0.5, check_keypoints: bool = True,
                  num_threads: int | None = None, label: str = "TFLite") -> ParityReport:
    """Check that a converted model computes what the Keras model computes on `frames`.

    Checks, in order: the flatbuffer loads in the interpreter; its input is float32
    [1, H, W, C] and its output float32 of the Keras output's shape with batch 1; all outputs are
    finite; max |tflite - keras| <= map_atol; and, if `check_keypoints`, the keypoints decoded
    from both agree: found in both within `keypoint_px`, or missing in both. A keypoint whose
    Keras decoding itself changes when the threshold moves by the measured max abs difference
    (at most `THRESHOLD_MARGIN`, 0.01) rests on pixels at the threshold, so either decoding is
    right; such keypoints are counted as ambiguous instead of compared. The cap keeps the
    keypoint check meaningful when `map_atol` is loosened (e.g. for int8 weights).

    Args:
        model: the Keras model the file was converted from.
        tflite: the converted flatbuffer.
        frames: N x H x W x C float32 frames as the model takes them.
        map_atol, keypoint_px, threshold, check_keypoints, num_threads: as in `to_tflite`.
        label: what the file is, for messages ("float16").
    Returns:
        A `ParityReport`.
    Raises:
        ExportVerificationError: naming what disagreed (max abs difference and where, or which
            keypoint of which frame and by how many pixels).
    """
    what = f"the {label} TFLite model"
    try:
        interpreter = _interpreter(tflite, num_threads)
    except Exception as exc:
        detail = str(exc).strip().splitlines()
        raise ExportVerificationError(f"{what} does not load in the interpreter ({type(exc).__name__}: "
                                      f"{detail[0] if detail else 'no detail'}); nothing written") from exc
    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    expected_in = [1, *frames.shape[1:]]
    keras_maps = np.asarray(model(frames, training=False), dtype=np.float32)
    expected_out = [1, *keras_maps.shape[1:]]
    if list(inp["shape"]) != expected_in or inp["dtype"] != np.float32:
        raise ExportVerificationError(f"{what} takes {np.dtype(inp['dtype']).name} {[int(d) for d in inp['shape']]}, "
                                      f"expected float32 {expected_in}; nothing written")
    if list(out["shape"]) != expected_out or out["dtype"] != np.float32:
        raise ExportVerificationError(f"{what} gives {np.dtype(out['dtype']).name} {[int(d) for d in out['shape']]}, "
                                      f"expected float32 {expected_out}; nothing written")
    tflite_maps = run_tflite(interpreter, frames)
    if not np.isfinite(tflite_maps).all():
        bad = int(np.count_nonzero(~np.isfinite(tflite_maps)))
        raise ExportVerificationError(f"{what} outputs {bad} NaN/infinite values where the Keras model outputs "
                                      "finite maps (weights lost in conversion?); nothing written")
    diff = np.abs(tflite_maps - keras_maps)
    max_diff = float(diff.max())
    if not max_diff <= map_atol:
        where = np.unravel_index(int(np.argmax(diff)), diff.shape)
        place = f"frame {where[0]}, map {where[-1]}, pixel (x={where[2]}, y={where[1]})" if diff.ndim == 4 \
            else f"index {tuple(int(i) for i in where)}"
        raise ExportVerificationError(
            f"{what} disagrees with the Keras model: max abs map difference {max_diff:.3g} > {map_atol:g} "
            f"at {place} (Keras {keras_maps[where]:.4g}, TFLite {tflite_maps[where]:.4g}); nothing written")
    compared = ambiguous = 0
    max_px = 0.0
    if check_keypoints and keras_maps.ndim == 4 and keras_maps.shape[-1] >= 2:
        compared, ambiguous, max_px = _compare_keypoints(keras_maps, tflite_maps, max_diff, threshold,
                                                         keypoint_px, what)
    return ParityReport(len(frames), max_diff, float(map_atol), compared, ambiguous, max_px, float(keypoint_px),
                        float(threshold))


def _compare_keypoints(keras_maps: np.ndarray, tflite_maps: np.ndarray, max_diff: float, threshold: float,
                       keypoint_px: float, what: str) -> tuple[int, int, float]:
    from fcnpose_tf.postprocess import maps_to_keypoints

    ref, _ = maps_to_keypoints(keras_maps, threshold)
    got, _ = maps_to_keypoints(tflite_maps, threshold)
    # The Keras decoding with every pixel within `margin` of the threshold switched on / off:
    # where these disagree with `ref`, the keypoint rests on pixels a faithful conversion may flip.
    margin = min(max_diff, THRESHOLD_MARGIN)
    low, _ = maps_to_keypoints(keras_maps, threshold - margin)
    high, _ = maps_to_keypoints(keras_maps, threshold + margin)

    def same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        missing_a, missing_b = np.isnan(a).any(-1), np.isnan(b).any(-1)
        close = np.linalg.norm(np.nan_to_num(a - b, nan=np.inf), axis=-1) <= keypoint_px
        return (missing_a & missing_b) | (~missing_a & ~missing_b & close)

    stable = same(ref, low) & same(ref, high)
    agree = same(ref, got)
    bad = np.argwhere(stable & ~agree)
    if len(bad):
        n, k = (int(i) for i in bad[0])

        def show(p: np.ndarray) -> str:
            return "missing" if np.isnan(p).any() else f"({p[0]:.1f}, {p[1]:.1f})"

        distance = "" if np.isnan(ref[n, k]).any() or np.isnan(got[n, k]).any() else \
            f", {np.linalg.norm(ref[n, k] - got[n, k]):.2f} px > {keypoint_px:g} px"
        raise ExportVerificationError(
            f"{what} decodes keypoint {k} of frame {n} at {show(got[n, k])}, the Keras model at {show(ref[n, k])}"
            f"{distance} ({len(bad)} keypoint(s) disagree; max abs map difference {max_diff:.3g}); nothing written")
    both = stable & ~np.isnan(ref).any(-1) & ~np.isnan(got).any(-1)
    max_px = float(np.linalg.norm(ref[both] - got[both], axis=-1).max()) if both.any() else 0.0
    return int(stable.sum()), int((~stable).sum()), max_px


# --------------------------------------------------------------------------------------------
# Inspection
# --------------------------------------------------------------------------------------------

def _enum_names(enum_class: type) -> dict[int, str]:
    return {value: name for name, value in vars(enum_class).items()
            if not name.startswith("_") and isinstance(value, int)}


def inspect_tflite(model: bytes | str | os.PathLike) -> dict[str, Any]:
    """Describe a .tflite flatbuffer: interface, operators, and how tensors and weights are stored.

    Reads the flatbuffer with the TFLite schema shipped in ai_edge_litert; neither TensorFlow nor
    an interpreter is needed, so files with Flex or custom ops can be inspected too.

    Args:
        model: the flatbuffer bytes or a path to a .tflite file.
    Returns:
        A dict with stable keys:
        ``size_bytes``; ``inputs`` and ``outputs`` (lists of {name, shape, dtype}, e.g.
        ``[1, 224, 224, 3]`` and ``"FLOAT32"``); ``ops`` (operator names in execution order, e.g.
        ``"CONV_2D"``) and ``op_counts``; ``custom_ops`` and ``flex_ops`` (custom op codes; Flex
        ops are custom ops named ``Flex...`` that need the TensorFlow delegate); ``builtin_only``;
        ``tensor_dtypes`` (count of tensors per type) and ``constant_dtypes`` (the same for tensors
        holding data: the stored weights); ``constant_bytes`` (bytes of stored weights);
        ``convolutions``: for every CONV_2D / DEPTHWISE_CONV_2D / FULLY_CONNECTED / TRANSPOSE_CONV, its
        filter shape, ``filter_dtype`` (what the op consumes), ``stored_dtype`` (what the file
        stores) and ``dequantized`` (the filter comes from a DEQUANTIZE of a stored constant).
    Raises:
        UserError: if the file is missing or is not a TFLite flatbuffer.
    Example:
        >>> info = inspect_tflite("saved_models/fcn_pose_p70_fp16.tflite")  # doctest: +SKIP
        >>> info["constant_dtypes"], info["op_counts"]["DEQUANTIZE"]  # doctest: +SKIP
        ({'FLOAT16': 20, 'INT32': 4}, 20)
    """
    from ai_edge_litert import schema_py_generated as schema

    if isinstance(model, (bytes, bytearray)):
        data, source = bytes(model), "TFLite data"
    else:
        path = Path(model)
        if not path.is_file():
            raise UserError(f"{path}: TFLite file not found")
        data, source = path.read_bytes(), str(path)
    if len(data) < 8 or data[4:8] != b"TFL3":
        raise UserError(f"{source}: not a TFLite flatbuffer (no TFL3 identifier)")
    try:
        tree = schema.ModelT.InitFromPackedBuf(data, 0)
    except Exception as exc:
        raise UserError(f"{source}: corrupt TFLite flatbuffer ({type(exc).__name__}: {exc})") from None
    type_names = _enum_names(schema.TensorType)
    op_names = _enum_names(schema.BuiltinOperator)
    custom_code = schema.BuiltinOperator.CUSTOM

    def op_name(index: int) -> str:
        code = tree.operatorCodes[index]
        builtin = max(int(code.builtinCode), int(code.deprecatedBuiltinCode))
        if builtin == custom_code:
            custom = code.customCode
            return custom.decode() if isinstance(custom, bytes) else str(custom)
        return op_names.get(builtin, f"BUILTIN_{builtin}")

    def is_custom(index: int) -> bool:
        code = tree.operatorCodes[index]
        return max(int(code.builtinCode), int(code.deprecatedBuiltinCode)) == custom_code

    def buffer_bytes(tensor) -> int:
        if not tree.buffers or tensor.buffer >= len(tree.buffers):
            return 0
        buffer = tree.buffers[tensor.buffer]
        if buffer.data is not None and len(buffer.data):
            return len(buffer.data)
        return int(buffer.size) if buffer.offset > 1 else 0

    def text(value) -> str:
        return value.decode() if isinstance(value, bytes) else str(value or "")

    graph = tree.subgraphs[0]
    tensors = graph.tensors or []

    def describe(index: int) -> dict[str, Any]:
        tensor = tensors[index]
        shape = tensor.shapeSignature if tensor.shapeSignature is not None and len(tensor.shapeSignature) \
            else tensor.shape
        return {"name": text(tensor.name), "shape": [int(d) for d in (shape if shape is not None else [])],
                "dtype": type_names.get(tensor.type, str(tensor.type))}

    operators = [op for g in tree.subgraphs for op in (g.operators or [])]
    ops = [op_name(op.opcodeIndex) for op in operators]
    custom = sorted({op_name(op.opcodeIndex) for op in operators if is_custom(op.opcodeIndex)})
    all_tensors = [t for g in tree.subgraphs for t in (g.tensors or [])]
    constant = [t for t in all_tensors if buffer_bytes(t) > 0]

    producer = {}
    for op in graph.operators or []:
        for out in op.outputs if op.outputs is not None else []:
            producer[int(out)] = op
    convolutions = []
    for op in graph.operators or []:
        name = op_name(op.opcodeIndex)
        if name not in ("CONV_2D", "DEPTHWISE_CONV_2D", "FULLY_CONNECTED", "TRANSPOSE_CONV"):
            continue
        filter_index = int(op.inputs[1])
        filt = tensors[filter_index]
        stored, dequantized = filt, False
        source_op = producer.get(filter_index)
        if source_op is not None and op_name(source_op.opcodeIndex) == "DEQUANTIZE":
            stored, dequantized = tensors[int(source_op.inputs[0])], True
        convolutions.append({"op": name, "filter_shape": [int(d) for d in filt.shape],
                             "filter_dtype": type_names.get(filt.type, str(filt.type)),
                             "stored_dtype": type_names.get(stored.type, str(stored.type)),
                             "dequantized": dequantized, "stored_bytes": buffer_bytes(stored)})
    return {
        "size_bytes": len(data),
        "subgraphs": len(tree.subgraphs),
        "inputs": [describe(int(i)) for i in graph.inputs],
        "outputs": [describe(int(i)) for i in graph.outputs],
        "ops": ops,
        "op_counts": dict(sorted(Counter(ops).items())),
        "builtin_only": not custom,
        "custom_ops": custom,
        "flex_ops": [name for name in custom if name.startswith("Flex")],
        "tensor_dtypes": dict(sorted(Counter(type_names.get(t.type, str(t.type)) for t in all_tensors).items())),
        "constant_dtypes": dict(sorted(Counter(type_names.get(t.type, str(t.type)) for t in constant).items())),
        "constant_bytes": int(sum(buffer_bytes(t) for t in constant)),
        "convolutions": convolutions,
    }
