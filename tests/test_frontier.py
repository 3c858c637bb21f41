"""tools/frontier.py: the frontier rule, its refusals, and a run over two tiny files that writes its table, JSON and
plot. No timing is asserted: the figures are what the tool is for (docs/results.md, "The frontier")."""

import json
from pathlib import Path

import numpy as np
import pytest

from test_train_evaluate import make_via_folder
from weights import randomize
from tools_loader import tool


@pytest.fixture(scope="module")
def frontier():
    yield from tool("frontier")


def test_a_file_is_on_the_frontier_unless_another_is_faster_and_at_least_as_accurate(frontier):
    points = [(10.0, 0.80), (12.0, 0.85), (12.0, 0.84), (20.0, 0.85), (30.0, 0.90), (5.0, 0.50)]
    assert frontier.pareto_front(points) == [True, True, False, False, True, True]
    assert frontier.pareto_front([(1.0, 0.5), (1.0, 0.5)]) == [True, True]  # equal points dominate neither


def test_files_of_the_same_name_are_told_apart_by_their_folder(frontier):
    files = ["runs/w16/m_p70_int8.tflite", "saved/m_p70_int8.tflite", "runs/c192/m_p70_192_int8.tflite"]
    assert frontier.file_labels(files) == ["w16/m_p70_int8.tflite", "saved/m_p70_int8.tflite", "m_p70_192_int8.tflite"]


def test_bad_files_and_folders_are_one_error_line(frontier, tmp_path, capsys):
    keras_file = tmp_path / "model.keras"
    keras_file.write_bytes(b"x")
    assert frontier.main([str(keras_file)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {keras_file}: not a .tflite file"
    assert frontier.main([str(tmp_path / "missing.tflite")]) == 2
    tflite = tmp_path / "m.tflite"
    tflite.write_bytes(b"x")
    assert frontier.main([str(tflite), "--plot", str(tmp_path / "no" / "f.png")]) == 2
    assert "no such folder" in capsys.readouterr().err


@pytest.mark.slow
def test_a_run_measures_every_file_and_marks_the_shipped_one(frontier, tmp_path, capsys):
    from fcnpose_tf.compression.export import write_tflite
    from fcnpose_tf.training.model import build_fcn_pose

    data = make_via_folder(tmp_path / "frames", n=6)
    base = randomize(build_fcn_pose(input_size=64), seed=0)
    kernel, bias = base.get_layer("conv10").get_weights()
    base.get_layer("conv10").set_weights([kernel, np.full_like(bias, -2.0)])
    base.save(tmp_path / "base.keras")
    small = randomize(build_fcn_pose((8, 8, 8, 8, 8, 8, 8, 8, 8), input_size=64), seed=1)
    files = []
    for name, model in (("a", base), ("b", small)):
        files.append(tmp_path / f"{name}_fp16.tflite")
        write_tflite(model, files[-1], "float16", check_keypoints=False)
    status = frontier.main([str(files[0]), "--shipped", str(files[1]), "--keras", str(tmp_path / "base.keras"),
                            "--data", str(data), "--frames", "4", "--warmup", "1", "--json", str(tmp_path / "f.json"),
                            "--plot", str(tmp_path / "f.png")])
    out = capsys.readouterr().out
    assert status == 0
    result = json.loads((tmp_path / "f.json").read_text())
    assert [Path(r["file"]).name for r in result["files"]] == ["a_fp16.tflite", "b_fp16.tflite"]
    assert [r["shipped"] for r in result["files"]] == [False, True]
    assert all(r["format"] == "float16" and r["input_size"] == 64 and r["ratio"] > 0 for r in result["files"])
    assert any(r["front"] for r in result["files"]) and result["frames_scored"] == 6
    assert "b_fp16.tflite" in out and "target (>= 18x A at PCK@0.05 >= 0.84)" in out
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
