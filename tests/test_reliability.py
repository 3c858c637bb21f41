"""Failures a user can cause end in one `error:` line, exit 2, and leave nothing half-written."""

import errno
import json
import os
import signal

import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.cli import build_parser, main
from fcnpose_tf.progress import Reporter


@pytest.mark.parametrize("command", [
    ["train", "--data", "d", "--out", "m.keras"],
    ["compress", "--rate", "0.5"],
    ["sweep"],
    ["evaluate", "--data", "d"],
    ["run", "m.tflite", "--source", "0"],
    ["bench", "m.tflite"],
])
@pytest.mark.parametrize("threads", ["0", "-1", "two"])
def test_every_threads_option_refuses_counts_below_one_while_parsing(command, threads, capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([*command, "--threads", threads])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: argument --threads:") and threads in err and "Traceback" not in err


def test_threads_parse_to_whole_counts():
    args = build_parser().parse_args(["train", "--data", "d", "--out", "m.keras", "--threads", "3"])
    assert args.threads == 3
    assert build_parser().parse_args(["bench", "m.tflite", "--threads", "1,2,2"]).threads == (1, 2)


@pytest.mark.parametrize("side_file", ["ow_train.json", "ow_loss.csv", "ow_loss.png"])
def test_train_refuses_an_existing_side_file_before_any_work(tmp_path, capsys, side_file):
    (tmp_path / side_file).write_text("mine")
    status = main(["train", "--data", str(tmp_path / "no_data"), "--out", str(tmp_path / "ow.keras")])
    assert status == 2
    assert f"{tmp_path / side_file}: already exists; pass --force" in capsys.readouterr().err
    assert (tmp_path / side_file).read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [side_file]


@pytest.mark.parametrize("side_file", ["m_p50_train.json", "m_p50_loss.csv", "m_p50_loss.png"])
def test_compress_refuses_an_existing_side_file_before_any_work(tmp_path, capsys, side_file):
    (tmp_path / "m.keras").write_bytes(b"a model would be read only after the outputs are checked")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / side_file).write_text("mine")
    status = main(["compress", "--model", str(tmp_path / "m.keras"), "--rate", "0.5", "--data",
                   str(tmp_path / "no_data"), "--out-dir", str(out_dir)])
    assert status == 2
    assert f"{out_dir / side_file}: already exists; pass --force" in capsys.readouterr().err
    assert [p.name for p in out_dir.iterdir()] == [side_file]


def test_compress_without_retraining_writes_no_training_side_files():
    from fcnpose_tf.compression.options import CompressOptions, output_files

    names = [p.name for p in output_files("m.keras", "out", CompressOptions(rate=0.5, retrain_epochs=0)).every]
    assert names == ["m_p50.keras", "m_p50_fp16.tflite", "m_p50_int8.tflite", "m_p50_report.json"]


def _interrupted_run(tmp_path, monkeypatch):
    """A training run on 32x32 frames stopped by Ctrl-C after its first epoch: (data folder, model path)."""
    from test_train_evaluate import make_via_folder

    from fcnpose_tf.training import train
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.errors import UserError

    data = make_via_folder(tmp_path / "d", n=6)
    out = tmp_path / "m.keras"
    original = train._CheckpointAndStop.on_epoch_end

    def interrupt_after_first(self, epoch, logs=None):
        original(self, epoch, logs)
        raise KeyboardInterrupt

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", interrupt_after_first)
    with pytest.raises(UserError, match="interrupted after 1 complete epochs"):
        train.train_fold(load_dataset(data), None, out, train.FitConfig(epochs=3), input_size=32,
                         augment_copies=0, reporter=Reporter(silent=True))
    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", original)
    return data, out


def test_resume_refuses_a_checkpoint_of_other_settings_or_data_before_preparing_data(tmp_path, monkeypatch,
                                                                                        capsys):
    from fcnpose_tf.data import dataset as dataset_module

    data, out = _interrupted_run(tmp_path, monkeypatch)
    state = json.loads((tmp_path / "m.ckpt" / "state.json").read_text())
    assert state["identity"]["input_size"] == 32 and len(state["identity"]["data_sha256"]) == 64

    def no_data_preparation(*args, **kwargs):
        raise AssertionError("the data was loaded before the checkpoint was checked")

    monkeypatch.setattr(dataset_module, "load_dataset", no_data_preparation)
    monkeypatch.setattr(dataset_module, "fold_data", no_data_preparation)
    resume = ["train", "--data", str(data), "--out", str(out), "--resume", "--epochs", "3",  # the interrupted
              "--augment", "paper", "--augment-copies", "0", "--init", "none"]  # run's (FitConfig's defaults are train's)
    assert main([*resume, "--input-size", "64"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{tmp_path / 'm.ckpt'} was started with --input-size 32 on " in err
    assert ", not with --input-size 64 on " in err and "resume with the same settings or pass --force" in err

    labels = data / "labels.json"
    project = json.loads(labels.read_text())
    next(iter(project["_via_img_metadata"].values()))["regions"].pop()  # a label changed since the run started
    labels.write_text(json.dumps(project))
    assert main([*resume, "--input-size", "32"]) == 2
    err = capsys.readouterr().err
    assert f"was started on {labels} (sha256 {state['identity']['data_sha256'][:12]})" in err
    assert (tmp_path / "m.ckpt" / "state.json").is_file()  # a refused resume keeps the checkpoint


def test_a_dynamic_input_tflite_is_refused_with_how_to_export_a_fixed_size(tmp_path, capsys):
    import cv2
    import numpy as np
    import tensorflow as tf
    import tf_keras as keras

    from fcnpose_tf.errors import UserError
    from fcnpose_tf.runtime.estimator import KeypointModel

    inputs = keras.Input((None, None, 3))
    model = keras.Model(inputs, keras.layers.Conv2D(9, 1, activation="sigmoid")(inputs))
    path = tmp_path / "dynamic.tflite"
    path.write_bytes(tf.lite.TFLiteConverter.from_keras_model(model).convert())
    with pytest.raises(UserError, match=r"input size is not fixed \(shape signature \[-1, -1, -1, 3\]\).*input_size="):
        KeypointModel(path)
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.zeros((64, 64, 3), np.uint8))
    assert main(["run", str(path), "--source", str(frame), "--out", str(tmp_path / "k.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "input size is not fixed" in err and "Traceback" not in err
    assert not (tmp_path / "k.jsonl").exists()


class _SignalAfterEachCall:
    """A file object that sends this process SIGTERM right after each write or flush it passes on."""

    def __init__(self, fh):
        self._fh = fh

    def __getattr__(self, name):
        return getattr(self._fh, name)

    def write(self, data):
        written = self._fh.write(data)
        os.kill(os.getpid(), signal.SIGTERM)
        return written

    def flush(self):
        self._fh.flush()
        os.kill(os.getpid(), signal.SIGTERM)


@pytest.mark.parametrize("suffix", [".jsonl", ".csv"])
def test_sigterm_right_after_a_record_is_written_is_counted_with_it(tmp_path, suffix):
    from types import SimpleNamespace

    import numpy as np

    from fcnpose_tf.keypoints import UR5
    from fcnpose_tf.runtime.sinks import open_record_writer

    def on_term(signum, frame):
        raise KeyboardInterrupt("terminated (SIGTERM)")

    frame = SimpleNamespace(index=0, timestamp=0.0, name="f.png", media_time_s=None, image=np.zeros((4, 4, 3)))
    prediction = SimpleNamespace(times=SimpleNamespace(preprocess_ms=1.0, invoke_ms=2.0, postprocess_ms=0.5), crop=None,
                                 records=lambda schema: [{"name": n, "x": None, "y": None, "confidence": 0.0}
                                                         for n in schema.keypoints])
    writer = open_record_writer(tmp_path / f"k{suffix}", UR5)
    writer._fh = _SignalAfterEachCall(writer._fh)
    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        with pytest.raises(KeyboardInterrupt):
            for _ in range(3):
                writer.write(frame, prediction)
    finally:
        signal.signal(signal.SIGTERM, previous)
        writer.close()
    lines = (tmp_path / f"k{suffix}").read_text().splitlines()
    assert writer.count == len(lines) - (suffix == ".csv") == 1


class _DiskFullsAfter:
    """A file object whose write number `n` (1-based) stores half its data, then fails with ENOSPC."""

    def __init__(self, fh, n):
        self._fh, self._left = fh, n

    def __getattr__(self, name):
        return getattr(self._fh, name)

    def write(self, data):
        self._left -= 1
        if self._left == 0:
            self._fh.write(data[:len(data) // 2])
            self._fh.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._fh.write(data)


def _fake_frame_and_prediction():
    from types import SimpleNamespace

    import numpy as np

    frame = SimpleNamespace(index=0, timestamp=0.0, name="f.png", media_time_s=None, image=np.zeros((4, 4, 3)))
    prediction = SimpleNamespace(times=SimpleNamespace(preprocess_ms=1.0, invoke_ms=2.0, postprocess_ms=0.5), crop=None,
                                 records=lambda schema: [{"name": n, "x": 1.5, "y": None, "confidence": 0.5}
                                                         for n in schema.keypoints])
    return frame, prediction


@pytest.mark.parametrize("suffix", [".jsonl", ".csv"])
def test_a_full_disk_leaves_only_whole_records(tmp_path, suffix):
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.keypoints import UR5
    from fcnpose_tf.runtime.sinks import open_record_writer

    frame, prediction = _fake_frame_and_prediction()
    path = tmp_path / f"k{suffix}"
    writer = open_record_writer(path, UR5)
    writer._fh = _DiskFullsAfter(writer._fh, 3)  # the third record finds the disk full
    writer.write(frame, prediction)
    writer.write(frame, prediction)
    with pytest.raises(UserError, match=rf"^{path}: no space left on device \(kept its 2 complete records\)$"):
        writer.write(frame, prediction)
    writer.close()
    text = path.read_text()
    assert text.endswith("\n") and len(text.splitlines()) == 2 + (suffix == ".csv") and writer.count == 2


@pytest.fixture
def small_disk(tmp_path):
    """`small_disk(size)`: a tmpfs folder of `size` ("200k", "3m"; root only), unmounted afterwards."""
    import shutil
    import subprocess

    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    mounted = []

    def mount(size):
        disk = tmp_path / f"disk{len(mounted) or ''}"
        disk.mkdir()
        if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(disk)]).returncode != 0:
            pytest.skip("cannot mount a tmpfs here")
        mounted.append(disk)
        return disk

    yield mount
    for disk in mounted:
        subprocess.run(["umount", str(disk)], check=True)


@pytest.fixture
def tiny_disk(small_disk):
    """A 200 KB tmpfs folder (root only), unmounted afterwards: a disk that fills up."""
    return small_disk("200k")


def _fill(disk, leave_kb):
    """Fill `disk` with a file `filler` until only `leave_kb` KB are free."""
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(bytes(free - leave_kb * 1024))


def _one_line_write_error(status, err, path_part):
    assert status == 2, err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and path_part in lines[0] and "no space left on device" in lines[0], err
    assert "Traceback" not in err


@pytest.mark.parametrize("workers", ["1", "2"])
def test_synth_on_a_full_disk_leaves_nothing(tiny_disk, capsys, workers):
    status = main(["synth", "--out", str(tiny_disk / "ds"), "--n", "40", "--width", "160", "--height", "120",
                   "--workers", workers, "--quiet"])
    err = capsys.readouterr().err
    _one_line_write_error(status, err, str(tiny_disk / "ds"))
    assert "kept" not in err and list(tiny_disk.iterdir()) == []  # frames without their VIA file are no output


def test_synth_preview_on_a_full_disk_keeps_the_whole_set_and_names_it(tiny_disk, capsys):
    ds = tiny_disk / "ds"
    status = main(["synth", "--out", str(ds), "--n", "3", "--width", "64", "--height", "64", "--workers", "2",
                   "--quiet", "--preview", str(tiny_disk / "preview.png")])
    err = capsys.readouterr().err
    _one_line_write_error(status, err, str(tiny_disk / "preview.png"))
    assert err.rstrip().endswith(f"; kept the files completed before it: {ds}")
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["ds"]
    names = [f["filename"] for f in json.loads((ds / "ur5_synth.json").read_text())["_via_img_metadata"].values()]
    assert len(names) == 3 and all((ds / "images" / name).is_file() for name in names)  # the set is whole


def test_data_inspect_preview_on_an_injected_full_disk(tmp_path, capsys, monkeypatch):
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=4)
    main(["data", "inspect", str(data)])  # the splits file, written before the disk fills
    capsys.readouterr()
    monkeypatch.setattr(os, "replace", lambda src, dst: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space")))
    status = main(["data", "inspect", str(data), "--out", str(tmp_path / "new" / "preview.png")])
    err = capsys.readouterr().err
    assert status == 2 and f"{tmp_path / 'new' / 'preview.png'}: no space" in err and "Traceback" not in err
    assert not (tmp_path / "new").exists()


# -- run --save-video: temporaries stranded by SIGKILL, and a full disk -------------------------------------

@pytest.fixture(scope="module")
def tflite_model(tmp_path_factory, structured_tflite):
    """The hand-set FCN-Pose of test_runtime as a .tflite file (converted once per session)."""
    path = tmp_path_factory.mktemp("rel_models") / "structured.tflite"
    path.write_bytes(structured_tflite)
    return path


def _noise_video(path, frames=20, size=(320, 240)):
    """A video of random frames: an mp4 of its overlays outgrows a 200 KB disk."""
    import numpy as np

    from test_runtime import write_video

    rng = np.random.default_rng(0)
    return write_video(path, [rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8) for _ in range(frames)])


def _temporary_made_by_a_process_now_gone(target):
    """A temporary of `target` made by `fileio.temporary_path` in a child process that then exits (as after SIGKILL)."""
    import subprocess
    import sys
    from pathlib import Path

    code = "import sys; from fcnpose_tf.fileio import temporary_path; print(temporary_path(sys.argv[1]))"
    done = subprocess.run([sys.executable, "-c", code, str(target)], capture_output=True, text=True, check=True,
                          env=dict(os.environ), timeout=PROCESS_TIMEOUT)
    return Path(done.stdout.strip())


def test_only_a_targets_temporaries_whose_writer_is_gone_are_removed(tmp_path):
    from fcnpose_tf.fileio import temporary_path
    from fcnpose_tf.runtime.sinks import VideoSink

    target = tmp_path / "o.mp4"
    live = temporary_path(target)  # this process's own: still being written
    stale = _temporary_made_by_a_process_now_gone(target)
    others = [_temporary_made_by_a_process_now_gone(tmp_path / name) for name in ("o.x.mp4", "o.avi", "o2.mp4")]
    mine = tmp_path / ".o.mp4.tmp.mp4"  # a user's file that only looks alike
    mine.write_text("keep")
    assert stale.is_file() and stale.name.startswith(".o.") and stale.name.endswith(".tmp.mp4")
    sink = VideoSink(target, fps=5)  # the next run with the same target
    assert not stale.exists()
    assert all(p.is_file() for p in [*others, live, mine])
    sink.discard()


def test_a_run_killed_with_sigkill_leaves_no_temporary_after_the_next_run(tmp_path, tflite_model):
    import subprocess
    import sys
    import time

    from test_runtime import RED_CYCLE, quadrant_frame, write_video

    long_video = write_video(tmp_path / "long.avi", [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(4)] * 1500)
    out, target = tmp_path / "k.jsonl", tmp_path / "o.mp4"
    proc = subprocess.Popen([sys.executable, "-m", "fcnpose_tf", "run", str(tflite_model), "--source", str(long_video),
                             "--threads", "1", "--out", str(out), "--save-video", str(target)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=dict(os.environ))
    deadline = time.monotonic() + PROCESS_TIMEOUT
    while time.monotonic() < deadline and proc.poll() is None and not (out.exists() and out.stat().st_size > 0):
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.kill()
    proc.wait(timeout=PROCESS_TIMEOUT)
    stranded = list(tmp_path.glob(".o.*.tmp.mp4"))
    assert len(stranded) == 1  # what SIGKILL leaves behind
    assert main(["run", str(tflite_model), "--source", str(long_video), "--threads", "1", "--max-frames", "2",
                 "--save-video", str(target)]) == 0
    assert not stranded[0].exists() and sorted(p.name for p in tmp_path.iterdir()) == ["k.jsonl", "long.avi", "o.mp4"]


@pytest.mark.parametrize("when", ["full before the run", "fills during the run"])
def test_run_save_video_on_a_full_disk_says_so_and_leaves_no_temporary(tiny_disk, tmp_path, tflite_model, capsys,
                                                                        when):
    video = _noise_video(tmp_path / "noise.avi")
    if when == "full before the run":
        with pytest.raises(OSError):
            (tiny_disk / "filler").write_bytes(bytes(400_000))
    status = main(["run", str(tflite_model), "--source", str(video), "--threads", "1",
                   "--save-video", str(tiny_disk / "o.mp4")])
    _one_line_write_error(status, capsys.readouterr().err, str(tiny_disk / "o.mp4"))
    assert [p.name for p in tiny_disk.iterdir()] == (["filler"] if when == "full before the run" else [])


def _fake_writer_that_does_not_open(*args):
    from types import SimpleNamespace

    return SimpleNamespace(isOpened=lambda: False, release=lambda: None)


def test_a_video_writer_that_does_not_open_blames_the_disk_only_when_it_refuses_data(tmp_path, monkeypatch):
    import numpy as np

    from fcnpose_tf import fileio
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.runtime import sinks

    monkeypatch.setattr(sinks.cv2, "VideoWriter", _fake_writer_that_does_not_open)
    frame = np.zeros((8, 8, 3), np.uint8)
    sink = sinks.VideoSink(tmp_path / "o.mp4")
    with pytest.raises(UserError, match=r"OpenCV cannot write mp4v video here; try an .avi file$"):
        sink.write(frame)  # the disk takes data: the codec is missing

    def full_disk_open(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(fileio, "open", full_disk_open, raising=False)  # the shared write path finds the disk full
    sink = sinks.VideoSink(tmp_path / "o.mp4")
    with pytest.raises(fileio.WriteError, match=rf"^{tmp_path / 'o.mp4'}: no space left on device$"):
        sink.write(frame)
    assert list(tmp_path.iterdir()) == []


def test_native_libraries_print_nothing_before_the_one_line_error(cli, tmp_path, tflite_model):
    """LiteRT's `INFO: Created ... XNNPACK delegate` and FFmpeg's `moov atom not found` stay off the terminal.

    A fresh process: LiteRT prints its INFO line once per process, so only a first load shows it.
    """
    bad_video = tmp_path / "bad.mp4"
    bad_video.write_bytes(b"not a video")
    proc = cli("run", tflite_model, "--source", bad_video, "--threads", "1", "--out", tmp_path / "k.jsonl")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [f"error: {bad_video}: cannot be opened as a video (unknown format or corrupt "
                                        "file: moov atom not found)"]
    assert not (tmp_path / "k.jsonl").exists()


def test_more_folds_than_frames_is_refused_before_any_split_is_stored(tmp_path, capsys):
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=6)
    splits = data / "labels.splits.json"
    expected = f"error: {data / 'labels.json'}: too few frames for 99 folds (6 usable frames, and each fold needs a " \
               "validation frame); pass --folds 6 or fewer\n"
    assert main(["data", "inspect", str(data), "--folds", "99", "--resplit"]) == 2
    assert capsys.readouterr().err == expected and not splits.exists()
    assert main(["data", "inspect", str(data), "--folds", "3"]) == 0  # stored: 3 folds
    stored = splits.read_text()
    capsys.readouterr()
    assert main(["data", "inspect", str(data), "--folds", "99", "--resplit"]) == 2
    assert capsys.readouterr().err == expected and splits.read_text() == stored
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "m.keras"), "--folds", "99", "--resplit",
                 "--init", "none"]) == 2  # train (as sweep and compress) loads through the same check
    assert capsys.readouterr().err == expected and splits.read_text() == stored
    assert main(["data", "inspect", str(data)]) == 0  # no K asked for: the stored 3 folds serve the hold-out split
    assert main(["data", "inspect", str(data), "--folds", "5"]) == 2  # another K asked for: refused
    assert "stored splits use seed 0, 3 folds" in capsys.readouterr().err and splits.read_text() == stored


def test_a_dataset_smaller_than_the_default_folds_still_loads_for_the_hold_out_split(tmp_path, capsys):
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=4)
    assert main(["data", "inspect", str(data)]) == 0
    assert "(too few frames for 5 folds)" in capsys.readouterr().out
    assert main(["data", "inspect", str(data), "--folds", "5"]) == 2
    assert "too few frames for 5 folds (4 usable frames" in capsys.readouterr().err


def test_a_keypoint_attribute_no_region_has_is_warned_about_naming_those_that_exist(cli, tmp_path):
    from test_train_evaluate import make_via_folder

    import json

    data = make_via_folder(tmp_path / "d", n=4)
    proc = cli("data", "inspect", data, "--keypoint-attr", "kp")  # the names are under another attribute: read by it
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines() == [f"{data / 'labels.json'}: no region has the attribute 'kp' (--keypoint-attr); "
                                        "reading the keypoint names from 'keypoint', whose values are all keypoint "
                                        "names"]
    proc = cli("data", "inspect", data)  # the attribute the regions use: no warning
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    project = json.loads((data / "labels.json").read_text())  # an attribute that names no keypoint: schema order
    for meta in project["_via_img_metadata"].values():
        for region in meta["regions"]:
            region["region_attributes"] = {"note": "x"}
    (data / "labels.json").write_text(json.dumps(project))
    proc = cli("data", "inspect", data, "--resplit")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines() == [f"{data / 'labels.json'}: no region has the attribute 'keypoint' "
                                        "(--keypoint-attr), so points are taken in schema order; the regions' "
                                        "attributes are: note"]


def test_run_warns_about_more_threads_than_cores_as_bench_does(tmp_path, tflite_model, capsys):
    import cv2
    import numpy as np

    from fcnpose_tf.system import available_cores, oversubscription_note

    over = available_cores() + 1
    note = oversubscription_note([over])
    assert note == f"A thread count above the {available_cores()} cores here ({over}) oversubscribes the CPU."
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.zeros((64, 64, 3), np.uint8))
    assert main(["run", str(tflite_model), "--source", str(frame), "--threads", str(over)]) == 0
    assert f"warning: {note}\n" in capsys.readouterr().err
    assert main(["run", str(tflite_model), "--source", str(frame), "--threads", "1"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["bench", str(tflite_model), "--threads", f"1,{over}", "--frames", "1", "--warmup", "0"]) == 0
    assert note in capsys.readouterr().out  # the same sentence, from the same function


def _json_report_command(command, tmp_path, model, out):
    if command == "bench":
        return ["bench", str(model), "--threads", "1", "--frames", "1", "--warmup", "0", "--json", str(out)]
    from test_train_evaluate import make_via_folder

    from fcnpose_tf.data.dataset import load_dataset

    data = make_via_folder(tmp_path / "d", n=4)
    load_dataset(data)  # the splits file, stored before the disk fills
    return ["evaluate", str(model), "--data", str(data), "--threads", "1", "--json", str(out)]


@pytest.mark.parametrize("command", ["evaluate", "bench"])
def test_json_report_on_an_injected_full_disk_is_one_line_and_leaves_nothing(tmp_path, tflite_model, capsys,
                                                                             monkeypatch, command):
    out = tmp_path / "new" / "report.json"
    args = _json_report_command(command, tmp_path, tflite_model, out)
    enospc = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "replace", lambda src, dst: (_ for _ in ()).throw(enospc))
    status = main(args)
    _one_line_write_error(status, capsys.readouterr().err, str(out))
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("command", ["evaluate", "bench"])
def test_json_report_on_a_full_disk_is_one_line_and_leaves_nothing(tiny_disk, tmp_path, tflite_model, capsys,
                                                                   command):
    args = _json_report_command(command, tmp_path, tflite_model, tiny_disk / "report.json")
    with pytest.raises(OSError):
        (tiny_disk / "filler").write_bytes(bytes(400_000))
    status = main(args)
    _one_line_write_error(status, capsys.readouterr().err, str(tiny_disk / "report.json"))
    assert [p.name for p in tiny_disk.iterdir()] == ["filler"]


# -- train and compress on a full disk: one line, no debris, the last good checkpoint kept -----------------

def _frames_with_stored_splits(folder):
    """A small VIA folder whose splits file is written before the disk fills (so no failure names it)."""
    from test_train_evaluate import make_via_folder

    from fcnpose_tf.data.dataset import load_dataset

    data = make_via_folder(folder, n=6)
    load_dataset(data)
    return data


TINY_TRAIN = ["--input-size", "64", "--init", "none", "--augment-copies", "0", "--threads", "1", "--quiet"]


def _error_lines(proc):
    assert "Traceback" not in proc.stderr, proc.stderr
    return [line for line in proc.stderr.splitlines() if line.startswith("error:")]


@pytest.mark.slow
@pytest.mark.parametrize("free_kb", [None, 4])  # an empty 200 KB disk; 4 KB free, where HDF5 used to segfault
def test_train_on_a_full_disk_is_one_line_and_leaves_nothing(tiny_disk, tmp_path, cli, free_kb):
    data = _frames_with_stored_splits(tmp_path / "d")
    if free_kb is not None:
        _fill(tiny_disk, free_kb)
    proc = cli("train", "--data", data, "--out", tiny_disk / "m.keras", "--epochs", "2", *TINY_TRAIN)
    assert proc.returncode == 2, proc.stderr
    assert _error_lines(proc) == [f"error: {tiny_disk / 'm.ckpt'}: no space left on device"]
    assert [p.name for p in tiny_disk.iterdir()] == ([] if free_kb is None else ["filler"])


@pytest.mark.slow
def test_a_checkpoint_the_disk_cannot_take_keeps_the_last_good_one_and_resume_continues(small_disk, tmp_path,
                                                                                          cli_few_timed):
    import subprocess

    import numpy as np

    data = _frames_with_stored_splits(tmp_path / "d")
    disk = small_disk("3m")  # holds epoch 1's checkpoint (2.2 MB at 64x64), not epoch 2's beside it
    train = ["train", "--data", data, "--out", disk / "m.keras", "--epochs", "3", *TINY_TRAIN]
    proc = cli_few_timed(*train)
    assert proc.returncode == 2, proc.stderr
    ckpt = disk / "m.ckpt"
    assert _error_lines(proc) == [f"error: {ckpt}: no space left on device; the checkpoint of epoch 1 is intact: "
                                  f"free some space, then continue with --resume; kept the files completed before "
                                  f"it: {ckpt}"]
    assert [p.name for p in disk.iterdir()] == ["m.ckpt"]
    assert sorted(p.name for p in ckpt.iterdir()) == ["best.npz", "last.keras", "state.json"]  # no temporary
    assert json.loads((ckpt / "state.json").read_text())["epoch"] == 1
    assert len(np.load(ckpt / "best.npz").files) > 0

    subprocess.run(["mount", "-o", "remount,size=20m", str(disk)], check=True)  # space freed
    proc = cli_few_timed(*train, "--resume")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((disk / "m_train.json").read_text())["epochs_run"] == 3
    assert sorted(p.name for p in disk.iterdir()) == ["m.keras", "m_loss.csv", "m_loss.png", "m_train.json"]


@pytest.fixture
def tiny_base(tmp_path):
    from fcnpose_tf.training.model import build_fcn_pose

    base = tmp_path / "base.keras"
    build_fcn_pose(input_size=64).save(base)
    return base


@pytest.mark.slow
def test_compress_retraining_on_a_full_disk_is_one_line_and_leaves_nothing(small_disk, tmp_path, tiny_base,
                                                                           cli_few_timed):
    """compress cannot resume: its retraining checkpoint goes too, and no --resume is suggested."""
    data = _frames_with_stored_splits(tmp_path / "d")
    disk = small_disk("450k")  # holds the pruned model's first checkpoint (about 300 KB), not a second beside it
    out = disk / "out"
    proc = cli_few_timed("compress", "--rate", "0.7", "--model", tiny_base, "--data", data, "--retrain-epochs", "3",
                         "--quantize", "float16", "--out-dir", out, "--threads", "1")  # 6 frames: too few for int8
    assert proc.returncode == 2, proc.stderr
    assert "Epoch 2/3" in proc.stdout  # the disk filled after a complete checkpoint
    assert _error_lines(proc) == [f"error: {out / 'base_p70.ckpt'}: no space left on device"]
    assert list(disk.iterdir()) == []


@pytest.mark.slow
def test_compress_names_the_model_it_completed_before_the_disk_filled(tiny_disk, tmp_path, tiny_base, cli_few_timed):
    """Room for the pruned model (116 KB), not for the .tflite (37 KB) after it; LiteRT's INFO line stays quiet."""
    data = _frames_with_stored_splits(tmp_path / "d")
    out = tiny_disk / "out"
    _fill(tiny_disk, 136)
    proc = cli_few_timed("compress", "--rate", "0.7", "--model", tiny_base, "--data", data, "--retrain-epochs", "0",
                         "--quantize", "float16", "--out-dir", out, "--threads", "1")  # 6 frames: too few for int8
    assert proc.returncode == 2, proc.stderr
    assert _error_lines(proc) == [f"error: {out / 'base_p70_fp16.tflite'}: no space left on device; kept the files "
                                  f"completed before it: {out / 'base_p70.keras'}"]
    assert "XNNPACK" not in proc.stderr, proc.stderr  # the export's check loads the .tflite quietly
    assert [p.name for p in out.iterdir()] == ["base_p70.keras"]


def _damaged_mp4(path):
    """An mp4v video whose middle third has bytes flipped: it opens, and FFmpeg complains while decoding."""
    import cv2
    import numpy as np

    from test_runtime import write_video

    rng = np.random.default_rng(0)
    frames = [cv2.GaussianBlur(rng.integers(0, 255, (96, 128, 3), dtype=np.uint8), (9, 9), 3) for _ in range(20)]
    data = bytearray(write_video(path, frames).read_bytes())
    for offset in range(len(data) // 3, 2 * len(data) // 3, 97):
        data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def test_ffmpeg_lines_while_decoding_a_damaged_video_become_one_warning(tmp_path, capfd):
    from fcnpose_tf.runtime.sources import VideoSource

    video = _damaged_mp4(tmp_path / "bad.mp4")
    warnings = []
    with VideoSource(video, warn=warnings.append) as source:
        frames = list(source)
    assert capfd.readouterr().err == ""  # nothing reached the terminal past us
    assert source.damaged_frames >= 1 and len(source.decoder_messages) >= source.damaged_frames
    summary = f"{video}: FFmpeg reported {len(source.decoder_messages)} decoding problems in {source.damaged_frames} "
    line = next(w for w in warnings if "FFmpeg reported" in w)  # beside it, a line per run of frames skipped
    assert line.startswith(summary) and line.endswith(f"the last: {source.decoder_messages[-1]}")
    assert all(w == line or w.endswith("cannot be read: skipped") or "video ended after" in w for w in warnings)
    assert not any("@ 0x" in line for line in source.decoder_messages)  # FFmpeg's `[mpeg4 @ 0x...]` prefix dropped
    assert len(frames) + len(warnings) >= 2  # every frame read or its end reported: no frame hidden silently


@pytest.mark.parametrize("call", [1, 2])  # the redirection, the restoring
def test_sigterm_while_stderr_is_switched_for_a_native_call_leaves_it_restored(monkeypatch, call):
    """Captured around every video frame's read, descriptor 2 must come back even when a kill lands mid-switch."""
    from fcnpose_tf import nativelog

    real_dup2, calls = os.dup2, []

    def dup2_then_sigterm(fd, fd2, *args):
        result = real_dup2(fd, fd2, *args)
        calls.append(fd2)
        if len(calls) == call:
            os.kill(os.getpid(), signal.SIGTERM)
        return result

    def on_term(signum, frame):
        raise KeyboardInterrupt("terminated (SIGTERM)")

    before = os.fstat(2)
    monkeypatch.setattr(nativelog.os, "dup2", dup2_then_sigterm)
    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        with pytest.raises(KeyboardInterrupt):
            with nativelog.native_stderr_captured():
                pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        monkeypatch.undo()
    after = os.fstat(2)
    assert calls == [2, 2] and (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)


def test_a_signal_taken_just_before_the_restoring_deferral_still_restores_stderr(monkeypatch):
    """The handler runs between any two bytecodes: also after the native call, before the restore's deferral."""
    import contextlib

    from fcnpose_tf import nativelog

    real, entered = nativelog.signals_deferred, []

    @contextlib.contextmanager
    def cut_short_on_the_restore():
        entered.append(1)
        if len(entered) == 2:  # the handler ran here: KeyboardInterrupt before anything is held back
            raise KeyboardInterrupt("terminated (SIGTERM)")
        with real():
            yield

    before = os.fstat(2)
    monkeypatch.setattr(nativelog, "signals_deferred", cut_short_on_the_restore)
    with pytest.raises(KeyboardInterrupt):
        with nativelog.native_stderr_captured():
            pass
    monkeypatch.undo()
    after = os.fstat(2)
    assert len(entered) == 2 and (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)


def test_a_signal_taken_while_the_deferral_swaps_handlers_leaves_them_as_they_were(monkeypatch):
    """SIGINT swapped, then a kill before SIGTERM is: both handlers come back, none is left recording."""
    from fcnpose_tf import fileio

    real_signal, swaps = signal.signal, []

    def signal_cut_after_first_swap(sig, handler):
        result = real_signal(sig, handler)
        swaps.append(sig)
        if len(swaps) == 1:
            raise KeyboardInterrupt("terminated (SIGTERM)")
        return result

    def on_int(signum, frame):
        raise KeyboardInterrupt

    previous = real_signal(signal.SIGINT, on_int)
    try:
        monkeypatch.setattr(fileio.signal, "signal", signal_cut_after_first_swap)
        with pytest.raises(KeyboardInterrupt):
            with fileio.signals_deferred():
                pass
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGINT) is on_int
    finally:
        real_signal(signal.SIGINT, previous)
