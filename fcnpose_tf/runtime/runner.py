"""The frame loop behind `fcnpose-tf run`: source -> model -> records, video, window; timings and a summary.

Ends cleanly at the end of the source, after `max_frames`, on `q`/Esc in the
window, or on Ctrl-C / SIGTERM (handled by the caller turning them into
KeyboardInterrupt): the frames processed so far are written, the video is
finalised and the summary reports why the run stopped. A signal never splits a
frame: its records, the `on_frame` hook (a VIA project's entry) and its count
are done with Ctrl-C and SIGTERM held back (`fileio.signals_deferred`).

Two loops share what happens to a decoded frame (`_Delivery`): the sequential one
(read, preprocess, invoke, decode, write, next) and the pipelined one, whose
invoke runs on a second thread (`runtime.pipeline`) while this thread decodes and
writes the previous frame and reads and preprocesses the next. Signals, records,
drawing and the window stay on the calling (main) thread in both.
"""

from __future__ import annotations

import sys
import time
from array import array
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence, TextIO

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import signals_deferred
from fcnpose_tf.runtime.estimator import KeypointPredictor, Prediction, StageTimes
from fcnpose_tf.runtime.sinks import RecordWriter, RollingFps, VideoSink, draw_overlay
from fcnpose_tf.runtime.sources import Frame, FrameSource, ImageSource
from fcnpose_tf.runtime.timing import FPS_DEFINITION, LatencyLog, describe_ms
from fcnpose_tf.smoothing import STILL_LEVELS, STILL_THUMBNAIL_WIDTH, KeypointSmoother, OneEuroParams, \
    frame_step_px, is_still, jitter_rms

WINDOW_NAME = "fcnpose-tf"

CAPTURE_LATENCY_DEFINITION = ("from the grab thread receiving the frame to its records written; time spent "
                              "in the camera, its driver and libcamera before that is not included")


DELIVERED_DEFINITION = ("frames/s from the first frame's records written to the last's; "
                        "read = the source handing the frame over")


def check_display() -> None:
    """UserError unless OpenCV can open a window (opencv-python-headless cannot)."""
    try:
        cv2.namedWindow(WINDOW_NAME, cv2.WINDOW_NORMAL)
    except cv2.error:
        raise UserError("--show needs OpenCV with GUI support and a display: `pip install opencv-python` "
                        "(not -headless), or use --save-video instead") from None


@dataclass
class RunSummary:
    """What a run did: frame counts, why it stopped, latencies, outputs."""

    frames: int = 0
    skipped: int = 0
    crop_edge_frames: int = 0
    """Frames with a keypoint at the edge of the model's crop (`Prediction.at_crop_edge`)."""
    missed_frames: int = 0
    """Frames in which the model did not find every keypoint."""
    missed_by_keypoint: list[int] = field(default_factory=list)
    """Per keypoint, in the model's order, the frames in which the model did not find it."""
    dropped: int = 0
    end_reason: str = ""
    wall_s: float = 0.0
    latency: LatencyLog = field(default_factory=LatencyLog)
    capture_to_keypoints_ms: array = field(default_factory=lambda: array("d"))
    """Live sources only: per frame, from its capture timestamp to its records written (ms)."""
    read_to_keypoints_ms: array = field(default_factory=lambda: array("d"))
    """Per frame, from the source handing it over to its records written (ms): the latency the loop adds."""
    first_written_s: float = 0.0
    last_written_s: float = 0.0
    """perf_counter() when the first and the last frame's records were written (the delivered rate's span)."""
    pipelined: bool = False
    """The invoke ran on its own thread, overlapping the other stages (`runtime.pipeline`)."""
    smoothing: OneEuroParams | None = None
    """The filter the keypoints went through (`run --smooth`), or None."""
    raw_steps_px: array = field(default_factory=lambda: array("d"))
    """Per pair of consecutive frames, how far the model's keypoints moved (`smoothing.frame_step_px`)."""
    steps_px: array = field(default_factory=lambda: array("d"))
    """The same for the keypoints written (smoothed with --smooth)."""
    still_raw_steps_px: array = field(default_factory=lambda: array("d"))
    still_steps_px: array = field(default_factory=lambda: array("d"))
    """raw_steps_px and steps_px over still frames only (`smoothing.is_still`: the image did not change), where
    every step is jitter."""
    outputs: list[str] = field(default_factory=list)

    @property
    def loop_fps(self) -> float:
        """Frames per wall-clock second, including capture, drawing and writing."""
        return self.frames / self.wall_s if self.wall_s > 0 else float("nan")

    @property
    def delivered_fps(self) -> float:
        """Frames per second from the first frame's records written to the last's (steady state: no
        warm-up, no start-up); NaN below two frames."""
        span = self.last_written_s - self.first_written_s
        return (self.frames - 1) / span if self.frames > 1 and span > 0 else float("nan")

    def _jitter(self) -> str:
        still = len(self.still_raw_steps_px)
        if not still:
            return (f"Jitter:  no still frames (every frame's image changed from the previous one by "
                    f"{STILL_LEVELS:g} grey levels or more somewhere): nothing to measure it on")
        written = (f", {jitter_rms(self.still_steps_px):.2f} px as written" if self.smoothing is not None else
                   " (--smooth filters it)")
        return (f"Jitter:  over {still} still frames (the image unchanged from the one before), the keypoints moved "
                f"RMS {jitter_rms(self.still_raw_steps_px):.2f} px as the model found them{written}")

    def count_missed(self, keypoints: np.ndarray) -> None:
        """Count a frame's keypoints the model did not find (NaN rows of its K x 2 `keypoints`, before smoothing)."""
        missed = np.isnan(keypoints).any(axis=1)
        self.missed_by_keypoint = [c + int(m) for c, m in zip(self.missed_by_keypoint or [0] * len(missed), missed)]
        self.missed_frames += bool(missed.any())

    def _found(self, names: tuple[str, ...]) -> str:
        if not self.missed_frames:
            return "Found:   every keypoint in every frame"
        worst = sorted(((-n, k) for k, n in enumerate(self.missed_by_keypoint) if n))
        listed = ", ".join(f"{names[k]} in {-n}" for n, k in worst[:4])
        more = f", {len(worst) - 4} more keypoints" if len(worst) > 4 else ""
        return (f"Found:   every keypoint in {self.frames - self.missed_frames} of {self.frames} frames; not found: "
                f"{listed}{more} (the records' nulls)")

    def report(self, model: KeypointPredictor, source: FrameSource) -> str:
        """The run's summary for the terminal: counts, the per-stage latency table, FPS with its definition, outputs.

        Args:
            model: the predictor that ran (its description and threads).
            source: the frames it read (their description).
        Returns:
            The lines, joined.
        """
        fps = self.latency.fps()
        lines = [f"Model:   {model.describe()}",
                 f"Source:  {source.describe()}; stopped: {self.end_reason}",
                 f"Frames:  {self.frames} processed, {self.skipped} skipped (unreadable), "
                 f"{self.dropped} dropped (stale camera frames); wall time {self.wall_s:.2f} s"]
        if self.frames:
            lines += ["", self.latency.table(), "",
                      f"FPS:     {fps['end_to_end']:.1f} end-to-end, {fps['invoke']:.1f} invoke-only "
                      f"({_threads(model.num_threads)}; {FPS_DEFINITION})",
                      f"Loop:    {self.loop_fps:.1f} frames/s wall clock (with capture, drawing and writing)"]
            d = describe_ms(self.read_to_keypoints_ms)
            rate = f"{self.delivered_fps:.1f} frames/s" if self.frames > 1 else "one frame (no rate)"
            lines.append(f"Delivered: {rate}, {self._mode()}; per frame "
                         f"{d['median']:.1f} ms p50, {d['p95']:.1f} ms p95 from read to records written "
                         f"({DELIVERED_DEFINITION})")
            lines.append(self._found(model.schema.keypoints))
        if len(self.raw_steps_px):
            raw = float(np.median(self.raw_steps_px))
            stills = isinstance(source, ImageSource)
            step = "from image to image in name order" if stills else "from frame to frame"
            meaning = ("the arm's motion and jitter; where the arm stands still it is all jitter"
                       + (", which --smooth filters" if self.smoothing is None else ""))
            if stills:
                meaning = f"for a sequence of frames, {meaning}; for stills that are not one it measures nothing"
            if self.smoothing is None:
                lines.append(f"Steadiness: keypoints moved a median {raw:.2f} px {step} ({meaning})")
            else:
                lines.append(f"Smoothing: {self.smoothing.describe()}; keypoints moved a median {raw:.2f} px {step} "
                             f"as the model found them, {float(np.median(self.steps_px)):.2f} px as written "
                             f"({meaning})")
            lines.append(self._jitter())
        if model.view.crop is not None:
            advice = (": the arm may reach past the crop there, in poses the training frames did not show; retrain "
                      "with frames of those poses (docs/training.md, \"Input size\")" if self.crop_edge_frames else "")
            lines.append(f"Crop:    the model sees {model.view.describe()}; {self.crop_edge_frames} of {self.frames} "
                         f"frames had a keypoint at its edge, beyond the training frames' keypoints (the records' "
                         f"crop_edge){advice}. An arm past the crop shows mostly as keypoints not found (Found above)")
        note = model.run_note()
        if note:
            lines.append(note)
        if len(self.capture_to_keypoints_ms):
            d = describe_ms(self.capture_to_keypoints_ms)
            lines.append(f"Latency: capture to keypoints written {d['median']:.1f} ms p50, {d['p95']:.1f} ms p95, "
                         f"{d['max']:.1f} ms max ({CAPTURE_LATENCY_DEFINITION})")
        for out in self.outputs:
            lines.append(f"Wrote:   {out}")
        return "\n".join(lines)


    def _mode(self) -> str:
        return "pipelined (invoke on its own thread)" if self.pipelined else "sequential"


def _threads(count: int | None) -> str:
    return "default threads" if count is None else f"{count} thread{'s' if count != 1 else ''}"


class ProgressLine:
    """A rolling status line on a terminal (carriage return, at most `rate_hz` updates a second)."""

    def __init__(self, stream: TextIO | None = None, rate_hz: float = 4.0):
        self.stream = stream or sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.period = 1.0 / rate_hz
        self._last = 0.0
        self._width = 0

    def update(self, frames: int, fps: float, loop_fps: float, times) -> None:
        """Redraw the line, unless the stream is no terminal or the last redraw is too recent.

        Args:
            frames: frames processed so far.
            fps: the model's rolling FPS.
            loop_fps: the whole loop's frames per second.
            times: the last frame's `StageTimes`.
        """
        now = time.monotonic()
        if not self.enabled or now - self._last < self.period:
            return
        self._last = now
        text = (f"frame {frames}  FPS {fps:5.1f}  loop {loop_fps:5.1f}/s  "
                f"pre {times.preprocess_ms:5.1f}  invoke {times.invoke_ms:5.1f}  post {times.postprocess_ms:5.1f} ms")
        self.stream.write("\r" + text.ljust(self._width))
        self.stream.flush()
        self._width = len(text)

    def close(self) -> None:
        """Erase the line (on a terminal)."""
        if self.enabled and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0


def frame_time_s(frame: Frame, source: FrameSource) -> float:
    """A frame's time for filtering: its position in a video, its capture time on a camera, else its index
    at the source's frame rate (30 FPS when it has none: an image folder).

    Args:
        frame: a frame the source delivered.
        source: the source.
    Returns:
        Seconds.
    """
    if frame.media_time_s is not None:
        return float(frame.media_time_s)
    if source.live:
        return float(frame.timestamp)
    return frame.index / float(source.fps or 30.0)


def run_stream(model: KeypointPredictor, source: FrameSource, writers: Sequence[RecordWriter] = (),
               video: VideoSink | None = None, show: bool = False, max_frames: int | None = None,
               progress: ProgressLine | None = None, fps_window: int = 30,
               on_frame: Callable[[Frame, Prediction], None] | None = None, every: int = 1,
               smooth: OneEuroParams | None = None, pipelined: bool = False) -> RunSummary:
    """Run the model on every frame of `source`, writing each frame's record as soon as it is decoded.

    Args:
        model: the loaded model.
        source: an opened frame source (closed by the caller).
        writers: record writers (JSONL/CSV); each frame is written and flushed at once.
        video: a video sink for frames with the overlay (finalised by the caller).
        show: show the overlay in a window (`q` or Esc stops).
        max_frames: stop after this many processed frames.
        progress: a ProgressLine for the terminal, or None.
        fps_window: frames averaged for the FPS drawn on the overlay and shown on the terminal.
        on_frame: called with each frame and its prediction (API users, `predict`'s VIA project).
        every: process only the frames whose index is a multiple of this (every Nth frame of a video).
        smooth: One-Euro parameters: every record, overlay and hook gets the smoothed keypoints
            (`frame_time_s` gives the filter its clock).
        pipelined: run the interpreter's invoke on a second thread, overlapping it with reading and
            preprocessing the next frame and decoding and writing the previous one (`runtime.pipeline`;
            the same keypoints, in the same order). Ignored for a model without the staged-frame
            methods (`KeypointPredictor.pipelinable`).
    Returns:
        The RunSummary; `end_reason` says why the loop ended (Ctrl-C included: KeyboardInterrupt
        during the loop ends it cleanly).
    """
    summary = RunSummary(pipelined=bool(pipelined and model.pipelinable), smoothing=smooth)
    delivery = _Delivery(model, source, summary, writers, video, show, max_frames, progress, fps_window,
                         on_frame, smooth)
    frames_iter = iter(source)
    try:
        if summary.pipelined:
            _pipelined_loop(model, source, frames_iter, every, delivery)
        else:
            _sequential_loop(model, source, frames_iter, every, delivery)
    except KeyboardInterrupt as exc:  # Ctrl-C, or a signal handler raising KeyboardInterrupt("reason")
        summary.end_reason = str(exc) or "interrupted (Ctrl-C)"
    finally:
        summary.wall_s = time.perf_counter() - delivery.start
        if progress is not None:
            progress.close()
        close = getattr(frames_iter, "close", None)
        if close is not None:
            close()
        if show:
            try:
                cv2.destroyWindow(WINDOW_NAME)
            except cv2.error:
                pass
    summary.skipped += source.skipped
    summary.dropped = source.dropped
    if not summary.end_reason:
        summary.end_reason = source.end_reason
    for writer in writers:
        summary.outputs.append(f"{writer.path} ({writer.count} records)")
    return summary


def _sequential_loop(model: KeypointPredictor, source: FrameSource, frames_iter, every: int,
                     delivery: "_Delivery") -> None:
    """One frame at a time: read, preprocess, invoke, decode, write, then the next."""
    warm = False
    for frame in frames_iter:
        read_at = time.perf_counter()
        if frame.index % every:
            continue
        if not warm:  # one untimed frame of the source's size: start-up costs stay out of the figures
            model.warmup(frame.image.shape)
            warm, read_at = True, time.perf_counter()
        try:
            prediction = model.predict(frame.image)
        except UserError as exc:  # e.g. a frame with an unexpected shape: skip, say so
            delivery.skip(frame, exc)
            continue
        if delivery.deliver(frame, prediction, read_at):
            return


def _pipelined_loop(model: KeypointPredictor, source: FrameSource, frames_iter, every: int,
                    delivery: "_Delivery") -> None:
    """Invoke frame n on the worker while this thread writes frame n-1 and reads and preprocesses n+1.

    A live source's frame n+1 does not exist until the camera sends it: there frame n is delivered as soon as its
    invoke ends, unless a newer frame came first (then that one is read and preprocessed meanwhile, as from a
    video), so a model faster than the camera adds no camera frame's wait to each frame's latency."""
    from fcnpose_tf.runtime.pipeline import InvokeWorker

    summary = delivery.summary
    worker: InvokeWorker | None = None
    in_flight = None  # (frame, slot, preprocess ms, read time) of the frame the worker is invoking
    slot = 0
    try:
        while True:
            if delivery.max_frames is not None and summary.frames + (in_flight is not None) >= delivery.max_frames:
                break  # the frame in flight is the last one wanted: read no more
            frame = next(frames_iter, None)
            if frame is None:
                break
            read_at = time.perf_counter()
            if frame.index % every:
                continue
            if worker is None:
                model.warmup(frame.image.shape)  # untimed, on this thread, before the worker exists
                worker, read_at = InvokeWorker(model), time.perf_counter()
            t0 = time.perf_counter()
            try:
                model.preprocess_into(frame.image, worker.inputs[slot])
            except UserError as exc:
                delivery.skip(frame, exc)
                continue
            preprocess_ms = (time.perf_counter() - t0) * 1e3
            done = None
            if in_flight is not None:
                done = (in_flight, *worker.wait())
            worker.start(slot)
            in_flight, slot = (frame, slot, preprocess_ms, read_at), 1 - slot
            if done is not None and delivery.deliver_raw(worker, *done):
                return
            if source.live and not _newer_frame_first(worker, source):
                done = (in_flight, *worker.wait())
                in_flight = None
                if delivery.deliver_raw(worker, *done):
                    return
        if in_flight is not None:
            done = (in_flight, *worker.wait())
            in_flight = None
            delivery.deliver_raw(worker, *done)
    finally:
        if worker is not None:
            worker.close()  # waits for an invoke still running (a stopped run drops its frame)


def _newer_frame_first(worker, source: FrameSource, poll_s: float = 0.001) -> bool:
    """Wait until the frame in flight is done (False) or the live source has a newer frame (True), whichever
    comes first: the invoke's end is seen at once, a camera frame within `poll_s`."""
    while not worker.finished(poll_s):
        if source.frame_waiting():
            return True
    return False


def _thumbnail(image: np.ndarray) -> np.ndarray:
    """The frame as a grey, area-averaged thumbnail STILL_THUMBNAIL_WIDTH wide (float32), for `is_still`."""
    h, w = image.shape[:2]
    size = (STILL_THUMBNAIL_WIDTH, max(1, round(h * STILL_THUMBNAIL_WIDTH / w)))
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32)


class _Delivery:
    """What happens to a frame once its keypoints are known, the same for both loops: smoothing, the
    latency log, records, hook and count (with Ctrl-C/SIGTERM held back), overlay, window, progress,
    --max-frames. `deliver` returns True when the run should stop."""

    def __init__(self, model, source, summary, writers, video, show, max_frames, progress, fps_window,
                 on_frame, smooth):
        self.model, self.source, self.summary = model, source, summary
        self.writers, self.video, self.show, self.max_frames = writers, video, show, max_frames
        self.progress, self.on_frame, self.smooth = progress, on_frame, smooth
        self.smoother: KeypointSmoother | None = None
        self.last_raw: np.ndarray | None = None  # the previous frame's keypoints, as found and as written
        self.last_written: np.ndarray | None = None
        self.last_thumbnail: np.ndarray | None = None  # the previous frame's grey thumbnail (still frames)
        self.last_overlay: tuple[int, np.ndarray] | None = None  # a live source's last frame in the video, by index
        self.rolling = RollingFps(fps_window)
        self.start = time.perf_counter()

    def _write_video(self, frame: Frame, overlay: np.ndarray) -> None:
        """The overlay into the video; from a live source, the last frame written held over the camera frames the
        model had no time for (their indices count every captured frame), so the video written at the camera's rate
        plays in real time."""
        if self.source.live and self.last_overlay is not None:
            last_index, last = self.last_overlay
            for _ in range(frame.index - last_index - 1):
                self.video.write(last)
        self.video.write(overlay)
        if self.source.live:
            self.last_overlay = (frame.index, overlay)

    def skip(self, frame: Frame, exc: UserError) -> None:
        self.summary.skipped += 1
        self.source.warn(f"skipped frame {frame.index} of {frame.name}: {exc}")

    def deliver_raw(self, worker, in_flight, slot: int, invoke_ms: float) -> bool:
        """Decode a pipelined frame's raw output (this thread) and deliver it."""
        frame, staged_slot, preprocess_ms, read_at = in_flight
        assert slot == staged_slot
        t0 = time.perf_counter()
        keypoints, confidence = self.model.decode_output(worker.outputs[slot], frame.image.shape)
        times = StageTimes(preprocess_ms, invoke_ms, (time.perf_counter() - t0) * 1e3)
        return self.deliver(frame, Prediction(keypoints, confidence, times, tuple(frame.image.shape),
                                              self.model.crop_box(frame.image.shape)), read_at)

    def deliver(self, frame: Frame, prediction: Prediction, read_at: float) -> bool:
        summary = self.summary
        raw = prediction.keypoints
        if self.smooth is not None:
            self.smoother = self.smoother or KeypointSmoother(len(prediction.keypoints), self.smooth,
                                                              prediction.frame_shape)
            prediction = replace(prediction, keypoints=self.smoother(prediction.keypoints,
                                                                     frame_time_s(frame, self.source)))
        thumbnail = _thumbnail(frame.image)
        still = is_still(self.last_thumbnail, thumbnail)
        for steps, still_steps, previous, current in (
                (summary.raw_steps_px, summary.still_raw_steps_px, self.last_raw, raw),
                (summary.steps_px, summary.still_steps_px, self.last_written, prediction.keypoints)):
            step = frame_step_px(previous, current)
            if step is not None:
                steps.append(step)
                if still:
                    still_steps.append(step)
        self.last_raw, self.last_written, self.last_thumbnail = raw, prediction.keypoints, thumbnail
        summary.latency.add(prediction.times)
        self.rolling.add(prediction.times.total_ms)
        summary.crop_edge_frames += bool(prediction.at_crop_edge().any())
        summary.count_missed(raw)
        with signals_deferred():  # Ctrl-C/SIGTERM take effect after a frame's records, hook and count
            for writer in self.writers:
                writer.write(frame, prediction)
            if self.source.live:
                summary.capture_to_keypoints_ms.append((time.time() - frame.timestamp) * 1e3)
            if self.on_frame is not None:
                self.on_frame(frame, prediction)
            summary.frames += 1
            written_at = time.perf_counter()
            summary.read_to_keypoints_ms.append((written_at - read_at) * 1e3)
            summary.first_written_s = summary.first_written_s or written_at
            summary.last_written_s = written_at
        if self.video is not None or self.show:
            overlay = draw_overlay(frame.image, prediction, self.model.schema, self.rolling.fps)
            if self.video is not None:
                self._write_video(frame, overlay)
            if self.show:
                cv2.imshow(WINDOW_NAME, overlay)
                if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
                    summary.end_reason = "stopped from the window (q/Esc)"
                    return True
        if self.progress is not None:
            elapsed = time.perf_counter() - self.start
            self.progress.update(summary.frames, self.rolling.fps,
                                 summary.frames / elapsed if elapsed > 0 else 0.0, prediction.times)
        if self.max_frames is not None and summary.frames >= self.max_frames:
            summary.end_reason = f"reached --max-frames {self.max_frames}"
            return True
        return False


__all__ = ["RunSummary", "ProgressLine", "run_stream", "check_display", "WINDOW_NAME"]
