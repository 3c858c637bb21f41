"""A stand-in for Picamera2 (raspberrypi/picamera2) on machines without a camera: the calls fcnpose-tf uses.

Semantics follow the library (picamera2/picamera2.py and its manual):

* `Picamera2(camera_num=0)` acquires camera `camera_num`; a number with no camera behind it, or a
  camera another Picamera2 holds, raises RuntimeError("Camera __init__ sequence did not complete.").
* `create_video_configuration(main={...})` returns a plain dict: use_case "video", the main stream
  (default format "XBGR8888", size (1280, 720)) updated with `main`, 6 buffers, and controls with
  FrameDurationLimits (33333, 33333) us, i.e. 30 fps.
* `configure(config)` refuses while started; `start()` refuses before `configure`.
* `capture_array("main")` waits for the next frame the sensor completes (it runs at the configured
  rate whether or not anyone reads; frames nobody waited for are gone) and returns it as an array:
  "RGB888" -> (h, w, 3) with B, G, R bytes per pixel; "BGR888" -> R, G, B; "XBGR8888" -> (h, w, 4)
  R, G, B, 255; "XRGB8888" -> B, G, R, 255 (Picamera2's table of pixel formats).
* `stop()` cancels a capture that is waiting (it raises CancelledError); `stop()` and `close()` may
  be called more than once; `close()` stops and releases the camera.

What the camera sees and how it fails is set by the environment variable PICAMERA2_STANDIN (JSON)
or, in-process, the dict `STANDIN`: `cameras` (attached, default 1), `scene` (path of an image file,
true colours, resized to the stream size; default mid-grey), `fps` (overrides the configured rate),
`fail_after` (capture_array raises RuntimeError after this many frames), `hang_after` (capture_array
never returns after this many frames), `log` (a file that gets one line per call: open, configure,
start, stop, close).
"""

from __future__ import annotations

import json
import os
import threading
import time

import cv2
import numpy as np
import simplejpeg  # noqa: F401 - as the real package does at import (its JPEG encoder); see simplejpeg's stand-in

STANDIN: dict = json.loads(os.environ.get("PICAMERA2_STANDIN", "{}"))
OPENED: list["Picamera2"] = []  # every camera made, for tests to inspect
_held: set[int] = set()
_lock = threading.Lock()

_CHANNELS = {"RGB888": (2, 1, 0), "BGR888": (0, 1, 2), "XBGR8888": (0, 1, 2), "XRGB8888": (2, 1, 0)}
"""Per format: which true-colour channel (0 = R, 1 = G, 2 = B) fills byte 0, 1, 2 of a pixel."""


def _log(line: str) -> None:
    if STANDIN.get("log"):
        with open(STANDIN["log"], "a") as fh:
            fh.write(line + "\n")


class CancelledError(Exception):
    """Raised to a caller whose capture was cancelled by stop() (picamera2.CancelledError)."""


class Picamera2:
    def __init__(self, camera_num: int = 0, tuning=None):
        with _lock:
            if not 0 <= camera_num < int(STANDIN.get("cameras", 1)) or camera_num in _held:
                raise RuntimeError("Camera __init__ sequence did not complete.")
            _held.add(camera_num)
        self.camera_idx = camera_num
        self.camera_config = None
        self.started = False
        self.is_open = True
        self.frames = 0  # frames handed out by capture_array
        self._start_time = 0.0
        self._last_frame = -1
        OPENED.append(self)
        _log(f"open {camera_num}")

    def create_video_configuration(self, main=None, lores=None, raw=None, transform=None, colour_space=None,
                                   buffer_count=6, controls=None, display="main", encode="main", queue=True,
                                   sensor=None, use_case="video"):
        stream = {"format": "XBGR8888", "size": (1280, 720)}
        stream.update(main or {})
        return {"use_case": use_case, "transform": transform, "colour_space": colour_space,
                "buffer_count": buffer_count, "queue": queue, "main": stream, "lores": lores, "raw": raw,
                "controls": {"NoiseReductionMode": 1, "FrameDurationLimits": (33333, 33333), **(controls or {})},
                "sensor": sensor or {}, "display": display, "encode": encode}

    def configure(self, camera_config=None) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        fmt = camera_config["main"]["format"]
        if fmt not in _CHANNELS:
            raise RuntimeError(f"Invalid format {fmt}")
        self.camera_config = camera_config
        self._frame = self._image()
        w, h = camera_config["main"]["size"]
        _log(f"configure {fmt} {w}x{h}")

    def start(self, config=None, show_preview=False) -> None:
        if config is not None:
            self.configure(config)
        if self.camera_config is None:
            raise RuntimeError("Camera has not been configured")
        if not self.started:
            self.started = True
            self._start_time = time.monotonic()
            self._last_frame = -1
            _log("start")

    def _period(self) -> float:
        if STANDIN.get("fps"):
            return 1.0 / float(STANDIN["fps"])
        return self.camera_config["controls"]["FrameDurationLimits"][0] / 1e6

    def _image(self) -> np.ndarray:
        main = self.camera_config["main"]
        w, h = main["size"]
        scene = cv2.imread(STANDIN["scene"], cv2.IMREAD_COLOR) if STANDIN.get("scene") else None
        bgr = cv2.resize(scene, (w, h), interpolation=cv2.INTER_AREA) if scene is not None \
            else np.full((h, w, 3), 128, np.uint8)
        rgb = bgr[:, :, ::-1]
        out = np.ascontiguousarray(rgb[:, :, list(_CHANNELS[main["format"]])])
        if main["format"].startswith("X"):
            out = np.dstack([out, np.full((h, w), 255, np.uint8)])
        return out

    def capture_array(self, name: str = "main", wait=None, signal_function=None) -> np.ndarray:
        if name != "main":
            raise KeyError(name)
        if not self.started:
            raise CancelledError("the camera is not running")
        if STANDIN.get("fail_after") is not None and self.frames >= int(STANDIN["fail_after"]):
            raise RuntimeError("Device timeout detected, attempting a restart")
        if STANDIN.get("hang_after") is not None and self.frames >= int(STANDIN["hang_after"]):
            while self.started:  # no frame ever completes; stop() from another thread cancels the wait
                time.sleep(0.01)
            raise CancelledError("the camera was stopped")
        period = self._period()
        now = time.monotonic() - self._start_time
        frame = max(int(now / period) + 1, self._last_frame + 1)  # the next frame to complete
        time.sleep(max(0.0, frame * period - now))
        self._last_frame = frame
        self.frames += 1
        return self._frame.copy()

    def stop(self) -> None:
        if self.started:
            self.started = False
            _log("stop")

    def close(self) -> None:
        self.stop()
        if self.is_open:
            self.is_open = False
            with _lock:
                _held.discard(self.camera_idx)
            _log("close")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
