"""Frame sources: a camera (index, /dev/videoN, stream URL, Picamera2), a video file, an image folder or an image.

`open_source(spec)` picks the kind from the spec. Every source yields `Frame`s
and ends cleanly: the end of a video, a camera that stops delivering, an
unreadable image (skipped with a message). Cameras are read in their own
thread that keeps only the newest frame, so grabbing overlaps inference and a
slow model processes fresh frames instead of a growing backlog; frames that
were overwritten before being used are counted as `dropped`.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable, Iterator

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import native_name, special_file_kind
from fcnpose_tf.nativelog import NativeOutput, native_stderr_captured
from fcnpose_tf.preprocess import read_image

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
    """Base class: iterate for frames; `end_reason` says why iteration stopped; use as a context manager.

    Args:
        name: what the source is called in lines and records (a path, a camera's index).
        warn: where warnings go (default: standard error).
    """

    kind: str = "source"
    live: bool = False
    """A camera or stream: frames are captured as they happen (timestamps are capture times)."""

    def __init__(self, name: str, warn: Warn | None = None):
        self.name = name
        self.warn: Warn = warn or _stderr
        self.fps: float | None = None  # nominal frame rate, if the source has one
        self.skipped = 0  # unreadable frames/images passed over
        self.dropped = 0  # camera frames replaced by newer ones before use
        self.end_reason = "not started"
        self.failed = False  # a live source whose device failed or went silent ended the frames (not a stop)

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file; safe to call twice."""

    def frame_waiting(self) -> bool:
        """Whether the next read returns without waiting for a frame to be captured: always, but for a live source
        (`LiveSource`), whose next frame may not exist yet."""
        return True

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        """One line for the run's summary: the kind of source and its name.

        Returns:
            The line.
        """
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
            image = read_image(path)
            if image is None:
                self.skipped += 1
                self.warn(f"skipped {path}: not a readable image")
                continue
            yield Frame(i, np.ascontiguousarray(image), time.time(), str(path))
        unreadable = f", {self.skipped} unreadable" if self.skipped else ""
        self.end_reason = f"end of the images ({len(self.paths) - self.skipped} read{unreadable})"

    def describe(self) -> str:
        """One line for the run's summary: "N images from NAME".

        Returns:
            The line.
        """
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
            self._cap = cv2.VideoCapture(native_name(path), cv2.CAP_ANY, self.DECODE_PARAMS)
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

    MAX_UNREADABLE_IN_A_ROW = 10
    """Unreadable frames in a row after which a video with frames left (by its header) is taken to end there: a
    damaged frame is skipped, a truncated file ends."""

    def __iter__(self) -> Iterator[Frame]:
        self.end_reason = "running"
        self.decoder_messages, self.damaged_frames = [], 0
        index = 0
        unreadable = 0  # frames in a row that could not be read, from index - unreadable
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
                    unreadable += 1
                    if self.frame_count is None or index + 1 >= self.frame_count \
                            or unreadable >= self.MAX_UNREADABLE_IN_A_ROW:
                        index -= unreadable - 1  # the frames after the last one read were not there to skip
                        break
                    index += 1  # a damaged frame: the next may read (it keeps its own number)
                    continue
                if unreadable:
                    first = index - unreadable
                    self.skipped += unreadable
                    self.warn(f"{self.path}: frame{f's {first}-{index - 1}' if unreadable > 1 else f' {first}'} "
                              "cannot be read: skipped")
                    unreadable = 0
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
        """Release the file (and the decoder's message capture)."""
        self._cap.release()
        if self._native_sink is not None:
            self._native_sink.close()
            self._native_sink = None

    def describe(self) -> str:
        """One line for the run's summary: "video NAME (N frames, F fps)".

        Returns:
            The line.
        """
        n = f"{self.frame_count} frames" if self.frame_count else "unknown length"
        rate = f", {self.fps:g} fps" if self.fps else ""
        return f"video {self.name} ({n}{rate})"


class CaptureError(Exception):
    """A live source's device failed for good (the message says how); ends the run."""


class LiveSource(FrameSource):
    """A live source read by a background thread that keeps only the newest frame.

    A subclass opens its device, implements `_read` (one frame, or None when none came this
    time) and `_release`, and calls `_start_grabbing()` last in its constructor. Reads that
    return None for longer than `stall_timeout_s` end the run ("stopped delivering frames");
    a read that raises `CaptureError` ends it at once with that message.
    """

    kind = "camera"
    live = True

    def __init__(self, name: str, warn: Warn | None = None, first_frame_timeout_s: float = 10.0,
                 stall_timeout_s: float = 5.0):
        super().__init__(name, warn)
        self.first_frame_timeout_s = first_frame_timeout_s
        self.stall_timeout_s = stall_timeout_s
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, float] | None = None
        self._captured = 0  # frames grabbed by the thread
        self._used = 0  # frames the consumer has taken (the newest at each take)
        self._failure: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab-{self.name}", daemon=True)

    def _read(self) -> np.ndarray | None:
        """One frame from the device, or None if none came this time; CaptureError if the device failed."""
        raise NotImplementedError

    def _release(self) -> None:
        """Close the device (called once the grab thread has stopped or given up)."""

    def _interrupt(self) -> None:
        """Make a read that is waiting for a frame return (called by close() before it joins the thread)."""

    def _start_grabbing(self) -> None:
        self._thread.start()

    def _grab_loop(self) -> None:
        failed_since = None
        while not self._stop.is_set():
            try:
                image = self._read()
            except CaptureError as exc:
                if self._stop.is_set():  # the read was cut short by close()
                    break
                with self._cond:
                    self._failure = str(exc)
                    self._cond.notify_all()
                return
            now = time.time()
            if image is None:
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

    def frame_waiting(self) -> bool:
        """Whether the next read returns at once: a frame newer than the last one taken, or the source's end."""
        with self._cond:
            return self._captured > self._used or self._failure is not None

    def __iter__(self) -> Iterator[Frame]:
        self.end_reason = "running"
        used = self._used = 0
        while True:
            # Twice the grab thread's limit: its own verdict (reads failing) comes first; this one
            # catches a read that blocks forever (some USB cameras when unplugged).
            timeout = self.first_frame_timeout_s if used == 0 else 2 * self.stall_timeout_s
            with self._cond:
                arrived = self._cond.wait_for(lambda: self._captured > used or self._failure is not None, timeout)
                if self._captured > used:
                    self.dropped += self._captured - used - 1
                    used = self._used = self._captured
                    image, stamp = self._latest
                    self._latest = None  # the consumer owns this buffer now
                elif self._failure is not None:
                    self.end_reason = self._failure
                    if self._failure != "stopped":
                        self.failed = True
                        self.warn(self._failure)
                    return
                elif not arrived:
                    self.end_reason = (f"{self.name} sent no frame within {timeout:g} s"
                                       + (" of opening" if used == 0 else " (disconnected?)"))
                    self.failed = True
                    self.warn(self.end_reason)
                    return
            yield Frame(used - 1, _as_bgr(image), stamp, self.name)

    def close(self) -> None:
        """Stop the capture thread (a waiting read interrupted, the thread joined for up to 2 s) and release the
        device."""
        self._stop.set()
        if self._thread.is_alive():
            self._interrupt()
            self._thread.join(timeout=2.0)
        self._release()


URL_SPEC = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*://")
"""A stream URL (rtsp://, http://, tcp://...): opened by OpenCV's FFmpeg like a camera."""


class CameraSource(LiveSource):
    """A camera or stream that OpenCV opens (index, /dev/videoN, URL), read by LiveSource's thread.

    Args:
        device: a camera index, a /dev/videoN path or a stream URL (rtsp://, http://, tcp://).
        size: requested (width, height); the camera may choose another.
        first_frame_timeout_s: give up if the camera sends nothing for this long after opening.
        stall_timeout_s: end the run if no new frame arrives for this long (camera unplugged).
    """

    def __init__(self, device: int | str, size: tuple[int, int] | None = None, warn: Warn | None = None,
                 first_frame_timeout_s: float = 10.0, stall_timeout_s: float = 5.0):
        super().__init__(f"camera {device}" if isinstance(device, int) else str(device), warn,
                         first_frame_timeout_s, stall_timeout_s)
        self.device = device
        url = isinstance(device, str) and URL_SPEC.match(device) is not None
        # a stream's server that accepts and sends nothing would hold FFmpeg's open (and Ctrl-C) for 30 s
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, round(first_frame_timeout_s * 1e3),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, round(stall_timeout_s * 1e3)] \
            if url and hasattr(cv2, "CAP_PROP_OPEN_TIMEOUT_MSEC") else []
        with quiet_opencv():
            self._cap = cv2.VideoCapture(device, cv2.CAP_ANY, params) if params else cv2.VideoCapture(device)
        if not self._cap.isOpened():
            self._cap.release()
            raise UserError(f"{self.name}: cannot be opened " + (
                f"(no stream there within {first_frame_timeout_s:g} s: is its server running, e.g. `rpicam-vid "
                "--listen`, at that address and port?)" if url else "(not connected, in use by another program, or "
                "no permission; list cameras with `v4l2-ctl --list-devices`)"))
        if size is not None:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        self._cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # where supported (V4L2): no driver-side backlog either
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 0 < fps < 1000 else None
        self._start_grabbing()

    def _read(self) -> np.ndarray | None:
        try:
            ok, image = self._cap.read()
        except cv2.error:
            return None
        return image if ok and image is not None else None

    def _release(self) -> None:
        self._cap.release()


PICAMERA2_SPEC = re.compile(r"picamera2(?::(\d+))?")
"""`--source picamera2` or `picamera2:N` (camera number N, as `rpicam-hello --list-cameras` numbers them)."""

PICAMERA2_DEFAULT_SIZE = (640, 480)

PICAMERA2_INSTALL = ("on Raspberry Pi OS: `sudo apt install -y python3-picamera2`, a venv made with "
                     "`python3 -m venv --system-site-packages`, and `pip install 'fcnpose-tf[pi-camera]'` in it "
                     "(docs/raspberry-pi.md, Raspberry Pi Camera Module)")

_NUMPY_ABI_ERROR = re.compile(r"numpy\.(dtype|ndarray) size changed|compiled using NumPy \d|"
                              r"numpy\.core\.multiarray failed to import|_ARRAY_API not found|"
                              r"compiled against (ABI|API) version", re.IGNORECASE)
"""What importing a compiled extension built for the other numpy major version raises (or prints)."""


def _one_line(exc: BaseException, limit: int = 160) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def import_picamera2():
    """The `Picamera2` class, imported on first use.

    Tells apart: no picamera2 at all, picamera2 without libcamera's Python bindings (a pip
    install in a venv that does not see the system packages), and the numpy trap: apt's
    picamera2 pulls in compiled modules (simplejpeg) built for Debian's numpy 1.x, which fail
    to import under numpy 2 (and the other way round). What numpy prints while failing is kept
    off the terminal; the one error line says what to do.

    Returns:
        The class.
    Raises:
        UserError: picamera2 cannot be imported, with the fix.
    """
    printed = io.StringIO()
    try:
        with contextlib.redirect_stderr(printed):
            from picamera2 import Picamera2
    except Exception as exc:  # noqa: BLE001 - every import failure becomes one line with the fix
        missing = exc.name if isinstance(exc, ModuleNotFoundError) else None
        if missing == "picamera2":
            raise UserError(f"--source picamera2 needs the picamera2 package, which {sys.executable} cannot "
                            f"import: {PICAMERA2_INSTALL}") from None
        if missing is not None and missing.split(".")[0] in ("libcamera", "pykms", "kms"):
            raise UserError(f"--source picamera2: picamera2 is installed but libcamera's Python bindings "
                            f"({missing}) are not visible to {sys.executable}; {PICAMERA2_INSTALL}") from None
        if _NUMPY_ABI_ERROR.search(f"{exc}\n{printed.getvalue()}"):
            import numpy

            frames = traceback.extract_tb(exc.__traceback__)
            where = f" (in {frames[-1].filename})" if frames else ""
            if int(numpy.__version__.split(".")[0]) >= 2:
                fix = ("apt's python3-picamera2 and its simplejpeg are built for Debian's numpy 1.x: install "
                       "numpy < 2 into the venv with `pip install 'fcnpose-tf[pi-camera]'`")
            else:
                fix = ("a module built for numpy 2 shadows apt's: `pip uninstall simplejpeg picamera2` in the "
                       "venv, so the apt packages (built for numpy 1.x) are used")
            raise UserError(f"--source picamera2: picamera2 cannot be imported with numpy {numpy.__version__} "
                            f"in this environment: a compiled module was built for another numpy{where}: "
                            f"{_one_line(exc, 100)}; {fix} (docs/raspberry-pi.md, Raspberry Pi Camera "
                            "Module)") from None
        raise UserError(f"--source picamera2: picamera2 cannot be imported ({type(exc).__name__}: "
                        f"{_one_line(exc)}); {PICAMERA2_INSTALL}") from None
    return Picamera2


class Picamera2Source(LiveSource):
    """The Raspberry Pi camera module through Picamera2 (libcamera), read by LiveSource's thread.

    The camera runs a video configuration whose main stream is "RGB888" at `size` (default
    640x480). Picamera2 names formats as libcamera/DRM do, so "RGB888" delivers B, G, R bytes per
    pixel: OpenCV's BGR, no conversion. `capture_array` waits for the next completed frame; an
    exception from it (the camera failed) ends the run with its message.

    Args:
        camera_num: the camera's number (`rpicam-hello --list-cameras`).
        size: (width, height) of the frames.
        first_frame_timeout_s, stall_timeout_s: as for CameraSource.
    """

    kind = "picamera2"

    def __init__(self, camera_num: int = 0, size: tuple[int, int] | None = None, warn: Warn | None = None,
                 first_frame_timeout_s: float = 10.0, stall_timeout_s: float = 5.0):
        super().__init__(f"picamera2 camera {camera_num}", warn, first_frame_timeout_s, stall_timeout_s)
        picamera2_class = import_picamera2()
        self.camera_num = camera_num
        self.size = tuple(size or PICAMERA2_DEFAULT_SIZE)
        try:
            self._camera = picamera2_class(camera_num)
        except (RuntimeError, OSError, IndexError) as exc:  # Picamera2's own: "Camera __init__ sequence ..."
            raise UserError(f"{self.name}: cannot be opened ({_one_line(exc)}); is it connected, enabled and "
                            "not in use by another program? list cameras with `rpicam-hello --list-cameras`"
                            ) from None
        try:
            config = self._camera.create_video_configuration(main={"size": self.size, "format": "RGB888"})
            self._camera.configure(config)
            self._camera.start()
        except Exception as exc:  # noqa: BLE001 - libcamera refusing the mode: one line, camera released
            self._release()
            raise UserError(f"{self.name}: cannot be started at {self.size[0]}x{self.size[1]} "
                            f"({_one_line(exc)})") from None
        limits = (config.get("controls") or {}).get("FrameDurationLimits") if isinstance(config, dict) else None
        if limits and limits[0] > 0:  # microseconds per frame
            self.fps = 1e6 / float(limits[0])
        self._start_grabbing()

    def _read(self) -> np.ndarray | None:
        try:
            return self._camera.capture_array("main")
        except Exception as exc:  # noqa: BLE001 - whatever libcamera raised: the camera is gone
            raise CaptureError(f"{self.name} failed: {_one_line(exc)}") from None

    def _interrupt(self) -> None:
        try:
            self._camera.stop()  # Picamera2 cancels the capture a stopped camera would never complete
        except Exception:  # noqa: BLE001 - _release tries again and closes
            pass

    def _release(self) -> None:
        for step in (self._camera.stop, self._camera.close):  # both safe to call twice in Picamera2
            try:
                step()
            except Exception:  # noqa: BLE001 - closing a failed camera must not hide why it failed
                pass

    def describe(self) -> str:
        """One line for the run's summary: the camera, its size and pixel format.

        Returns:
            The line.
        """
        return f"{self.name} ({self.size[0]}x{self.size[1]} RGB888 = BGR bytes)"


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
    error to quote or a summary to count.

    Args:
        native: also capture what native libraries print on stderr (False: OpenCV's log level only, the
            cheapest).
        sink: a reused capture file (see `native_stderr_captured`), cheap enough for every frame.
    Yields:
        What the native libraries printed, once the block ends.
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
    """Image files directly in `folder`, sorted by name (natural order: frame2 before frame10).

    Args:
        folder: the folder.
    Returns:
        The image paths.
    """
    def natural(p: Path):
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]

    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural)


def parse_size(text: str) -> tuple[int, int]:
    """`640x480` -> (640, 480).

    Args:
        text: WIDTHxHEIGHT.
    Returns:
        (width, height).
    Raises:
        UserError: another text.
    """
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not match or int(match.group(1)) < 1 or int(match.group(2)) < 1:
        raise UserError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    return int(match.group(1)), int(match.group(2))


def open_source(spec: str | int | os.PathLike, camera_size: tuple[int, int] | None = None,
                warn: Warn | None = None, refuse_cameras: str | None = None, flag: str = "--source") -> FrameSource:
    """Open a frame source from a command-line spec.

    `0`, `1`, ... -> camera index; `/dev/videoN` -> that camera; `rtsp://...`/`http://...` -> a stream
    (read like a camera); `picamera2` / `picamera2:N` -> the Raspberry Pi camera module through
    Picamera2; an existing folder -> its images; an existing image file -> that image; any other
    existing file -> a video.

    Args:
        spec: the --source value.
        camera_size: (width, height) to ask a camera for (None: its default).
        warn: where a source's warnings go (default: stderr).
        refuse_cameras: with it (the reason, for the error) only files are accepted: a camera spec is refused before
            anything is opened.
        flag: the option the spec was given with, for the errors.
    Returns:
        The source.
    Raises:
        UserError: nothing at that path, a camera that cannot be opened (or is not accepted), an
            unreadable video or image, a folder without images, picamera2 missing or unimportable.
    """
    text = os.fspath(spec) if not isinstance(spec, int) else str(spec)
    if not text.strip():  # an empty shell variable: not the current folder's images
        raise UserError(f"{flag} is empty: give a camera index, picamera2, a video, an image folder or an image")
    picamera2 = PICAMERA2_SPEC.fullmatch(text)
    index = isinstance(spec, int) or text.strip().isdigit()
    url = URL_SPEC.match(text) is not None
    if refuse_cameras and (picamera2 or text.startswith("picamera2:") or index or url or text.startswith("/dev/")):
        raise UserError(f"{flag} {text}: {refuse_cameras}")
    if picamera2:
        return Picamera2Source(int(picamera2.group(1) or 0), camera_size, warn)
    if text.startswith("picamera2:"):
        raise UserError(f"--source {text}: expected picamera2 or picamera2:N (N = camera number, e.g. picamera2:1)")
    if index:
        return CameraSource(int(text), camera_size, warn)
    if url:
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
        expected = "a video file" if refuse_cameras else "a camera index, /dev/videoN, picamera2, a video file"
        raise UserError(f"{path}: no such file or folder (expected {expected}, an image folder or an image)")
    kind = special_file_kind(path)
    if kind is not None:
        raise UserError(f"{path}: is {kind}, not a video or image file (a stream is read from a camera or a URL)")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        if read_image(path) is None:
            raise UserError(f"{path}: cannot be read as an image")
        return ImageSource([path], str(path), warn)
    return VideoSource(path, warn)
