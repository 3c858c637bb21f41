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
