"""The maintainer scripts in tools/ end as the package's commands do: a user error is one `error:` line, status 2."""

import subprocess
import sys
from pathlib import Path

import pytest

from conftest import PROCESS_TIMEOUT

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def _tool(name, *args, cwd):
    return subprocess.run([sys.executable, str(TOOLS / name), *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=PROCESS_TIMEOUT)


@pytest.mark.parametrize("name, args, message", [
    ("bench_pipeline.py", ["missing.tflite", "--video", "missing.mp4"], "missing.mp4: no such file or folder"),
    ("check_frame_path.py", ["--tflite", "missing.tflite", "--out", "k.npz"], "missing.tflite"),
    ("limb_prior.py", ["missing_frames"], "missing_frames"),
])
def test_a_package_user_error_is_one_line_and_status_2(tmp_path, name, args, message):
    proc = _tool(name, *args, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and message in last, proc.stderr


def test_an_existing_json_is_not_overwritten_without_force(tmp_path):
    (tmp_path / "pipe.json").write_text("mine")
    proc = _tool("bench_pipeline.py", "m.tflite", "--video", "v.mp4", "--json", "pipe.json", cwd=tmp_path)
    assert proc.returncode == 2 and "pipe.json: already exists" in proc.stderr.strip().splitlines()[-1], proc.stderr
    assert (tmp_path / "pipe.json").read_text() == "mine"
