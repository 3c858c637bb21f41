"""Load a .tflite file with the best interpreter available, check it is an FCN-Pose model, and read its cost.

Backends, in order: LiteRT (`ai_edge_litert`, the maintained one, with aarch64
wheels for a 64-bit Raspberry Pi OS), `tflite_runtime` (the old standalone
package, the only choice on a 32-bit OS) and `tf.lite` (deprecated, needs
TensorFlow; only tried when the other two are missing). Nothing here imports
TensorFlow unless the first two are unavailable.
"""

from __future__ import annotations

import functools
import importlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import entry_problem, native_name
from fcnpose_tf.metrics import conv_macs
from fcnpose_tf.keypoints import KeypointSchema, named_schema
from fcnpose_tf.nativelog import native_stderr_captured
from fcnpose_tf.preprocess import FrameView
from fcnpose_tf.records import distribution_version
from fcnpose_tf.runtime.tflite_metadata import SCHEMA_METADATA, VIEW_METADATA, read_metadata
from fcnpose_tf.system import available_cores

BACKENDS: tuple[str, ...] = ("ai_edge_litert", "tflite_runtime", "tensorflow")
"""Interpreter providers in the order `auto` tries them."""

_INPUT_DTYPES = (np.float32, np.float16, np.uint8, np.int8)


@dataclass(frozen=True)
class Backend:
    """The package that provides the Interpreter class, its version, and why earlier ones were skipped."""

    name: str
    version: str
    interpreter_class: Any = field(repr=False, compare=False)
    skipped: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """Short description for reports, e.g. `ai_edge_litert 2.3.0`."""
        return f"{self.name} {self.version}"


def _version(module_name: str, module: Any) -> str:
    # the installed distribution's version; a vendored build without metadata: the module's own
    return distribution_version(module_name) or str(getattr(module, "__version__", "unknown"))


def _import_backend(name: str) -> Any:
    """The Interpreter class of one backend; ImportError/OSError if it cannot be loaded."""
    if name == "ai_edge_litert":
        return importlib.import_module("ai_edge_litert.interpreter").Interpreter
    if name == "tflite_runtime":
        return importlib.import_module("tflite_runtime.interpreter").Interpreter
    if name == "tensorflow":
        tf = importlib.import_module("tensorflow")
        return tf.lite.Interpreter
    raise UserError(f"unknown interpreter backend {name!r}; expected auto or one of {', '.join(BACKENDS)}")


def find_backend(preferred: str = "auto") -> Backend:
    """The first importable backend (or exactly `preferred`), recording why earlier ones were skipped.

    Args:
        preferred: "auto" (LiteRT, then tflite_runtime, then tf.lite) or one of them by name.
    Returns:
        The backend: its name, version and interpreter class.
    Raises:
        UserError: if no backend can be imported, naming what to install.
    """
    names = BACKENDS if preferred == "auto" else (preferred,)
    skipped = []
    for name in names:
        try:
            cls = _import_backend(name)
        except (ImportError, OSError, AttributeError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            skipped.append(f"{name}: {first}")
            continue
        module = importlib.import_module(name)
        return Backend(name, _version(name, module), cls, tuple(skipped))
    raise UserError("no TFLite interpreter available (" + "; ".join(skipped)
                    + "); install one with `pip install ai-edge-litert` (64-bit OS) or `tflite-runtime` (32-bit)")


def default_num_threads() -> int:
    """CPU cores this process may run on (the interpreter's default thread count here).

    Returns:
        The core count.
    """
    return available_cores()


def check_tflite_file(path: str | os.PathLike) -> Path:
    """Check that `path` is a TFLite model file before an interpreter reads it.

    Args:
        path: the file.
    Returns:
        `path` as a Path.
    Raises:
        UserError: unless `path` is an existing, non-empty file with the TFLite identifier `TFL3`.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: model file not found")
    if not path.is_file():
        raise UserError(f"{path}: is not a file, expected a .tflite model")
    with open(path, "rb") as fh:
        head = fh.read(8)
    if len(head) < 8 or head[4:8] != b"TFL3":
        raise UserError(f"{path}: not a TFLite model (no 'TFL3' identifier; a Keras .keras/.h5 file? "
                        "make one with `fcnpose-tf compress`)")
    return path


def load_interpreter(path: str | os.PathLike, num_threads: int | None = None,
                     backend: str = "auto") -> tuple[Any, Backend]:
    """Create and allocate an interpreter for a .tflite file.

    Args:
        path: the .tflite file.
        num_threads: interpreter threads (>= 1); None means all cores (`default_num_threads()`).
        backend: `auto` (LiteRT, then tflite_runtime, then tf.lite) or one of BACKENDS.
    Returns:
        (interpreter, backend); the interpreter has its tensors allocated.
    Raises:
        UserError: missing or corrupt file, bad thread count, no interpreter installed.
    """
    path = check_tflite_file(path)
    threads = default_num_threads() if num_threads is None else num_threads
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise UserError(f"threads must be a positive integer, got {num_threads!r}")
    found = find_backend(backend)
    try:
        with native_stderr_captured():  # LiteRT's `INFO: Created ... XNNPACK delegate` and its own error lines
            interpreter = found.interpreter_class(model_path=native_name(path), num_threads=threads)
            interpreter.allocate_tensors()
    except (ValueError, RuntimeError) as exc:
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise UserError(f"{path}: cannot be loaded as a TFLite model ({detail})") from None
    return interpreter, found


@dataclass(frozen=True)
class TensorSpec:
    """Index, shape (with batch), dtype and affine quantization of a model input or output."""

    index: int
    name: str
    shape: tuple[int, ...]
    dtype: np.dtype
    scale: float = 0.0
    zero_point: int = 0

    # Cached: the runtime asks for both on every frame, and np.isclose alone costs tens of microseconds
    # there (the frame path's budget is a few hundred; docs/runtime.md, "Frame path").
    @functools.cached_property
    def quantized(self) -> bool:
        """True for integer tensors carrying a real value as (q - zero_point) * scale."""
        return bool(np.issubdtype(self.dtype, np.integer) and self.scale > 0)

    @functools.cached_property
    def holds_pixel_bytes(self) -> bool:
        """True for a uint8 input with scale 1/255 and zero point 0: the resized frame's RGB bytes as they are."""
        return self.dtype == np.uint8 and self.zero_point == 0 and bool(np.isclose(self.scale, 1 / 255, rtol=1e-6))

    def quantize(self, values: np.ndarray) -> np.ndarray:
        """Real values as this integer tensor holds them.

        Args:
            values: real values (any shape).
        Returns:
            round(v / scale) + zero_point, saturated to the tensor's integer type.
        """
        info = np.iinfo(self.dtype)
        return np.clip(np.rint(np.asarray(values, np.float32) / self.scale) + self.zero_point,
                       info.min, info.max).astype(self.dtype)

    @classmethod
    def from_details(cls, details: dict) -> "TensorSpec":
        """The spec of one entry of the interpreter's `get_input_details()` / `get_output_details()` (no
        quantization: scale 0, zero point 0).

        Args:
            details: one entry of those lists.
        Returns:
            The spec.
        """
        scale, zero = details.get("quantization", (0.0, 0)) or (0.0, 0)
        return cls(int(details["index"]), str(details.get("name", "")), tuple(int(d) for d in details["shape"]),
                   np.dtype(details["dtype"]), float(scale), int(zero))


@dataclass(frozen=True)
class ModelIO:
    """The input and output an FCN-Pose .tflite must have: 1xHxWx3 image in, 1xHxWxC maps out (C >= 2)."""

    input: TensorSpec
    output: TensorSpec

    @property
    def input_shape(self) -> tuple[int, int]:
        """(height, width) of the model input in pixels."""
        return self.input.shape[1], self.input.shape[2]

    @property
    def num_maps(self) -> int:
        """Output maps: keypoints + 1 skeleton map."""
        return self.output.shape[3]

    def describe(self) -> str:
        """One line of the shapes and types.

        Returns:
            e.g. `224x224x3 float32 -> 224x224x9 float32`.
        """
        i, o = self.input, self.output
        return (f"{'x'.join(map(str, i.shape[1:]))} {i.dtype.name} -> "
                f"{'x'.join(map(str, o.shape[1:]))} {o.dtype.name}")


def inspect_io(interpreter: Any, path: str | os.PathLike = "model") -> ModelIO:
    """Read and check the model's input and output.

    Args:
        interpreter: an allocated interpreter.
        path: the model's file, to name in errors.
    Returns:
        The input and output tensors' specs.
    Raises:
        UserError: naming what an FCN-Pose model needs (one fixed 1 x H x W x 3 input, one output of maps of the
            input's size, supported types).
    """
    inputs, outputs = interpreter.get_input_details(), interpreter.get_output_details()
    if len(inputs) != 1 or len(outputs) != 1:
        raise UserError(f"{path}: expected one input image and one output of maps, "
                        f"found {len(inputs)} inputs and {len(outputs)} outputs (not an FCN-Pose model)")
    spec_in, spec_out = TensorSpec.from_details(inputs[0]), TensorSpec.from_details(outputs[0])
    signature = [int(d) for d in inputs[0].get("shape_signature", spec_in.shape)]
    if any(d < 0 for d in signature[1:]):  # allocated as [1, 1, 1, 3]: keypoints would land at the frame centre
        raise UserError(f"{path}: the input size is not fixed (shape signature {signature}); the runtime needs "
                        "a fixed H x W input: export the model with one, e.g. "
                        "fcnpose_tf.compression.export.write_tflite(model, 'model.tflite', input_size=224), or build it on "
                        "tf_keras.Input((224, 224, 3))")
    shape = spec_in.shape
    if len(shape) != 4 or shape[0] != 1 or shape[3] != 3:
        raise UserError(f"{path}: input shape {list(shape)}, expected [1, H, W, 3] (one RGB image; "
                        "not an FCN-Pose model)")
    if min(shape[1], shape[2]) < 1:
        raise UserError(f"{path}: input {shape[1]}x{shape[2]} is empty")
    if not any(spec_in.dtype == np.dtype(t) for t in _INPUT_DTYPES):
        raise UserError(f"{path}: input type {spec_in.dtype.name}, expected float32, float16, uint8 or int8")
    if np.issubdtype(spec_in.dtype, np.integer) and not spec_in.quantized:
        raise UserError(f"{path}: integer input without quantization parameters; cannot feed it an image")
    shape = spec_out.shape
    if len(shape) != 4 or shape[0] != 1 or shape[3] < 2:
        raise UserError(f"{path}: output shape {list(shape)}, expected [1, H, W, C] maps with C >= 2 "
                        "(keypoints + skeleton; not an FCN-Pose model)")
    if tuple(shape[1:3]) != tuple(spec_in.shape[1:3]):
        raise UserError(f"{path}: output maps {shape[1]}x{shape[2]} differ from the {spec_in.shape[1]}x"
                        f"{spec_in.shape[2]} input (FCN-Pose maps have the input's size)")
    if not (np.issubdtype(spec_out.dtype, np.floating) or spec_out.quantized):
        raise UserError(f"{path}: output type {spec_out.dtype.name} without quantization parameters; "
                        "expected probability maps")
    return ModelIO(spec_in, spec_out)


def _metadata_entry(path: str | os.PathLike, name: str) -> bytes | None:
    """One metadata entry of a .tflite file (`tflite_metadata.read_metadata`), None when absent; UserError when the
    file's metadata cannot be read."""
    try:
        return read_metadata(path).get(name)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: its metadata cannot be read ({exc})") from exc


def read_schema(path: str | os.PathLike, io: ModelIO) -> KeypointSchema | None:
    """What a .tflite model names its maps.

    Args:
        path: the .tflite file.
        io: its input and output (`inspect_io`).
    Returns:
        The schema in its metadata (`tflite_metadata.SCHEMA_METADATA`), else its training record's
        (`keypoints.named_schema`); None when neither names one (`keypoints.schema_for_maps` is the default).
    Raises:
        UserError: unreadable metadata, or a stored schema that does not fit the file's maps.
    """
    return named_schema(io.num_maps, _metadata_entry(path, SCHEMA_METADATA), path)


def read_view(path: str | os.PathLike, io: ModelIO) -> FrameView:
    """What a .tflite model sees of a frame.

    Args:
        path: the .tflite file.
        io: its input and output (`inspect_io`).
    Returns:
        The view in its metadata (`tflite_metadata.VIEW_METADATA`), else the whole frame at its input size.
    Raises:
        UserError: unreadable metadata, or a stored view that does not fit the file's input.
    """
    stored = _metadata_entry(path, VIEW_METADATA)
    if stored is None:
        return FrameView(*io.input_shape)
    try:
        view = FrameView.from_json(json.loads(stored.decode("utf-8")))
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise UserError(f"{path}: its {VIEW_METADATA} metadata is not a frame view ({entry_problem(exc)})") from exc
    if view.shape != io.input_shape:
        raise UserError(f"{path}: its stored view ({view.describe()}) does not fit its "
                        f"{io.input_shape[0]}x{io.input_shape[1]} input")
    return view


@dataclass(frozen=True)
class ModelStats:
    """What a .tflite costs: weights, multiply-accumulates per frame, bytes on disk.

    `params` counts the elements of every weighted op's weights and biases (per
    use, as Keras counts them; the converter may share identical constants).
    `macs` is H*W*k*k*Cin*Cout per convolution (FLOPs = 2 x MACs), plus
    depthwise and fully-connected ops if a model has them.
    """

    params: int | None
    macs: int | None
    size_bytes: int
    weight_dtypes: tuple[str, ...]
    conv_layers: int
    op_counts: dict[str, int]

    def to_dict(self) -> dict:
        """The costs as reports hold them: params, macs, size_bytes, weight_dtypes, conv_layers, op_counts.

        Returns:
            The object.
        """
        return {"params": self.params, "macs": self.macs, "size_bytes": self.size_bytes,
                "weight_dtypes": list(self.weight_dtypes), "conv_layers": self.conv_layers,
                "op_counts": dict(self.op_counts)}


_WEIGHTED_OPS = ("CONV_2D", "DEPTHWISE_CONV_2D", "FULLY_CONNECTED", "TRANSPOSE_CONV")


def model_stats(interpreter: Any, path: str | os.PathLike) -> ModelStats:
    """Parameters and MACs from the interpreter's op and tensor details, and the file size.

    Uses the interpreter's op table (`_get_ops_details`, available in LiteRT,
    tflite_runtime and tf.lite); where an old interpreter lacks it, params and
    macs are None rather than a guess.

    Args:
        interpreter: an allocated interpreter.
        path: its .tflite file.
    Returns:
        Parameters, MACs, size, weight types, convolution and op counts.
    """
    size = Path(path).stat().st_size
    try:
        ops = interpreter._get_ops_details()  # noqa: SLF001 - the public API has no op table
        tensors = {int(t["index"]): t for t in interpreter.get_tensor_details()}
    except (AttributeError, ValueError, RuntimeError):
        return ModelStats(None, None, size, (), 0, {})
    ops = [op for op in ops if op.get("op_name") and op["op_name"] != "DELEGATE"]
    producer = {int(t): op for op in ops for t in op["outputs"] if int(t) >= 0}

    def shape(index: int) -> tuple[int, ...]:
        return tuple(int(d) for d in tensors[index]["shape"]) if index in tensors else ()

    def stored(index: int) -> int:
        """The constant a weight comes from: follow DEQUANTIZE (float16/int8 storage) back to it."""
        op = producer.get(index)
        while op is not None and op["op_name"] == "DEQUANTIZE":
            index = int(op["inputs"][0])
            op = producer.get(index)
        return index

    # A CONV_2D feeding DEPTH_TO_SPACE(b) is an upsampling folded into a convolution by
    # fcnpose_tf.compression.inference_graph.fold_upsampling: its b*b phase kernels stand for one 3x3 kernel
    # (3x3 taps per phase for a 3x3 or 1x1 per phase for a 1x1 original), so count its weights / (b*b).
    consumers: dict[int, list] = {}
    for op in ops:
        for t in op["inputs"]:
            consumers.setdefault(int(t), []).append(op)

    def fold_block(op) -> int:
        out = int(op["outputs"][0])
        users = consumers.get(out, [])
        while len(users) == 1 and users[0]["op_name"] in ("LOGISTIC", "TANH", "RELU", "RELU6", "ELU"):
            users = consumers.get(int(users[0]["outputs"][0]), [])  # an activation between them
        if len(users) != 1 or users[0]["op_name"] != "DEPTH_TO_SPACE":
            return 1
        before, after = shape(out), shape(int(users[0]["outputs"][0]))
        if len(before) != 4 or len(after) != 4 or before[1] == 0 or after[1] % before[1]:
            return 1
        return after[1] // before[1]

    params = macs = convs = 0
    dtypes: set[str] = set()
    counts: dict[str, int] = {}
    for op in ops:
        name = op["op_name"]
        counts[name] = counts.get(name, 0) + 1
        if name not in _WEIGHTED_OPS:
            continue
        ins = [int(t) for t in op["inputs"]]
        if name == "TRANSPOSE_CONV":  # inputs: output_shape, weights, input[, bias]
            weights = [ins[1]] + [t for t in ins[3:] if t >= 0]
        else:  # inputs: activation, weights[, bias]
            weights = [t for t in ins[1:] if t >= 0]
        block = fold_block(op) if name == "CONV_2D" else 1
        for t in weights:
            params += int(np.prod(shape(t), dtype=np.int64)) // (block * block)
            source = stored(t)
            if source in tensors:
                dtypes.add(np.dtype(tensors[source]["dtype"]).name)
        out = shape(int(op["outputs"][0]))
        w = shape(weights[0]) if weights else ()
        if name == "CONV_2D" and len(out) == 4 and len(w) == 4:  # filter: Cout x kh x kw x Cin
            macs += conv_macs(out[1], out[2], w[1], w[2], w[3], w[0])
            convs += 1
        elif name == "DEPTHWISE_CONV_2D" and len(out) == 4 and len(w) == 4:  # filter: 1 x kh x kw x Cout
            macs += int(out[1]) * int(out[2]) * int(w[1]) * int(w[2]) * int(w[3])
            convs += 1
        elif name == "TRANSPOSE_CONV" and len(w) == 4:  # MACs over the input grid: Hin*Win*k*k*Cin*Cout
            x = shape(ins[2])
            if len(x) == 4:
                macs += conv_macs(x[1], x[2], w[1], w[2], w[3], w[0])
            convs += 1
        elif name == "FULLY_CONNECTED" and len(w) == 2:
            rows = int(np.prod(out[:-1], dtype=np.int64)) if len(out) > 1 else 1
            macs += rows * int(w[0]) * int(w[1])
    return ModelStats(params, macs, size, tuple(sorted(dtypes)), convs, counts)
