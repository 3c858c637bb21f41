"""The pipelined frame loop (`run_stream(pipelined=True)`, `runtime.pipeline`): the sequential loop's
keypoints and records in the same order, the invoke on its own thread, and the same endings (the
source's end, --max-frames, a skipped frame, Ctrl-C / SIGTERM, an error) with no thread left behind.

No timing is asserted: the speed is measured by tools/bench_pipeline.py (docs/runtime.md).
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fcnpose_tf.cli import main
from fcnpose_tf.fileio import stop_signals_as_interrupt
from fcnpose_tf.runtime.estimator import KeypointModel
from fcnpose_tf.runtime.pipeline import WORKER_NAME
from fcnpose_tf.runtime.runner import run_stream
from fcnpose_tf.runtime.sinks import JsonlWriter
from fcnpose_tf.runtime.sources import Frame, FrameSource, LiveSource, open_source
from test_run_bench_cli import model_path  # noqa: F401 - the structured .tflite fixture, one definition
from test_runtime import RED_CYCLE, quadrant_frame, write_video


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    frames = [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(10)]
    return write_video(tmp_path_factory.mktemp("pipe_video") / "clip.avi", frames)


class ListSource(FrameSource):
    """Frames from a list, counting how many were handed over."""

    kind = "list"

    def __init__(self, images):
        super().__init__("list")
        self.images, self.handed = images, 0

    def __iter__(self):
        self.end_reason = "running"
        for i, image in enumerate(self.images):
            self.handed += 1
            yield Frame(i, image, 1700000000.0 + i, self.name)
        self.end_reason = "end of list"


def _frames(n=9, width=96, height=64):
    return [quadrant_frame(width, height, RED_CYCLE[i % 4]) for i in range(n)]


def _records(path: Path) -> list[dict]:
    """The records without their timings (which differ from run to run)."""
    out = []
    for line in path.read_text().splitlines():
        record = json.loads(line)
        del record["latency_ms"], record["timestamp"]
        out.append(record)
    return out


def _workers_alive() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == WORKER_NAME]


def _run_both(model, make_source, tmp_path, **kwargs):
    results = {}
    for pipelined in (False, True):
        path = tmp_path / f"{pipelined}.jsonl"
        writer = JsonlWriter(path, model.schema)
        source = make_source()
        try:
            summary = run_stream(model, source, [writer], pipelined=pipelined, **kwargs)
        finally:
            source.close()
            writer.close()
        assert summary.pipelined is pipelined
        results[pipelined] = (summary, _records(path), source)
    assert not _workers_alive()
    return results


@pytest.mark.parametrize("bundled", [False, True], ids=["float16", "int8"])
def test_pipelined_keypoints_and_records_equal_the_sequential_ones(model_path, video, tmp_path, monkeypatch, bundled):
    """Float maps and the int8 file's quantized ones (decoded from copies of the raw output): the same
    records, frame for frame; the invoke ran on the worker thread, nothing else did."""
    if bundled:
        from fcnpose_tf.bundled import models_dir
        from fcnpose_tf.data.synth.frame import render_frame

        model = KeypointModel(models_dir() / "fcnpose_ur5_p70_int8.tflite", 2)
        images = [render_frame(1, i)[0] for i in range(4)]
        make_source = lambda: ListSource(images)  # noqa: E731
    else:
        model = KeypointModel(model_path, 2)
        make_source = lambda: open_source(video)  # noqa: E731
    threads = {"forward": set(), "decode_output": set(), "preprocess_into": set()}
    for name in threads:
        def spy(*args, _method=getattr(model, name), _name=name):
            threads[_name].add(threading.current_thread().name)
            return _method(*args)
        monkeypatch.setattr(model, name, spy)
    results = _run_both(model, make_source, tmp_path)
    (seq, seq_records, _), (pipe, pipe_records, _) = results[False], results[True]
    assert seq.frames == pipe.frames == (4 if bundled else 10)
    assert pipe_records == seq_records
    assert [r["frame"] for r in pipe_records] == list(range(pipe.frames))
    found = sum(k["x"] is not None for r in pipe_records for k in r["keypoints"])
    assert found >= (30 if bundled else 60)  # keypoints to compare, not empty maps
    assert threads["forward"] == {WORKER_NAME}
    assert threads["decode_output"] == threads["preprocess_into"] == {threading.main_thread().name}
    assert len(pipe.read_to_keypoints_ms) == pipe.frames and pipe.delivered_fps > 0
    report = pipe.report(model, ListSource([]))
    assert "Delivered:" in report and "pipelined (invoke on its own thread)" in report
    assert "sequential" in seq.report(model, ListSource([]))


def test_max_frames_every_and_a_skipped_frame_read_what_the_sequential_loop_reads(model_path, tmp_path):
    """Every 2nd frame, one of them unreadable (no colour channels), stop after 3: the same frames read,
    the same skipped, the same records; the pipelined loop reads no frame beyond the last one wanted."""
    model = KeypointModel(model_path, 1)
    images = _frames(12)
    images[4] = np.zeros((64, 96), np.uint8)  # skipped: preprocessing refuses it (a UserError)
    warnings = []

    def make_source():
        source = ListSource(images)
        source.warn = warnings.append
        return source

    results = _run_both(model, make_source, tmp_path, every=2, max_frames=3)
    (seq, seq_records, seq_source), (pipe, pipe_records, pipe_source) = results[False], results[True]
    assert [r["frame"] for r in pipe_records] == [0, 2, 6] and pipe_records == seq_records
    assert pipe.skipped == seq.skipped == 1 and len(warnings) == 2
    assert pipe.end_reason == seq.end_reason == "reached --max-frames 3"
    assert pipe_source.handed == seq_source.handed == 7


class GatedCamera(LiveSource):
    """A live source whose next frame is captured only once the one before it has been delivered (`delivered`, the
    run's on_frame hook): a camera slower than the model, with no timing in the test."""

    def __init__(self, image):
        super().__init__("gated", first_frame_timeout_s=60.0, stall_timeout_s=60.0)  # a defect ends it in 2 min
        self.image, self.gate = image, threading.Semaphore(1)
        self._start_grabbing()

    def _read(self):
        return self.image.copy() if self.gate.acquire(timeout=0.01) else None

    def delivered(self, frame, prediction):
        self.gate.release()


def test_a_live_frame_is_delivered_when_its_invoke_ends_not_when_the_next_frame_comes(model_path):
    """Pipelined on a camera slower than the model: each frame's keypoints are delivered as soon as its invoke
    ends, not held until the camera's next frame arrives (a whole frame period of latency; here it never would)."""
    model = KeypointModel(model_path, 1)
    camera = GatedCamera(_frames(1)[0])
    try:
        summary = run_stream(model, camera, on_frame=camera.delivered, max_frames=4, pipelined=True)
    finally:
        camera.close()
    assert summary.pipelined and summary.frames == 4 and summary.end_reason == "reached --max-frames 4"
    assert camera.dropped == 0 and not _workers_alive()


def test_ctrl_c_in_a_pipelined_run_keeps_what_was_written_and_stops_the_worker(model_path, tmp_path):
    model = KeypointModel(model_path, 1)
    path = tmp_path / "k.jsonl"
    writer = JsonlWriter(path, model.schema)

    def interrupt(frame, prediction):
        if frame.index == 3:
            raise KeyboardInterrupt

    summary = run_stream(model, ListSource(_frames()), [writer], on_frame=interrupt, pipelined=True)
    writer.close()
    assert summary.end_reason == "interrupted (Ctrl-C)" and summary.frames == 3
    assert [r["frame"] for r in _records(path)] == [0, 1, 2, 3]  # frame 3's record, then its hook stopped
    assert not _workers_alive()
    model.predict(_frames(1)[0])  # the interpreter is free again


def test_sigterm_while_the_worker_invokes_ends_the_run_cleanly(model_path, tmp_path):
    """The signal is sent from the worker thread during frame 2's invoke; the main thread (waiting for it,
    or writing a record with signals held back) ends the run: whole records, counted, in order."""
    model = KeypointModel(model_path, 1)
    real_forward, calls = model.forward, []

    def forward(staged, raw):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # still invoking when the main thread takes the signal
        return real_forward(staged, raw)

    model.forward = forward
    path = tmp_path / "k.jsonl"
    writer = JsonlWriter(path, model.schema)
    with stop_signals_as_interrupt():
        summary = run_stream(model, ListSource(_frames(40)), [writer], pipelined=True)
    writer.close()
    records = _records(path)
    assert summary.end_reason == "terminated (SIGTERM)"
    assert summary.frames == writer.count == len(records) and 0 < len(records) < 40
    assert [r["frame"] for r in records] == list(range(len(records)))
    assert not _workers_alive()


def test_an_error_in_the_worker_reaches_the_caller_after_the_frames_before_it(model_path, tmp_path):
    model = KeypointModel(model_path, 1)
    real_forward, calls = model.forward, []

    def forward(staged, raw):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("interpreter failed")
        return real_forward(staged, raw)

    model.forward = forward
    path = tmp_path / "k.jsonl"
    writer = JsonlWriter(path, model.schema)
    with pytest.raises(RuntimeError, match="interpreter failed"):
        run_stream(model, ListSource(_frames()), [writer], pipelined=True)
    writer.close()
    assert [r["frame"] for r in _records(path)] == [0, 1, 2]
    assert not _workers_alive()


def test_run_cli_pipeline_flag(capsys, model_path, video, tmp_path):
    """--pipeline and --no-pipeline: the same records; the summary says which loop ran."""
    outs = {}
    for flag in ("--pipeline", "--no-pipeline"):
        outs[flag] = tmp_path / f"k{flag}.jsonl"
        code = main(["run", str(model_path), "--source", str(video), "--threads", "1", "--out", str(outs[flag]), flag])
        stdout = capsys.readouterr().out
        assert code == 0
        assert ("pipelined (invoke on its own thread)" in stdout) == (flag == "--pipeline")
        assert "Delivered:" in stdout
    assert _records(outs["--pipeline"]) == _records(outs["--no-pipeline"])


class LiveList(ListSource):
    """Frames of a camera the model kept up with only now and then: their indices count every captured frame."""

    live = True

    def __init__(self, images, indices):
        super().__init__(images)
        self.indices = indices

    def __iter__(self):
        self.end_reason = "running"
        for index, image in zip(self.indices, self.images):
            yield Frame(index, image, time.time(), self.name)
        self.end_reason = "stopped"


class CountingVideo:
    def __init__(self):
        self.frames = []

    def write(self, image):
        self.frames.append(image)


@pytest.mark.parametrize("pipelined", [False, True])
def test_a_live_run_s_video_holds_a_frame_over_the_camera_frames_the_model_had_no_time_for(model_path, pipelined):
    """--save-video from a camera faster than the model: written at the camera's rate, the video holds each frame
    until the next processed one, so it plays in real time (it played 5x too fast with the dropped frames left out)."""
    model = KeypointModel(model_path, 1)
    video = CountingVideo()
    source = LiveList(_frames(4), [0, 3, 4, 9])
    summary = run_stream(model, source, video=video, pipelined=pipelined)
    assert summary.frames == 4 and len(video.frames) == 10
    held = [next(i for i, f in enumerate(video.frames) if f is frame) for frame in video.frames]
    assert held == [0, 0, 0, 3, 4, 4, 4, 4, 4, 9]  # frame 0 three times, 3, then 4 held until 9
