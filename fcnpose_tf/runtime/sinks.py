"""Where keypoints go: JSON Lines or CSV records flushed per frame, and a video with the overlay drawn.

Record files stream: each frame's line is written and flushed before the next
frame is read, so a crash or kill loses at most the frame in flight. A new one
is written directly under its final name (so `tail -f` works); one that
`force` replaces stays whole until the run has written a complete record: the
new records go to a temporary file beside it, renamed over it when they are
closed (a run that ends before its first record leaves the earlier file as it was). A saved video is written to a temporary
name (`fileio.temporary_path`: one a SIGKILL stranded is removed by the next
run with the same target) and renamed into place when it is closed, so an
existing video is only replaced by a complete one; a disk that fills up ends
the run with `PATH: no space left on device` and no video, not a broken one.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections import deque
from pathlib import Path
from typing import Any, NotRequired, Sequence, TypedDict

import cv2
import numpy as np

from fcnpose_tf.draw import draw_keypoints
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import (check_writable, full_disk_error, native_name, os_error_reason, record_completed,
                               set_default_permissions, signals_deferred, temporary_path)
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.runtime.estimator import KeypointRecord, Prediction
from fcnpose_tf.runtime.sources import Frame, quiet_opencv

RECORD_SUFFIXES = {".jsonl": "jsonl", ".ndjson": "jsonl", ".csv": "csv"}
VIDEO_CODECS = {".mp4": "mp4v", ".m4v": "mp4v", ".mov": "mp4v", ".avi": "MJPG", ".mkv": "MJPG"}


class Latency(TypedDict):
    """Milliseconds of one frame's stages (`RecordedFrame`)."""

    preprocess: float
    invoke: float
    postprocess: float


class RecordedFrame(TypedDict):
    """One frame's line of a JSON Lines record file (`frame_record`), keys in this order; coordinates in frame
    pixels."""

    frame: int
    """The source's frame index."""
    timestamp: float
    """When the frame was read (seconds, `Frame.timestamp`)."""
    source: str
    width: int
    height: int
    media_time_s: NotRequired[float]
    """The frame's time in its video."""
    latency_ms: Latency
    keypoints: list[KeypointRecord]
    crop_xywh: NotRequired[list[int]]
    """The crop the model saw, when its view has one."""
    crop_edge: NotRequired[list[str]]
    """The keypoints at the crop's edge (the arm may carry on past it)."""


def frame_record(frame: Frame, prediction: Prediction, schema: KeypointSchema) -> RecordedFrame:
    """The JSON record of one frame (keys in a stable order; coordinates in frame pixels).

    Args:
        frame: the frame read.
        prediction: its keypoints and stage times.
        schema: the keypoints' names.
    Returns:
        The record.
    """
    h, w = frame.image.shape[:2]
    t = prediction.times
    media = {"media_time_s": round(frame.media_time_s, 6)} if frame.media_time_s is not None else {}
    record: RecordedFrame = {"frame": frame.index, "timestamp": round(frame.timestamp, 6), "source": frame.name,
                             "width": w, "height": h, **media,
                             "latency_ms": {"preprocess": round(t.preprocess_ms, 3), "invoke": round(t.invoke_ms, 3),
                                            "postprocess": round(t.postprocess_ms, 3)},
                             "keypoints": prediction.records(schema)}
    if prediction.crop is not None:  # what the model saw, and the keypoints the arm may carry past it
        edge = prediction.at_crop_edge()
        record["crop_xywh"] = list(prediction.crop)
        record["crop_edge"] = [name for name, at_edge in zip(schema.keypoints, edge) if at_edge]
    return record


class RecordWriter:
    """Base of the per-frame record writers; a context manager. Subclasses implement `_line`.

    Each record is one line, written whole in one call and counted while SIGINT and SIGTERM are
    held back, so `count` always equals the lines in the file. A write that fails (a full disk)
    truncates the file back to its last complete record and raises UserError naming the path,
    the reason and the records kept. A file that `force` replaces is written beside it (`staging`) and
    renamed over it by `close` once it holds a complete record.
    """

    def __init__(self, path: str | os.PathLike, schema: KeypointSchema, force: bool = False):
        self.path = check_writable(path, force)
        self.schema = schema
        self.count = 0
        self._size = 0  # bytes of the complete records (and header) written so far
        try:
            self.staging = temporary_path(self.path) if force and self.path.exists() else None
            if self.staging is not None:
                set_default_permissions(self.staging)
            # "x": a file that appeared since the check is still not overwritten; unbuffered: one write per line
            self._fh = open(self.staging or self.path, "wb" if self.staging else "xb", buffering=0)
        except FileExistsError:
            raise UserError(f"{self.path}: already exists; pass --force to replace it") from None
        except OSError as exc:
            raise UserError(f"{self.path}: cannot be written ({os_error_reason(exc)})") from None

    def write(self, frame: Frame, prediction: Prediction) -> None:
        """Append one frame's record line and hand it to the operating system.

        Args:
            frame: the frame read (its index, time and file).
            prediction: its keypoints.
        Raises:
            UserError: the write failed (the file cut back to its last complete record).
        """
        self._write_line(self._line(frame_record(frame, prediction, self.schema)), counted=True)

    def _write_line(self, line: str, counted: bool) -> None:
        data = line.encode("utf-8", "backslashreplace")  # a file name that is not UTF-8: \udce9, still UTF-8 text
        with signals_deferred():
            try:
                view = memoryview(data)
                while view:  # a short write (a nearly full disk) continues where it stopped, or fails
                    view = view[self._fh.write(view):]
            except OSError as exc:
                self._fh.truncate(self._size)  # no partial line stays behind
                self._fh.seek(self._size)
                raise UserError(f"{self.path}: {os_error_reason(exc)} (kept its {self.count} complete "
                                "records)") from None
            self._size += len(data)
            self.count += counted

    def _line(self, record: RecordedFrame) -> str:
        raise NotImplementedError

    def close(self) -> None:
        """Close the file; one that holds a complete record is a completed output (named however the command ends).

        A replacing file (`staging`) is renamed over the earlier one only then; without a record it is dropped."""
        if not self._fh.closed:
            self._fh.close()
        if self.staging is not None:
            staging, self.staging = self.staging, None
            if self.count:
                with signals_deferred():
                    os.replace(staging, self.path)
            else:
                staging.unlink(missing_ok=True)
        if self.count:
            record_completed(self.path)

    def __enter__(self) -> "RecordWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class JsonlWriter(RecordWriter):
    """One JSON object per line (JSON Lines); a missing keypoint has x and y null."""

    def _line(self, record: RecordedFrame) -> str:
        return json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n"


class CsvWriter(RecordWriter):
    """A header, then one row per frame: frame facts, then `<name>_x, <name>_y, <name>_confidence` per keypoint.

    A missing keypoint has empty x and y cells.
    """

    BASE_COLUMNS = ("frame", "timestamp", "source", "width", "height", "media_time_s",
                    "preprocess_ms", "invoke_ms", "postprocess_ms")

    def __init__(self, path: str | os.PathLike, schema: KeypointSchema, force: bool = False):
        super().__init__(path, schema, force)
        self.columns = list(self.BASE_COLUMNS) + [f"{n}_{f}" for n in schema.keypoints
                                                  for f in ("x", "y", "confidence")]
        self._write_line(self._row(self.columns), counted=False)

    @staticmethod
    def _row(cells: Sequence[Any]) -> str:
        text = io.StringIO()
        csv.writer(text, lineterminator="\n").writerow(cells)
        return text.getvalue()

    def _line(self, record: RecordedFrame) -> str:
        row: list[Any] = [record["frame"], record["timestamp"], record["source"], record["width"],
                          record["height"], record.get("media_time_s", ""), record["latency_ms"]["preprocess"],
                          record["latency_ms"]["invoke"], record["latency_ms"]["postprocess"]]
        for kp in record["keypoints"]:
            row += ["" if kp[k] is None else kp[k] for k in ("x", "y", "confidence")]
        return self._row(row)


def record_format(path: str | os.PathLike) -> str:
    """The record format a file name asks for.

    Args:
        path: the output file.
    Returns:
        "jsonl" or "csv".
    Raises:
        UserError: another ending.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in RECORD_SUFFIXES:
        raise UserError(f"{path}: unknown keypoint file type {suffix or '(none)'!r}; use .jsonl or .csv")
    return RECORD_SUFFIXES[suffix]


def open_record_writer(path: str | os.PathLike, schema: KeypointSchema, force: bool = False) -> RecordWriter:
    """A JsonlWriter for .jsonl/.ndjson, a CsvWriter for .csv.

    Args:
        path: the output file.
        schema: the keypoints' names.
        force: an existing file may be replaced.
    Returns:
        The writer (a context manager).
    Raises:
        UserError: another ending, or a file that exists (without `force`) or cannot be written.
    """
    return (JsonlWriter if record_format(path) == "jsonl" else CsvWriter)(path, schema, force)


# -- overlay -----------------------------------------------------------------------------------------------

CROP_BOX_BGR = (160, 160, 160)
"""The overlay's outline of the crop a model read (grey: not a keypoint colour)."""


def draw_overlay(image: np.ndarray, prediction: Prediction, schema: KeypointSchema, fps: float | None = None,
                 labels: bool = True, copy: bool = True) -> np.ndarray:
    """Draw the skeleton, the keypoints (with names), the crop the model read (if any) and an FPS figure top-left on a
    BGR frame.

    Missing keypoints and the edges touching them are not drawn (`fcnpose_tf.draw`'s style and palette).

    Args:
        image: the BGR frame.
        prediction: its keypoints.
        schema: the keypoints' names and skeleton.
        fps: the figure to draw (None: none).
        labels: write the keypoints' names.
        copy: draw on a copy (False: on `image`).
    Returns:
        The frame drawn on.
    """
    out = draw_keypoints(image, prediction.keypoints, schema, labels=labels, copy=copy)
    h, w = out.shape[:2]
    scale = max(h, w) / 640.0
    thick = max(1, round(2 * scale))
    if prediction.crop is not None:  # the part of the frame the model saw: its workspace, or `--track`'s box
        x, y, cw, ch = prediction.crop
        cv2.rectangle(out, (x, y), (x + cw - 1, y + ch - 1), CROP_BOX_BGR, 1)
    if fps is not None and math.isfinite(fps):
        text = f"FPS {fps:.1f}"
        fs = 0.6 * max(scale, 0.75)
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, thick)
        cv2.rectangle(out, (0, 0), (tw + 12, th + base + 12), (0, 0, 0), -1)
        cv2.putText(out, text, (6, th + 6), cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 255, 0), thick, cv2.LINE_AA)
    return out


class RollingFps:
    """Frames per second averaged over the last `window` frames.

    `add(ms)` takes a frame's end-to-end model time (preprocess + invoke +
    postprocess, the FPS definition of docs/runtime.md); `fps` is
    window / sum of those times.

    Args:
        window: frames averaged over (at least 1).
    """

    def __init__(self, window: int = 30):
        self._ms: deque[float] = deque(maxlen=max(1, int(window)))
        self._sum = 0.0

    def add(self, ms: float) -> None:
        """Add one frame's end-to-end model time (ms); the oldest leaves a full window.

        Args:
            ms: the frame's time in milliseconds.
        """
        if len(self._ms) == self._ms.maxlen:
            self._sum -= self._ms[0]
        self._ms.append(ms)
        self._sum += ms

    @property
    def fps(self) -> float:
        """Frames in the window * 1000 / their summed ms; NaN before any frame."""
        return len(self._ms) * 1e3 / self._sum if self._sum > 0 else float("nan")


class VideoSink:
    """Writes BGR frames to a video (codec from the file ending), renamed into place on `close()`.

    The frame size is fixed by the first frame; later frames of another size
    (an image folder of mixed sizes) are resized to it. OpenCV does not report
    a failed write, so the folder is checked after each frame (`fileio.full_disk_error`,
    a statvfs call unless the disk looks full) and once more before the rename.
    """

    def __init__(self, path: str | os.PathLike, fps: float | None = None, force: bool = False):
        suffix = Path(path).suffix.lower()
        if suffix not in VIDEO_CODECS:
            raise UserError(f"{path}: unknown video type {suffix or '(none)'!r}; use "
                            + ", ".join(sorted(VIDEO_CODECS)))
        self.path = check_writable(path, force)
        self.force = force
        self.fps = float(fps) if fps and fps > 0 else 10.0
        self.codec = VIDEO_CODECS[suffix]
        self._tmp = temporary_path(self.path)  # removes this target's temporaries stranded by a killed run
        set_default_permissions(self._tmp)
        self._writer: cv2.VideoWriter | None = None
        self.size: tuple[int, int] | None = None
        self.count = 0

    def write(self, image: np.ndarray) -> None:
        """Append a frame, resized to the first frame's size when another.

        Args:
            image: H x W x 3 BGR uint8.
        Raises:
            WriteError: the disk is full (`PATH: no space left on device`; the partial file removed).
            UserError: OpenCV cannot write this codec here.
        """
        if self._writer is None:
            h, w = image.shape[:2]
            self.size = (w, h)
            with quiet_opencv():
                writer = cv2.VideoWriter(native_name(self._tmp), cv2.VideoWriter_fourcc(*self.codec), self.fps,
                                         self.size)
            if not writer.isOpened():
                with quiet_opencv():
                    writer.release()
                error = full_disk_error(self.path)  # the disk refusing data, or OpenCV lacking the codec
                self._tmp.unlink(missing_ok=True)
                if error is not None:
                    raise error
                raise UserError(f"{self.path}: OpenCV cannot write {self.codec} video here; try an .avi file")
            self._writer = writer
        if (image.shape[1], image.shape[0]) != self.size:
            image = cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
        with quiet_opencv(native=False):  # OpenCV's `Failed to write frame` warnings; the check below reports
            self._writer.write(np.ascontiguousarray(image))
        self.count += 1
        error = full_disk_error(self.path, quick=True)
        if error is not None:
            self.discard()
            raise error

    def close(self) -> Path | None:
        """Finish the file and move it into place.

        Returns:
            Its path, or None if no frame was written.
        Raises:
            WriteError: the end of the file did not fit on the disk (no partial video is left in place).
            UserError: a file appeared at the path during the run (without force): the video is kept beside it.
        """
        self._release()
        if not self._tmp.exists():
            return None
        if self.count == 0:
            self._tmp.unlink()
            return None
        error = full_disk_error(self.path)  # the end of the file may not have fit: no broken video in place
        if error is not None:
            self._tmp.unlink(missing_ok=True)
            raise error
        if self.path.exists() and not self.force:  # appeared while we were recording: keep both
            kept = _unused_name(self.path)
            os.replace(self._tmp, kept)
            record_completed(kept)
            raise UserError(f"{self.path}: appeared during the run; the video was kept as {kept}")
        os.replace(self._tmp, self.path)
        record_completed(self.path)
        return self.path

    def discard(self) -> None:
        """Drop the partial video (on a failed run)."""
        self._release()
        self._tmp.unlink(missing_ok=True)

    def _release(self) -> None:
        if self._writer is not None:
            with quiet_opencv():
                self._writer.release()
            self._writer = None


def _unused_name(path: Path) -> Path:
    """NAME-1.EXT, NAME-2.EXT, ...: the first that does not exist (a name no stale-temporary sweep touches)."""
    n = 1
    while path.with_name(f"{path.stem}-{n}{path.suffix}").exists():
        n += 1
    return path.with_name(f"{path.stem}-{n}{path.suffix}")


def parse_outputs(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """Check record-output names (known ending, no duplicates) before anything runs.

    Args:
        paths: the --out values.
    Returns:
        The paths.
    Raises:
        UserError: an unknown ending or a file given twice.
    """
    seen: set[Path] = set()
    out = []
    for p in paths:
        path = Path(p)
        record_format(path)
        key = path.resolve()
        if key in seen:
            raise UserError(f"{path}: given twice as an output")
        seen.add(key)
        out.append(path)
    return out


__all__ = ["RecordWriter", "JsonlWriter", "CsvWriter", "open_record_writer", "record_format", "frame_record",
           "draw_overlay", "RollingFps", "VideoSink", "parse_outputs", "RECORD_SUFFIXES",
           "VIDEO_CODECS"]
