"""Frame sources: a camera (index, /dev/videoN or stream URL), a video file, an image folder or one image.

`open_source(spec)` picks the kind from the spec. Every source yields `Frame`s
and ends cleanly: the end of a video, a camera that stops delivering, an
unreadable image (skipped with a message). Cameras are read in their own
thread that keeps only the newest frame, so grabbing overlaps inference and a
slow model processes fresh frames instead of a growing backlog; frames that
were overwritten before being used are counted as `dropped`.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable, Iterator

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.nativelog import NativeOutput, native_stderr_captured

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".pbm"})
"""File name endings read as still images (anything else that exists is tried as a video)."""

Warn = Callable[[str], None]


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Frame:
    """One frame: its index in the source, BGR uint8 pixels, capture time and origin.

    `index` is the frame's position in the video / image list, or the camera's
    capture counter (gaps are dropped stale frames). `timestamp` is Unix time in
    seconds when the frame was captured or read; `media_time_s` is the position
    in a video file (None for other sources). `name` is the image's path for
    image sources, else the source's name.
    """

    index: int
    image: np.ndarray
    timestamp: float
    name: str
    media_time_s: float | None = None


class FrameSource:
    """Base class: iterate for frames; `end_reason` says why iteration stopped; use as a context manager."""

    kind: str = "source"

    def __init__(self, name: str, warn: Warn | None = None):
        self.name = name
        self.warn: Warn = warn or _stderr
        self.fps: float | None = None  # nominal frame rate, if the source has one
        self.skipped = 0  # unreadable frames/images passed over
        self.dropped = 0  # camera frames replaced by newer ones before use
        self.end_reason = "not started"

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file; safe to call twice."""

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        return f"{self.kind} {self.name}"


class ImageSource(FrameSource):
    """Still images, in the given order; unreadable ones are skipped with a message."""

    kind = "images"

    def __init__(self, paths: list[Path], name: str, warn: Warn | None = None):
        super().__init__(name, warn)
        self.paths = list(paths)

    def __iter__(self) -> Iterator[Frame]:
        self.end_reason = "running"
        for i, path in enumerate(self.paths):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                self.skipped += 1
                self.warn(f"skipped {path}: not a readable image")
                continue
            yield Frame(i, np.ascontiguousarray(image), time.time(), str(path))
        self.end_reason = f"read {len(self.paths) - self.skipped} of {len(self.paths)} images"

    def describe(self) -> str:
        return f"{len(self.paths)} image{'s' if len(self.paths) != 1 else ''} from {self.name}"


class VideoSource(FrameSource):
    """A video file, decoded frame by frame; ends at the last readable frame and says if that was early.

    What FFmpeg prints while decoding a damaged file (`[mpeg4 @ 0x...] ac-tex damaged at 2 5`, often
    several lines per frame) is captured per frame and summarised in one warning when reading ends.
    The file is decoded on one thread (DECODE_PARAMS): FFmpeg's own decoding threads print whenever
    they get to a frame, outside the read being captured, and would compete with the model's threads.
    """

    DECODE_PARAMS = [cv2.CAP_PROP_N_THREADS, 1] if hasattr(cv2, "CAP_PROP_N_THREADS") else []  # OpenCV >= 4.6

    kind = "video"

    def __init__(self, path: Path, warn: Warn | None = None):
        super().__init__(str(path), warn)
        self.path = path
        self.decoder_messages: list[str] = []  # FFmpeg's lines while frames were read
        self.damaged_frames = 0  # reads during which FFmpeg printed something
        with quiet_opencv() as native:
            self._cap = cv2.VideoCapture(str(path), cv2.CAP_ANY, self.DECODE_PARAMS)
        if not self._cap.isOpened():
            self._cap.release()
            detail = f": {native.last_line()}" if native.last_line() else ""
            raise UserError(f"{path}: cannot be opened as a video (unknown format or corrupt file{detail})")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 0 < fps < 1000 else None
        count = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.frame_count = int(count) if count and count > 0 else None
        try:
            self._native_sink: IO[bytes] | None = tempfile.TemporaryFile()  # reused for every frame's capture
        except OSError:
            self._native_sink = None

    def __iter__(self) -> Iterator[Frame]:
        self.end_reason = "running"
        self.decoder_messages, self.damaged_frames = [], 0
        index = 0
        try:
            while True:
                with quiet_opencv(sink=self._native_sink) as native:
                    try:
                        ok, image = self._cap.read()
                    except cv2.error as exc:  # a decoder failure on a damaged file
                        ok, image, failure = False, None, " ".join(str(exc).split())[:120]
                    else:
                        failure = None
                lines = native.lines()
                if lines:
                    self.decoder_messages += lines
                    self.damaged_frames += 1
                if failure is not None:
                    self.warn(f"{self.path}: frame {index} cannot be decoded ({failure})")
                if not ok or image is None:
                    break
                media = self._cap.get(cv2.CAP_PROP_POS_MSEC)
                yield Frame(index, _as_bgr(image), time.time(), self.name, media / 1e3 if media >= 0 else None)
                index += 1
        finally:  # also when the reader stops early (--max-frames, Ctrl-C)
            self._summarise_decoder_messages()
        if self.frame_count is not None and index < self.frame_count:
            self.end_reason = (f"video ended after {index} of {self.frame_count} frames "
                               "(truncated file or unreadable frame)")
            self.warn(f"{self.path}: {self.end_reason}")
        else:
            self.end_reason = f"end of video ({index} frames)"

    def _summarise_decoder_messages(self) -> None:
        """One warning for what FFmpeg printed while decoding (nothing if it printed nothing)."""
        if self.decoder_messages:
            count = len(self.decoder_messages)
            self.warn(f"{self.path}: FFmpeg reported {count} decoding problem{'s' if count != 1 else ''} in "
                      f"{self.damaged_frames} frame{'s' if self.damaged_frames != 1 else ''} (damaged file?); "
                      f"the last: {self.decoder_messages[-1]}")

    def close(self) -> None:
        self._cap.release()
        if self._native_sink is not None:
            self._native_sink.close()
            self._native_sink = None

    def describe(self) -> str:
        n = f"{self.frame_count} frames" if self.frame_count else "unknown length"
        rate = f", {self.fps:g} fps" if self.fps else ""
        return f"video {self.name} ({n}{rate})"


class CameraSource(FrameSource):
    """A live camera read by a background thread that keeps only the newest frame.

    Args:
        device: a camera index, a /dev/videoN path or a stream URL (rtsp://, http://).
        size: requested (width, height); the camera may choose another.
        first_frame_timeout_s: give up if the camera sends nothing for this long after opening.
        stall_timeout_s: end the run if no new frame arrives for this long (camera unplugged).
    """

    kind = "camera"

    def __init__(self, device: int | str, size: tuple[int, int] | None = None, warn: Warn | None = None,
                 first_frame_timeout_s: float = 10.0, stall_timeout_s: float = 5.0):
        super().__init__(f"camera {device}" if isinstance(device, int) else str(device), warn)
        self.device = device
        self.first_frame_timeout_s = first_frame_timeout_s
        self.stall_timeout_s = stall_timeout_s
        with quiet_opencv():
            self._cap = cv2.VideoCapture(device)
        if not self._cap.isOpened():
            self._cap.release()
            raise UserError(f"{self.name}: cannot be opened (not connected, in use by another program, "
                            "or no permission; list cameras with `v4l2-ctl --list-devices`)")
        if size is not None:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        self._cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # where supported (V4L2): no driver-side backlog either
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 0 < fps < 1000 else None
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, float] | None = None
        self._captured = 0  # frames grabbed by the thread
        self._failure: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab-{self.name}", daemon=True)
        self._thread.start()

    def _grab_loop(self) -> None:
        failed_since = None
        while not self._stop.is_set():
            try:
                ok, image = self._cap.read()
            except cv2.error:
                ok, image = False, None
            now = time.time()
            if not ok or image is None:
                failed_since = failed_since or now
                if now - failed_since > self.stall_timeout_s:
                    with self._cond:
                        self._failure = f"{self.name} stopped delivering frames (disconnected?)"
                        self._cond.notify_all()
                    return
                time.sleep(0.01)
                continue
            failed_since = None
            with self._cond:
                self._latest = (image, now)
                self._captured += 1
                self._cond.notify_all()
        with self._cond:
            self._failure = self._failure or "stopped"
            self._cond.notify_all()

    def __iter__(self) -> Iterator[Frame]:
        self.end_reason = "running"
        used = 0
        while True:
            # Twice the grab thread's limit: its own verdict (reads failing) comes first; this one
            # catches a read() that blocks forever (some USB cameras when unplugged).
            timeout = self.first_frame_timeout_s if used == 0 else 2 * self.stall_timeout_s
            with self._cond:
                arrived = self._cond.wait_for(lambda: self._captured > used or self._failure is not None, timeout)
                if self._captured > used:
                    self.dropped += self._captured - used - 1
                    used = self._captured
                    image, stamp = self._latest
                    self._latest = None  # the consumer owns this buffer now
                elif self._failure is not None:
                    self.end_reason = self._failure
                    if self._failure != "stopped":
                        self.warn(self._failure)
                    return
                elif not arrived:
                    self.end_reason = (f"{self.name} sent no frame within {timeout:g} s"
                                       + (" of opening" if used == 0 else " (disconnected?)"))
                    self.warn(self.end_reason)
                    return
            yield Frame(used - 1, _as_bgr(image), stamp, self.name)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._cap.release()


def _as_bgr(image: np.ndarray) -> np.ndarray:
    """C-contiguous 3-channel BGR (grey or BGRA frames from some cameras/codecs converted)."""
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(image)


@contextlib.contextmanager
def quiet_opencv(native: bool = True, sink: IO[bytes] | None = None) -> Iterator[NativeOutput]:
    """Silence OpenCV's own warnings (e.g. `can't open camera by index`) and, with `native`, what FFmpeg prints.

    We report failures ourselves, in one line; FFmpeg's text is in the yielded NativeOutput for an
    error to quote or a summary to count. `native=False` (OpenCV's log level only) is the cheapest;
    a reused `sink` (see `native_stderr_captured`) makes the capture cheap enough for every frame.
    """
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    with contextlib.ExitStack() as stack:
        output = stack.enter_context(native_stderr_captured(sink)) if native else NativeOutput()
        if logging is not None:
            previous = logging.getLogLevel()
            logging.setLogLevel(logging.LOG_LEVEL_SILENT)
            stack.callback(logging.setLogLevel, previous)
        yield output


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, sorted by name (natural order: frame2 before frame10)."""
    def natural(p: Path):
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]

    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural)


def parse_size(text: str) -> tuple[int, int]:
    """`640x480` -> (640, 480); UserError otherwise."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not match or int(match.group(1)) < 1 or int(match.group(2)) < 1:
        raise UserError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    return int(match.group(1)), int(match.group(2))


def open_source(spec: str | int | os.PathLike, camera_size: tuple[int, int] | None = None,
                warn: Warn | None = None) -> FrameSource:
    """Open a frame source from a command-line spec.

    `0`, `1`, ... -> camera index; `/dev/videoN` -> that camera; `rtsp://...`/`http://...` -> a stream
    (read like a camera); an existing folder -> its images; an existing image file -> that image;
    any other existing file -> a video.

    Raises:
        UserError: nothing at that path, a camera that cannot be opened, an unreadable video or image,
            a folder without images.
    """
    text = os.fspath(spec) if not isinstance(spec, int) else str(spec)
    if isinstance(spec, int) or text.strip().isdigit():
        return CameraSource(int(text), camera_size, warn)
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", text):
        return CameraSource(text, camera_size, warn)
    path = Path(text).expanduser()
    if text.startswith("/dev/"):
        if not path.exists():
            raise UserError(f"{text}: no such camera device (see `ls /dev/video*`)")
        return CameraSource(str(path), camera_size, warn)
    if path.is_dir():
        images = list_images(path)
        if not images:
            raise UserError(f"{path}: folder has no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        return ImageSource(images, str(path), warn)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder (expected a camera index, /dev/videoN, "
                        "a video file, an image folder or an image)")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        if cv2.imread(str(path), cv2.IMREAD_COLOR) is None:
            raise UserError(f"{path}: cannot be read as an image")
        return ImageSource([path], str(path), warn)
    return VideoSource(path, warn)
