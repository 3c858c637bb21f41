"""`--source picamera2`: the Raspberry Pi camera module through Picamera2, against a stand-in module.

tests/standins/picamera2 implements the calls the source makes with Picamera2's documented
semantics (a plain configuration dict, "RGB888" = B, G, R bytes, capture_array waiting for the
next frame of a sensor that runs at its own rate, stop/close); tests/standins/simplejpeg fails
under numpy 2 as apt's build for numpy 1.x does. The structured model of test_runtime.py gives
known keypoints, so a frame delivered in the wrong channel order would move them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.cli import main
from fcnpose_tf.errors import UserError
from fcnpose_tf.runtime import sources as rsources
from test_runtime import BLOCKER, expected_keypoints, quadrant_frame
from test_run_bench_cli import _one_line_error, _run, model_path  # noqa: F401 - model_path is a fixture

STANDINS = Path(__file__).parent / "standins"


@pytest.fixture
def standin(monkeypatch, tmp_path):
    """The stand-in picamera2 importable in this process, seeing quadrant_frame; yields its STANDIN dict."""
    for name in ("picamera2", "simplejpeg"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.delenv("SIMPLEJPEG_STANDIN_BUILT_FOR", raising=False)
    monkeypatch.syspath_prepend(str(STANDINS))
    scene = tmp_path / "scene.png"
    cv2.imwrite(str(scene), quadrant_frame(640, 480, "tl"))
    import picamera2

    picamera2.STANDIN.clear()
    picamera2.STANDIN.update(scene=str(scene), log=str(tmp_path / "camera.log"))
    picamera2.OPENED.clear()
    yield picamera2.STANDIN
    for camera in picamera2.OPENED:
        camera.close()


def _events(standin) -> list[str]:
    return Path(standin["log"]).read_text().splitlines()


def test_frames_are_bgr_at_the_configured_size(standin):
    import picamera2

    with rsources.open_source("picamera2", (320, 240)) as src:
        assert isinstance(src, rsources.Picamera2Source) and src.live and src.fps == pytest.approx(30.0, abs=0.01)
        frames = []
        for frame in src:
            frames.append(frame)
            if len(frames) == 3:
                break
    camera = picamera2.OPENED[0]
    assert camera.camera_config["main"] == {"format": "RGB888", "size": (320, 240)}
    want = cv2.resize(quadrant_frame(640, 480, "tl"), (320, 240), interpolation=cv2.INTER_AREA)
    for frame in frames:
        assert frame.image.shape == (240, 320, 3) and frame.image.flags.c_contiguous
        assert np.array_equal(frame.image, want)  # RGB888's bytes are B, G, R: OpenCV's order, unconverted
        assert abs(time.time() - frame.timestamp) < 5 and frame.name == "picamera2 camera 0"
    assert src.describe() == "picamera2 camera 0 (320x240 RGB888 = BGR bytes)"
    assert _events(standin) == ["open 0", "configure RGB888 320x240", "start", "stop", "close"]


def test_only_the_newest_frame_is_kept_and_drops_are_counted(standin):
    standin["fps"] = 500  # a 2 ms sensor; the consumer below takes 50 ms per frame
    src = rsources.Picamera2Source(0)
    seen = []
    for frame in src:
        seen.append(frame.index)
        time.sleep(0.05)
        if len(seen) == 8:
            break
    src.close()
    assert seen == sorted(seen) and len(set(seen)) == 8
    # stale frames were dropped, not queued (a queue hands over 0, 1, 2, ...); how many depends on how often the
    # stand-in's thread runs, which a loaded machine slows down, so only that some were
    assert np.diff(seen).max() > 1
    assert src.dropped == seen[-1] + 1 - len(seen) > 0
    assert not src._thread.is_alive() and _events(standin)[-2:] == ["stop", "close"]


def test_a_camera_that_raises_mid_run_ends_it(standin):
    standin.update(fps=200, fail_after=5)
    messages = []
    src = rsources.Picamera2Source(0, warn=messages.append)
    frames = list(src)
    src.close()
    assert 1 <= len(frames) <= 5
    assert src.end_reason == "picamera2 camera 0 failed: Device timeout detected, attempting a restart"
    assert messages == [src.end_reason] and _events(standin)[-2:] == ["stop", "close"] and src.failed


def test_a_camera_that_stops_delivering_ends_the_run(standin):
    standin.update(fps=200, hang_after=3)
    messages = []
    src = rsources.Picamera2Source(0, warn=messages.append, stall_timeout_s=0.1)
    frames = list(src)
    assert len(frames) <= 3 and "sent no frame within 0.2 s (disconnected?)" in src.end_reason and messages
    assert src.failed
    src.close()  # stop() releases the capture_array that waits forever
    assert not src._thread.is_alive() and _events(standin)[-2:] == ["stop", "close"]


def test_cameras_that_cannot_be_opened(standin):
    with pytest.raises(UserError, match=r"picamera2 camera 1: cannot be opened \(Camera __init__ sequence did "
                                        r"not complete.\); .*rpicam-hello --list-cameras"):
        rsources.open_source("picamera2:1")
    with rsources.open_source("picamera2:0"):
        with pytest.raises(UserError, match="picamera2 camera 0: cannot be opened"):  # held by the first
            rsources.open_source("picamera2")
    for spec in ("picamera2:x", "picamera2:", "picamera2:-1"):
        with pytest.raises(UserError, match="expected picamera2 or picamera2:N"):
            rsources.open_source(spec)
    with pytest.raises(UserError, match="picamera2-1: no such file or folder"):  # other names are paths
        rsources.open_source("picamera2-1")


def test_missing_picamera2_names_the_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import picamera2 -> ModuleNotFoundError
    with pytest.raises(UserError) as exc:
        rsources.open_source("picamera2")
    message = str(exc.value)
    assert message.startswith("--source picamera2 needs the picamera2 package, which ")
    for fix in ("sudo apt install -y python3-picamera2", "python3 -m venv --system-site-packages",
                "pip install 'fcnpose-tf[pi-camera]'", "docs/raspberry-pi.md"):
        assert fix in message


@pytest.mark.parametrize("failure", ["cython", "import_array"])
def test_numpy_mismatch_is_detected_and_explained(standin, monkeypatch, capfd, failure):
    import numpy

    for name in ("picamera2", "simplejpeg"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.setenv("SIMPLEJPEG_STANDIN_BUILT_FOR", "numpy1")
    monkeypatch.setenv("SIMPLEJPEG_STANDIN_FAILURE", failure)
    with pytest.raises(UserError) as exc:
        rsources.open_source("picamera2")
    message = str(exc.value)
    assert int(numpy.__version__.split(".")[0]) >= 2  # the environment the trap needs
    assert f"picamera2 cannot be imported with numpy {numpy.__version__}" in message
    assert f"{os.sep}simplejpeg{os.sep}__init__.py" in message  # where it broke
    assert "install numpy < 2 into the venv with `pip install 'fcnpose-tf[pi-camera]'`" in message
    assert "\n" not in message
    assert "compiled using NumPy 1.x" not in capfd.readouterr().err  # numpy's own essay kept off the terminal


def test_a_numpy2_build_in_a_numpy1_venv_is_explained(standin, monkeypatch):
    import numpy

    for name in ("picamera2", "simplejpeg"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.setattr(numpy, "__version__", "1.26.4")  # as in a venv made with the pi-camera extra
    monkeypatch.setenv("SIMPLEJPEG_STANDIN_BUILT_FOR", "numpy2")
    with pytest.raises(UserError, match=r"cannot be imported with numpy 1\.26\.4 .* `pip uninstall simplejpeg "
                                        r"picamera2` in the venv"):
        rsources.open_source("picamera2")


def test_run_cli_on_the_camera_module(capsys, tmp_path, standin, model_path):
    out = tmp_path / "k.jsonl"
    code, stdout, err = _run(capsys, "run", model_path, "--source", "picamera2", "--camera-size", "320x240",
                             "--out", out, "--max-frames", 6, "--threads", 1, "--via", tmp_path / "via" / "cam.json",
                             "--via-every", 2)
    assert code == 0, err
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 6
    want = expected_keypoints(320, 240, "tl")
    for record in records:
        kp = record["keypoints"]
        assert (kp[0]["x"], kp[0]["y"]) == pytest.approx(tuple(want[0]), abs=0.01)  # red found where it is
        assert (kp[2]["x"], kp[2]["y"]) == pytest.approx(tuple(want[2]), abs=0.01)  # blue too
    last = records[-1]["frame"]
    assert f"Frames:  6 processed, 0 skipped (unreadable), {last + 1 - 6} dropped" in stdout
    assert "Source:  picamera2 camera 0 (320x240 RGB888 = BGR bytes); stopped: reached --max-frames 6" in stdout
    assert "Latency: capture to keypoints written" in stdout and "p95" in stdout
    saved = sorted((tmp_path / "via" / "images").glob("picamera2-camera-0_*.png"))
    assert [int(p.stem[-6:]) for p in saved] == [r["frame"] for r in records[::2]]  # processed frames 1, 3, 5
    assert "cam.json: 3 frames" in stdout
    assert _events(standin)[-2:] == ["stop", "close"]


def test_a_camera_that_fails_mid_run_ends_run_with_status_1_and_its_outputs_kept(capsys, tmp_path, standin,
                                                                                   model_path):
    """A camera that fails is not a clean stop: a script or a systemd unit (Restart=on-failure) can tell them apart
    by the status (1: done, part of the work failed), and the records written are kept."""
    standin.update(fps=200, fail_after=5)
    out = tmp_path / "k.jsonl"
    code, stdout, err = _run(capsys, "run", model_path, "--source", "picamera2", "--out", out, "--threads", 1)
    assert code == 1, err
    assert err.strip().splitlines()[-1] == ("error: picamera2 camera 0 failed: Device timeout detected, attempting a "
                                            "restart: the run ended early (its outputs are kept)")
    assert 1 <= len(out.read_text().splitlines()) <= 5 and "Frames:  " in stdout


def test_run_cli_errors_are_one_line(capsys, tmp_path, standin, model_path, monkeypatch):
    code, _, err = _run(capsys, "run", model_path, "--source", "picamera2:3", "--out", tmp_path / "k.jsonl")
    _one_line_error(code, err, "picamera2 camera 3: cannot be opened")
    assert not (tmp_path / "k.jsonl").exists()
    monkeypatch.setitem(sys.modules, "picamera2", None)
    code, _, err = _run(capsys, "run", model_path, "--source", "picamera2", "--out", tmp_path / "k.jsonl")
    _one_line_error(code, err, "--source picamera2 needs the picamera2 package")


@pytest.fixture
def no_tf_camera_env(tmp_path) -> dict:
    """This Python with TensorFlow unimportable (as on a Pi) and the stand-in picamera2 on the path."""
    folder = tmp_path / "no_tf"
    folder.mkdir()
    (folder / "sitecustomize.py").write_text(BLOCKER + "\nimport faulthandler, signal\n"
                                             "faulthandler.register(signal.SIGUSR1, all_threads=True)\n")
    scene = tmp_path / "scene.png"
    cv2.imwrite(str(scene), quadrant_frame(640, 480, "tl"))
    paths = [str(folder), str(STANDINS)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return dict(os.environ, PYTHONPATH=os.pathsep.join(paths), TF_CPP_MIN_LOG_LEVEL="2",
                PICAMERA2_STANDIN=json.dumps({"scene": str(scene), "log": str(tmp_path / "camera.log")}))


INHERITED_SIGINT = {"terminal": signal.SIG_DFL, "background": signal.SIG_IGN}
"""SIGINT's action as a command inherits it: started in a terminal, or in the background from a script
(`cmd &` in `sh -c`), where the shell sets it ignored; a test suite started so passes that on to every
command it starts."""


@pytest.mark.parametrize("inherited", INHERITED_SIGINT)
@pytest.mark.parametrize("sig, reason", [(signal.SIGINT, "interrupted (Ctrl-C)"),
                                         (signal.SIGTERM, "terminated (SIGTERM)")])
def test_ctrl_c_and_sigterm_end_a_camera_run_cleanly_without_tensorflow(tmp_path, model_path, no_tf_camera_env,
                                                                         sig, reason, inherited):
    """Also a run started in the background: the ignored SIGINT it inherits must not make Ctrl-C a no-op."""
    out = tmp_path / "k.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "fcnpose_tf", "run", str(model_path), "--source", "picamera2",
                             "--threads", "1", "--out", str(out), "--via", "hard/frames.json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=no_tf_camera_env,
                            cwd=tmp_path, preexec_fn=lambda: signal.signal(signal.SIGINT, INHERITED_SIGINT[inherited]))
    deadline = time.monotonic() + PROCESS_TIMEOUT
    while time.monotonic() < deadline and proc.poll() is None and not (out.exists() and out.stat().st_size > 0):
        time.sleep(0.02)
    assert proc.poll() is None and out.stat().st_size > 0, proc.communicate()[1]
    proc.send_signal(sig)
    try:
        stdout, stderr = proc.communicate(timeout=PROCESS_TIMEOUT)
    except subprocess.TimeoutExpired:  # show where every thread is, then fail
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2)
        proc.kill()
        stdout, stderr = proc.communicate()
        pytest.fail(f"the run did not end within 120 s of the signal; its threads:\n{stderr[-8000:]}")
    assert proc.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig], stdout + stderr
    assert f"stopped: {reason}" in stdout and "Latency: capture to keypoints written" in stdout
    assert stderr.splitlines()[-1].startswith(f"{reason}; kept the files completed before it: {out}")
    lines = out.read_text().splitlines()
    assert f"Wrote:   {out} ({len(lines)} records)" in stdout
    assert "Traceback" not in stderr
    log = (tmp_path / "camera.log").read_text().splitlines()
    assert log[0] == "open 0" and log[1] == "configure RGB888 640x480" and log[-2:] == ["stop", "close"]
    from fcnpose_tf.data.via import read_via

    saved = sorted((tmp_path / "hard" / "images").glob("*.png"))
    via_frames = read_via(tmp_path / "hard" / "frames.json", min_visible=0).frames
    assert len(via_frames) == len(saved) == len(lines) > 0  # every saved frame is in the project and the records


def test_numpy_mismatch_is_one_line_from_the_command(tmp_path, model_path, no_tf_camera_env):
    env = dict(no_tf_camera_env, SIMPLEJPEG_STANDIN_BUILT_FOR="numpy1", SIMPLEJPEG_STANDIN_FAILURE="import_array")
    result = subprocess.run([sys.executable, "-m", "fcnpose_tf", "run", str(model_path), "--source", "picamera2",
                             "--out", "k.jsonl"], env=env, cwd=tmp_path, capture_output=True, text=True,
                          timeout=PROCESS_TIMEOUT)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0, result.stderr  # numpy's explanation is not on the terminal
    assert result.stderr.startswith("error: --source picamera2: picamera2 cannot be imported with numpy 2")
    assert "pip install 'fcnpose-tf[pi-camera]'" in result.stderr and not (tmp_path / "k.jsonl").exists()
