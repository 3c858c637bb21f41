"""Named metadata entries of a .tflite file, read from its flatbuffer with the standard library alone.

A .tflite model is a FlatBuffer whose root table (`Model` in TFLite's schema) lists `metadata` entries: a
name and the index of a buffer holding the bytes. The exporter stores the model's frame view there
(`VIEW_METADATA`: the crop and input size as JSON), the names of its keypoints (`SCHEMA_METADATA`) and which frames
it was trained on (`RECORD_METADATA`), so that the one file copied to a Raspberry Pi, or anywhere else, carries
everything the runtime and `evaluate` need. Reading it takes four table look-ups; this module does them by the
FlatBuffers layout rules so that every interpreter package (LiteRT, the old tflite_runtime of a 32-bit Pi OS)
can read it, with no schema package installed.
"""

from __future__ import annotations

import os
import struct

VIEW_METADATA = "fcnpose_tf.view"
"""The metadata entry holding the model's `preprocess.FrameView` as JSON (`FrameView.to_json`)."""
SCHEMA_METADATA = "fcnpose_tf.schema"
"""The metadata entry holding the keypoint schema of the model's maps as JSON (`KeypointSchema.to_dict`)."""
RECORD_METADATA = "fcnpose_tf.training_record"
"""The metadata entry holding what the file keeps of its model's training record as JSON
(`records.TrainingRecord.deployed`: which frames it was trained on, no paths)."""

# Field numbers in TFLite's schema.fbs: Model.buffers = 4, Model.metadata = 6; Metadata.name = 0,
# Metadata.buffer = 1; Buffer.data = 0, Buffer.offset = 1 (for files over 2 GB, data stored after the buffer).
_MODEL_BUFFERS, _MODEL_METADATA = 4, 6
_METADATA_NAME, _METADATA_BUFFER = 0, 1
_BUFFER_DATA, _BUFFER_OFFSET, _BUFFER_SIZE = 0, 1, 2


class _Reader:
    def __init__(self, data: bytes):
        self.data = data

    def u32(self, pos: int) -> int:
        return struct.unpack_from("<I", self.data, pos)[0]

    def field(self, table: int, index: int) -> int | None:
        """Absolute position of field `index` of the table at `table`, or None when absent."""
        vtable = table - struct.unpack_from("<i", self.data, table)[0]
        vtable_size = struct.unpack_from("<H", self.data, vtable)[0]
        slot = 4 + 2 * index
        if slot >= vtable_size:
            return None
        offset = struct.unpack_from("<H", self.data, vtable + slot)[0]
        return table + offset if offset else None

    def indirect(self, pos: int) -> int:
        return pos + self.u32(pos)

    def vector(self, pos: int) -> tuple[int, int]:
        """(start of the elements, length) of the vector referenced at `pos`."""
        start = self.indirect(pos)
        return start + 4, self.u32(start)

    def tables(self, table: int, index: int) -> list[int]:
        pos = self.field(table, index)
        if pos is None:
            return []
        start, length = self.vector(pos)
        return [self.indirect(start + 4 * i) for i in range(length)]

    def bytes_at(self, table: int, index: int) -> bytes | None:
        pos = self.field(table, index)
        if pos is None:
            return None
        start, length = self.vector(pos)
        return self.data[start:start + length]


def read_metadata(model: bytes | str | os.PathLike) -> dict[str, bytes]:
    """The file's metadata entries by name (e.g. `VIEW_METADATA`, the converter's `min_runtime_version`).

    Args:
        model: the flatbuffer bytes or a .tflite file.
    Returns:
        Name -> the entry's bytes.
    Raises:
        ValueError: bytes that are not a FlatBuffer of that shape (a truncated or foreign file).
    """
    if isinstance(model, (bytes, bytearray, memoryview)):
        data = model
    else:
        with open(os.fspath(model), "rb") as file:
            data = file.read()
    data = bytes(data)
    reader = _Reader(data)
    try:
        root = reader.u32(0)
        buffers = reader.tables(root, _MODEL_BUFFERS)
        entries: dict[str, bytes] = {}
        for meta in reader.tables(root, _MODEL_METADATA):
            name_pos = reader.field(meta, _METADATA_NAME)
            buffer_pos = reader.field(meta, _METADATA_BUFFER)
            if name_pos is None or buffer_pos is None:
                continue
            start, length = reader.vector(name_pos)
            name = data[start:start + length].decode("utf-8", "replace")
            buffer = buffers[reader.u32(buffer_pos)]
            content = reader.bytes_at(buffer, _BUFFER_DATA)
            if content is None:  # a file over 2 GB keeps buffers after the FlatBuffer: offset and size
                offset_pos, size_pos = reader.field(buffer, _BUFFER_OFFSET), reader.field(buffer, _BUFFER_SIZE)
                if offset_pos is None or size_pos is None:
                    content = b""
                else:
                    offset, size = struct.unpack_from("<Q", data, offset_pos)[0], struct.unpack_from("<Q", data, size_pos)[0]
                    content = data[offset:offset + size]
            entries[name] = content
        return entries
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a TFLite FlatBuffer ({type(exc).__name__}: {exc})") from exc
