"""Failures a user can cause end in one `error:` line, exit 2, and leave nothing half-written."""

import pytest

from fcnpose_tf.cli import build_parser, main


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
