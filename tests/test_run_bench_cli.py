"""`fcnpose-tf run` and `fcnpose-tf bench` as a user meets them: help, outputs, and one-line errors (exit 2).

Commands run in-process through `fcnpose_tf.cli.main` (fast); the subprocess
runs without TensorFlow live in test_runtime.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT

from fcnpose_tf.cli import build_parser, main
from test_runtime import RED_CYCLE, _convert_plain, expected_keypoints, quadrant_frame, write_video


@pytest.fixture(scope="module")
def model_path(tmp_path_factory, structured_tflite) -> Path:
    path = tmp_path_factory.mktemp("cli_models") / "structured.tflite"
    path.write_bytes(structured_tflite)
    return path


@pytest.fixture(scope="module")
def dense_model(tmp_path_factory) -> Path:
    import tf_keras as keras

    path = tmp_path_factory.mktemp("cli_models") / "dense.tflite"
    path.write_bytes(_convert_plain(keras.Sequential([keras.Input((16,)), keras.layers.Dense(4)])))
    return path


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    frames = [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(8)]
    return write_video(tmp_path_factory.mktemp("cli_video") / "clip.avi", frames)


def _run(capsys, *args):
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse refused an option
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(code, err, pattern):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("error: ") and pattern in lines[-1], err
    assert "Traceback" not in err


def test_help_lists_commands_and_examples(capsys):
    parser = build_parser()
    assert "run" in parser.format_help() and "bench" in parser.format_help()
    for command in ("run", "bench"):
        with pytest.raises(SystemExit) as exc:
            parser.parse_args([command, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        assert "examples:" in text and f"fcnpose-tf {command} model.tflite" in text


def test_run_writes_records_and_prints_the_summary(capsys, tmp_path, model_path, video):
    out = tmp_path / "k.jsonl"
    code, stdout, err = _run(capsys, "run", model_path, "--source", video, "--out", out, "--max-frames", 5,
                             "--threads", 1)
    assert code == 0, err
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 5
    assert records[3]["keypoints"][0]["x"] == pytest.approx(expected_keypoints(320, 240, RED_CYCLE[3])[0, 0])
    for expected in ("reached --max-frames 5", "Frames:  5 processed", "preprocess", "invoke", "postprocess",
                     "end-to-end", "p50 (ms)", "p95 (ms)", "FPS:", "invoke-only", "1 thread;", "ai_edge_litert",
                     f"Wrote:   {out} (5 records)"):
        assert expected in stdout, expected


def test_run_never_overwrites_without_force(capsys, tmp_path, model_path, video):
    out = tmp_path / "k.jsonl"
    out.write_text("precious\n")
    code, _, err = _run(capsys, "run", model_path, "--source", video, "--out", out)
    _one_line_error(code, err, "already exists; pass --force")
    assert out.read_text() == "precious\n"
    code, _, err = _run(capsys, "run", model_path, "--source", video, "--out", out, "--force")
    assert code == 0, err
    assert len(out.read_text().splitlines()) == 8


def test_run_force_keeps_the_earlier_records_when_it_fails_before_a_frame(capsys, tmp_path, model_path, video):
    kept = {tmp_path / "k.jsonl": "precious\n", tmp_path / "k.csv": "a,b\n1,2\n"}
    for path, text in kept.items():
        path.write_text(text)
    outs = [arg for path in kept for arg in ("--out", path)]
    code, _, err = _run(capsys, "run", model_path, "--source", video, *outs, "--force",
                        "--save-video", tmp_path / "o.xyz")
    _one_line_error(code, err, "unknown video type")
    unreadable = tmp_path / "frames"
    unreadable.mkdir()
    (unreadable / "a.png").write_bytes(b"not a png")
    code, _, err = _run(capsys, "run", model_path, "--source", unreadable, *outs, "--force")
    assert code == 2, err
    assert {path: path.read_text() for path in kept} == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "k.csv", "k.jsonl"]


def test_run_single_image_csv_and_video(capsys, tmp_path, model_path):
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), quadrant_frame(400, 300, "bl"))
    code, stdout, err = _run(capsys, "run", model_path, "--source", image, "--out", tmp_path / "k.csv",
                             "--save-video", tmp_path / "o.avi")
    assert code == 0, err
    assert "Delivered: one frame (no rate), " in stdout and "nan" not in stdout
    lines = (tmp_path / "k.csv").read_text().splitlines()
    assert len(lines) == 2 and lines[0].startswith("frame,timestamp,source,width,height")
    row = dict(zip(lines[0].split(","), lines[1].split(",")))
    exp = expected_keypoints(400, 300, "bl")
    assert float(row["base_x"]) == pytest.approx(exp[0, 0]) and row["flange_x"] == ""
    cap = cv2.VideoCapture(str(tmp_path / "o.avi"))
    ok, first = cap.read()
    cap.release()
    assert ok and first.shape == (300, 400, 3)
    assert np.abs(first.astype(int) - quadrant_frame(400, 300, "bl").astype(int)).max() > 100  # overlay drawn


def test_run_truncated_video_ends_cleanly(capsys, tmp_path, model_path):
    frames = [quadrant_frame(320, 240, "tl") for _ in range(30)]
    full = write_video(tmp_path / "full.avi", frames)
    cut = tmp_path / "cut.avi"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    code, stdout, err = _run(capsys, "run", model_path, "--source", cut, "--out", tmp_path / "k.jsonl")
    assert code == 0, err
    assert "of 30 frames (truncated file or unreadable frame)" in stdout + err
    assert 0 < len((tmp_path / "k.jsonl").read_text().splitlines()) < 30


@pytest.mark.parametrize("args, message", [
    (["--source", "{missing}"], "no such file or folder"),
    (["--source", " "], "--source is empty"),  # an unset shell variable: not the current folder's images
    (["--source", "{video}", "--out", "records.jsonl"], "is a folder, expected a file path"),  # not "pass --force"
    (["--source", "{video}", "--smooth", "--smooth-min-cutoff", "0", "--smooth-coast", "-1"],
     "--smooth-min-cutoff must be above 0 Hz, got 0; --smooth-coast must be >= 0 frames, got -1"),
    (["--source", "97"], "camera 97: cannot be opened"),
    (["--source", "/dev/video97"], "no such camera device"),
    (["--source", "{video}", "--out", "k.txt"], "use .jsonl or .csv"),
    (["--source", "{video}", "--out", "k.jsonl", "--save-video", "k.jsonl"], "given both as --out and --save-video"),
    (["--source", "{video}", "--out", "k.jsonl", "--out", "k.jsonl"], "given twice"),
    (["--source", "{video}", "--save-video", "o.gif"], "unknown video type"),
    (["--source", "{video}", "--threads", "0"], "argument --threads: expected at least 1 thread, got 0"),
    (["--source", "{video}", "--max-frames", "0"], "--max-frames must be at least 1"),
    (["--source", "{video}", "--threshold", "1.5"], "threshold must be between 0 and 1"),
    (["--source", "{video}", "--fallback", "0.6"], "fallback threshold must be above 0 and below the threshold 0.5"),
    (["--source", "{video}", "--camera-size", "big"], "expected WIDTHxHEIGHT"),
    (["--source", "{video}", "--show"], "--show needs OpenCV with GUI support"),
    (["--source", "{video}", "--out", "k.jsonl", "--via", "v.txt"], "v.txt: a VIA project is a .json file"),
    (["--source", "{video}", "--out", "k.jsonl", "--via", "v.json", "--via-every", "0"],
     "--via-every must be at least 1"),
])
def test_run_user_errors(capsys, tmp_path, monkeypatch, model_path, video, args, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "records.jsonl").mkdir()  # a folder where a file is named
    args = [a.format(missing=tmp_path / "nope.mp4", video=video) for a in args]
    code, _, err = _run(capsys, "run", model_path, *args)
    _one_line_error(code, err, message)
    assert not (tmp_path / "k.jsonl").exists()  # nothing written for a run that never started


@pytest.mark.parametrize("command", ["run", "bench"])
def test_bad_models_are_user_errors(capsys, tmp_path, dense_model, video, command):
    extra = ["--source", video] if command == "run" else ["--frames", "2"]
    code, _, err = _run(capsys, command, dense_model, *extra)
    _one_line_error(code, err, "input shape [1, 16], expected [1, H, W, 3]")
    corrupt = tmp_path / "corrupt.tflite"
    corrupt.write_bytes(b"\x1c\x00\x00\x00TFL3" + bytes(64))
    code, _, err = _run(capsys, command, corrupt, *extra)
    _one_line_error(code, err, "cannot be loaded as a TFLite model")
    code, _, err = _run(capsys, command, tmp_path / "missing.tflite", *extra)
    _one_line_error(code, err, "model file not found")


def test_bench_table_markdown_and_json(capsys, tmp_path, model_path):
    out = tmp_path / "bench.json"
    code, stdout, err = _run(capsys, "bench", model_path, "--threads", "1,2", "--frames", 4, "--warmup", 1,
                             "--json", out, "--markdown")
    assert code == 0, err
    assert "| Threads | Status | Invoke p50 (ms)" in stdout and "FPS invoke |" in stdout
    assert "MACs per frame" in stdout and "parameters" in stdout
    assert "1 thread: 1 warm-up + 4 timed frames" in err
    data = json.loads(out.read_text())
    assert [r["threads"] for r in data["results"]] == [1, 2] and data["frames"] == 4
    assert data["frame"] == "synthetic 640x480" and data["fps_definition"].startswith("FPS = 1000 / mean")
    code, _, err = _run(capsys, "bench", model_path, "--frames", 2, "--json", out)
    _one_line_error(code, err, "already exists")


def test_a_stopped_bench_keeps_the_thread_counts_that_finished(capsys, tmp_path, model_path, monkeypatch):
    """Ctrl-C during a long run (a Pi's --frames 1000): the finished counts printed and written, status 130."""
    from fcnpose_tf.runtime import bench

    measured = bench.bench_threads
    calls = []

    def stopped_at_the_second_count(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return measured(*args, **kwargs)

    monkeypatch.setattr(bench, "bench_threads", stopped_at_the_second_count)
    out = tmp_path / "bench.json"
    code, stdout, err = _run(capsys, "bench", model_path, model_path, "--threads", "1,2,3", "--frames", 3,
                             "--warmup", 0, "--json", out)
    assert code == 130, err
    assert "Stopped: 1 of 3 thread counts finished." in stdout and stdout.count("Model:   ") == 1
    assert err.strip().splitlines()[-1].startswith("interrupted (Ctrl-C)") and str(out) in err
    data = json.loads(out.read_text())
    assert [r["threads"] for r in data["results"]] == [1] and data["stopped_after_of"] == [1, 3]
    calls.clear()
    monkeypatch.setattr(bench, "bench_threads", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    code, stdout, err = _run(capsys, "bench", model_path, "--threads", "1", "--frames", 3, "--json",
                             tmp_path / "none.json")  # stopped before anything finished: nothing written
    assert code == 130 and "Model:" not in stdout and not (tmp_path / "none.json").exists()


def test_bench_several_models_one_table_each(capsys, tmp_path, model_path):
    """`bench INT8 FP16`: the bundled int8 file beside another, each with its own header and table."""
    from fcnpose_tf.bundled import models_dir

    int8 = models_dir() / "fcnpose_ur5_p70_int8.tflite"
    out = tmp_path / "both.json"
    code, stdout, err = _run(capsys, "bench", int8, model_path, "--threads", "1", "--frames", 3, "--warmup", 1,
                             "--json", out)
    assert code == 0, err
    assert stdout.count("Model:   ") == 2 and stdout.index(int8.name) < stdout.index(str(model_path))
    assert "224x224x3 uint8 -> 224x224x9 int8" in stdout
    data = json.loads(out.read_text())
    assert [Path(m["model"]).name for m in data["models"]] == [int8.name, Path(model_path).name]
    assert all(m["results"][0]["threads"] == 1 for m in data["models"])
    comparison = stdout.split("Comparison (the models ran one after the other")[1].splitlines()
    assert f"FPS vs {int8.name}" in comparison[1]
    first, second = comparison[3], comparison[4]
    assert int8.name in first and first.rstrip().endswith("1.00x")
    fps = [float(data["models"][i]["results"][0]["fps_end_to_end"]) for i in (0, 1)]
    assert Path(model_path).name in second
    assert float(second.split()[-1].rstrip("x")) == pytest.approx(fps[1] / fps[0], abs=0.011)  # JSON FPS is rounded


def test_bench_on_a_real_image(capsys, tmp_path, model_path):
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), quadrant_frame(320, 240, "tr"))
    code, stdout, err = _run(capsys, "bench", model_path, "--threads", "1", "--frames", 3, "--image", image)
    assert code == 0, err
    assert f"frame: {image} (320x240)" in stdout


@pytest.mark.parametrize("args, message", [
    (["--threads", "0"], "expected positive integers"),
    (["--threads", "1,x"], "expected positive integers"),
    (["--frames", "0"], "--frames must be >= 1"),
    (["--image", "{missing}"], "image not found"),
    (["--image", "{folder}"], "a folder, not an image"),
    (["--frame-size", "640"], "expected WIDTHxHEIGHT"),
])
def test_bench_user_errors(capsys, tmp_path, model_path, args, message):
    args = [a.format(missing=tmp_path / "nope.png", folder=tmp_path) for a in args]
    code, _, err = _run(capsys, "bench", model_path, *args)
    _one_line_error(code, err, message)


def test_sigterm_ends_a_run_cleanly(tmp_path, model_path):
    """`kill` during a run: exit 143, summary printed, every record written so far is complete and named."""
    import time

    frames = [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(4)] * 1500
    long_video = write_video(tmp_path / "long.avi", frames, fps=30)
    out = tmp_path / "k.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "fcnpose_tf", "run", str(model_path), "--source", str(long_video),
                             "--threads", "1", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2"))
    deadline = time.monotonic() + PROCESS_TIMEOUT
    while time.monotonic() < deadline and proc.poll() is None and not (out.exists() and out.stat().st_size > 0):
        time.sleep(0.02)
    assert proc.poll() is None and out.stat().st_size > 0, "the run did not start writing records in time"
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 143, stderr
    assert "stopped: terminated (SIGTERM)" in stdout
    assert stderr.splitlines()[-1] == f"terminated (SIGTERM); kept the files completed before it: {out}"
    lines = out.read_text().splitlines()
    assert 0 < len(lines) < 6000 and f"Wrote:   {out} ({len(lines)} records)" in stdout
    assert [json.loads(line)["frame"] for line in lines] == list(range(len(lines)))


def test_run_smooth_filters_the_records(capsys, tmp_path, model_path, video):
    """--smooth: the first frame as found, then every record between the last smoothed one and the raw one."""
    raw_out, smooth_out = tmp_path / "raw.jsonl", tmp_path / "smooth.jsonl"
    assert _run(capsys, "run", model_path, "--source", video, "--out", raw_out, "--threads", 1)[0] == 0
    code, _, err = _run(capsys, "run", model_path, "--source", video, "--out", smooth_out, "--threads", 1, "--smooth")
    assert code == 0, err

    def xy(path):
        return np.array([[[k["x"], k["y"]] for k in json.loads(line)["keypoints"]]
                         for line in path.read_text().splitlines()], float)

    raw, smooth = xy(raw_out), xy(smooth_out)
    np.testing.assert_allclose(smooth[0], raw[0])
    ok = np.isfinite(raw[1:]) & np.isfinite(smooth[:-1]) & np.isfinite(smooth[1:])  # tracked in both frames
    moved = ok & (np.abs(raw[1:] - np.nan_to_num(smooth[:-1])) > 1.0)
    assert moved.any()
    lo, hi = np.minimum(raw[1:], smooth[:-1])[ok], np.maximum(raw[1:], smooth[:-1])[ok]
    assert np.all((smooth[1:][ok] >= lo - 0.01) & (smooth[1:][ok] <= hi + 0.01))
    assert np.all(np.abs(smooth[1:] - raw[1:])[moved] > 0.01)  # pulled back, not copied


def _unblock_unless_done(fifo: Path, done: threading.Event, timeout: float, unblocked: list) -> None:
    """After `timeout` s without `done`: open `fifo`'s writing end and close it (a reader blocked in open() goes on
    and reads its end), and note it in `unblocked`. Only a command that waits on the pipe gets there."""
    if done.wait(timeout):
        return
    while not done.is_set():
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            unblocked.append(True)
        except OSError:  # no reader on the pipe (yet)
            pass
        done.wait(0.1)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
@pytest.mark.parametrize("command, name", [("run", "feed.mp4"), ("run", "feed.png"), ("predict", "feed.mp4"),
                                           ("data", "labels.json")])
def test_a_named_pipe_is_refused_without_waiting_for_a_writer(tmp_path, model_path, command, name, cli_here):
    # Opening a FIFO blocks, in OpenCV's native code, until something writes to it: no signal ends the command. It
    # runs here (cli_here); a thread opens the pipe's other end if it still runs after 10 minutes (the cost of a
    # failure only), so that it ends and the test fails instead of hanging.
    fifo = tmp_path / name
    os.mkfifo(fifo)
    args = {"run": ["run", model_path, "--source", fifo, "--out", tmp_path / "k.jsonl"],
            "predict": ["predict", model_path, "--source", fifo, "--via", tmp_path / "p.json"],
            "data": ["data", "inspect", fifo]}[command]
    done, unblocked = threading.Event(), []
    watchdog = threading.Thread(target=_unblock_unless_done, args=(fifo, done, 600, unblocked), daemon=True)
    watchdog.start()
    try:
        status, _, err = cli_here(*args)
    finally:
        done.set()
        watchdog.join()
    assert not unblocked, f"{command} waited on the named pipe (ended by opening its other end)"
    assert status == 2, err
    assert err.strip().splitlines()[-1].startswith(f"error: {fifo}: is a named pipe"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_a_model_whose_path_is_not_utf8_loads(capsys, tmp_path, model_path):
    odd = tmp_path / "m\udce9.tflite"  # the byte \xe9 in the name (Latin-1), as Python holds it
    odd.write_bytes(model_path.read_bytes())
    code, out, err = _run(capsys, "bench", odd, "--frames", 2, "--threads", 1)
    assert code == 0, err


def test_run_reports_how_steady_the_keypoints_are_and_what_smoothing_did(capsys, tmp_path, model_path, video):
    from fcnpose_tf.smoothing import frame_step_px

    assert frame_step_px(None, np.zeros((2, 2))) is None
    assert frame_step_px(np.array([[0.0, 0.0], [np.nan, 0.0]]), np.array([[3.0, 4.0], [1.0, 1.0]])) == 5.0
    code, out, err = _run(capsys, "run", model_path, "--source", video, "--threads", 1)
    assert code == 0, err
    assert "Steadiness: keypoints moved a median" in out and "all jitter, which --smooth filters" in out
    code, out, err = _run(capsys, "run", model_path, "--source", video, "--threads", 1, "--smooth")
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("Smoothing: One-Euro filter (cut-off"))
    raw, written = (float(part.split(" px")[0].split()[-1]) for part in line.split("; ")[1].split(", ")[:2])
    assert written < raw  # the quadrant patch jumps every frame: the filter holds the keypoints back


def test_jitter_is_measured_on_still_frames_only(capsys, tmp_path, model_path):
    """run's Jitter line: the RMS keypoint step over frames whose image did not change (camera noise averages out
    in the thumbnail; a patch that moves does not), raw and, with --smooth, as written."""
    from fcnpose_tf.runtime.runner import _thumbnail
    from fcnpose_tf.smoothing import is_still, jitter_rms

    rng = np.random.default_rng(0)
    base = quadrant_frame(640, 480, "tl")
    noisy = lambda image: np.clip(image + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)  # noqa: E731
    assert is_still(_thumbnail(noisy(base)), _thumbnail(noisy(base)))
    shifted = np.roll(base, 1, axis=1)  # every edge one pixel to the right
    assert not is_still(_thumbnail(base), _thumbnail(shifted)) and not is_still(None, _thumbnail(base))
    assert jitter_rms([3.0, 4.0]) == pytest.approx(np.sqrt(12.5)) and np.isnan(jitter_rms([]))
    order = ["tl", "tl", "tl", "tl", "bl", "bl", "tl", "tl"]  # 5 still pairs, 2 that move
    clip = write_video(tmp_path / "still.avi", [noisy(quadrant_frame(320, 240, red)) for red in order])
    code, out, err = _run(capsys, "run", model_path, "--source", clip, "--threads", 1)
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("Jitter:"))
    assert "over 5 still frames" in line and "RMS 0.00 px as the model found them" in line, line
    code, out, err = _run(capsys, "run", model_path, "--source", clip, "--threads", 1, "--smooth")
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("Jitter:"))
    assert "over 5 still frames" in line and "px as written" in line, line
    moving = write_video(tmp_path / "moving.avi", [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(4)])
    code, out, err = _run(capsys, "run", model_path, "--source", moving, "--threads", 1)
    assert "Jitter:  no still frames" in out


def test_a_stop_signal_while_run_closes_its_outputs_waits_for_them(capsys, tmp_path, monkeypatch, model_path, video):
    """A second Ctrl-C (or a `kill`) while the outputs are being finished is remembered, not obeyed at once: the
    video and the VIA project with its frames are finished whole, named as kept, and no temporary video stays."""
    from fcnpose_tf.runtime.sinks import VideoSink

    close = VideoSink.close

    def close_stopped(self):
        os.kill(os.getpid(), signal.SIGINT)  # arrives while the video is being finished
        return close(self)

    monkeypatch.setattr(VideoSink, "close", close_stopped)
    out, clip, via = tmp_path / "k.jsonl", tmp_path / "o.avi", tmp_path / "via" / "p.json"
    code, _, err = _run(capsys, "run", model_path, "--source", video, "--out", out, "--save-video", clip, "--via", via,
                        "--via-every", 2, "--threads", 1)
    assert code == 130, err
    assert err.strip().splitlines()[-1].startswith("interrupted (Ctrl-C); kept the files completed before it: ")
    assert len(out.read_text().splitlines()) == 8
    capture = cv2.VideoCapture(str(clip))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 8
    capture.release()
    frames = read_via_frames(via)
    assert len(frames) == 4 and all((via.parent / "images" / name).is_file() for name in frames)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.jsonl", "o.avi", "via"]  # no temporary video


def read_via_frames(via: Path) -> list[str]:
    """The image file names a VIA project lists."""
    return [entry["filename"] for entry in json.loads(via.read_text())["_via_img_metadata"].values()]


class _ScriptedCapture:
    """A cv2.VideoCapture stand-in reading a script: True gives a frame, False a frame that cannot be decoded."""

    def __init__(self, script):
        self.script, self.at = list(script), 0

    def read(self):
        ok = self.at < len(self.script) and self.script[self.at]
        self.at += 1
        return (True, quadrant_frame(64, 48, "tl")) if ok else (False, None)

    def get(self, prop):
        return -1.0

    def release(self):
        pass


@pytest.mark.parametrize("script, read, skipped, ended", [
    ([True] * 4 + [False] + [True] * 3, [0, 1, 2, 3, 5, 6, 7], 1, "end of video"),  # a damaged frame: skipped
    ([True] * 3 + [False, False] + [True] * 3, [0, 1, 2, 5, 6, 7], 2, "end of video"),
    ([True] * 3 + [False] * 5, [0, 1, 2], 0, "video ended after 3 of 8 frames"),  # truncated: ends, nothing skipped
])
def test_a_video_frame_that_cannot_be_read_is_skipped_and_counted(video, script, read, skipped, ended):
    """One undecodable frame (a glitch on an SD card) is skipped with a warning, not the end of the video; frames
    that never come (a truncated file) end it where the readable part ends."""
    from fcnpose_tf.runtime.sources import VideoSource

    warnings = []
    source = VideoSource(video, warn=warnings.append)
    source._cap.release()
    source._cap, source.frame_count = _ScriptedCapture(script), len(script)
    source.MAX_UNREADABLE_IN_A_ROW = 4
    try:
        assert [frame.index for frame in source] == read
    finally:
        source.close()
    assert source.skipped == skipped and source.end_reason.startswith(ended)
    if skipped:
        assert any("cannot be read: skipped" in line for line in warnings)


def test_a_stream_whose_server_sends_nothing_is_refused_after_the_first_frame_timeout():
    """A stream server that accepts and never sends (rpicam-vid starting, a wrong port forward) held FFmpeg's open,
    and Ctrl-C with it, for 30 s; the open now gives up after the first frame's timeout, saying what to check."""
    import socket

    from fcnpose_tf.errors import UserError
    from fcnpose_tf.runtime.sources import CameraSource

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    accepted = []
    thread = threading.Thread(target=lambda: accepted.append(server.accept()), daemon=True)
    thread.start()
    try:
        with pytest.raises(UserError, match=r"no stream there within 1 s: is its server running, e\.g\. `rpicam-vid "
                                            r"--listen`"):
            CameraSource(f"tcp://127.0.0.1:{server.getsockname()[1]}", first_frame_timeout_s=1.0)
    finally:
        for connection, _ in accepted:
            connection.close()
        server.close()
