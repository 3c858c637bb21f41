"""Output to a file (a log, nohup, CI) reads top to bottom: no carriage-return progress bars, every `error:` at the
start of a line (fcnpose_tf.progress). Commands run in this process with stdout and stderr in one file, as
`fcnpose-tf ... > log 2>&1` writes them."""

import contextlib
import io

import pytest

from fcnpose_tf import progress


def _logged(*argv):
    """(exit status, everything the command wrote to stdout and stderr, interleaved as in one log file)."""
    from fcnpose_tf.cli import main

    log = io.StringIO()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            status = main([str(a) for a in argv])
        except SystemExit as exc:
            status = exc.code
    return status, log.getvalue()


def _reads_well(text):
    assert "\r" not in text, text[-2000:]
    for line in text.splitlines():
        assert "error:" not in line or line.startswith("error:"), line


@pytest.fixture(scope="module")
def logged_runs(tmp_path_factory):
    """One small dataset made, inspected, trained on and evaluated through the CLI, each output kept."""
    root = tmp_path_factory.mktemp("logs")
    data, model = root / "frames", root / "m.keras"
    runs = {
        "synth": _logged("synth", "--out", data, "--n", 12, "--width", 160, "--height", 120, "--workers", 1),
        "inspect": _logged("data", "inspect", data, "--out", root / "preview.png"),
        "train": _logged("train", "--data", data, "--out", model, "--epochs", 2, "--input-size", 64, "--init", "none",
                         "--augment", "paper", "--augment-copies", 1, "--threads", 1),
        "train --quiet": _logged("train", "--data", data, "--out", root / "q.keras", "--epochs", 1, "--input-size", 64,
                                 "--init", "none", "--augment", "paper", "--augment-copies", 1, "--threads", 1,
                                 "--quiet"),
        "evaluate": _logged("evaluate", model, "--data", data, "--threads", 1),
        "summary": _logged("summary", model),
        "export": _logged("export", model, "--data", data, "--quantize", "float16", "--out-dir", root / "tfl",
                          "--threads", 1),
        "run": _logged("run", "workcell-p70-int8", "--source", data / "images", "--out", root / "k.jsonl",
                       "--threads", 1),
        "bench": _logged("bench", "workcell-p70-int8", "--frames", 5, "--warmup", 1, "--threads", 1),
        "predict": _logged("predict", "workcell-p70-fp16", "--source", data / "images", "--via", root / "pre.json",
                           "--threads", 1),
        "train again": _logged("train", "--data", data, "--out", model, "--epochs", 1, "--input-size", 64),
        "bad rate": _logged("compress", "--rate", 2),
        "bad model": _logged("evaluate", root / "nope.keras", "--data", data),
    }
    return runs


@pytest.mark.parametrize("name", ["synth", "inspect", "train", "train --quiet", "evaluate", "summary", "export", "run",
                                  "bench", "predict", "train again", "bad rate", "bad model"])
def test_a_command_writing_to_a_file_draws_no_bars(logged_runs, name):
    status, text = logged_runs[name]
    _reads_well(text)
    assert (status == 0) == (name not in ("train again", "bad rate", "bad model")), text[-2000:]
    if status:
        assert status == 2 and "\nerror: " in "\n" + text


def test_loops_report_every_tenth_and_training_every_epoch(logged_runs):
    _, synth = logged_runs["synth"]
    assert "synth: 12/12 frames (100 %)" in synth and len([s for s in synth.splitlines() if s.startswith("synth:")]) <= 11
    _, train = logged_runs["train"]
    assert "frames at 64x64: " in train  # data preparation, a line per ~10 %
    assert train.count("Epoch 1/2") == 1 and train.count("Epoch 2/2") == 1 and " - val_loss: " in train
    _, quiet = logged_runs["train --quiet"]
    assert " - val_loss: " in quiet and "frames at 64x64: " not in quiet  # --quiet: per epoch, no loop progress
    _, evaluate = logged_runs["evaluate"]
    assert "evaluating: " in evaluate


def test_an_error_after_a_bar_starts_its_own_line(monkeypatch):
    """On a terminal a bar is open when a command fails: the CLI closes it before the `error:` line."""
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    screen = Terminal()
    reporter = progress.Reporter(stream=screen)
    monkeypatch.setattr("sys.stderr", screen)
    previous = progress.use(reporter)
    try:
        items = reporter.progress(range(10), "work")
        next(items)  # a bar is drawn (carriage returns, no newline yet)
        assert reporter._bars
        reporter.end_line()
        print("error: something", file=screen)
    finally:
        progress.use(previous)
    before, _, after = screen.getvalue().rpartition("error: something")
    assert before.endswith(("\n", "\r")) and before.rstrip("\r").split("\r")[-1].strip() == ""  # bar cleared
    assert after == "\n" and not reporter._bars


def test_the_reporter_modes():
    log = io.StringIO()
    lines = progress.Reporter(stream=log)
    assert not lines.bars and lines.keras_verbose == 2
    assert list(lines.progress(range(100), "loop")) == list(range(100))
    reported = [line for line in log.getvalue().splitlines() if line.startswith("loop:")]
    assert len(reported) == 10 and reported[-1] == "loop: 100/100 frames (100 %)"
    silent = progress.Reporter(silent=True, stream=log)
    assert silent.keras_verbose == 0 and progress.Reporter(quiet=True).keras_verbose == 2
