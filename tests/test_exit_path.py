"""One exit path for every command: however a command ends (a user error, an OSError, Ctrl-C, SIGTERM),
what it created and did not complete is gone, what it completed is named, in one line with a documented
exit status (2; 130 for SIGINT, 143 for SIGTERM)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.cli import main
from fcnpose_tf.data.via import read_via

LONG = "n" * 300  # longer than any file system's file name limit (255 bytes)
STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}
LINE = {signal.SIGINT: "interrupted (Ctrl-C)", signal.SIGTERM: "terminated (SIGTERM)"}


@pytest.fixture(scope="module")
def tflite_model(tmp_path_factory, structured_tflite):
    """The hand-set FCN-Pose of test_runtime as a .tflite file (converted once per session)."""
    path = tmp_path_factory.mktemp("exit_models") / "structured.tflite"
    path.write_bytes(structured_tflite)
    return path


def _one_error_line(status, err, *parts):
    assert status == 2, err
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and err.strip().splitlines()[-1] == lines[0], err  # the last line, the only error
    for part in parts:
        assert part in lines[0], err
    return lines[0]


# -- 1. what a failed command created up front goes ------------------------------------------------------

def _empty_folder(tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    return folder


USER_ERRORS = {
    "predict --via": lambda t, m: ["predict", m, "--source", _empty_folder(t), "--via", t / "out" / "p.json"],
    "run --out": lambda t, m: ["run", m, "--source", _empty_folder(t), "--out", t / "out" / "k.jsonl"],
    "run --save-video": lambda t, m: ["run", m, "--source", _empty_folder(t), "--save-video", t / "out" / "v.avi"],
    "run --via": lambda t, m: ["run", m, "--source", _empty_folder(t), "--via", t / "out" / "sub" / "p.json"],
    "bench --json": lambda t, m: ["bench", m, "--image", t / "missing.png", "--json", t / "out" / "b.json"],
    "evaluate --json": lambda t, m: ["evaluate", m, "--data", _empty_folder(t), "--json", t / "out" / "e.json"],
    "data inspect --out": lambda t, m: ["data", "inspect", _empty_folder(t), "--out", t / "out" / "p.png"],
}


@pytest.mark.parametrize("case", USER_ERRORS)
def test_a_user_error_leaves_no_folder_the_command_created(tmp_path, tflite_model, capsys, case):
    args = USER_ERRORS[case](tmp_path, tflite_model)
    status = main(list(map(str, args)))
    _one_error_line(status, capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_train_with_bad_data_leaves_no_output_folder(tmp_path, capsys):
    status = main(["train", "--data", str(_empty_folder(tmp_path)), "--out", str(tmp_path / "models" / "m.keras"),
                   "--init", "none", "--augment", "paper"])
    _one_error_line(status, capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]



@pytest.mark.parametrize("args", [["data", "inspect", "{data}", "--split-seed", "-1"],
                                  ["train", "--data", "{data}", "--out", "{out}", "--init", "none", "--seed", "-1"]],
                         ids=["split-seed", "seed"])
def test_a_negative_seed_is_one_line_not_a_traceback(tmp_path, capsys, args):
    from tests.test_via import write_dataset

    via, _ = write_dataset(tmp_path / "d", n=4)
    status = main([a.format(data=via, out=tmp_path / "models" / "m.keras") for a in args])
    _one_error_line(status, capsys.readouterr().err, "seed must be a whole number from 0 to 2**32 - 1, got -1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"] and not via.with_suffix(".splits.json").exists()

def test_ctrl_c_removes_what_the_command_made_and_exits_130(tmp_path, tflite_model, capsys, monkeypatch):
    from fcnpose_tf.runtime import bench

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(bench, "benchmark", interrupted)
    status = main(["bench", str(tflite_model), "--json", str(tmp_path / "out" / "deeper" / "b.json")])
    assert status == 130
    assert capsys.readouterr().err.splitlines() == ["interrupted (Ctrl-C)"]
    assert list(tmp_path.iterdir()) == []


def test_a_failed_command_names_what_it_completed_and_removes_the_rest(tmp_path, capsys):
    from fcnpose_tf import fileio
    from fcnpose_tf.commands import bench as bench_command
    from fcnpose_tf.errors import UserError

    def run(args):
        fileio.write_text(tmp_path / "out" / "done.txt", "kept")
        fileio.make_folder(tmp_path / "out" / "half" / "made")
        (tmp_path / "out" / "half" / "made" / "part").write_text("not completed")
        raise UserError("it went wrong")

    original = bench_command.run
    bench_command.run = run
    try:
        status = main(["bench", "m.tflite", "--json", str(tmp_path / "out" / "b.json")])
    finally:
        bench_command.run = original
    line = _one_error_line(status, capsys.readouterr().err)
    assert line == f"error: it went wrong; kept the files completed before it: {tmp_path / 'out' / 'done.txt'}"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["done.txt"]


# -- 2. a name longer than the file system takes: one line naming it ---------------------------------------

LONG_NAMES = {
    "bench --json": lambda t, m: ["bench", m, "--json", t / LONG / "b.json"],
    "bench model": lambda t, m: ["bench", t / f"{LONG}.tflite"],
    "run --source": lambda t, m: ["run", m, "--source", t / f"{LONG}.mp4"],
    "run --out": lambda t, m: ["run", m, "--source", t / "x.mp4", "--out", t / f"{LONG}.jsonl"],
    "predict --via": lambda t, m: ["predict", m, "--source", t, "--via", t / f"{LONG}.json"],
    "predict --source": lambda t, m: ["predict", m, "--source", t / LONG, "--via", t / "p.json"],
    "evaluate --data": lambda t, m: ["evaluate", m, "--data", t / LONG],
    "evaluate --json": lambda t, m: ["evaluate", m, "--data", t, "--json", t / "o" / f"{LONG}.json"],
    "data inspect": lambda t, m: ["data", "inspect", t / f"{LONG}.json"],
    "synth --out": lambda t, m: ["synth", "--out", t / LONG, "--n", "1"],
    "train --out": lambda t, m: ["train", "--data", t, "--out", t / f"{LONG}.keras"],
    "export --out-dir": lambda t, m: ["export", t / "m.keras", "--out-dir", t / LONG],
    "compress --out-dir": lambda t, m: ["compress", "--rate", "0.5", "--out-dir", t / LONG],
    "sweep --out": lambda t, m: ["sweep", "--out", t / LONG, "--report-only"],
}


@pytest.mark.parametrize("case", LONG_NAMES)
def test_a_file_name_too_long_is_one_line_naming_it(tmp_path, tflite_model, capsys, case):
    status = main(list(map(str, LONG_NAMES[case](tmp_path, tflite_model))))
    _one_error_line(status, capsys.readouterr().err, LONG, "file name too long")
    assert not any(LONG in p.name for p in tmp_path.rglob("*"))


# -- 3. an image file name that is not UTF-8 --------------------------------------------------------------

@pytest.fixture
def odd_name_folder(tmp_path):
    """A folder with two frames, one named `im\\xe9.png` (Latin-1 bytes, not UTF-8)."""
    import cv2
    import numpy as np

    folder = tmp_path / "frames"
    folder.mkdir()
    frame = np.zeros((64, 64, 3), np.uint8)
    frame[:32, :32] = 255
    cv2.imwrite(str(folder / "a.png"), frame)
    odd = os.path.join(os.fsencode(folder), b"im\xe9.png")
    os.rename(os.fsencode(folder / "a.png"), odd)
    cv2.imwrite(str(folder / "b.png"), frame)
    return folder, os.fsdecode(odd)


def test_image_names_that_are_not_utf8_are_read(cli, tmp_path, tflite_model, odd_name_folder):
    folder, odd = odd_name_folder
    proc = cli("run", tflite_model, "--source", folder, "--threads", "1", "--out", tmp_path / "k.jsonl")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "skipped" not in proc.stderr
    assert len((tmp_path / "k.jsonl").read_text().splitlines()) == 2
    proc = cli("predict", tflite_model, "--source", folder, "--threads", "1", "--via", folder / "pre.json")
    assert proc.returncode == 0, proc.stderr
    from fcnpose_tf.data.via import read_via

    assert sorted(f.image_path.name for f in read_via(folder / "pre.json", min_visible=0).frames) == \
        sorted(["b.png", os.path.basename(odd)])
    proc = cli("bench", tflite_model, "--image", odd, "--frames", "2", "--warmup", "0", "--threads", "1")
    assert proc.returncode == 0, proc.stderr


def test_video_names_that_are_not_utf8_are_read_and_written(cli, tmp_path, tflite_model):
    from test_runtime import RED_CYCLE, quadrant_frame, write_video

    video = write_video(tmp_path / "clip.avi", [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(4)])
    odd = os.fsdecode(os.path.join(os.fsencode(tmp_path), b"clip\xe9.avi"))
    os.rename(video, odd)
    overlay = os.fsdecode(os.path.join(os.fsencode(tmp_path), b"overlay\xe9.avi"))
    proc = cli("run", tflite_model, "--source", odd, "--threads", "1", "--save-video", overlay,
               "--out", tmp_path / "k.csv")
    assert proc.returncode == 0, proc.stderr
    rows = (tmp_path / "k.csv").read_text("utf-8").splitlines()  # still UTF-8 text, the name escaped
    assert os.path.getsize(overlay) > 0 and len(rows) == 5 and "clip\\udce9.avi" in rows[1]


def test_read_image_takes_any_name_and_reads_what_imread_reads(odd_name_folder):
    import cv2
    import numpy as np

    from fcnpose_tf.preprocess import read_image

    folder, odd = odd_name_folder
    assert np.array_equal(read_image(odd), cv2.imread(str(folder / "b.png")))
    assert read_image(folder) is None and read_image(folder / "missing.png") is None


# -- 4. SIGTERM and SIGINT end every command the same way ----------------------------------------------------

def _start(tmp_path, *args, env=None):
    """`python -m fcnpose_tf ARGS` in the background, its output in files (no pipe to fill and block it)."""
    out, err = open(tmp_path / "stdout.txt", "w"), open(tmp_path / "stderr.txt", "w")
    proc = subprocess.Popen([sys.executable, "-m", "fcnpose_tf", *map(str, args)], stdout=out, stderr=err,
                            cwd=tmp_path, env=dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", **(env or {})))
    out.close()
    err.close()
    return proc


def _exists(test):
    try:
        return bool(test())
    except OSError:  # a folder renamed or removed while it was looked at
        return False


def _signal_once_started(proc, sig, started, what, timeout=PROCESS_TIMEOUT):
    """Poll (no fixed sleep) until `started()` holds, send `sig`, and wait for the end; returns (stdout, stderr)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None and not _exists(started):
        time.sleep(0.05)
    assert proc.poll() is None, f"the command ended before {what}"
    assert _exists(started), f"{what} did not happen within {timeout} s"
    proc.send_signal(sig)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"the command did not end within {timeout} s of the signal")
    return proc.returncode


def _outputs(tmp_path):
    return (tmp_path / "stdout.txt").read_text(), (tmp_path / "stderr.txt").read_text()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_synth_stopped_leaves_nothing_and_a_rerun_works(tmp_path, sig):
    ds = tmp_path / "ds"
    proc = _start(tmp_path, "synth", "--out", ds, "--n", "3000", "--width", "64", "--height", "64",
                  "--workers", "1", "--quiet")
    status = _signal_once_started(proc, sig, lambda: any(ds.rglob("*.png")), "the first frame")
    stdout, stderr = _outputs(tmp_path)
    assert status == STATUS[sig], stderr
    assert stderr.splitlines() == [LINE[sig]]
    assert not ds.exists()
    assert main(["synth", "--out", str(ds), "--n", "2", "--width", "64", "--height", "64", "--quiet"]) == 0


def test_synth_force_stopped_keeps_the_earlier_set_whole(tmp_path):
    ds = tmp_path / "ds"
    assert main(["synth", "--out", str(ds), "--n", "3", "--width", "64", "--height", "64", "--workers", "1",
                 "--quiet"]) == 0
    before = {p.relative_to(ds): p.read_bytes() for p in ds.rglob("*") if p.is_file()}
    proc = _start(tmp_path, "synth", "--out", ds, "--n", "3000", "--seed", "1", "--width", "64", "--height", "64",
                  "--workers", "1", "--quiet", "--force")

    def new_frame():
        return any(p.name.endswith(".png") and p.relative_to(ds) not in before for p in ds.rglob("*"))

    status = _signal_once_started(proc, signal.SIGTERM, new_frame, "the first new frame")
    assert status == 143, _outputs(tmp_path)[1]
    after = {p.relative_to(ds): p.read_bytes() for p in ds.rglob("*") if p.is_file()}
    assert after == before and sorted(p.name for p in ds.iterdir()) == ["images", "ur5_synth.json"]


def test_a_pipe_whose_reader_has_gone_loses_the_report_not_the_files(tmp_path):
    """`synth ... | head -1`: the reader gone (here before the first line), the command still writes every frame and
    its project and ends with status 0 and nothing on stderr; what it would have printed is dropped."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # every write to the pipe now fails with EPIPE
    ds = tmp_path / "ds"
    try:
        done = subprocess.run([sys.executable, "-m", "fcnpose_tf", "synth", "--out", str(ds), "--n", "3", "--width",
                               "64", "--height", "64", "--workers", "1"], stdout=write_end, stderr=subprocess.PIPE,
                              text=True, cwd=tmp_path, timeout=PROCESS_TIMEOUT,
                              env=dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2"))
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr) == (0, "")
    assert len(read_via(ds / "ur5_synth.json").frames) == 3
    assert sorted(p.name for p in (ds / "images").iterdir()) == [f"synth_{i:05d}.png" for i in range(3)]


def _tmpdir_holds_a_file(tmpdir):
    return any(p.is_file() for p in tmpdir.rglob("*"))


@pytest.mark.slow
def test_export_stopped_leaves_no_out_dir_and_nothing_in_tmpdir(tmp_path):
    from fcnpose_tf.training.model import build_fcn_pose

    model = tmp_path / "m.keras"
    build_fcn_pose(input_size=64).save(model)
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    proc = _start(tmp_path, "export", model, "--out-dir", tmp_path / "out", "--quantize", "float16",
                  env={"TMPDIR": str(tmpdir)})
    status = _signal_once_started(proc, signal.SIGTERM, lambda: _tmpdir_holds_a_file(tmpdir),
                                  "the converter's first temporary file")
    stdout, stderr = _outputs(tmp_path)
    assert status == 143, stderr
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == "terminated (SIGTERM)"
    assert not (tmp_path / "out").exists()
    assert list(tmpdir.iterdir()) == []


@pytest.mark.slow
def test_train_stopped_says_so_in_one_line_with_the_signal_status(tmp_path):
    from test_reliability import TINY_TRAIN, _frames_with_stored_splits

    data = _frames_with_stored_splits(tmp_path / "d")
    out = tmp_path / "models" / "m.keras"
    proc = _start(tmp_path, "train", "--data", data, "--out", out, "--epochs", "500", *TINY_TRAIN)
    status = _signal_once_started(proc, signal.SIGTERM, lambda: (out.parent / "m.ckpt" / "state.json").is_file(),
                                  "the first epoch's checkpoint")
    stdout, stderr = _outputs(tmp_path)
    assert status == 143, stderr
    assert "Traceback" not in stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("terminated (SIGTERM): interrupted after ") and "--resume" in last, stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bench_stopped_removes_its_json_folder(tmp_path, tflite_model, sig):
    out = tmp_path / "out" / "b.json"
    proc = _start(tmp_path, "bench", tflite_model, "--threads", "1", "--frames", "100000000", "--warmup", "0",
                  "--json", out)
    status = _signal_once_started(proc, sig, lambda: (tmp_path / "stdout.txt").stat().st_size > 0
                                  or (tmp_path / "stderr.txt").stat().st_size > 0, "the first line of output")
    stdout, stderr = _outputs(tmp_path)
    assert status == STATUS[sig], stderr
    assert stderr.strip().splitlines()[-1] == LINE[sig] and "Traceback" not in stderr
    assert not (tmp_path / "out").exists()


def test_the_private_temporary_folder_is_removed_and_a_killed_ones_later(tmp_path, monkeypatch, capsys):
    import tempfile

    from fcnpose_tf import fileio

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    seen = []

    def run(args):
        seen.append(tempfile.gettempdir())
        open(os.path.join(tempfile.mkdtemp(), "x"), "w").close()  # what a library leaves in $TMPDIR
        return 0

    from fcnpose_tf.commands import bench as bench_command

    stranded = tmp_path / f"fcnpose-tf.999999999-{fileio._host_tag()}.abcdefgh"  # a process that is gone
    stranded.mkdir()
    monkeypatch.setattr(bench_command, "run", run)
    assert main(["bench", "m.tflite"]) == 0
    assert seen and seen[0] != str(tmp_path) and os.path.dirname(seen[0]) == str(tmp_path)
    assert list(tmp_path.iterdir()) == [] and tempfile.gettempdir() == str(tmp_path)


# -- 5. JSON nested deeper than Python's parser goes ----------------------------------------------------------

@pytest.fixture
def nested(tmp_path):
    path = tmp_path / "deep" / "labels.json"
    path.parent.mkdir()
    path.write_text("[" * 200_000 + "]" * 200_000)
    return path


@pytest.mark.parametrize("command", ["data", "evaluate", "train"])
def test_deeply_nested_json_is_not_a_via_project(tmp_path, tflite_model, nested, capsys, command):
    args = {"data": ["data", "inspect", nested],
            "evaluate": ["evaluate", tflite_model, "--data", nested],
            "train": ["train", "--data", nested, "--out", tmp_path / "m.keras", "--init", "none", "--augment",
                      "paper"]}[command]
    status = main(list(map(str, args)))
    _one_error_line(status, capsys.readouterr().err, str(nested), "not a VIA project")


def test_a_deeply_nested_training_record_reads_as_none(tmp_path):
    from fcnpose_tf.records import training_record

    (tmp_path / "m_train.json").write_text("[" * 200_000 + "]" * 200_000)
    assert training_record(tmp_path / "m.keras") is None


# -- 6. a Keras model whose input size is not fixed -----------------------------------------------------------

@pytest.fixture(scope="module")
def dynamic_keras(tmp_path_factory):
    import tf_keras as keras

    inputs = keras.Input((None, None, 3))
    outputs = keras.layers.Conv2D(9, 3, padding="same", activation="sigmoid")(inputs)
    path = tmp_path_factory.mktemp("dynamic") / "dyn.keras"
    keras.Model(inputs, outputs).save(path)
    return path


@pytest.mark.parametrize("command", ["predict", "evaluate", "export"])
def test_a_keras_model_without_a_fixed_input_size_is_refused_with_how_to_fix_it(tmp_path, dynamic_keras, capsys,
                                                                               odd_name_folder, command):
    folder, _ = odd_name_folder
    args = {"predict": ["predict", dynamic_keras, "--source", folder, "--via", tmp_path / "out" / "p.json"],
            "evaluate": ["evaluate", dynamic_keras, "--data", tmp_path / "nothing"],
            "export": ["export", dynamic_keras, "--out-dir", tmp_path / "out"]}[command]
    status = main(list(map(str, args)))
    _one_error_line(status, capsys.readouterr().err, str(dynamic_keras), "input size is not fixed")
    assert not (tmp_path / "out").exists()


# -- 8. the smaller ones -------------------------------------------------------------------------------------

def test_bench_frame_size_is_bounded(capsys, monkeypatch):
    from fcnpose_tf.runtime import bench

    def load_frame(*args):  # a regression must fail here, not allocate 2.7 GB (and its copies) on the test machine
        raise AssertionError(f"a frame of {args[1]} was about to be made")

    monkeypatch.setattr(bench, "load_frame", load_frame)
    status = main(["bench", "m.tflite", "--frame-size", "30000x30000"])
    _one_error_line(status, capsys.readouterr().err, "--frame-size 30000x30000", "at most 8192")


def _disk_full_at_write(n: int, monkeypatch) -> None:
    """`fileio.write_bytes` fails as a full disk does (`PATH: no space left on device`) at its n-th call."""
    from fcnpose_tf import fileio

    original, calls = fileio.write_bytes, []

    def write_bytes(path, data, force=False):
        calls.append(path)
        if len(calls) == n:
            raise fileio.WriteError(f"{path}: no space left on device")
        return original(path, data, force)

    monkeypatch.setattr(fileio, "write_bytes", write_bytes)


def test_predict_on_a_full_disk_names_no_frame_and_leaves_no_folder(tmp_path, tflite_model, capsys, monkeypatch):
    """The third saved frame finds the disk full: the frames saved are parts of a project never written."""
    from test_runtime import RED_CYCLE, quadrant_frame, write_video

    video = write_video(tmp_path / "clip.avi", [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(8)])
    _disk_full_at_write(3, monkeypatch)
    status = main(["predict", str(tflite_model), "--source", str(video), "--threads", "1",
                   "--via", str(tmp_path / "p" / "pre.json")])
    line = _one_error_line(status, capsys.readouterr().err, "no space left on device")
    assert "kept" not in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.avi"]


def test_records_kept_after_a_failure_are_named(tmp_path, tflite_model, capsys, monkeypatch):
    """A run that fails after writing records keeps them (a stream of complete lines) and says so."""
    from fcnpose_tf.runtime import sinks
    from test_runtime import RED_CYCLE, quadrant_frame, write_video

    video = write_video(tmp_path / "clip.avi", [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(8)])
    original, calls = sinks.JsonlWriter.write, []

    def write(self, frame, prediction):
        calls.append(frame.index)
        if len(calls) == 3:
            raise OSError(28, "No space left on device", str(self.path))
        return original(self, frame, prediction)

    monkeypatch.setattr(sinks.JsonlWriter, "write", write)
    out = tmp_path / "o" / "k.jsonl"
    status = main(["run", str(tflite_model), "--source", str(video), "--threads", "1", "--out", str(out)])
    line = _one_error_line(status, capsys.readouterr().err)
    assert line == f"error: {out}: no space left on device; kept the files completed before it: {out}"
    assert len(out.read_text().splitlines()) == 2
    assert [json.loads(x)["frame"] for x in out.read_text().splitlines()] == [0, 1]


@pytest.mark.slow
def test_compress_stopped_while_retraining_leaves_nothing_and_suggests_no_resume(tmp_path):
    from fcnpose_tf.training.model import build_fcn_pose
    from test_reliability import _frames_with_stored_splits

    data = _frames_with_stored_splits(tmp_path / "d")
    base = tmp_path / "base.keras"
    build_fcn_pose(input_size=64).save(base)
    out = tmp_path / "out"
    proc = _start(tmp_path, "compress", "--rate", "0.7", "--model", base, "--data", data, "--retrain-epochs", "500",
                  "--quantize", "float16", "--out-dir", out, "--threads", "1")  # 6 frames: too few for int8's gate
    status = _signal_once_started(proc, signal.SIGTERM, lambda: (out / "base_p70.ckpt" / "state.json").is_file(),
                                  "the first retraining checkpoint")
    stdout, stderr = _outputs(tmp_path)
    assert status == 143, stderr
    assert "Traceback" not in stderr and "--resume" not in stderr
    assert stderr.strip().splitlines()[-1].startswith("terminated (SIGTERM)"), stderr
    assert not out.exists()


def test_a_sweep_stopped_by_sigterm_is_named_as_such():
    """The sweep's executor takes the signals while jobs run; the CLI still learns which one came (143, not 130)."""
    from fcnpose_tf import fileio
    from fcnpose_tf.sweep.executors import stop_on_signals

    with fileio.stop_signals_handled():
        with pytest.raises(KeyboardInterrupt):
            with stop_on_signals():
                signal.raise_signal(signal.SIGTERM)
        assert fileio.stop_signal() == signal.SIGTERM


def test_a_stop_signal_that_c_code_turned_into_another_exception_still_ends_as_the_stop(cli_here, monkeypatch):
    """SIGTERM's KeyboardInterrupt raised while C code runs (TensorFlow tracing a graph) can surface as a SystemError
    ("bad argument to internal function"): after a stop signal any exception ends with the signal's line and status,
    not a traceback; without one an unexpected exception is still a defect with its traceback."""
    from fcnpose_tf.commands import synth

    def mangled(args):
        try:
            signal.raise_signal(signal.SIGTERM)
        except KeyboardInterrupt:
            raise SystemError("Objects/listobject.c:338: bad argument to internal function") from None

    monkeypatch.setattr(synth, "run", mangled)
    status, _, err = cli_here("synth", "--out", "frames", "--n", "1")
    assert status == 143 and err.strip().splitlines() == ["terminated (SIGTERM)"]

    def defect(args):
        raise SystemError("a defect")

    monkeypatch.setattr(synth, "run", defect)
    with pytest.raises(SystemError, match="a defect"):
        cli_here("synth", "--out", "frames", "--n", "1")


def test_synth_on_a_full_disk_names_the_output_folder_not_its_staging_folder(tmp_path, capsys, monkeypatch):
    _disk_full_at_write(2, monkeypatch)
    out = tmp_path / "set"
    status = main(["synth", "--out", str(out), "--n", "3", "--width", "64", "--height", "48", "--workers", "1",
                   "--quiet"])
    line = _one_error_line(status, capsys.readouterr().err)
    assert line == f"error: {out}: no space left on device"
    assert list(tmp_path.iterdir()) == []
