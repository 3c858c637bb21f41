"""TFLite export with post-training quantization, verified by running the converted file.

A tf_keras model is converted with a static 1 x H x W x C input (through a concrete function with a fixed input
signature, the model passed as the trackable object so the converter sees its variables), built-in ops only, in one
of five formats:

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

The converted model is never trusted: it is loaded in the LiteRT interpreter, run on sample frames, and its maps
are compared with the Keras model's (max abs difference) and decoded into keypoints with the same post-processing
the runtime uses. A model that disagrees raises `ExportVerificationError` and `write_tflite` writes nothing.
(Converting through ``from_concrete_functions`` without the trackable object can silently drop the weights and give
a ~19 KB file whose output is NaN; this check is what catches that kind of failure.)

The gate is `fcnpose_tf.compression.verify`; what a written file holds, `fcnpose_tf.compression.tflite_file`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError
from fcnpose_tf import settings
from fcnpose_tf.settings import QUANTIZE_MODES, TFLITE_FORMATS
from fcnpose_tf.compression.frames import GENERIC_SAMPLES, checked_frames, random_inputs
from fcnpose_tf.compression.verify import (ExportVerificationError, OutputParity, ParityReport, verify_outputs,
                                           verify_tflite)

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
DEFAULT_SAMPLES = 2
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
    parity: ParityReport | OutputParity
    graph_rewrites: tuple[str, ...] = ()
    calibration_frames: int = 0

    @property
    def size_bytes(self) -> int:
        return len(self.data)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (without the bytes).

        Returns:
            {"quantize", "input_shape", "size_bytes", "convert_seconds", "verify_seconds", "parity", "graph_rewrites",
            "calibration_frames"} (the report's "export").
        """
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
             calibration: np.ndarray | None = None, pixel_interface: bool = True) -> bytes:
    """The converted flatbuffer; `pixel_interface` False keeps an int8 file's float32 input and output."""
    import tensorflow as tf

    name = model.inputs[0].name.split(":")[0] or "image"
    forward = tf.function(lambda x: model(x, training=False),
                          input_signature=[tf.TensorSpec(input_shape, tf.float32, name=name)])
    # The model as trackable object: the converter then freezes the model's own variables
    # (without it, they can be garbage-collected away and the file holds no weights).
    trackable = model
    if type(model).__module__.split(".")[0] == "keras":  # Keras 3: its model is no trackable of the converter's;
        trackable = tf.Module()  # a module holding its variables is (without it: NaN outputs, no weights)
        trackable.held_variables = [weight.value for weight in model.weights]
    converter = tf.lite.TFLiteConverter.from_concrete_functions([forward.get_concrete_function()], trackable)
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
        if pixel_interface:
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
    return _pixel_scaled_input(data) if quantize == FULL_INTEGER and pixel_interface else data


def _with_metadata(data: bytes, model: keras.Model, trained_on: dict[str, Any] | None = None) -> bytes:
    """The file with the model's crop and input size (`runtime.tflite_metadata.VIEW_METADATA`, when it has a crop),
    its keypoint schema (`SCHEMA_METADATA`, when it was given one) and `trained_on` (`RECORD_METADATA`) in its
    metadata, where the runtime and `records.training_record` read them; else the file as converted."""
    import json

    from fcnpose_tf.runtime.tflite_metadata import RECORD_METADATA, SCHEMA_METADATA, VIEW_METADATA
    from fcnpose_tf.training.model import given_schema, given_view

    entries: dict[str, Any] = {}
    if (view := given_view(model)) is not None and view.crop is not None:
        entries[VIEW_METADATA] = view.to_json()
    if (keypoints := given_schema(model)) is not None:
        entries[SCHEMA_METADATA] = keypoints.to_dict()
    if trained_on:
        entries[RECORD_METADATA] = trained_on
    if not entries:
        return data
    from ai_edge_litert import schema_py_generated as schema
    import flatbuffers

    tree = schema.ModelT.InitFromPackedBuf(data, 0)
    tree.metadata = list(tree.metadata or [])
    for name, value in entries.items():
        buffer = schema.BufferT()
        buffer.data = list(json.dumps(value, sort_keys=True).encode("utf-8"))
        tree.buffers.append(buffer)
        entry = schema.MetadataT()
        entry.name, entry.buffer = name.encode("utf-8"), len(tree.buffers) - 1
        tree.metadata.append(entry)
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


def export_tflite(model: keras.Model, quantize: str = DEFAULT_QUANTIZE, *, sample_frames: np.ndarray | None = None,
                  num_samples: int = DEFAULT_SAMPLES, seed: int = 0, input_size: int | tuple[int, int] | None = None,
                  map_atol: float | None = None, keypoint_px: float | None = None, threshold: float = 0.5,
                  check_keypoints: bool = True, num_threads: int | None = None,
                  fold_upsampling: bool | None = None,
                  calibration_frames: np.ndarray | None = None,
                  reference: keras.Model | None = None, trained_on: dict[str, Any] | None = None) -> TFLiteExport:
    """Convert a tf_keras model to TFLite and verify the result by running it.

    Same as `to_tflite`, but returns the bytes together with the conversion time, the parity
    report and the graph rewrites (for `compress` reports).

    Args:
        model, quantize, sample_frames, num_samples, seed, input_size, map_atol, keypoint_px, threshold,
            check_keypoints, num_threads, fold_upsampling, calibration_frames: as for `to_tflite`.
        reference: the model the file is verified against (default: `model` itself): a quantization-aware copy of
            a model (`fcnpose_tf.compression.qat`) is converted, and its file is held to the model it was trained
            from.
        trained_on: which frames the model was trained on, stored in the file (`records.TrainingRecord.deployed`
            of its training record; None: nothing stored).
    Returns:
        A `TFLiteExport`.
    Raises:
        UserError: for a bad argument or a conversion that fails.
        ExportVerificationError: if the converted model does not load or disagrees with Keras.
    """
    _check_quantize(quantize)
    fmt = TFLITE_FORMATS[quantize]
    map_atol = fmt.map_atol if map_atol is None else map_atol
    keypoint_px = fmt.keypoint_px if keypoint_px is None else keypoint_px
    fold_upsampling = fmt.fold_upsampling if fold_upsampling is None else fold_upsampling
    input_shape = _static_input_shape(model, input_size)
    calibration = None
    if quantize == FULL_INTEGER:
        if sample_frames is None or calibration_frames is None:
            raise UserError("int8 (full-integer) export needs real preprocessed frames: calibration_frames to "
                            "calibrate on and sample_frames to verify keypoints on (random images say nothing "
                            "about the ranges a camera frame gives)")
        calibration = checked_frames(calibration_frames, input_shape, 1, seed, what="calibration frames")
    frames = checked_frames(sample_frames, input_shape, num_samples, seed)
    if len(frames) < fmt.min_frames:
        raise UserError(f"{quantize} export is verified on keypoints of at least {fmt.min_frames} "
                        f"real frames, got {len(frames)} sample frame(s)")
    start = time.perf_counter()
    graph, rewrites = _inference_graph(model) if fold_upsampling else (model, ())
    data = _with_metadata(_convert(graph, quantize, input_shape, calibration),
                          model if reference is None else reference, trained_on)
    convert_seconds = time.perf_counter() - start
    start = time.perf_counter()
    # Always against the original model: the rewrite is checked together with the conversion.
    parity = verify_tflite(model if reference is None else reference, data, frames, map_atol=map_atol,
                           keypoint_px=keypoint_px, threshold=threshold,
                           check_keypoints=check_keypoints, num_threads=num_threads, label=quantize,
                           keypoint_share=fmt.keypoint_share,
                           pixel_input=quantize == FULL_INTEGER)
    return TFLiteExport(data, quantize, input_shape, convert_seconds, time.perf_counter() - start, parity,
                        rewrites, 0 if calibration is None else len(calibration))


def is_keypoint_model(model: Any) -> bool:
    """Whether `model` is held to the keypoint gate: a tf_keras model with one output of 2-D maps (N x H x W x C,
    C >= 2), as FCN-Pose and its pruned and fine-tuned forms are. Any other model (Keras 3, a classifier, ...) is
    held to output parity (`export_generic`).

    Args:
        model: a tf_keras or Keras 3 model.
    Returns:
        True for a keypoint-map model.
    """
    if type(model).__module__.split(".")[0] != "tf_keras" or len(getattr(model, "outputs", None) or []) != 1:
        return False
    shape = tuple(model.outputs[0].shape)
    return len(shape) == 4 and (shape[-1] or 0) >= 2


def export_generic(model: Any, quantize: str = DEFAULT_QUANTIZE, *, sample_inputs: np.ndarray | None = None,
                   calibration_inputs: np.ndarray | None = None, num_samples: int = GENERIC_SAMPLES,
                   calibration_count: int = settings.CALIBRATION_FRAMES.default,
                   input_range: tuple[float, float] = (0.0, 1.0), seed: int = 0,
                   num_threads: int | None = None) -> TFLiteExport:
    """Convert a model that is not a keypoint model (tf_keras or Keras 3: a classifier, any CNN with one image
    input and one output) and verify the file by output parity (`verify.verify_outputs`).

    The file has a static 1 x H x W x C float32 input and float32 output in every format (an int8 file quantizes
    and dequantizes inside). Bounds per format: `settings.TFLITE_FORMATS`' output_rtol and top1_share.

    Args:
        model: the model to convert.
        quantize: the format (`settings.TFLITE_FORMATS`).
        sample_inputs: inputs to verify on (N x the model's input); None: `num_samples` seeded random inputs
            uniform in `input_range`.
        calibration_inputs: int8's calibration inputs; None: `calibration_count` random inputs in `input_range`
            (another seed).
        num_samples: random inputs to verify on without `sample_inputs`.
        calibration_count: random calibration inputs without `calibration_inputs`.
        input_range: (low, high) of the values the model takes.
        seed: seed of the random inputs.
        num_threads: interpreter threads of the check (None: the interpreter's default).
    Returns:
        A `TFLiteExport` (its parity a `verify.OutputParity`).
    Raises:
        UserError: for a bad argument or a conversion that fails.
        ExportVerificationError: if the file does not load or disagrees with the Keras model.
    """
    _check_quantize(quantize)
    fmt = TFLITE_FORMATS[quantize]
    input_shape = _static_input_shape(model, None)
    frames = (checked_frames(sample_inputs, input_shape, num_samples, seed, what="sample inputs")
              if sample_inputs is not None else random_inputs(input_shape, num_samples, input_range, seed))
    calibration = None
    if fmt.calibrated:
        calibration = (checked_frames(calibration_inputs, input_shape, 1, seed, what="calibration inputs")
                       if calibration_inputs is not None else
                       random_inputs(input_shape, calibration_count, input_range, seed + 1))
    start = time.perf_counter()
    data = _with_metadata(_convert(model, quantize, input_shape, calibration, pixel_interface=False), model)
    convert_seconds = time.perf_counter() - start
    start = time.perf_counter()
    parity = verify_outputs(model, data, frames, output_rtol=fmt.output_rtol, top1_share=fmt.top1_share,
                            num_threads=num_threads, label=quantize)
    return TFLiteExport(data, quantize, input_shape, convert_seconds, time.perf_counter() - start, parity, (),
                        0 if calibration is None else len(calibration))


def _inference_graph(model: keras.Model) -> tuple[keras.Model, tuple[str, ...]]:
    """The model with its upsampling folded (and what was folded), or the model itself when its
    structure is not one `fold_upsampling` can rewrite (e.g. branches): folding only saves time."""
    from fcnpose_tf.compression.inference_graph import UnsupportedGraphError, fold_and_describe

    try:
        graph, rewrites = fold_and_describe(model)
        return graph, tuple(rewrites)
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
    for int8 at least 95 % (`settings.TFLITE_FORMATS`) on at least 16 frames, none lost or gained.

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
            (`settings.TFLITE_FORMATS`: 1e-2 for float32 and float16, 0.2 for int8-weights, whose
            on-the-fly activation quantization moves trained FCN-Pose maps by up to ~0.14).
        keypoint_px: largest allowed distance between decoded keypoints, in map pixels; None: the
            mode's default (`settings.TFLITE_FORMATS`: 1 px, 2 px for int8-weights, where trained
            models' keypoints move by up to 1.4 px, median 0.15 px).
        threshold: map threshold for decoding keypoints.
        check_keypoints: decode and compare keypoints (needs C >= 2 output maps, skeleton last).
        num_threads: interpreter threads for the check (None: the interpreter's default).
        fold_upsampling: convert `fcnpose_tf.compression.inference_graph.fold_upsampling(model)` instead of
            `model` (exact; each nearest UpSampling2D + 'same' Conv2D pair becomes a low-resolution
            Conv2D + DEPTH_TO_SPACE, which XNNPACK runs faster; the file holds f*f times larger
            kernels for those layers). A model whose structure cannot be folded (branches, several
            inputs, ...) is converted as it is. Verification is always against `model`.
            None: the mode's default, `settings.TFLITE_FORMATS` (on for int8, whose forward pass
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
        >>> from fcnpose_tf.compression.tflite_file import inspect_tflite
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
        >>> export = write_tflite(model, "out/fcnpose_ur5_p70_fp16.tflite")  # doctest: +SKIP
    """
    path = Path(path)
    if path.suffix != ".tflite":
        raise UserError(f"{path}: a TFLite model file should end in .tflite")
    _check_quantize(quantize)
    fileio.check_writable(path, force)
    export = export_tflite(model, quantize, **options)
    fileio.write_bytes(path, export.data, force)
    return export
