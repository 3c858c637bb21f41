"""TFLite export with post-training quantization, verified by running the converted file.

A tf_keras model is converted with a static 1 x H x W x C input (through a concrete function
with a fixed input signature, with the model passed as the trackable object so the converter
sees its variables), built-in ops only, in one of five formats:

    float32        no optimisation (the reference, largest file)
    float16        weights stored as float16, dequantized to float32 when the model is loaded
                   (the paper's choice: about half the size, same accuracy)
    int8-weights   dynamic-range quantization: weights stored as int8 with a scale per output
                   channel; convolutions run as hybrid kernels that quantize their inputs on the
                   fly (big enough kernels only, small ones stay float32)
    int8           full-integer quantization: int8 weights and activations calibrated on real
                   preprocessed frames (`calibration_frames`), built-in int8 kernels only; a uint8
                   RGB input with scale 1/255 and zero point 0 (the resized frame's bytes as they
                   are) and an int8 output (the sigmoid's fixed scale 1/256, zero point -128), so
                   the runtime neither converts its input to float nor dequantizes its maps.
                   The fastest file on CPUs without fp16 arithmetic (a Raspberry Pi 3/4).
    float16-native float16 weights plus the converter's reduced-precision metadata (float16
                   accumulation allowed): XNNPACK then computes it in float16 on a CPU with
                   float16 arithmetic (ARMv8.2-A: a Raspberry Pi 5's Cortex-A76) and in float32
                   elsewhere (a Pi 3/4, x86), where it is the float16 file. Gated like float16.

Before conversion, `fcnpose_tf.compression.inference_graph.fold_upsampling` may rewrite the network exactly
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
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError
from fcnpose_tf import settings
from fcnpose_tf.preprocess import ViewLike
from fcnpose_tf.settings import QUANTIZE_MODES, TFLITE_FORMATS

if TYPE_CHECKING:  # TensorFlow is imported only when converting
    import tf_keras as keras


@settings.config_class(settings.QUANTIZE, settings.CALIBRATION_FRAMES, ("seed", settings.CALIBRATION_SEED),
                       settings.THREADS)
class ExportOptions:
    """What `fcnpose-tf export` writes: quantize (one verified file per format), calibration_frames and seed (the
    int8 file's calibration frames) and threads. The defaults are the command's; defaults, checks and meanings:
    `fcnpose_tf.settings`."""


DEFAULT_QUANTIZE = settings.QUANTIZE.default[0]
"""The format of one file when none is named: the first of the default formats (float16, the paper's)."""
FULL_INTEGER = "int8"
"""The full-integer mode: calibrated on real frames, integer input and output."""
FLOAT16_NATIVE = "float16-native"
"""float16 with reduced-precision metadata: computed in float16 where the CPU can (a Pi 5)."""
INT8_INPUT_SCALE = 1.0 / 255.0
"""Scale of the int8 file's uint8 input (zero point 0): one step per grey level of the resized frame."""
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
# Full-integer int8 quantizes every activation to 256 levels, so maps move further; its gate is
# stated in keypoint terms (KEYPOINT_SHARE_BY_MODE, MIN_FRAMES_BY_MODE), not in map values: map_atol 1
# accepts any map that is a probability (the sigmoid output stays in [0, 1]).
# float16-native is gated as float16: where the gate runs (x86, a Pi 4) it computes in float32 like the float16
# file; on a Pi 5 its float16 arithmetic is checked by tools/pi_emulated_check.sh --cpu cortex-a76.
# The values live in one table, `settings.TFLITE_FORMATS`; these are its columns by format.
MAP_ATOL_BY_MODE = {name: f.map_atol for name, f in TFLITE_FORMATS.items()}
KEYPOINT_PX_BY_MODE = {name: f.keypoint_px for name, f in TFLITE_FORMATS.items()}
# Share of the compared keypoints that must lie within keypoint_px; a keypoint found by one model
# and not by the other (lost or gained) always fails. For int8: at least 95 % within 2 map px.
KEYPOINT_SHARE_BY_MODE = {name: f.keypoint_share for name, f in TFLITE_FORMATS.items()}
# Real frames the keypoint gate needs: int8 is refused on fewer than 16 (a share of 95 % means
# little on two frames); the other modes compare maps value by value and accept any number.
MIN_FRAMES_BY_MODE = {name: f.min_frames for name, f in TFLITE_FORMATS.items()}
DEFAULT_SAMPLES = 2
# Default of export_tflite / to_tflite `fold_upsampling`. Off: folding makes the 70% model's forward
# pass ~1.35x faster here but stores f*f phase kernels, so its float16 file grows from 40,304 to
# 103,276 bytes (the paper's size column, and compress's 45 KB bound for the 70% model, are about the
# plain network). The runtime counts a folded file's parameters and MACs as the original network's.
FOLD_UPSAMPLING = False
# Per mode, the default of `fold_upsampling` (export_tflite's fold_upsampling=None), measured with
# tools/bench_speedup.py on the bundled 70% model, one thread (docs/runtime.md, "Full-integer int8"):
# folded, the int8 file's forward pass is 1.37x faster (2.85 vs 3.90 ms; its frame 1.28x), for 65 KB
# instead of 27 KB; the float modes keep the plain network (FOLD_UPSAMPLING, above).
FOLD_UPSAMPLING_BY_MODE = {name: f.fold_upsampling or FOLD_UPSAMPLING for name, f in TFLITE_FORMATS.items()}
# Map values within this much of the threshold are "on the threshold": which side they fall on is
# arbitrary for maps only this accurate, so keypoints resting on such pixels are not compared.
THRESHOLD_MARGIN = 1e-2


class ExportVerificationError(UserError):
    """A converted model disagrees with its Keras model (or does not load); nothing was written.

    Attributes:
        facts: what the gate measured before it refused, JSON-ready (e.g. ``max_abs_diff``,
            ``keypoints_compared``, ``keypoints_within_px``, ``keypoints_lost_or_gained``); empty when the
            file was refused before its maps were compared (it did not load, wrong interface).
    """

    def __init__(self, message: str, facts: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.facts = dict(facts or {})

    @property
    def reason(self) -> str:
        """The gate's reason without the trailing "; nothing written": a refused format's row says it."""
        text = str(self)
        return text[:-len(NOTHING_WRITTEN)] if text.endswith(NOTHING_WRITTEN) else text


NOTHING_WRITTEN = "; nothing written"


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
        keypoints_within_px: compared keypoints found by both models within keypoint_px of each
            other, or missing in both.
        keypoints_lost_or_gained: compared keypoints found by one model only (always refused).
        min_keypoint_share: the gate: keypoints_within_px / keypoints_compared must reach it
            (1 for the float modes, 0.95 for int8).
    """

    frames: int
    max_abs_diff: float
    map_atol: float
    keypoints_compared: int
    keypoints_ambiguous: int
    max_keypoint_px: float
    keypoint_px: float
    threshold: float
    keypoints_within_px: int = 0
    keypoints_lost_or_gained: int = 0
    min_keypoint_share: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, stable keys (pixel distances in map pixels)."""
        return asdict(self)


@dataclass(frozen=True)
class TFLiteExport:
    """A verified TFLite model and what it took to make it.

    Attributes:
        data: the .tflite flatbuffer.
        quantize: one of `QUANTIZE_MODES`.
        input_shape: the static input shape, (1, H, W, C).
        convert_seconds: time spent in the TFLite converter.
        verify_seconds: time spent loading and comparing the converted model.
        parity: the comparison with the Keras model.
        graph_rewrites: the exact rewrites applied before conversion (`fold_upsampling`), one line
            each, e.g. "up4 + conv10 -> conv10 at 1/4 size + depth_to_space(4)"; empty if none.
        calibration_frames: frames the int8 activation ranges were calibrated on (0: no calibration).
    """

    data: bytes
    quantize: str
    input_shape: tuple[int, ...]
    convert_seconds: float
    verify_seconds: float
    parity: ParityReport
    graph_rewrites: tuple[str, ...] = ()
    calibration_frames: int = 0

    @property
    def size_bytes(self) -> int:
        return len(self.data)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (without the bytes)."""
        return {"quantize": self.quantize, "input_shape": list(self.input_shape), "size_bytes": self.size_bytes,
                "convert_seconds": round(self.convert_seconds, 3), "verify_seconds": round(self.verify_seconds, 3),
                "parity": self.parity.to_dict(), "graph_rewrites": list(self.graph_rewrites),
                "calibration_frames": self.calibration_frames}


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


def _convert(model: keras.Model, quantize: str, input_shape: tuple[int, ...],
             calibration: np.ndarray | None = None) -> bytes:
    import tensorflow as tf

    name = model.inputs[0].name.split(":")[0] or "image"
    forward = tf.function(lambda x: model(x, training=False),
                          input_signature=[tf.TensorSpec(input_shape, tf.float32, name=name)])
    # The model as trackable object: the converter then freezes the model's own variables
    # (without it, they can be garbage-collected away and the file holds no weights).
    converter = tf.lite.TFLiteConverter.from_concrete_functions([forward.get_concrete_function()], model)
    converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS]
    if quantize in ("float16", FLOAT16_NATIVE):
        converter.optimizations = [tf.lite.Optimize.DEFAULT]
        converter.target_spec.supported_types = [tf.float16]
        if quantize == FLOAT16_NATIVE:  # writes the `reduced_precision_support` metadata XNNPACK reads
            converter.target_spec._experimental_supported_accumulation_type = tf.float16
    elif quantize == "int8-weights":
        converter.optimizations = [tf.lite.Optimize.DEFAULT]  # no representative data: dynamic range
    elif quantize == FULL_INTEGER:
        converter.optimizations = [tf.lite.Optimize.DEFAULT]
        converter.representative_dataset = lambda: ([frame[None]] for frame in calibration)
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]  # no float fallback
        converter.inference_input_type = tf.uint8
        converter.inference_output_type = tf.int8  # the sigmoid's own type: no requantizing op at the end
    from fcnpose_tf.nativelog import native_stderr_captured

    try:
        with native_stderr_captured():  # the converter's own lines (`fully_quantize: 0, inference_type: 6, ...`)
            data = bytes(converter.convert())
    except Exception as exc:  # ConverterError and friends: an op without a built-in kernel, ...
        detail = str(exc).strip().splitlines()
        raise UserError(f"TFLite conversion of model {model.name} ({quantize}) failed: "
                        f"{type(exc).__name__}: {detail[0] if detail else 'no detail'}") from exc
    return _pixel_scaled_input(data) if quantize == FULL_INTEGER else data


def _with_view(data: bytes, model: keras.Model) -> bytes:
    """The file with the model's crop and input size in its metadata (`runtime.tflite_metadata.VIEW_METADATA`),
    where the runtime reads it; a whole-frame model's file as converted."""
    import json

    from fcnpose_tf.runtime.tflite_metadata import VIEW_METADATA
    from fcnpose_tf.training.model import given_view

    view = given_view(model)
    if view is None or view.crop is None:
        return data
    from ai_edge_litert import schema_py_generated as schema
    import flatbuffers

    tree = schema.ModelT.InitFromPackedBuf(data, 0)
    buffer = schema.BufferT()
    buffer.data = list(json.dumps(view.to_json(), sort_keys=True).encode("utf-8"))
    tree.buffers.append(buffer)
    entry = schema.MetadataT()
    entry.name, entry.buffer = VIEW_METADATA.encode("utf-8"), len(tree.buffers) - 1
    tree.metadata = [*(tree.metadata or []), entry]
    builder = flatbuffers.Builder(len(data) + 1024)
    builder.Finish(tree.Pack(builder), file_identifier=b"TFL3")
    return bytes(builder.Output())


def _pixel_scaled_input(data: bytes) -> bytes:
    """The int8 file with its uint8 input read as pixel / 255 (scale 1/255, zero point 0).

    The converter gives the uint8 input the calibrated range of the first activation (the darkest
    to the brightest calibration pixel), so a frame's bytes would need rescaling. Declaring the
    input as the bytes themselves is exact: the QUANTIZE op behind it maps uint8 to the network's
    int8 domain whatever the two scales are, and saturates pixels outside the calibrated range as
    the converter's own input would.
    """
    from ai_edge_litert import schema_py_generated as schema
    import flatbuffers

    tree = schema.ModelT.InitFromPackedBuf(data, 0)
    graph = tree.subgraphs[0]
    tensor = graph.tensors[int(graph.inputs[0])]
    quant = tensor.quantization
    if tensor.type != schema.TensorType.UINT8 or quant is None or quant.scale is None or len(quant.scale) != 1:
        raise ExportVerificationError("the int8 TFLite model's input is not a per-tensor quantized uint8 image; "
                                      "nothing written")
    if float(quant.scale[0]) == np.float32(INT8_INPUT_SCALE) and int(quant.zeroPoint[0]) == 0:
        return data
    quant.scale, quant.zeroPoint = [float(np.float32(INT8_INPUT_SCALE))], [0]
    quant.min = quant.max = None
    builder = flatbuffers.Builder(len(data) + 1024)
    builder.Finish(tree.Pack(builder), file_identifier=b"TFL3")
    return bytes(builder.Output())


def export_frames(quantize: str, input_size: ViewLike, train_dataset: Any, train_indices: Sequence[int],
                  check_dataset: Any, check_indices: Sequence[int], calibration_count: int,
                  seed: int = settings.CALIBRATION_SEED.default) -> tuple[np.ndarray, np.ndarray | None]:
    """Real frames for `export_tflite`: (sample_frames, calibration_frames or None).

    The file is verified on the first `MIN_FRAMES_BY_MODE` frames of `check_indices` (16, topped
    up with training frames when there are fewer); an int8 file is calibrated on up to
    `calibration_count` frames drawn (seeded) from `train_indices`, which should hold no frame a
    result is measured on.
    """
    from fcnpose_tf.preprocess import preprocess_frame

    count = max(MIN_FRAMES_BY_MODE.values())
    chosen = [(check_dataset, int(i)) for i in list(check_indices)[:count]]
    chosen += [(train_dataset, int(i)) for i in list(train_indices)[:count - len(chosen)]]
    samples = np.stack([preprocess_frame(dataset.load_image(i), input_size) for dataset, i in chosen])
    calibration = None
    if quantize == FULL_INTEGER:
        calibration = calibration_frames(train_dataset, train_indices, min(calibration_count, len(train_indices)),
                                         input_size, seed)
    return samples, calibration


def calibration_frames(dataset: Any, indices: Sequence[int], count: int, input_size: ViewLike,
                       seed: int = settings.CALIBRATION_SEED.default) -> np.ndarray:
    """`count` frames drawn (seeded, without replacement) from `indices` of `dataset`, preprocessed as
    the runtime does: the representative data of a full-integer export.

    Draw them from training frames, never from the frames a result is measured on.

    Raises:
        UserError: if `count` is not a positive number or `indices` holds fewer frames.
    """
    from fcnpose_tf.preprocess import preprocess_frame

    indices = np.asarray(list(indices), dtype=np.int64)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise UserError(f"calibration frames must be a positive number, got {count!r}")
    if count > len(indices):
        raise UserError(f"{count} calibration frames asked for, but only {len(indices)} training frames are there")
    chosen = np.sort(np.random.default_rng(seed).choice(indices, size=count, replace=False))
    return np.stack([preprocess_frame(dataset.load_image(int(i)), input_size) for i in chosen])


def export_tflite(model: keras.Model, quantize: str = DEFAULT_QUANTIZE, *, sample_frames: np.ndarray | None = None,
                  num_samples: int = DEFAULT_SAMPLES, seed: int = 0, input_size: int | tuple[int, int] | None = None,
                  map_atol: float | None = None, keypoint_px: float | None = None, threshold: float = 0.5,
                  check_keypoints: bool = True, num_threads: int | None = None,
                  fold_upsampling: bool | None = None,
                  calibration_frames: np.ndarray | None = None,
                  reference: keras.Model | None = None) -> TFLiteExport:
    """Convert a tf_keras model to TFLite and verify the result by running it.

    Same as `to_tflite`, but returns the bytes together with the conversion time, the parity
    report and the graph rewrites (for `compress` reports). `reference` is the model the file is
    verified against (default: `model` itself): a quantization-aware copy of a model
    (`fcnpose_tf.compression.qat`) is converted, and its file is held to the model it was trained from.

    Returns:
        A `TFLiteExport`.
    Raises:
        UserError: for a bad argument or a conversion that fails.
        ExportVerificationError: if the converted model does not load or disagrees with Keras.
    """
    _check_quantize(quantize)
    map_atol = MAP_ATOL_BY_MODE[quantize] if map_atol is None else map_atol
    keypoint_px = KEYPOINT_PX_BY_MODE[quantize] if keypoint_px is None else keypoint_px
    fold_upsampling = FOLD_UPSAMPLING_BY_MODE[quantize] if fold_upsampling is None else fold_upsampling
    input_shape = _static_input_shape(model, input_size)
    calibration = None
    if quantize == FULL_INTEGER:
        if sample_frames is None or calibration_frames is None:
            raise UserError("int8 (full-integer) export needs real preprocessed frames: calibration_frames to "
                            "calibrate on and sample_frames to verify keypoints on (random images say nothing "
                            "about the ranges a camera frame gives)")
        calibration = _sample_frames(calibration_frames, input_shape, 1, seed, what="calibration frames")
    frames = _sample_frames(sample_frames, input_shape, num_samples, seed)
    if len(frames) < MIN_FRAMES_BY_MODE[quantize]:
        raise UserError(f"{quantize} export is verified on keypoints of at least {MIN_FRAMES_BY_MODE[quantize]} "
                        f"real frames, got {len(frames)} sample frame(s)")
    start = time.perf_counter()
    graph, rewrites = _inference_graph(model) if fold_upsampling else (model, ())
    data = _with_view(_convert(graph, quantize, input_shape, calibration), model if reference is None else reference)
    convert_seconds = time.perf_counter() - start
    start = time.perf_counter()
    # Always against the original model: the rewrite is checked together with the conversion.
    parity = verify_tflite(model if reference is None else reference, data, frames, map_atol=map_atol,
                           keypoint_px=keypoint_px, threshold=threshold,
                           check_keypoints=check_keypoints, num_threads=num_threads, label=quantize,
                           keypoint_share=KEYPOINT_SHARE_BY_MODE[quantize],
                           pixel_input=quantize == FULL_INTEGER)
    return TFLiteExport(data, quantize, input_shape, convert_seconds, time.perf_counter() - start, parity,
                        rewrites, 0 if calibration is None else len(calibration))


def _inference_graph(model: keras.Model) -> tuple[keras.Model, tuple[str, ...]]:
    """The model with its upsampling folded (and what was folded), or the model itself when its
    structure is not one `fold_upsampling` can rewrite (e.g. branches): folding only saves time."""
    from fcnpose_tf.compression.inference_graph import UnsupportedGraphError, describe_folds, fold_upsampling

    try:
        rewrites = tuple(describe_folds(model))
        return (fold_upsampling(model) if rewrites else model), rewrites
    except UnsupportedGraphError:
        return model, ()


def to_tflite(model: keras.Model, quantize: str = DEFAULT_QUANTIZE, *, sample_frames: np.ndarray | None = None,
              num_samples: int = DEFAULT_SAMPLES, seed: int = 0, input_size: int | tuple[int, int] | None = None,
              map_atol: float | None = None, keypoint_px: float | None = None, threshold: float = 0.5,
              check_keypoints: bool = True, num_threads: int | None = None,
              fold_upsampling: bool | None = None, calibration_frames: np.ndarray | None = None) -> bytes:
    """Convert a tf_keras model to a verified TFLite flatbuffer.

    The converted model has a static ``1 x H x W x C`` input, uses built-in TFLite ops only, and
    stores its weights as `quantize` says: float32 input and output, or for ``"int8"`` a uint8
    input (pixel / 255) and an int8 output. Before it is returned it is loaded in the LiteRT
    interpreter and run on the sample frames: every map must be within `map_atol` (max abs) of the
    Keras model's, and the keypoints decoded from the maps
    (`fcnpose_tf.postprocess.maps_to_keypoints`) within `keypoint_px` map pixels: all of them, or
    for int8 at least 95 % (`KEYPOINT_SHARE_BY_MODE`) on at least 16 frames, none lost or gained.

    Args:
        model: a built tf_keras model (e.g. FCN-Pose, pruned or not) with one image input.
        quantize: ``"float16"`` (weights stored as float16; the paper's choice), ``"float32"``
            (no quantization), ``"int8-weights"`` (dynamic-range int8 weights) or ``"int8"``
            (full integer, calibrated on `calibration_frames`).
        sample_frames: preprocessed frames (N x H x W x C or H x W x C float, as the model takes
            them, e.g. from `fcnpose_tf.preprocess.preprocess_frame`) to compare on. Real frames
            make the keypoint check meaningful; if None, `num_samples` seeded random images in
            [0, 1) are used (not for int8, which needs at least 16 real frames).
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
        fold_upsampling: convert `fcnpose_tf.compression.inference_graph.fold_upsampling(model)` instead of
            `model` (exact; each nearest UpSampling2D + 'same' Conv2D pair becomes a low-resolution
            Conv2D + DEPTH_TO_SPACE, which XNNPACK runs faster; the file holds f*f times larger
            kernels for those layers). A model whose structure cannot be folded (branches, several
            inputs, ...) is converted as it is. Verification is always against `model`.
            None: the mode's default, `FOLD_UPSAMPLING_BY_MODE` (on for int8, whose forward pass
            it makes 1.37x faster; off for the float modes, whose files it makes 2.5x larger for a
            ~1.35x faster forward pass; docs/runtime.md has the figures).
        calibration_frames: for ``"int8"``, the representative frames the converter measures
            activation ranges on (N x H x W x C, preprocessed like `sample_frames`; e.g.
            `calibration_frames()` of training frames, never the frames results are measured on).
    Returns:
        The .tflite flatbuffer as bytes.
    Raises:
        UserError: for a bad argument (unknown quantize, wrong frame shape) or a failed conversion.
        ExportVerificationError: if the converted model does not load, has the wrong interface,
            or disagrees with the Keras model; the message says by how much and where.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose
        >>> data = to_tflite(build_fcn_pose(input_size=64), "float16")
        >>> inspect_tflite(data)["inputs"][0]["shape"]
        [1, 64, 64, 3]
    """
    return export_tflite(model, quantize, sample_frames=sample_frames, num_samples=num_samples, seed=seed,
                         input_size=input_size, map_atol=map_atol, keypoint_px=keypoint_px, threshold=threshold,
                         check_keypoints=check_keypoints, num_threads=num_threads,
                         fold_upsampling=fold_upsampling, calibration_frames=calibration_frames).data


def write_tflite(model: keras.Model, path: str | os.PathLike, quantize: str = DEFAULT_QUANTIZE, *,
                 force: bool = False, **options: Any) -> TFLiteExport:
    """Convert, verify, and only then write the .tflite file atomically.

    The output path is checked before converting (an existing file without `force`, or a folder
    that cannot be written, fails fast), and the file appears only once verification passed:
    a model that disagrees leaves nothing behind.

    Args:
        model: a built tf_keras model.
        path: the .tflite file to write.
        quantize: one of `QUANTIZE_MODES`.
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
                   seed: int, what: str = "sample frames") -> np.ndarray:
    if frames is None:
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
            raise UserError(f"num_samples must be a positive integer, got {num_samples!r}")
        return np.random.default_rng(seed).random((num_samples, *input_shape[1:]), dtype=np.float32)
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[1:] != tuple(input_shape[1:]) or len(frames) == 0:
        raise UserError(f"{what} must be N x {' x '.join(map(str, input_shape[1:]))} (the model's input), "
                        f"got shape {np.shape(frames)}")
    if not np.isfinite(frames).all():
        raise UserError(f"{what} contain NaN or infinite values")
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
    """Run a batch-1 interpreter on each frame (N x H x W x C float, as the Keras model takes them);
    returns the stacked N x ... outputs as float32 (quantized inputs and outputs converted)."""
    from fcnpose_tf.postprocess import dequantize
    from fcnpose_tf.runtime.interpreter import TensorSpec

    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    spec_in, spec_out = TensorSpec.from_details(inp), TensorSpec.from_details(out)
    results = []
    for frame in frames:
        batch = spec_in.quantize(frame[None]) if spec_in.quantized else np.asarray(frame[None], spec_in.dtype)
        interpreter.set_tensor(spec_in.index, np.ascontiguousarray(batch))
        interpreter.invoke()
        maps = interpreter.get_tensor(spec_out.index)[0]
        results.append(dequantize(maps, spec_out.scale, spec_out.zero_point) if spec_out.quantized
                       else maps.copy())
    return np.stack(results)


def _check_interface(interpreter, frames: np.ndarray, keras_shape: tuple[int, ...], pixel_input: bool,
                     what: str) -> None:
    """The converted file's input and output as the runtime expects them (ExportVerificationError if not)."""
    from fcnpose_tf.runtime.interpreter import TensorSpec

    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    spec_in, spec_out = TensorSpec.from_details(inp), TensorSpec.from_details(out)
    expected_in, expected_out = [1, *frames.shape[1:]], [1, *keras_shape[1:]]
    if pixel_input:
        in_ok, in_type = spec_in.holds_pixel_bytes, "uint8 (scale 1/255, zero point 0)"
        out_ok, out_type = spec_out.quantized, "quantized integer"
    else:
        in_ok, in_type = spec_in.dtype == np.float32, "float32"
        out_ok, out_type = spec_out.dtype == np.float32, "float32"
    if list(spec_in.shape) != expected_in or not in_ok:
        scale = f" (scale {spec_in.scale:.6g}, zero point {spec_in.zero_point})" if spec_in.quantized else ""
        raise ExportVerificationError(f"{what} takes {spec_in.dtype.name} {list(spec_in.shape)}{scale}, "
                                      f"expected {in_type} {expected_in}; nothing written")
    if list(spec_out.shape) != expected_out or not out_ok:
        raise ExportVerificationError(f"{what} gives {spec_out.dtype.name} {list(spec_out.shape)}, "
                                      f"expected {out_type} {expected_out}; nothing written")


def verify_tflite(model: keras.Model, tflite: bytes, frames: np.ndarray, *, map_atol: float = MAP_ATOL,
                  keypoint_px: float = KEYPOINT_PX, threshold: float = 0.5, check_keypoints: bool = True,
                  num_threads: int | None = None, label: str = "TFLite", keypoint_share: float = 1.0,
                  pixel_input: bool = False) -> ParityReport:
    """Check that a converted model computes what the Keras model computes on `frames`.

    Checks, in order: the flatbuffer loads in the interpreter; its input is float32
    [1, H, W, C] (with `pixel_input`: uint8 with scale 1/255 and zero point 0) and its output
    float32 (with `pixel_input`: quantized integers) of the Keras output's shape with batch 1; all
    outputs are finite; max |tflite - keras| <= map_atol; and, if `check_keypoints`, the
    keypoints decoded from both agree: none found by one model and missing in the other, and at
    least `keypoint_share` of them within `keypoint_px` (or missing in both). A keypoint whose
    Keras decoding itself changes when the threshold moves by the measured max abs difference
    (at most `THRESHOLD_MARGIN`, 0.01) rests on pixels at the threshold, so either decoding is
    right; such keypoints are counted as ambiguous instead of compared. The cap keeps the
    keypoint check meaningful when `map_atol` is loosened (e.g. for int8).

    Args:
        model: the Keras model the file was converted from.
        tflite: the converted flatbuffer.
        frames: N x H x W x C float32 frames as the model takes them.
        map_atol, keypoint_px, threshold, check_keypoints, num_threads: as in `to_tflite`.
        label: what the file is, for messages ("float16").
        keypoint_share: share of the compared keypoints that must agree within keypoint_px.
        pixel_input: the file is a full-integer export (uint8 pixel input, integer maps).
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
    keras_maps = np.asarray(model(frames, training=False), dtype=np.float32)
    _check_interface(interpreter, frames, keras_maps.shape, pixel_input, what)
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
            f"at {place} (Keras {keras_maps[where]:.4g}, TFLite {tflite_maps[where]:.4g}); nothing written",
            {"frames": len(frames), "max_abs_diff": max_diff, "map_atol": float(map_atol)})
    agreement = _KeypointAgreement(0, 0, 0.0, 0, 0)
    if check_keypoints and keras_maps.ndim == 4 and keras_maps.shape[-1] >= 2:
        agreement = _compare_keypoints(keras_maps, tflite_maps, max_diff, threshold, keypoint_px,
                                       keypoint_share, what)
    return ParityReport(len(frames), max_diff, float(map_atol), agreement.compared, agreement.ambiguous,
                        agreement.max_px, float(keypoint_px), float(threshold), agreement.within,
                        agreement.lost_or_gained, float(keypoint_share))


@dataclass(frozen=True)
class _KeypointAgreement:
    compared: int
    ambiguous: int
    max_px: float
    within: int
    lost_or_gained: int


def _compare_keypoints(keras_maps: np.ndarray, tflite_maps: np.ndarray, max_diff: float, threshold: float,
                       keypoint_px: float, keypoint_share: float, what: str) -> _KeypointAgreement:
    from fcnpose_tf.postprocess import maps_to_keypoints

    # The gate compares Algorithm 1's clusters (the plain centroid is a function of which pixels a cluster holds);
    # the weighted read also moves with the values inside it, which evaluate measures on the written file.
    ref, _ = maps_to_keypoints(keras_maps, threshold, centroid="plain")
    got, _ = maps_to_keypoints(tflite_maps, threshold, centroid="plain")
    # The Keras decoding with every pixel within `margin` of the threshold switched on / off:
    # where these disagree with `ref`, the keypoint rests on pixels a faithful conversion may flip.
    margin = min(max_diff, THRESHOLD_MARGIN)
    low, _ = maps_to_keypoints(keras_maps, threshold - margin, centroid="plain")
    high, _ = maps_to_keypoints(keras_maps, threshold + margin, centroid="plain")

    def same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        missing_a, missing_b = np.isnan(a).any(-1), np.isnan(b).any(-1)
        close = np.linalg.norm(np.nan_to_num(a - b, nan=np.inf), axis=-1) <= keypoint_px
        return (missing_a & missing_b) | (~missing_a & ~missing_b & close)

    stable = same(ref, low) & same(ref, high)
    agree = same(ref, got)
    lost_or_gained = stable & (np.isnan(ref).any(-1) != np.isnan(got).any(-1))
    compared, within = int(stable.sum()), int((stable & agree).sum())
    share_ok = within >= keypoint_share * compared
    bad = np.argwhere(lost_or_gained if lost_or_gained.any() or share_ok else stable & ~agree)
    if len(bad):
        n, k = (int(i) for i in bad[0])

        def show(p: np.ndarray) -> str:
            return "missing" if np.isnan(p).any() else f"({p[0]:.1f}, {p[1]:.1f})"

        distance = "" if np.isnan(ref[n, k]).any() or np.isnan(got[n, k]).any() else \
            f", {np.linalg.norm(ref[n, k] - got[n, k]):.2f} px > {keypoint_px:g} px"
        gate = (f"{int(lost_or_gained.sum())} keypoint(s) lost or gained" if lost_or_gained.any() else
                f"{within} of {compared} keypoints within {keypoint_px:g} px, "
                f"{keypoint_share:.0%} required" if keypoint_share < 1 else
                f"{compared - within} keypoint(s) disagree")
        raise ExportVerificationError(
            f"{what} decodes keypoint {k} of frame {n} at {show(got[n, k])}, the Keras model at {show(ref[n, k])}"
            f"{distance} ({gate}; max abs map difference {max_diff:.3g}); nothing written",
            {"frames": len(keras_maps), "max_abs_diff": max_diff, "keypoints_compared": compared,
             "keypoints_within_px": within, "keypoints_lost_or_gained": int(lost_or_gained.sum()),
             "keypoint_px": float(keypoint_px), "min_keypoint_share": float(keypoint_share)})
    both = stable & ~np.isnan(ref).any(-1) & ~np.isnan(got).any(-1)
    max_px = float(np.linalg.norm(ref[both] - got[both], axis=-1).max()) if both.any() else 0.0
    return _KeypointAgreement(compared, int((~stable).sum()), max_px, within, int(lost_or_gained.sum()))


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
        stores) and ``dequantized`` (the filter comes from a DEQUANTIZE of a stored constant);
        ``metadata``: the file's metadata entries by name (short text values as text, e.g. the
        float16-native file's ``reduced_precision_support``; others as their size).
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
        "metadata": {text(m.name): _metadata_value(tree, m.buffer) for m in (tree.metadata or [])},
    }


def _metadata_value(tree, index: int) -> str:
    """A metadata entry's buffer as text when it is short printable text (``reduced_precision_support``:
    ``fp16inferencefp16accumulation``), else its size."""
    buffer = tree.buffers[index] if tree.buffers and 0 <= index < len(tree.buffers) else None
    data = bytes(bytearray(buffer.data)) if buffer is not None and buffer.data is not None else b""
    if data and len(data) <= 256 and all(32 <= b < 127 for b in data.rstrip(b"\0")):
        return data.rstrip(b"\0").decode("ascii")
    return f"{len(data)} bytes"


def finish_formats(written: Sequence[Path], refused: Sequence[str], any_tflite: bool, named: bool) -> int:
    """The end of a command whose formats the keypoint gate may refuse (`export`, `compress`): name every
    file written, then its exit status. UserError (exit 2) when no .tflite file was written, or when a
    format the user named with --quantize was refused; else 0, with a note naming the refused formats."""
    for path in written:
        print(f"wrote {path}")
    names = ", ".join(refused)
    kept = f"kept {', '.join(map(str, written))}" if written else "nothing written"
    if not any_tflite:
        raise UserError(f"no TFLite file written: {names} refused by the keypoint gate (the table above gives the "
                        f"reasons); {kept}")
    if named and refused:
        raise UserError(f"{names} (named with --quantize) refused by the keypoint gate (the table above gives the "
                        f"reason); {kept}")
    if refused:
        print(f"note: {names} refused by the keypoint gate (see above); the other formats were written")
    return 0
