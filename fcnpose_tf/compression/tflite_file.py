"""What a .tflite file holds, read from its FlatBuffer: interface, operators, tensor types, metadata.

`inspect_tflite` reads the file with the TFLite schema that ships in ai_edge_litert, so tests and reports check how
weights are stored without matching strings; it needs neither TensorFlow nor an interpreter.
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import TypedDict

from fcnpose_tf.errors import UserError


class TensorInfo(TypedDict):
    """An input or output tensor of a .tflite file (`TFLiteInfo`)."""

    name: str
    shape: list[int]
    """e.g. [1, 224, 224, 3] (the shape signature where the file has one)."""
    dtype: str
    """The TFLite type's name, e.g. "FLOAT32", "UINT8"."""


class ConvolutionInfo(TypedDict):
    """How a CONV_2D, DEPTHWISE_CONV_2D, FULLY_CONNECTED or TRANSPOSE_CONV stores its filter (`TFLiteInfo`)."""

    op: str
    filter_shape: list[int]
    filter_dtype: str
    """What the op consumes."""
    stored_dtype: str
    """What the file stores."""
    dequantized: bool
    """The filter comes from a DEQUANTIZE of a stored constant."""
    stored_bytes: int


class TFLiteInfo(TypedDict):
    """What a .tflite file holds (`inspect_tflite`)."""

    size_bytes: int
    subgraphs: int
    inputs: list[TensorInfo]
    outputs: list[TensorInfo]
    ops: list[str]
    """Operator names in execution order, e.g. "CONV_2D"."""
    op_counts: dict[str, int]
    """Operators by name, sorted."""
    builtin_only: bool
    custom_ops: list[str]
    """Custom op codes."""
    flex_ops: list[str]
    """The custom ops named Flex...: they need the TensorFlow delegate."""
    tensor_dtypes: dict[str, int]
    """Tensors per type."""
    constant_dtypes: dict[str, int]
    """Tensors holding data (the stored weights) per type."""
    constant_bytes: int
    """Bytes of stored weights."""
    convolutions: list[ConvolutionInfo]
    metadata: dict[str, str]
    """The file's metadata entries by name: short text as text (the float16-native file's
    ``reduced_precision_support``), others as their size ("1234 bytes")."""


def _enum_names(enum_class: type) -> dict[int, str]:
    return {value: name for name, value in vars(enum_class).items()
            if not name.startswith("_") and isinstance(value, int)}


def inspect_tflite(model: bytes | str | os.PathLike) -> TFLiteInfo:
    """Describe a .tflite flatbuffer: interface, operators, and how tensors and weights are stored.

    Reads the flatbuffer with the TFLite schema shipped in ai_edge_litert; neither TensorFlow nor
    an interpreter is needed, so files with Flex or custom ops can be inspected too.

    Args:
        model: the flatbuffer bytes or a path to a .tflite file.
    Returns:
        The interface, the operators, how tensors and weights are stored, and the metadata (`TFLiteInfo`: stable
        keys).
    Raises:
        UserError: if the file is missing or is not a TFLite flatbuffer.
    Example:
        >>> info = inspect_tflite("saved_models/fcnpose_ur5_p70_fp16.tflite")  # doctest: +SKIP
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

    def describe(index: int) -> TensorInfo:
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
    convolutions: list[ConvolutionInfo] = []
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
