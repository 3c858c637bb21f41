"""Steady keypoints on video: a One-Euro filter per keypoint, coasting over short gaps. numpy only (Pi core).

The One-Euro filter (Casiez, Roussel and Vogel, CHI 2012) is a low-pass filter whose cut-off rises with
the signal's speed: a keypoint at rest is smoothed hard (no jitter), a moving one lightly (little lag).
Per keypoint, on the (x, y) position in frame pixels:

    a(fc)   = 1 / (1 + 1 / (2 pi fc dt))                       the smoothing factor of cut-off fc (Hz)
    v       = low-pass of (x_t - x^_{t-1}) / dt at d_cutoff      speed, px/s
    fc      = min_cutoff + beta |v| 800 / diagonal               Hz
    x^_t    = x^_{t-1} + a(fc) (x_t - x^_{t-1})

A keypoint the model misses is held at its last estimate for up to `max_coast` frames (coasting),
then reported missing, and its filter starts afresh at its next detection (a reset after a gap, so a
keypoint that reappears elsewhere is not dragged there slowly). The speed counts in pixels of a 640 x 480 frame
(times REFERENCE_DIAGONAL_PX / the frame's diagonal), so the defaults, tuned there, smooth a camera of any
resolution alike. Defaults and what they measured: docs/runtime.md, "Smoothing".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_MIN_CUTOFF_HZ = 0.5
"""Cut-off of a keypoint at rest (Hz)."""
DEFAULT_BETA = 0.03
"""Cut-off added per pixel/second of speed (Hz per px/s, pixels of a 640 x 480 frame: REFERENCE_DIAGONAL_PX)."""
REFERENCE_DIAGONAL_PX = 800.0
"""The diagonal of the 640 x 480 frames the defaults were tuned on: a frame of diagonal D counts a speed of v px/s as
v * 800 / D (the same motion on 1920 x 1440 frames, 3x the pixels a second, smoothed 0.65x instead of 0.50x
without it)."""
DEFAULT_D_CUTOFF_HZ = 1.0
"""Cut-off of the speed estimate (Hz)."""
DEFAULT_MAX_COAST = 2
"""Frames a missing keypoint is held at its last estimate before it is reported missing."""


def _alpha(cutoff_hz: np.ndarray | float, dt: float) -> np.ndarray:
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * np.asarray(cutoff_hz, np.float64) * dt))


@dataclass
class OneEuroParams:
    """The filter's parameters in frame pixels and Hz (see the module's docstring)."""

    min_cutoff_hz: float = DEFAULT_MIN_CUTOFF_HZ
    beta: float = DEFAULT_BETA
    d_cutoff_hz: float = DEFAULT_D_CUTOFF_HZ
    max_coast: int = DEFAULT_MAX_COAST

    def describe(self) -> str:
        """`One-Euro filter (cut-off 0.5 Hz at rest + 0.03 Hz per px/s of a 640x480 frame, speed cut-off 1 Hz, coasting 2
        frames)`."""
        return (f"One-Euro filter (cut-off {self.min_cutoff_hz:g} Hz at rest + {self.beta:g} Hz per px/s of a 640x480 "
                f"frame, speed cut-off {self.d_cutoff_hz:g} Hz, coasting {self.max_coast} frame{'s' if self.max_coast != 1 else ''})")

    def check(self) -> "OneEuroParams":
        from fcnpose_tf.errors import UserError

        wrong = []  # each in the words of its option
        if not self.min_cutoff_hz > 0:
            wrong.append(f"--smooth-min-cutoff must be above 0 Hz, got {self.min_cutoff_hz:g}")
        if not self.d_cutoff_hz > 0:
            wrong.append(f"the speed's cut-off must be above 0 Hz, got {self.d_cutoff_hz:g}")
        if not self.beta >= 0:
            wrong.append(f"--smooth-beta must be >= 0, got {self.beta:g}")
        if not self.max_coast >= 0:
            wrong.append(f"--smooth-coast must be >= 0 frames, got {self.max_coast:g}")
        if wrong:
            raise UserError("; ".join(wrong))
        return self


class KeypointSmoother:
    """One-Euro filters for K keypoints of a video, fed one frame at a time.

    Example:
        >>> smoother = KeypointSmoother(8)
        >>> steady = smoother(keypoints_xy, t_seconds)   # K x 2, NaN where missing
    """

    def __init__(self, num_keypoints: int, params: OneEuroParams | None = None,
                 frame_shape: tuple[int, ...] | None = None) -> None:
        """`frame_shape` (height, width[, channels]) of the video's frames: speeds count in pixels of a 640 x 480 frame
        (REFERENCE_DIAGONAL_PX); None: they are such frames."""
        self.params = (params or OneEuroParams()).check()
        self.k = int(num_keypoints)
        self.speed_scale = 1.0 if frame_shape is None else REFERENCE_DIAGONAL_PX / math.hypot(*frame_shape[:2])
        self.reset()

    def reset(self) -> None:
        """Forget every track (e.g. when a new video starts)."""
        self._x = np.full((self.k, 2), np.nan)  # filtered positions
        self._v = np.zeros((self.k, 2))  # filtered velocities, px/s
        self._missed = np.zeros(self.k, np.int64)  # frames since the last detection
        self._t: float | None = None

    def __call__(self, keypoints: np.ndarray, t: float) -> np.ndarray:
        """The smoothed K x 2 keypoints at time t (seconds, increasing); NaN rows in `keypoints` are misses."""
        obs = np.asarray(keypoints, np.float64).reshape(self.k, 2)
        seen = np.isfinite(obs).all(1)
        dt = None if self._t is None else float(t) - self._t
        self._t = float(t)
        tracked = np.isfinite(self._x).all(1)
        if dt is None or dt <= 0:
            fresh = seen
            update = np.zeros(self.k, bool)
        else:
            fresh = seen & ~tracked
            update = seen & tracked
        self._x[fresh] = obs[fresh]
        self._v[fresh] = 0.0
        if update.any():
            p = self.params
            raw_v = (obs[update] - self._x[update]) / dt
            self._v[update] += _alpha(p.d_cutoff_hz, dt) * (raw_v - self._v[update])
            speed = np.linalg.norm(self._v[update], axis=1) * self.speed_scale
            a = _alpha(p.min_cutoff_hz + p.beta * speed, dt)[:, None]
            self._x[update] += a * (obs[update] - self._x[update])
        self._missed[seen] = 0
        self._missed[~seen] += 1
        lost = ~seen & (self._missed > self.params.max_coast)
        self._x[lost] = np.nan  # a gap longer than the coasting: the track starts afresh at its next detection
        self._v[lost] = 0.0
        return self._x.copy()


def smooth_track(keypoints: np.ndarray, fps: float, params: OneEuroParams | None = None,
                 frame_shape: tuple[int, ...] | None = None) -> np.ndarray:
    """A whole N x K x 2 sequence at `fps` frames per second, smoothed frame by frame (as `run` does live); its
    frames' `frame_shape` as `KeypointSmoother`'s."""
    keypoints = np.asarray(keypoints, np.float64)
    smoother = KeypointSmoother(keypoints.shape[1], params, frame_shape)
    return np.stack([smoother(frame, i / float(fps)) for i, frame in enumerate(keypoints)])


def add_smoothing_arguments(parser, video_only: bool = False) -> None:
    """--smooth and the filter's parameters (run, predict and evaluate share them)."""
    where = "on a video, " if video_only else ""
    parser.add_argument("--smooth", action="store_true",
                        help=f"{where}steady keypoints: a One-Euro filter per keypoint, coasting over up to "
                             "--smooth-coast missed frames (docs/runtime.md, Smoothing)")
    parser.add_argument("--smooth-min-cutoff", type=float, default=DEFAULT_MIN_CUTOFF_HZ, metavar="HZ",
                        help=f"cut-off of a keypoint at rest (default {DEFAULT_MIN_CUTOFF_HZ:g} Hz; lower: steadier)")
    parser.add_argument("--smooth-beta", type=float, default=DEFAULT_BETA, metavar="B",
                        help=f"cut-off added per px/s of speed, in pixels of a 640x480 frame (scaled to the frame's "
                             f"diagonal) (default {DEFAULT_BETA:g}; higher: less lag)")
    parser.add_argument("--smooth-coast", type=int, default=DEFAULT_MAX_COAST, metavar="N",
                        help=f"frames a missed keypoint is held (default {DEFAULT_MAX_COAST})")


def params_from_args(args) -> OneEuroParams | None:
    """The filter's parameters if --smooth was given, else None."""
    if not getattr(args, "smooth", False):
        return None
    return OneEuroParams(args.smooth_min_cutoff, args.smooth_beta, DEFAULT_D_CUTOFF_HZ, args.smooth_coast).check()


STILL_THUMBNAIL_WIDTH = 64
"""Frames are compared as grey thumbnails this wide (area-averaged: a camera's pixel noise averages out)."""
STILL_LEVELS = 3.0
"""A frame is *still* when no thumbnail pixel changed by this many grey levels (of 255) since the previous frame:
camera noise of a few levels averages to under one in a thumbnail pixel, while an edge that moves by one frame pixel
changes the thumbnail pixels it crosses by several (docs/runtime.md, "Smoothing")."""


def is_still(previous: np.ndarray | None, current: np.ndarray) -> bool:
    """Whether two grey thumbnails (`thumbnail`) show the same picture: no pixel changed by STILL_LEVELS or more."""
    if previous is None or previous.shape != current.shape:
        return False
    return float(np.abs(current - previous).max()) < STILL_LEVELS


def jitter_rms(steps_px) -> float:
    """The RMS of frame-to-frame keypoint steps (px): over still frames, the keypoints' jitter."""
    steps = np.asarray(steps_px, np.float64)
    return float(np.sqrt(np.mean(steps ** 2))) if steps.size else float("nan")


def frame_step_px(previous: np.ndarray | None, current: np.ndarray) -> float | None:
    """How far the keypoints moved since the previous frame: the mean distance over the keypoints found in both
    (frame pixels), None when none was. On an arm at rest this is all jitter."""
    if previous is None:
        return None
    both = np.isfinite(previous).all(axis=1) & np.isfinite(current).all(axis=1)
    if not both.any():
        return None
    return float(np.hypot(*(current[both] - previous[both]).T).mean())
