"""tools/pi_emulated/pi_check.py, the helper of tools/pi_emulated_check.sh, on the host: every shipped format
goes through its raw-map step (the int8 file's uint8 pixel input and int8 maps included) and compares
with itself exactly. The emulated arm64 side runs the same code (docs/raspberry-pi.md)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.bundled import models_dir

HELPER = Path(__file__).resolve().parents[1] / "tools" / "pi_emulated" / "pi_check.py"


def _helper(*args, cwd=None):
    return subprocess.run([sys.executable, str(HELPER), *map(str, args)], capture_output=True, text=True,
                          timeout=PROCESS_TIMEOUT, cwd=cwd)


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("pi_frames")
    result = _helper("frames", folder, "--count", 2, "--width", 160, "--height", 120)
    assert result.returncode == 0, result.stderr
    return folder


@pytest.mark.parametrize("name", ["fcnpose_ur5_p70_int8.tflite", "fcnpose_ur5_p70_fp16.tflite"])
def test_every_shipped_format_passes_the_raw_map_step(tmp_path, frames, name):
    model = models_dir() / name
    first, second = tmp_path / "a.npz", tmp_path / "b.npz"
    result = _helper("maps", model, "--frames", frames, "--out", first)
    assert result.returncode == 0, result.stderr
    assert "XNNPACK delegate: yes" in result.stdout
    data = np.load(first)
    int8 = "int8" in name
    assert data["inputs"].dtype == (np.uint8 if int8 else np.float32)  # the model's own input type
    assert data["raw_maps"].dtype == (np.int8 if int8 else np.float32)
    assert data["maps"].dtype == np.float32 and 0.0 <= data["maps"].min() and data["maps"].max() <= 1.0
    np.testing.assert_allclose(data["inputs_real"], data["inputs"].astype(np.float32) / (255 if int8 else 1),
                               rtol=1e-6, atol=0)
    assert _helper("save-inputs", first, tmp_path / "in.npy").returncode == 0
    result = _helper("maps", model, "--frames", frames, "--inputs", tmp_path / "in.npy", "--out", second)
    assert result.returncode == 0, result.stderr
    result = _helper("compare-maps", first, second, "--result", tmp_path / "diff.txt")
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "diff.txt").read_text().strip() == "0"
    assert ("0 quantization levels" in result.stdout) == int8


def test_inputs_of_another_type_are_refused_in_one_line(tmp_path, frames):
    """The float16 file's saved float32 inputs fed to the int8 file (uint8 pixel input): one error line."""
    float_run = tmp_path / "f.npz"
    assert _helper("maps", models_dir() / "fcnpose_ur5_p70_fp16.tflite", "--frames", frames,
                   "--out", float_run).returncode == 0
    assert _helper("save-inputs", float_run, tmp_path / "in.npy").returncode == 0
    result = _helper("maps", models_dir() / "fcnpose_ur5_p70_int8.tflite", "--frames", frames,
                     "--inputs", tmp_path / "in.npy", "--out", tmp_path / "i.npz")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith("error: ") and "uint8" in result.stderr
