import os
import subprocess
import sys

import pytest

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


@pytest.fixture
def cli(tmp_path):
    """Run `python -m fcnpose_tf ARGS` in a subprocess; returns CompletedProcess with text output."""

    def run(*args, cwd=None, env=None, timeout=600):
        full_env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", **(env or {}))
        return subprocess.run([sys.executable, "-m", "fcnpose_tf", *map(str, args)], cwd=cwd or tmp_path,
                              env=full_env, capture_output=True, text=True, timeout=timeout)

    return run


@pytest.fixture
def cli_here(capsys):
    """Run `fcnpose-tf ARGS` in this process through `fcnpose_tf.cli.main`: (status, stdout, stderr).

    The same parser, exit path and messages as `cli` without a new interpreter importing TensorFlow
    again (seconds per call): for checks that do not depend on a fresh process (thread settings,
    signals, what a process imports).
    """
    from fcnpose_tf.cli import main

    def run(*args):
        capsys.readouterr()
        try:
            status = main([str(a) for a in args])
        except SystemExit as exc:  # argparse's own errors and --help
            status = exc.code
        out, err = capsys.readouterr()
        return status, out, err

    return run
