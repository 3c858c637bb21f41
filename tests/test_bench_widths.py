"""tools/bench_widths.py: its width arithmetic against FCN-Pose, its errors, and that a run prints a row per variant.

No timing is asserted: the figures are what the tool is for (docs/results.md, "Widths the kernels like?").
"""

import json
import subprocess
import sys

import pytest

from conftest import PROCESS_TIMEOUT
from tools_loader import TOOLS, tool

TOOL = TOOLS / "bench_widths.py"
P70 = "30,15,12,12,8,8,12,12,15"
P70_FLOOR12 = tuple(int(w) for w in P70.split(","))  # the 70 % widths with a floor of 12 (the default until 2026-11-28)
ROUNDED = "32,16,8,8,8,8,8,16,16"


@pytest.fixture(scope="module")
def bw():
    yield from tool("bench_widths")


@pytest.fixture
def run(bw, capsys):
    def call(*args):
        capsys.readouterr()
        status = bw.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return status, out, err
    return call


def test_nearest_multiples_and_floor_ceil(bw):
    assert bw.nearest_multiples(30, 8) == (32,)
    assert bw.nearest_multiples(12, 8) == (8, 16)  # halfway: both
    assert bw.nearest_multiples(15, 8) == (16,)
    assert bw.nearest_multiples(3, 8) == (8,)  # at least N
    assert bw.nearest_multiples(16, 8) == (16,)
    assert bw.nearest_multiples(30, 4) == (28, 32)
    assert bw.floor_ceil_multiples(30, 8) == (24, 32)
    assert bw.floor_ceil_multiples(5, 8) == (8,)
    nearest, every = bw.rounded_lists(P70_FLOOR12, 8)
    assert len(nearest) == 2 ** 4 and len(every) == 2 ** 7  # four 12s tie; 8, 8 are multiples already
    assert tuple(int(w) for w in ROUNDED.split(",")) in nearest
    assert all(w % 8 == 0 and w >= 8 for ws in every for w in ws)


def test_parameter_and_mac_arithmetic_matches_build_fcn_pose(bw):
    from fcnpose_tf.training.model import NUM_POOLS, UPSAMPLE_FACTORS, build_fcn_pose, describe

    assert (bw.NUM_POOLS, bw.UPSAMPLE_FACTORS) == (NUM_POOLS, UPSAMPLE_FACTORS)
    assert bw.fcn_params(P70_FLOOR12) == 14_344 and bw.fcn_params(bw.P70_WIDTHS) == 14_611
    for widths in (bw.P70_WIDTHS, P70_FLOOR12, (32, 16, 8, 8, 8, 8, 8, 16, 16), (1, 2, 3, 4, 5, 6, 7, 8, 9)):
        model = build_fcn_pose(widths, input_size=64)
        rows = [row for row in describe(model) if row.kind == "Conv2D"]
        assert bw.fcn_params(widths) == model.count_params()
        assert bw.fcn_macs(widths, 64) == sum(row.macs for row in rows)
        sites = bw.conv_sites(64)
        assert [(s.name, s.side) for s in sites] == [(row.name, row.output_shape[0]) for row in rows]
        assert [s.activation for s in sites] == ["relu"] * 9 + ["sigmoid"]


def test_p70_widths_are_the_shipped_models(bw):
    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.training.model import conv_widths, load_model

    path = models_dir() / "fcnpose_ur5_p70.keras"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    assert conv_widths(load_model(path)) == (*bw.P70_WIDTHS, bw.NUM_MAPS)


def test_budget_round_prints_the_rounded_lists_without_tensorflow(tmp_path):
    out = tmp_path / "budget.json"
    probe = ("import runpy, sys; sys.argv = sys.argv[1:]; "
             "code = 0\ntry:\n    runpy.run_path(sys.argv[0], run_name='__main__')\n"
             "except SystemExit as e:\n    code = e.code\n"
             "assert 'tensorflow' not in sys.modules, 'imported TensorFlow'\nsys.exit(code)")
    proc = subprocess.run([sys.executable, "-c", probe, str(TOOL), "--budget-round", "4,8", "--widths", P70,
                           "--json", str(out)], capture_output=True, text=True, timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 0, proc.stderr
    assert "14,344" in proc.stdout and ROUNDED in proc.stdout and "28,16,12,12,8,8,12,12,16" in proc.stdout
    report = json.loads(out.read_text())
    for entry in report["lists"]:
        rows = entry["rows"]
        assert rows[0]["kind"] == "original" and rows[0]["params"] == 14_344
        assert all(w % entry["round_to"] == 0 for r in rows[1:] for w in r["widths"])
        assert all(abs(r["params_change_percent"]) <= 5.0 for r in rows if r["kind"] == "floor/ceil")


@pytest.mark.parametrize("args,message", [
    (["--widths", "30,15"], "expected 9 widths"),
    (["--widths", "30,15,12,12,8,8,12,12,x"], "comma-separated positive integers"),
    (["--widths", "30,15,12,12,8,0,12,12,15"], "at least 1"),
    (["--budget-round", "8"], "needs a --widths list"),
    (["--budget-round", "8", "--widths", "1,2"], "expected 9 widths"),
    (["--layer", "conv11"], "conv1..conv10"),
    (["--layer", "conv3=9:6"], "A:B"),
    (["--layer", "conv3", "--widths", P70, "--widths", P70], "at most one --widths"),
    (["--widths", P70, "--threads", "1,2", "--clock", "cpu"], "--threads 1"),
    (["--widths", P70, "--size", "70"], "multiple of 32"),
    ([], "give --layer"),
])
def test_bad_arguments_give_one_error_line(run, args, message):
    status, out, err = run(*args)
    assert status == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ") and message in err, err


@pytest.mark.slow
def test_widths_run_prints_a_row_per_variant_and_format(run, tmp_path):
    out = tmp_path / "widths.json"
    status, stdout, err = run("--widths", P70, "--widths", ROUNDED, "--size", 64, "--rounds", 3, "--warmup", 1,
                              "--threads", 1, "--json", out)
    assert status == 0, err
    assert "int8 (folded), 1 thread(s)" in stdout and "float16, 1 thread(s)" in stdout
    for widths in (P70, ROUNDED):  # the parameter table and the two timing tables
        assert stdout.count(widths) == 3
    results = json.loads(out.read_text())["results"]
    assert sorted((r["variant"], r["format"]) for r in results) == [(1, "float16"), (1, "int8"), (2, "float16"),
                                                                    (2, "int8")]
    assert all(r["median_us"] > 0 and r["threads"] == 1 for r in results)
    assert {r["time_ratio_to_first"] for r in results if r["variant"] == 1} == {1.0}
    assert {r["params"] for r in results} == {14_344, 13_809}


@pytest.mark.slow
def test_layer_sweep_prints_a_row_per_width_format_and_thread_count(run, tmp_path):
    out = tmp_path / "layers.json"
    status, stdout, err = run("--layer", "conv3=6:7", "--layer", "conv10=9", "--size", 64, "--rounds", 3,
                              "--warmup", 1, "--threads", "1,2", "--json", out)
    assert status == 0, err
    for table in ("int8, 1 thread(s)", "int8, 2 thread(s)", "float16, 1 thread(s)", "float16, 2 thread(s)"):
        assert table in stdout
    results = json.loads(out.read_text())["results"]
    assert len(results) == 3 * 2 * 2  # (conv3 6, 7; conv10 9) x formats x threads
    conv10 = {r["format"]: r for r in results if r["layer"] == "conv10" and r["threads"] == 1}
    # int8 as exported: folded (16 phases of 9 maps at 16 x 16); float16 not; both read conv9's 15 channels
    assert (conv10["int8"]["kernel_c_out"], conv10["float16"]["kernel_c_out"]) == (144, 9)
    assert conv10["int8"]["input"] == "16x16x15" and conv10["int8"]["macs"] == 64 * 64 * 9 * 15 * 9
    conv3 = [r for r in results if r["layer"] == "conv3"]
    assert {r["c_out"] for r in conv3} == {6, 7} and {r["c_in"] for r in conv3} == {15}
    assert all(r["median_us"] > 0 and r["us_per_mmac"] > 0 for r in results)
