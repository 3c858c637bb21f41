import subprocess
import sys

import pytest

from conftest import PROCESS_TIMEOUT


def test_importing_cli_does_not_import_tensorflow():
    code = ("import sys, fcnpose_tf.cli as c; c.build_parser(); "
            "bad = [m for m in ('tensorflow', 'tf_keras', 'keras') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_summary_prints_paper_figures(cli_here):
    status, out, err = cli_here("summary")
    assert status == 0, err
    assert "131,705" in out
    assert "(224, 224, 128)" in out and "(7, 7, 8)" in out and "(224, 224, 9)" in out
    assert "1,481,675,328" in out  # MACs of the unpruned network at 224


@pytest.mark.slow
def test_summary_of_a_saved_model_reports_size(cli_here, tmp_path):
    from fcnpose_tf.training.model import build_fcn_pose

    path = tmp_path / "m.keras"
    build_fcn_pose(input_size=64).save(path)
    status, out, err = cli_here("summary", path)
    assert status == 0, err
    assert "(64, 64, 9)" in out and "File size:" in out
    odd = path.rename(tmp_path / "m\udce9.keras")  # a name that is not UTF-8 (the byte \xe9): loaded all the same
    status, out, err = cli_here("summary", odd)
    assert status == 0, err
    assert "(64, 64, 9)" in out


@pytest.mark.slow
@pytest.mark.parametrize("args, message", [
    (["summary", "--input-size", "100"], "multiple of 32"),
    (["summary", "missing.keras"], "missing.keras: model file not found"),
    (["summary", "--input-size", "abc"], "expected auto, S or HxW"),
    (["summary", "--input-size", "224x100"], "multiple of 32"),
    (["summary", "--input-size", "99968"], "at most 1024"),
    (["data", "inspect", "missing", "--input-size", "100000"], "at most 1024"),
    (["summary", "--input-size", "auto"], "--input-size auto is chosen from a dataset"),
    (["no-such-command"], "invalid choice"),
])
def test_user_errors_are_one_line_exit_2(cli_here, args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # missing.keras is looked up here
    status, _, err = cli_here(*args)  # in-process: a defect would raise here instead of printing a traceback
    assert status == 2
    assert message in err
    assert "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("error:")]


@pytest.mark.slow
def test_corrupt_model_file(cli_here, tmp_path):
    bad = tmp_path / "broken.keras"
    bad.write_bytes(b"not a zip")
    status, _, err = cli_here("summary", bad)
    assert status == 2 and "broken.keras: cannot be read" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("args, pointer", [
    (["run", "m.tflite", "--source", "0", "--bogus"], "fcnpose-tf run --help"),
    (["data", "merge", "a.json", "--out", "b.json", "--bogus"], "fcnpose-tf data merge --help"),
    (["--bogus"], "fcnpose-tf --help"),
])
def test_an_unknown_option_points_to_the_help_of_the_command_given(cli_here, args, pointer):
    status, _, err = cli_here(*args)
    assert status == 2
    assert err.strip().splitlines() == [f"error: unrecognized arguments: --bogus (see `{pointer}`)"]


def test_every_command_help_shows_an_example(cli_here):
    from fcnpose_tf.commands import COMMAND_MODULES
    import importlib

    for name in COMMAND_MODULES:
        module = importlib.import_module(f"fcnpose_tf.commands.{name}")
        status, out, _ = cli_here(module.NAME, "--help")
        assert status == 0
        assert "examples:" in out and f"fcnpose-tf {module.NAME}" in out


def test_a_help_shows_a_default_of_zero_once_and_hides_none_and_false(cli_here, monkeypatch):
    """0 == False in Python: the help's rule must tell them apart, or a seed's default 0 goes unsaid."""
    monkeypatch.setenv("COLUMNS", "400")  # one line per option
    status, out, _ = cli_here("synth", "--help")
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip().startswith("--")}
    assert status == 0
    assert lines["--seed"].endswith("(default: 0)") and lines["--scene-seed"].count("(default: 0)") == 1
    assert "(default: None)" not in out and "(default: False)" not in out
    status, out, _ = cli_here("run", "--help")  # a help that states its default is not given another
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip().startswith("--")}
    assert status == 0 and lines["--smooth-coast"].endswith("(default 2)")
    assert all(line.count("(default") <= 1 for line in lines.values())


@pytest.mark.parametrize("command, reads_record", [("evaluate", True), ("export", True), ("compress", True),
                                                   ("train", False), ("sweep", False)])
def test_split_seed_help_names_the_training_record_only_where_it_is_read(cli_here, command, reads_record):
    """Left out, --split-seed takes a model's recorded seed in the commands that read a model's splits
    (`splits_of_record`): only their help says so."""
    status, out, _ = cli_here(command, "--help")
    entry = out.split("\n  --split-seed", 1)[1].split("\n  -", 1)[0]
    assert status == 0 and ("training record" in " ".join(entry.split())) == reads_record, entry


def test_every_command_takes_quiet_from_one_setting():
    """--quiet is one setting the CLI adds to every command, as --debug: the command's reporter is quiet with it and
    only with it (synth's --no-progress, its name before, is the same option)."""
    import argparse

    from fcnpose_tf import cli, settings

    def commands(parser, prefix=""):  # every command and subcommand (`data inspect`, `data merge`)
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, command in action.choices.items():
                    yield f"{prefix}{name}", command
                    yield from commands(command, f"{prefix}{name} ")

    parser = cli.build_parser()
    named = dict(commands(parser))
    assert "data merge" in named and "compress" in named
    for name, command in named.items():
        quiet = [a for a in command._actions if a.dest == "quiet" and a.help != argparse.SUPPRESS]
        assert [getattr(a, "setting", None) for a in quiet] == [settings.QUIET], name
    assert parser.parse_args(["synth", "--out", "x"]).quiet is False
    assert parser.parse_args(["synth", "--out", "x", "--quiet"]).quiet is True
    assert parser.parse_args(["synth", "--out", "x", "--no-progress"]).quiet is True
    assert parser.parse_args(["summary", "--quiet"]).quiet is True
    assert parser.parse_args(["data", "inspect", "d", "--quiet"]).quiet is True
    assert parser.parse_args(["data", "inspect", "d"]).quiet is False


def test_quiet_makes_the_commands_reporter_quiet(monkeypatch):
    from fcnpose_tf import cli, progress

    seen = []
    for argv in (["summary", "--quiet"], ["summary"]):
        monkeypatch.setattr("fcnpose_tf.commands.summary.run", lambda args: seen.append(progress.current().quiet) or 0)
        assert cli.main(argv) == 0
    assert seen == [True, False]


def _dests(parser):
    """Every option destination of `parser` and of its subcommands (`data inspect`, `data merge`)."""
    import argparse

    dests = set()
    for action in parser._actions:
        dests.add(action.dest)
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                dests |= _dests(sub)
    return dests


def test_every_command_module_declares_the_outputs_it_creates():
    """The options naming what a command creates are declared in its own module (OUTPUTS), none kept for it in
    cli.py: the one exit path removes what those options name when a command fails or is stopped."""
    import argparse
    import importlib

    from fcnpose_tf import cli
    from fcnpose_tf.commands import COMMAND_MODULES

    assert not hasattr(cli, "OWNERS_OUTPUTS")
    commands = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    declared = {}
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"fcnpose_tf.commands.{name}")
        declared[module.NAME] = (*getattr(module, "OUTPUTS", ()), *getattr(module, "RESUMABLE_OUTPUTS", ()))
        assert set(declared[module.NAME]) <= _dests(commands[module.NAME]), module.NAME
        assert commands[module.NAME].get_default("_outputs") == getattr(module, "OUTPUTS", ())
    assert declared["compress"] == ("out_dir", "more_frames_via") and declared["export"] == ("out_dir", "json")
    for command in ("train", "evaluate", "bench", "run", "predict", "synth", "sweep"):
        assert declared[command], command


def test_commands_set_tensorflows_environment_where_the_user_did_not():
    from fcnpose_tf.training.tfsetup import TENSORFLOW_ENVIRONMENT, set_tensorflow_environment

    mine = {"TF_ENABLE_ONEDNN_OPTS": "0", "OTHER": "x"}
    set_tensorflow_environment(mine)
    assert mine == {"TF_ENABLE_ONEDNN_OPTS": "0", "OTHER": "x", "TF_CPP_MIN_LOG_LEVEL": "3"}  # the user's value kept
    empty: dict[str, str] = {}
    set_tensorflow_environment(empty)
    assert empty == TENSORFLOW_ENVIRONMENT and empty["TF_ENABLE_ONEDNN_OPTS"] == "1"


@pytest.mark.parametrize("args", [
    ["train", "--data", "frames", "--out", "exists.keras"],
    ["evaluate", "--data", "frames", "--json", "exists.keras"],
    ["export", "m.keras", "--json", "exists.keras"],
])
def test_an_existing_output_is_refused_before_tensorflow_is_imported(tmp_path, args):
    import subprocess
    import sys

    (tmp_path / "exists.keras").write_text("mine")
    code = ("import sys; from fcnpose_tf.cli import main; status = main(sys.argv[1:]); "
            "assert 'tensorflow' not in sys.modules, 'TensorFlow was imported first'; sys.exit(status)")
    proc = subprocess.run([sys.executable, "-c", code, *args], cwd=tmp_path, capture_output=True, text=True,
                          timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "error: exists.keras: already exists; pass --force to replace it"
    assert (tmp_path / "exists.keras").read_text() == "mine"


def test_the_console_command_leaves_stop_signals_to_their_default_action_for_the_wind_down(monkeypatch):
    import signal

    from fcnpose_tf import cli

    monkeypatch.setattr(cli, "main", lambda: 0)
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert cli.console_main() == 0
        assert all(signal.getsignal(signum) == signal.SIG_DFL for signum in before)
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


@pytest.mark.parametrize("signum, line, status", [("SIGINT", "interrupted (Ctrl-C)", 130),
                                                  ("SIGTERM", "terminated (SIGTERM)", 143)])
def test_a_stop_signal_while_the_commands_load_is_one_line_even_if_sigint_was_ignored(monkeypatch, capsys, signum,
                                                                                      line, status):
    """Ctrl-C (or a `kill`) before a command's exit path begins, while the commands' modules load: the signal's one
    line and status, no traceback; and a SIGINT the process inherited as ignored (a script's `cmd &`) still stops
    it."""
    import os
    import signal

    from fcnpose_tf import cli

    build = cli.build_parser

    def build_stopped():
        os.kill(os.getpid(), getattr(signal, signum))  # arrives while the parser is being built
        return build()

    monkeypatch.setattr(cli, "build_parser", build_stopped)
    monkeypatch.setattr(sys, "argv", ["fcnpose-tf", "summary"])
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        assert cli.console_main() == status
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
    assert capsys.readouterr().err.strip().splitlines() == [line]


def test_the_entry_point_takes_a_stop_signal_before_the_command_line_modules_load(tmp_path):
    """`fcnpose-tf` (`console.main`) handles SIGINT before it imports `cli`: a Ctrl-C or `kill -INT` while the
    modules load is the one line and status 130, also in a process that inherited an ignored SIGINT."""
    code = ("import importlib.abc, os, signal, sys\n"
            "signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a script's `cmd &` starts it\n"
            "class StopOnImport(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path, target=None):\n"
            "        if name == 'fcnpose_tf.cli':\n"
            "            os.kill(os.getpid(), signal.SIGINT)\n"
            "sys.meta_path.insert(0, StopOnImport())\n"
            "from fcnpose_tf.console import main\n"
            "sys.argv = ['fcnpose-tf', 'summary']\n"
            "sys.exit(main())\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines() == ["interrupted (Ctrl-C)"] and proc.stdout == ""
