"""`fcnpose-tf compress` end to end on a tiny model, and its refusals (nothing partial left behind)."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fcnpose_tf.compression.report import (CompressReport, ModelStep, QATFacts, RefusedFormat, Retraining,
                                           TFLiteStep)
from fcnpose_tf.compression.summary import report_table
from test_train_evaluate import make_via_folder
from weights import randomize

REPORT_KEYS_L1 = ["base_model", "method", "recipe", "options", "evaluation_frames", "pck_normalisation", "threads",
                  "preset", "base", "pruning", "pruned_before_retraining", "retrain_data", "retraining", "retrained",
                  "quantized", "other_quantized", "refused", "files", "seconds"]
"""The keys of a retrained filter-surgery run's NAME_p70_report.json, in order, as written before the report was a
`CompressReport` (with the command's metadata "preset")."""

P70_WIDTHS = (15, 15, 15, 15, 8, 8, 15, 15, 15)
"""Filter surgery's widths at 0.7 with compress's default floor (no layer under 15 filters): 14,611 parameters."""


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from fcnpose_tf.training.model import build_fcn_pose

    root = tmp_path_factory.mktemp("compress")
    data = make_via_folder(root / "frames", n=20)  # 16 real frames for the int8 keypoint gate
    base = root / "base.keras"
    # Seeded weights, and maps that start below the threshold as a trained model's background does: with Keras's
    # zero biases a random FCN-Pose outputs exactly 0.5 wherever ReLU leaves conv10 nothing, and on such plateaus a
    # float16 file may switch a different set of threshold pixels on than Keras (6e-8 apart), so the export gate
    # would depend on the draw.
    model = randomize(build_fcn_pose(input_size=64), seed=0)
    kernel, bias = model.get_layer("conv10").get_weights()
    model.get_layer("conv10").set_weights([kernel, np.full_like(bias, -2.0)])
    model.save(base)
    return root, data, base


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_writes_model_tflite_and_report(setup, cli_here):
    root, data, base = setup
    out = root / "out"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--retrain-epochs",
                                   "1", "--out-dir", out, "--threads", "1", "--lr-patience", "2")
    assert status == 0, stdout + err
    names = {"base_p70.keras", "base_p70_fp16.tflite", "base_p70_int8.tflite", "base_p70_report.json"}
    assert names <= {p.name for p in out.iterdir()}
    report = json.loads((out / "base_p70_report.json").read_text())
    assert report["base"]["params"] == 131705 and report["preset"] == "recommended"
    # the file is CompressReport.to_json(): its sections in this order, the command's "preset" among the facts
    assert list(report) == REPORT_KEYS_L1
    assert CompressReport.from_json(report).to_json() == report
    # the default --min-filters 15: no layer under 15 filters (conv5/conv6 keep all 8) within the keep rule's
    # 14,668 parameters, instead of the paper's widths (39, 20, 10, 5, 3, 3, 5, 10, 20)
    assert report["retrained"]["params"] == 14611 == report["quantized"]["params"]
    assert report["retrained"]["widths"] == [*P70_WIDTHS, 9]
    assert report["pruned_before_retraining"]["widths"] == report["retrained"]["widths"]
    assert report["pruning"]["min_filters"] == report["options"]["min_filters"] == 15
    assert report["recipe"].startswith("filter surgery at 0.7 (no layer under 15 filters, same parameter budget), ")
    assert report["quantized"]["tflite_size_bytes"] == (out / "base_p70_fp16.tflite").stat().st_size < 45_000
    for step in ("base", "pruned_before_retraining", "retrained", "quantized"):
        assert "pck@0.05_bbox" in report[step]["metrics"]
    assert report["quantized"]["timing"]["threads"] == 1
    assert "14,611" in stdout and "PCK normalised by max(bbox w, h)" in stdout
    # the table: sizes of each row's own file in KB, PCK always with 3 decimals, FPS labelled end to end
    header = next(line for line in stdout.splitlines() if line.startswith("model "))
    assert "size KB" in header and "FPS e2e" in header
    tflite_row = next(line for line in stdout.splitlines() if line.startswith("float16 TFLite (.tflite)"))
    assert f"{report['quantized']['tflite_size_bytes'] / 1e3:.1f}" in tflite_row
    assert f"{report['quantized']['metrics']['pck@0.05_bbox']:.3f}" in tflite_row
    # the default --quantize float16,int8: a second file with its own row, calibrated on training frames only
    (int8,) = report["other_quantized"]
    assert int8["quantize"] == "int8" and report["quantized"]["quantize"] == "float16"
    assert int8["tflite_size_bytes"] == (out / "base_p70_int8.tflite").stat().st_size
    assert 0 < int8["export"]["calibration_frames"] <= 100 and int8["export"]["parity"]["frames"] >= 16
    int8_row = next(line for line in stdout.splitlines() if line.startswith("int8 TFLite (.tflite)"))
    assert f"{int8['metrics']['pck@0.05_bbox']:.3f}" in int8_row
    assert f"calibrated on {int8['export']['calibration_frames']} training frames; verified on" in stdout
    assert "upsampling folded" in stdout and "upsampling not folded" in stdout  # int8, float16
    # --lr-patience reaches the retraining's FitConfig; the base model has no record: plain BCE
    assert report["options"]["lr_patience"] == 2
    assert json.loads((out / "base_p70_train.json").read_text())["config"]["lr_patience"] == 2
    assert report["retraining"]["loss"] == "binary_crossentropy"
    assert report["retraining"]["learning_rates"] == [pytest.approx(3e-3)]  # compress's default rate
    # the kept epoch by the validation frames' keypoints (--keep-best keypoints, compress's default)
    assert report["retraining"]["kept_by"] == "keypoints" and report["options"]["keep_best"] == "keypoints"
    assert set(report["retraining"]["best_val_keypoints"]) == {"mean_pck", "pck_fine", "epe_px"}
    assert (out / "base_p70_loss.csv").read_text().startswith("epoch,loss,val_loss,val_mean_pck,")
    # the default criterion: first-order Taylor on (at most 256) training frames, never the measured ones
    assert report["pruning"]["importance"] == "taylor" and report["options"]["importance"] == "taylor"
    assert report["pruning"]["importance_frames"] == 16 and report["options"]["distill"] == 0.0

    before = {p.name: p.read_bytes() for p in out.iterdir()}
    status, _, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--retrain-epochs", "0",
                              "--out-dir", out)
    assert status == 2 and "already exists; pass --force" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_data_aware_criterion_and_distillation_are_recorded(setup, cli_here):
    """--importance taylor --distill 0.5: filters ranked on training frames, retrained against the base model's
    maps too; the report, its table line and NAME_train.json name the recipe (and --cluster chain the reading)."""
    root, data, base = setup
    out = root / "taylor"
    status, stdout, err = cli_here("compress", "--rate", "0.5", "--model", base, "--data", data, "--retrain-epochs",
                                   "1", "--importance", "taylor", "--importance-frames", "6", "--distill", "0.5",
                                   "--quantize", "float16", "--positive-weight", "20", "--lr-schedule", "cosine",
                                   "--min-filters", "0", "--out-dir", out, "--threads", "1", "--cluster", "chain")
    assert status == 0, stdout[-3000:] + err[-3000:]
    report = json.loads((out / "base_p50_report.json").read_text())
    assert report["pruning"]["importance"] == "taylor" and report["pruning"]["importance_frames"] == 6
    assert report["options"]["cluster"] == "chain" and "(--cluster chain); PCK normalised" in stdout
    assert report["options"]["importance"] == "taylor" and report["options"]["distill"] == 0.5
    assert report["distillation"]["weight"] == 0.5 and report["distillation"]["teacher_maps"] == "cached"
    assert report["retraining"]["loss"] == "distillation" and report["retraining"]["distill"] == 0.5
    assert report["retrained"]["params"] == 35185
    recipe = ("filter surgery at 0.5, filters ranked by taylor (independent, 6 training frames), retrained up to 1 "
              "epoch on binary cross-entropy, keypoint pixels weighted 20, teacher weight 0.5, learning rate 0.003 on a "
              "cosine")
    assert report["recipe"] == recipe and recipe in stdout
    record = json.loads((out / "base_p50_train.json").read_text())
    assert record["importance"] == "taylor" and record["importance_frames"] == 6 and record["recipe"] == recipe
    assert record["config"]["distill"] == 0.5 and record["distillation"]["teacher_maps"] == "cached"
    assert record["config"]["lr_schedule"] == "cosine" and report["options"]["lr_schedule"] == "cosine"


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_freeze_keeps_the_first_convolutions_of_the_pruned_model(setup, cli_here):
    """--freeze 2: conv1 and conv2 come out of retraining exactly as surgery left them (at rate 0 surgery keeps
    every filter, so they equal the base model's), conv3 is trained; the recipe says so."""
    import numpy as np
    from fcnpose_tf.training.model import load_model

    root, data, base = setup
    out = root / "frozen"
    status, stdout, err = cli_here("compress", "--rate", "0", "--model", base, "--data", data, "--retrain-epochs", "1",
                                   "--importance", "l1", "--freeze", "2", "--quantize", "float16", "--out-dir", out,
                                   "--threads", "1", "--total-minutes", "0.01")
    assert status == 0, stdout[-3000:] + err[-3000:]
    before, after = load_model(base), load_model(next(out.glob("*.keras")))
    for name in ("conv1", "conv2"):
        for w0, w1 in zip(before.get_layer(name).get_weights(), after.get_layer(name).get_weights()):
            np.testing.assert_array_equal(w0, w1)
    assert not np.array_equal(before.get_layer("conv3").get_weights()[0], after.get_layer("conv3").get_weights()[0])
    assert all(layer.trainable for layer in after.layers)  # the file fine-tunes like any other
    report = json.loads(next(out.glob("*_report.json")).read_text())
    assert report["options"]["freeze"] == 2 and report["recipe"].endswith(", conv1-2 fixed")
    # a total budget the first steps used up leaves the retraining its least, said and recorded
    assert "retraining budget 2.0 min (the least it gets: this run takes longer than its total)" in stdout
    assert report["options"]["max_minutes"] == 2.0 and report["options"]["total_minutes"] == 0.01
    assert json.loads(next(out.glob("*_train.json")).read_text())["config"]["max_minutes"] == 2.0
    assert isinstance(report["retraining"]["stopped_by_time_budget"], bool)  # written (which: the machine's load)


def recipe_of(options, base_path=None, floor=None) -> str:
    """The recipe a run of these options states (`PruningMethod.recipe`), checked as the command checks them, at a plan
    whose floor is `floor` (default: the one asked)."""
    from pathlib import Path

    from fcnpose_tf.compression.methods import pruned_start, pruning_method
    from fcnpose_tf.compression.plan import WidthPlan

    checked = options.checked(base_path)
    asked = checked.options.min_filters if checked.options.method == "l1" else 0
    plan = WidthPlan(checked.options.rate, asked, asked if floor is None else floor, (), 0, 0)
    start = pruned_start(checked, Path(base_path or "base.keras"), plan, "fcn-pose")
    return pruning_method(checked.options, plan, *start).recipe


def test_recipe_names_the_floor_and_a_lowered_one():
    from fcnpose_tf.compression.options import CompressOptions

    options = CompressOptions(rate=0.9, min_filters=12, importance="taylor", retrain_epochs=0)
    assert recipe_of(options).startswith("filter surgery at 0.9 (no layer under 12 filters, same parameter budget), ")
    assert recipe_of(options, floor=5).startswith("filter surgery at 0.9 (no layer under 5 filters: --min-filters 12 "
                                                  "lowered to fit the parameter budget), filters ranked by taylor")
    assert recipe_of(CompressOptions.preset("paper", rate=0.7), floor=0).startswith(
        "filter surgery at 0.7, filters ranked by l1")
    assert recipe_of(CompressOptions(rate=0.7)).startswith("filter surgery at 0.7 (no layer under 15 filters")


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_a_floor_that_does_not_fit_is_lowered_and_said(setup, cli_here):
    """At 0.9 FCN-Pose has 2,480 parameters: five layers of 15 do not fit, so compress keeps no layer under 5."""
    root, data, base = setup
    out = root / "floor"
    status, stdout, err = cli_here("compress", "--rate", "0.9", "--model", base, "--data", data, "--retrain-epochs",
                                   "0", "--importance", "l1", "--quantize", "float16", "--out-dir", out, "--threads",
                                   "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "--min-filters 15 does not fit the parameter budget of rate 0.9: no layer under 5 filters" in stdout
    report = json.loads((out / "base_p90_report.json").read_text())
    assert report["retrained"]["widths"] == [6, 5, 5, 5, 5, 5, 5, 5, 5, 9] and report["retrained"]["params"] <= 2480
    assert report["pruning"]["min_filters"] == 5 and report["options"]["min_filters"] == 15
    assert "(no layer under 5 filters: --min-filters 15 lowered to fit the parameter budget)" in report["recipe"]


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_magnitude_retraining_uses_the_weighted_loss_and_lr_patience(setup, cli_here):
    """--method magnitude retrains with the same loss as the l1 path (compile_for_training), not plain BCE."""
    root, data, base = setup
    out = root / "magnitude"
    status, stdout, err = cli_here("compress", "--rate", "0.5", "--method", "magnitude", "--model", base, "--data",
                                   data, "--retrain-epochs", "2", "--positive-weight", "20", "--lr-patience", "1",
                                   "--quantize", "float16", "--out-dir", out, "--threads", "1")  # int8: not its subject
    assert status == 0, stdout[-3000:] + err[-3000:]
    report = json.loads((out / "base_m50_report.json").read_text())
    assert list(report) == [{"pruning": "magnitude_sparsity"}.get(key, key) for key in REPORT_KEYS_L1]
    retraining = report["retraining"]
    assert retraining["loss"] == "keypoint_bce" and retraining["positive_weight"] == 20
    assert retraining["epochs_run"] == 2 and len(retraining["learning_rates"]) == 2  # fit's per-epoch rates
    assert retraining["learning_rates"][0] == pytest.approx(3e-3)
    assert report["options"]["lr_patience"] == 1 and report["retrained"]["params"] == 131705
    assert report["options"]["importance"] == "l1" and "pruning" not in report  # no criterion: smallest weights go


@pytest.mark.slow
@pytest.mark.parametrize("extra, message", [
    (["--lr-patience", "-1", "--rate", "0.5"], "learning-rate patience must be 0 (off) or more"),
    (["--augment-copies", "-1", "--rate", "0.5"], "augmented copies must be >= 0"),
    (["--rate", "1.2"], "pruning rate must be in [0, 1)"),
    (["--rate", "-0.1"], "pruning rate must be in [0, 1)"),
    (["--rate", "0.5", "--data", "MISSING"], "MISSING: not found"),
    (["--rate", "0.5", "--quantize", "float16,int4"], "expected one or more of float32, float16, int8-weights, int8"),
    (["--rate", "0.5", "--calibration-frames", "0"], "calibration frames must be at least 1"),
    (["--rate", "0.5", "--importance", "l3"], "argument --importance: invalid choice: 'l3'"),
    (["--rate", "0.5", "--importance-frames", "0"], "importance frames must be at least 1"),
    (["--rate", "0.5", "--distill", "1.5"], "distillation weight must be a number in [0, 1], got 1.5"),
    (["--rate", "0.5", "--distill", "-0.1"], "distillation weight must be a number in [0, 1]"),
    (["--rate", "0.5", "--distill", "half"], "argument --distill: invalid float value: 'half'"),
    (["--rate", "0.5", "--method", "magnitude", "--importance", "taylor"], "--importance taylor ranks filters for"),
    (["--rate", "0.5", "--strategy", "greedy", "--importance", "activation"], "--strategy greedy re-ranks kernels"),
    (["--rate", "0.5", "--lr-schedule", "cosine", "--lr-patience", "2"], "--lr-schedule cosine sets every epoch"),
    (["--rate", "0.5", "--method", "magnitude", "--freeze", "1"], "--freeze 1 keeps the first convolutions"),
    (["--rate", "0.5", "--freeze", "10"], "frozen layers must be 0 to 9"),
    (["--rate", "0.5", "--method", "magnitude", "--min-filters", "8"], "--min-filters 8 sets the widths of filter"),
    (["--rate", "0.5", "--min-filters", "-1"], "narrowest layer must be a whole number >= 0, got -1"),
    (["--rate", "0.5", "--min-filters", "wide"], "argument --min-filters: invalid int value: 'wide'"),
])
def test_bad_input_leaves_nothing(setup, cli_here, extra, message, tmp_path, monkeypatch):
    root, data, base = setup
    monkeypatch.chdir(tmp_path)  # a relative --data MISSING is looked up here
    out = root / "refused"
    args = ["compress", "--model", base, "--out-dir", out, "--retrain-epochs", "0"] + extra
    if "--data" not in extra:
        args += ["--data", data]
    status, _, err = cli_here(*args)  # in-process: a defect would raise here instead of printing a traceback
    assert status == 2 and message in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.startswith("error:")]) == 1
    assert not out.exists()  # not even an empty folder


@pytest.mark.slow
def test_unsupported_layer_and_unwritable_output(setup, cli_here, tmp_path):
    import tf_keras as keras

    root, data, base = setup
    inp = keras.Input((64, 64, 3))
    a = keras.layers.Conv2D(8, 3, padding="same", name="conv1")(inp)
    b = keras.layers.Conv2D(8, 3, padding="same", name="conv2")(a)
    skip = keras.layers.Add(name="skip")([a, b])
    outp = keras.layers.Conv2D(9, 3, padding="same", activation="sigmoid", name="conv3")(skip)
    odd = tmp_path / "skip.keras"
    keras.Model(inp, outp).save(odd)
    out = tmp_path / "out"
    status, stdout, err = cli_here("compress", "--rate", "0.5", "--model", odd, "--data", data, "--retrain-epochs", "0",
                                   "--out-dir", out)  # in-process: a defect would raise here instead of a traceback
    assert status == 2 and "unsupported layer" in err and "Traceback" not in err
    assert "[1/" not in stdout  # refused before measuring or preparing anything
    assert not out.exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    status, _, err = cli_here("compress", "--rate", "0.5", "--model", base, "--data", data, "--out-dir", blocker)
    assert status == 2 and "not a folder" in err


def test_compress_with_too_few_frames_for_int8_refuses_before_any_work(setup, cli_here, tmp_path):
    """int8's gate needs 16 real frames: a project with fewer is refused before measuring or retraining anything, as
    `export` refuses it, not after the retraining with the float16 file written and no report."""
    _, _, base = setup
    data = make_via_folder(tmp_path / "frames", n=12)
    out = tmp_path / "out"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--out-dir", out,
                                   "--threads", "1")
    assert status == 2, err
    assert err.strip().splitlines()[-1].startswith("error: int8 export is verified on keypoints of at least 16 real "
                                                   "frames;")
    assert "has 12 (add frames, or leave int8 out of --quantize)" in err
    assert "[1/" not in stdout and not out.exists()


@pytest.mark.slow
def test_export_command_writes_verified_files_next_to_the_model(setup, cli_here, tmp_path):
    """`fcnpose-tf export`: one file per format, the int8 one calibrated on the data's training split."""
    import shutil

    from fcnpose_tf.compression.frames import describe_check_frames
    from fcnpose_tf.data.dataset import load_dataset

    root, data, base = setup
    model = tmp_path / "arm.keras"
    shutil.copy(base, model)
    status, stdout, err = cli_here("export", model, "--data", data, "--json", tmp_path / "export.json", "--threads",
                                   "1")
    assert status == 0, stdout + err
    assert (tmp_path / "arm_fp16.tflite").is_file() and (tmp_path / "arm_int8.tflite").is_file()
    record = json.loads((tmp_path / "export.json").read_text())
    fp16, int8 = record["files"]
    assert fp16["quantize"] == "float16" and fp16["calibration_frames"] == 0 and not fp16["graph_rewrites"]
    assert int8["quantize"] == "int8" and int8["calibration_frames"] == 16 and int8["graph_rewrites"]
    assert int8["parity"]["frames"] == 16 and int8["parity"]["min_keypoint_share"] == 0.95
    assert "arm_int8.tflite" in stdout and "folded" in stdout
    validation = len(load_dataset(data).split(None)[1])  # fewer than 16: topped up with training frames, said so
    assert validation < 16 and record["verification_frames"] == (
        f"the {validation} frames of the validation split and the first {16 - validation} of the training split")
    assert f"on {record['verification_frames']} of " in stdout
    assert describe_check_frames(16, 40) == "the first 16 frames of the validation split"
    assert record["schema"]["keypoints"][0] == "base"  # the names the files' maps stand for
    status, _, err = cli_here("export", model, "--data", data, "--quantize", "int8")
    assert status == 2 and "already exists; pass --force" in err


def test_export_at_another_input_size_names_its_files_and_runs_at_it(setup, cli_here, tmp_path):
    """`export --input-size S`: the model rebuilt at S with its weights (for `run --track`), NAME_S_fp16.tflite."""
    import shutil

    from fcnpose_tf.runtime.estimator import KeypointModel

    root, data, base = setup
    model = tmp_path / "arm.keras"
    shutil.copy(base, model)
    status, stdout, err = cli_here("export", model, "--data", data, "--input-size", "96", "--quantize", "float16",
                                   "--threads", "1")
    assert status == 0, stdout + err
    assert KeypointModel(tmp_path / "arm_96_fp16.tflite", num_threads=1).view.shape == (96, 96)
    assert not (tmp_path / "arm_fp16.tflite").exists()
    status, _, err = cli_here("export", model, "--data", data, "--input-size", "90")
    assert status == 2 and "multiple of 32" in err


def test_compress_options_refuse_combinations_no_run_can_do():
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.errors import UserError

    with pytest.raises(UserError, match="--importance taylor ranks filters for filter surgery"):
        CompressOptions(rate=0.5, method="magnitude", importance="taylor").validate()
    with pytest.raises(UserError, match="--strategy greedy re-ranks kernels"):
        CompressOptions(rate=0.5, strategy="greedy", importance="activation").validate()
    with pytest.raises(UserError, match="importance criterion must be one of l1, l2, activation, taylor"):
        CompressOptions(rate=0.5, importance="random").validate()
    with pytest.raises(UserError, match=r"distillation weight must be a number in \[0, 1\], got 1.5"):
        CompressOptions(rate=0.5, distill=1.5).validate()
    CompressOptions(rate=0.5, strategy="greedy", importance="l2", distill=1.0).validate()


_STAGE = {"mean": 2.0, "std": 0.1, "median": 2.0}
TIMING = {"threads": 1, "backend": "b", "frames_timed": 50, "preprocess_ms": _STAGE, "inference_ms": _STAGE,
          "postprocess_ms": _STAGE, "total_ms": _STAGE, "fps": 100.0, "fps_inference_only": 500.0}


def _step(params: int, pck: float, **more) -> ModelStep | TFLiteStep:
    """A Keras step, or a TFLite one given its "quantize"."""
    metrics = {"pck@0.5_bbox": pck, "pck@0.2_bbox": pck, "pck@0.05_bbox": pck, "epe_px": 1.5}
    kind = TFLiteStep if "quantize" in more else ModelStep
    return kind.from_json({"params": params, "macs": 2_000_000, "metrics": metrics, **more})


def _report(**changes) -> CompressReport:
    timing = TIMING
    fields = dict(base_model="base.keras", method="l1", recipe="filter surgery at 0.7",
                  options={"quantize": ("float16", "int8"), "rate": 0.7}, evaluation_frames="4 frames of via.json",
                  pck_normalisation="max(w, h)", threads=1, metadata={"preset": "recommended"},
                  base=_step(100, 0.9, h5_size_bytes=4000, timing=timing), pruning={"importance": "l1"},
                  pruned_before_retraining=_step(30, 0.5),
                  retrain_data={"fold": None}, retraining=Retraining(epochs_run=1),
                  retrained=_step(30, 0.8, h5_size_bytes=1200, timing=timing),
                  quantized=_step(30, 0.8, quantize="float16", status="written", tflite_size_bytes=600, timing=timing),
                  refused=[RefusedFormat("int8", "keypoint 3 lost", post_training={"reason": "keypoint 3 lost"})],
                  files={"keras": "out/base_p70.keras", "tflite_fp16": "out/base_p70_fp16.tflite"}, seconds=12.5)
    return CompressReport(**{**fields, **changes})


def test_a_file_that_loses_more_than_the_papers_pck_gets_a_note_naming_a_lower_rate():
    """`accuracy_note`: the best file written against the unpruned model; within 0.02 no note; beyond, the loss and a
    lower rate (the views-that-vary figure above 0.5); no file written, no note."""
    from fcnpose_tf.compression.summary import accuracy_note

    timing = TIMING
    written = _step(30, 0.95, quantize="float16", status="written", tflite_size_bytes=600, timing=timing)
    assert accuracy_note(_report(base=_step(100, 0.96, h5_size_bytes=4000, timing=timing), quantized=written)) is None
    note = accuracy_note(_report(quantized=_step(30, 0.8, quantize="float16", status="written"),
                                 other_quantized=[_step(30, 0.85, quantize="int8", status="written")]))
    assert note == ("note: PCK@0.5 0.850 (int8) is 0.050 below the unpruned model's 0.900 on these frames, more than "
                    "the 0.02 the paper's files lose; PCK@0.05 0.050 below, more than 0.03; more frames of your own "
                    "camera, labelled by your model and given the minutes, keep more of it (--more-frames "
                    "VIDEO_OR_FOLDER: docs/compression.md, \"More frames of your look\"); else a lower "
                    "--rate keeps more of it: on views that vary --rate 0.5 came closest (docs/compression.md, "
                    "\"Views that vary: a lower rate\"); --rates 0.5,0.7 compares them in one run")
    at_half = accuracy_note(_report(options={"quantize": ("float16",), "rate": 0.5}))
    assert at_half.endswith("more than the 0.02 the paper's files lose; PCK@0.05 0.100 below, more than 0.03; more "
                            "frames of your own camera, labelled by your model and given the minutes, keep more of "
                            "it (--more-frames VIDEO_OR_FOLDER: docs/compression.md, \"More frames of your "
                            "look\"); else a lower "
                            "--rate keeps more of it")
    assert accuracy_note(_report(quantized=None)) is None
    added = {"fold": None, "added_frames": {"source": "cell.mp4", "labelled_by": "arm.keras", "frames": 720,
                                            "description": "720 frames"}}
    after_more = accuracy_note(_report(retrain_data=added))
    assert "; this run retrained on 720 more frames of cell.mp4: more of them (--more-frames-count), or every one " \
           "of their labels corrected (--more-frames-via OUT.json, then --more-frames OUT.json) may keep more of it " \
           "(docs/compression.md, \"More frames of your look\"); else a lower --rate" in after_more
    assert "VIDEO_OR_FOLDER" not in after_more
    as_corrected = dict(added, added_frames=dict(added["added_frames"], source="more.json", labelled_by=None))
    assert "720 more frames of more.json: more of them (--more-frames-count) may keep more of it" in accuracy_note(
        _report(retrain_data=as_corrected))
    # the README's command: no camera's frames to add; a loss within the task's spread names the spread and the
    # bundled files, a larger one a lower rate
    readme = _report(base=_at({0.5: 1.0, 0.05: 0.877}, h5_size_bytes=4000, timing=TIMING),
                     quantized=_at({0.5: 0.996, 0.05: 0.838}, quantize="float16", status="written"))
    bundled = accuracy_note(readme, bundled_task=True)
    assert bundled.endswith("; on the bundled task fine localisation varies from run to run with the seed, the "
                            "thread count and the kept epoch (70 % files at PCK@0.05 0.86-0.89 on the defaults, "
                            "0.80-0.89 with --keep-best loss, against the unpruned 0.877: "
                            "docs/compression.md, \"Retraining in fcnpose-tf compress\"); the bundled 70 % files in "
                            "saved_models/ are a run at 0.886, and --seed S makes another"), bundled
    assert "--more-frames" not in bundled and "--rate" not in bundled
    shipped = json.loads((Path(__file__).parents[1] / "saved_models" / "fcnpose_ur5_p70_report.json").read_text())
    assert f"against the unpruned {shipped['base']['metrics']['pck@0.05_bbox']:.3f}" in bundled  # the files' figures
    assert f"a run at {shipped['quantized']['metrics']['pck@0.05_bbox']:.3f}" in bundled
    for beyond in (_at({0.5: 0.996, 0.05: 0.790}, quantize="float16", status="written"),  # PCK@0.05 past the spread
                   _at({0.5: 0.970, 0.05: 0.838}, quantize="float16", status="written")):  # PCK@0.5 lost
        far = accuracy_note(replace(readme, quantized=beyond), bundled_task=True)
        assert far.endswith("; a lower --rate keeps more of it: on views that vary --rate 0.5 came closest "
                            "(docs/compression.md, \"Views that vary: a lower rate\"); --rates 0.5,0.7 compares "
                            "them in one run"), far


def _at(pck: dict, **more) -> ModelStep | TFLiteStep:
    """A step whose PCK@0.5 and PCK@0.05 differ: `pck` maps 0.5 and 0.05 to theirs."""
    step = _step(30, pck[0.5], **more).to_json()
    step["metrics"]["pck@0.05_bbox"] = pck[0.05]
    return (TFLiteStep if "quantize" in more else ModelStep).from_json(step)


def test_a_file_that_keeps_pck_at_half_but_loses_fine_localisation_gets_its_own_note():
    """PCK@0.5 within 0.02 but PCK@0.05 beyond 0.03 (keypoints on the right part, less finely placed: views that
    vary): the note says so, from the file best at PCK@0.05; within both budgets none."""
    from fcnpose_tf.compression.summary import accuracy_note

    base = _at({0.5: 0.958, 0.05: 0.517}, h5_size_bytes=4000, timing=TIMING)
    fp16 = _at({0.5: 0.946, 0.05: 0.477}, quantize="float16", status="written")
    int8 = _at({0.5: 0.946, 0.05: 0.483}, quantize="int8", status="written")
    note = accuracy_note(_report(base=base, quantized=fp16, other_quantized=[int8]))
    assert note.startswith("note: PCK@0.05 0.483 (int8) is 0.034 below the unpruned model's 0.517 on these frames, "
                           "more than the 0.03 budget for fine localisation (PCK@0.5 within 0.02: keypoints on the "
                           "right part of the arm, less finely placed); more frames of your own camera"), note
    close = _at({0.5: 0.946, 0.05: 0.490}, quantize="int8", status="written")
    assert accuracy_note(_report(base=base, quantized=fp16, other_quantized=[close])) is None
    # a retraining the time budget ended (a busy machine): that first, then the lower rate
    cut = accuracy_note(_report(base=base, quantized=fp16, options={"quantize": ("float16",), "rate": 0.7,
                                                                      "retrain_epochs": 25},
                                retraining=Retraining(epochs_run=18, stopped_by_time_budget=True)))
    assert ("; the retraining stopped at its time budget after 18 of 25 epochs (a slow or busy machine): more "
            "minutes may recover it (--max-minutes none --total-minutes none runs every epoch") in cut and cut.endswith(
        "else a lower --rate keeps more of it: on views that vary --rate 0.5 came closest (docs/compression.md, "
        "\"Views that vary: a lower rate\"); --rates 0.5,0.7 compares them in one run"), cut


def test_the_best_rate_note_names_the_rate_within_both_budgets_when_the_best_loses_fine_localisation():
    """`best_rate_note`: the highest rate within 0.02 PCK@0.5; when it loses more than 0.03 PCK@0.05, by how much and
    the highest rate within both (or none); no rate within 0.02: says so."""
    from fcnpose_tf.compression.summary import best_rate_note

    base = _at({0.5: 0.95, 0.05: 0.50}, h5_size_bytes=4000, timing=TIMING)

    def at(rate, pck):
        return _report(base=base, options={"quantize": ("float16",), "rate": rate},
                       quantized=_at(pck, quantize="float16", status="written"))

    half, six, seven = (at(0.5, {0.5: 0.945, 0.05: 0.49}), at(0.6, {0.5: 0.94, 0.05: 0.45}),
                        at(0.7, {0.5: 0.90, 0.05: 0.40}))
    assert best_rate_note([seven, half, six]) == (
        "Best rate within the 0.02 PCK@0.5 budget: 0.6 (its best file +0.010 below the unpruned model's 0.950); "
        "0.7 loses 0.050; at 0.6 PCK@0.05 loses 0.050, more than 0.03 (fine localisation): 0.5 keeps both")
    assert best_rate_note([six]).endswith("more than 0.03 (fine localisation): no rate measured keeps both")
    assert best_rate_note([half]) == ("Best rate within the 0.02 PCK@0.5 budget: 0.5 (its best file +0.005 below the "
                                      "unpruned model's 0.950)")
    assert best_rate_note([seven]).startswith("note: no rate kept PCK@0.5 within 0.02 of the unpruned model's 0.950")


def test_a_rate_at_a_pruned_starts_height_is_judged_and_shown_against_the_unpruned_model_there():
    """`compress --rates` on the generalist: 0.5 by surgery at the model's height, 0.7 from generalist-p70 at 256
    (`methods.start_height`). Each rate's note figure is its own unpruned measurement, and the table gives the
    other height's unpruned row beside that rate's."""
    from fcnpose_tf.compression.summary import best_rate_note, rates_table

    at_224 = _at({0.5: 0.95, 0.05: 0.50}, h5_size_bytes=4000, timing=TIMING)
    at_256 = _at({0.5: 0.94, 0.05: 0.49}, h5_size_bytes=4000, timing=TIMING)
    half = _report(base=at_224, options={"quantize": ("float16",), "rate": 0.5, "input_size": None},
                   quantized=_at({0.5: 0.945, 0.05: 0.49}, quantize="float16", status="written"))
    seven = _report(base=at_256, options={"quantize": ("float16",), "rate": 0.7, "input_size": 256},
                    quantized=_at({0.5: 0.93, 0.05: 0.48}, quantize="float16", status="written"))
    assert best_rate_note([half, seven]) == ("Best rate within the 0.02 PCK@0.5 budget: 0.7 (its best file +0.010 "
                                             "below the unpruned model's 0.940)")
    table = rates_table([half, seven]).splitlines()
    unpruned = [line for line in table if "unpruned" in line]
    assert [line.split("  ")[0] for line in unpruned] == ["unpruned (Keras; size as .h5)",
                                                          "rate 0.7: unpruned at height 256 (Keras)"]
    assert "0.950" in unpruned[0] and "0.940" in unpruned[1]
    assert sum("unpruned" in line for line in rates_table([half]).splitlines()) == 1


def test_the_report_is_written_as_its_sections_in_order():
    """`to_json` is the NAME_pXX_report.json object: the sections in the file's order, the caller's metadata in
    its place, a section the run does not have left out (but "quantized", null when every format was refused)."""
    report = _report()
    written = report.to_json()
    assert list(written) == REPORT_KEYS_L1
    assert written["preset"] == "recommended" and written["threads"] == 1
    assert written["refused"] == [{"quantize": "int8", "status": "refused", "reason": "keypoint 3 lost",
                                   "post_training": {"reason": "keypoint 3 lost"}}]
    assert CompressReport.from_json(json.loads(json.dumps(written))).to_json() == json.loads(json.dumps(written))
    assert report.tflite_files == [report.quantized]

    distilled = _report(distillation={"weight": 0.5}).to_json()
    assert list(distilled)[list(distilled).index("retrain_data"):][:3] == ["retrain_data", "distillation", "retraining"]
    magnitude = _report(method="magnitude", pruning=None, magnitude_sparsity=0.889, metadata={}).to_json()
    assert "pruning" not in magnitude and "preset" not in magnitude
    assert list(magnitude)[8:10] == ["magnitude_sparsity", "pruned_before_retraining"]
    unretrained = _report(retrain_data=None, retraining=None, quantized=None).to_json()
    assert "retrain_data" not in unretrained and "retraining" not in unretrained
    assert unretrained["quantized"] is None and unretrained["other_quantized"] == []


def test_a_refused_format_keeps_quantization_aware_trainings_facts():
    qat = {"epochs_run": 3, "minutes": 1.5}
    entry = RefusedFormat("int8", "after 3 epoch(s) of quantization-aware training: x", {"reason": "y"},
                          qat=QATFacts.from_json(qat))
    assert entry.to_json() == {"quantize": "int8", "status": "refused", "reason": entry.reason,
                               "post_training": {"reason": "y"}, "qat": qat}
    assert RefusedFormat.from_json(entry.to_json()) == entry and entry.qat.epochs_run == 3


def test_quantization_aware_trainings_facts_are_typed_and_written_as_before():
    """A file's QAT facts read typed (`QATFacts`) and are written back with every key in its order, one unknown to
    this version too; `QATFacts.of` writes what `QATResult.to_dict` and the run add, in that order."""
    from fcnpose_tf.compression.qat import QATResult

    written = {"passed": True, "epochs_run": 2, "seconds": 61.0, "minutes": 1.02,
               "epochs": [{"epoch": 1, "passed": False}, {"epoch": 2, "passed": True}], "learning_rate": 1e-4,
               "post_training_refused": {"reason": "keypoint 3 lost", "keypoints_lost_or_gained": 1}, "later": 1}
    step = {**_step(14611, 0.9, quantize="int8", status="written", quantization="quantization-aware training")
            .to_json(), "qat": written}
    read = TFLiteStep.from_json(step)
    assert read.qat.epochs_run == 2 and read.qat.post_training_refused["reason"] == "keypoint 3 lost"
    assert read.to_json() == step and list(read.to_json()["qat"]) == list(written)
    result = QATResult(export=None, epochs_run=1, seconds=30.04, epochs=[{"epoch": 1}], reason="still lost")
    facts = QATFacts.of(result, 1e-4, {"reason": "lost"}).to_json()
    assert facts == {**result.to_dict(), "learning_rate": 1e-4, "post_training_refused": {"reason": "lost"}}
    assert list(facts) == [*result.to_dict(), "learning_rate", "post_training_refused"]


def test_a_written_report_reads_back_older_ones_too():
    """from_json: a key without a field is a further fact (the sweep's "retimed"); a report written before
    "recipe", "other_quantized" and "refused" existed reads them as "", [] and []; one without a section every
    report has is no report."""
    written = _report().to_json()
    written["retimed"] = {"threads": 1}
    back = CompressReport.from_json(written)
    assert back.metadata == {"preset": "recommended", "retimed": {"threads": 1}}
    assert back.refused == _report().refused and back.quantized.to_json() == written["quantized"]

    older = {k: v for k, v in _report().to_json().items() if k not in ("recipe", "other_quantized", "refused")}
    older["options"] = {"quantize": "float16"}
    del older["quantized"]["quantize"]
    old = CompressReport.from_json(older)
    assert (old.recipe, old.other_quantized, old.refused) == ("", [], [])
    assert "float16 TFLite (.tflite)" in report_table(older)

    with pytest.raises(ValueError, match="not a compress report: no base, retrained"):
        CompressReport.from_json({k: v for k, v in written.items() if k not in ("base", "retrained")})
    with pytest.raises(TypeError, match="a compress report is a JSON object, not list"):
        CompressReport.from_json([])


def test_report_metadata_cannot_replace_a_section(tmp_path):
    from fcnpose_tf.compression.compress import compress_model
    from fcnpose_tf.compression.options import CompressOptions

    with pytest.raises(ValueError, match="report metadata cannot hold base, method: a section of the report"):
        _report(metadata={"method": "x", "base": {}, "preset": "paper"})
    with pytest.raises(ValueError, match="cannot hold seconds"):  # before any work: no model is read
        compress_model(tmp_path / "missing.keras", None, None, [], tmp_path / "out", CompressOptions(rate=0.5),
                       metadata={"seconds": 1})
    assert not (tmp_path / "out").exists()


def test_the_table_of_a_report_and_of_its_file_are_the_same():
    report = _report(options={"quantize": ("int8", "float16")})
    table = report_table(report)
    assert table == report_table(json.loads(json.dumps(report.to_json())))
    lines = table.splitlines()
    assert lines[-2].startswith("int8 TFLite: REFUSED (gate)")  # in --quantize order
    assert lines[-1].startswith("float16 TFLite (.tflite)") and "0.6" in lines[-1]


def test_compress_inherits_the_base_models_augmentation(tmp_path):
    """Left unset, the retraining augments as the base model's training did (its NAME_train.json), as with its
    keypoint weight; a model without a record, or a record without it, gets the paper's copies; a value given wins."""
    import json

    from fcnpose_tf.compression.options import CompressOptions

    base = tmp_path / "views.keras"
    base.write_bytes(b"")  # only the record beside it is read
    (tmp_path / "views_train.json").write_text(json.dumps({"augment": "online", "config": {"positive_weight": 20}}))
    resolved = CompressOptions(rate=0.7).resolved(base)
    assert (resolved.augment, resolved.positive_weight) == ("online", 20.0)
    assert "retrained up to 25 epochs with online augmentation on" in recipe_of(CompressOptions(rate=0.7), base)
    assert CompressOptions(rate=0.7, augment="paper").resolved(base).augment == "paper"
    (tmp_path / "views_train.json").write_text(json.dumps({"augment": "sideways"}))
    assert CompressOptions(rate=0.7).resolved(base).augment == "paper"
    assert CompressOptions(rate=0.7).resolved(tmp_path / "none.keras").augment == "paper"
    assert "online" not in recipe_of(CompressOptions(rate=0.7))


def test_compress_retrains_on_as_many_copies_as_the_base_model(tmp_path):
    """Left unset, the retraining makes as many copies of each frame as the base model's training did (train's 4 on
    one fixed camera); a record without them, or none, gives the paper's 2; a value given wins."""
    import json

    from fcnpose_tf.compression.options import CompressOptions

    base = tmp_path / "fixed.keras"
    base.write_bytes(b"")  # only the record beside it is read
    (tmp_path / "fixed_train.json").write_text(json.dumps({"augment": "paper", "augment_copies": 4}))
    assert CompressOptions(rate=0.7).resolved(base).augment_copies == 4
    assert CompressOptions(rate=0.7, augment_copies=1).resolved(base).augment_copies == 1
    (tmp_path / "fixed_train.json").write_text(json.dumps({"augment": "paper", "augment_copies": "four"}))
    assert CompressOptions(rate=0.7).resolved(base).augment_copies == 2
    assert CompressOptions(rate=0.7).resolved(tmp_path / "none.keras").augment_copies == 2
    # a record that does not say its copies were the paper's kind (the bundled baseline's: "augment_copies": 0, no
    # "augment") keeps the paper's 2, as compress always retrained it
    (tmp_path / "fixed_train.json").write_text(json.dumps({"augment_copies": 0}))
    assert CompressOptions(rate=0.7).resolved(base).augment_copies == 2
    assert CompressOptions.preset("paper", rate=0.7).augment_copies == 2


@pytest.fixture
def bundled_pruned_generalist(tmp_path, monkeypatch):
    """A bundled-models folder whose generalist-p70 is a 64 x 64 FCN-Pose at filter surgery's widths at 0.7 (no layer
    under 15 filters); returns the folder."""
    from fcnpose_tf.training.model import build_fcn_pose

    folder = tmp_path / "bundled"
    folder.mkdir()
    for name in ("fcnpose_ur5.keras", "fcnpose_ur5_generalist.keras"):
        (folder / name).write_bytes(b"")  # only their paths are read
    randomize(build_fcn_pose(P70_WIDTHS, input_size=64), seed=3).save(
        folder / "fcnpose_ur5_generalist_p70.keras")
    monkeypatch.setenv("FCNPOSE_MODELS_DIR", str(folder))
    return folder


def test_auto_starts_the_generalist_as_it_is_from_the_pruned_generalist(bundled_pruned_generalist, tmp_path):
    """--start auto (the default): generalist-p70 for the generalist itself and for a model `train` kept unchanged
    from it on views that vary (no epoch beat it, or the start as saved measured better; through kept rounds), at the
    rate and floor whose widths it has; surgery otherwise (a model trained from it, a fixed camera, another start),
    and for --start surgery and magnitude pruning."""
    from fcnpose_tf.compression.methods import pruned_start
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.compression.plan import plan_widths
    from fcnpose_tf.progress import Reporter
    from fcnpose_tf.training.model import build_fcn_pose

    base = build_fcn_pose(input_size=64)
    path = tmp_path / "mine.keras"
    path.write_bytes(b"")
    round2 = tmp_path / "round2.keras"
    round2.write_bytes(b"")
    expected = bundled_pruned_generalist / "fcnpose_ur5_generalist_p70.keras"
    lines = []

    class Lines(Reporter):  # keeps what the choice says
        def say(self, line):
            lines.append(line)

    def start(options, model_path=path, floor=15, architecture="fcn-pose"):
        return pruned_start(options.checked(), model_path, plan_widths(base, options.rate, floor), architecture,
                            Lines())

    def record(model, **fields):
        (model.parent / f"{model.stem}_train.json").write_text(json.dumps(fields))

    auto = CompressOptions(rate=0.7)
    assert auto.start == "auto"  # the default
    assert start(auto) == ("surgery", None)  # no record: not known to be the generalist
    record(path, init="generalist", augment="online", best_epoch=4)
    assert start(auto) == ("surgery", None)  # fine-tuned from it: its own weights
    record(path, init="generalist", augment="online", best_epoch=0)
    assert start(auto) == ("generalist-p70", expected)  # no epoch beat the generalist: kept as it is
    record(path, init="generalist", augment="online", best_epoch=6, start_as_saved={"chose": "start"})
    assert start(auto) == ("generalist-p70", expected)  # the start as saved measured better
    record(round2, init=str(path), augment="online", best_epoch=0)
    assert start(auto, round2) == ("generalist-p70", expected)  # a second round that kept the first round's weights
    record(round2, init=str(path), augment="online", best_epoch=3)
    assert start(auto, round2) == ("surgery", None)
    record(path, init="generalist", augment="paper", best_epoch=0)
    assert start(auto) == ("surgery", None)  # a fixed camera: the paper's copies
    record(path, init="workcell", augment="online", best_epoch=0)
    assert start(auto) == ("surgery", None)  # kept, but not the generalist
    (bundled_pruned_generalist / "fcnpose_ur5_generalist_train.json").write_text(json.dumps({"augment": "online"}))
    assert start(auto, bundled_pruned_generalist / "fcnpose_ur5_generalist.keras") == ("generalist-p70", expected)
    record(path, init="generalist", augment="online", best_epoch=0)
    assert start(CompressOptions(rate=0.7, start="surgery")) == ("surgery", None)
    assert start(CompressOptions(rate=0.7, method="magnitude", start="auto")) == ("surgery", None)
    assert lines == []
    # other widths: another rate, or the paper's floor
    assert start(CompressOptions(rate=0.5, start="auto")) == ("surgery", None)
    assert start(CompressOptions(rate=0.7, min_filters=0, start="auto"), floor=0) == ("surgery", None)
    assert len(lines) == 2 and "generalist-p70's widths are not filter surgery's at rate 0.5" in lines[0]
    # a model with the skip: the bundled start has none
    assert start(CompressOptions(rate=0.7, start="auto"), architecture="fcn-pose-skip") == ("surgery", None)
    assert "generalist-p70 is an fcn-pose network" in lines.pop()
    # named explicitly: a bundled name or a file, whatever the base model's lineage
    assert start(CompressOptions(rate=0.7, start="generalist-p70")) == ("generalist-p70", expected)
    assert start(CompressOptions(rate=0.5, start=str(expected))) == (str(expected), expected)
    expected.unlink()  # an installation without the file: surgery, said
    assert start(CompressOptions(rate=0.7, start="auto")) == ("surgery", None) and "is missing" in lines[-1]


def test_a_pruned_start_is_named_in_the_recipe_and_refused_with_magnitude_pruning():
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.errors import UserError

    recipe = recipe_of(CompressOptions(rate=0.7, start="generalist-p70", retrain_epochs=0))
    assert recipe == ("filter surgery's widths at 0.7 (no layer under 15 filters, same parameter budget), the weights "
                      "of generalist-p70, not retrained")
    assert CompressOptions.preset("paper", rate=0.7).start == "surgery"
    with pytest.raises(UserError, match="--start generalist-p70 gives filter surgery's pruned network its weights"):
        CompressOptions(rate=0.7, method="magnitude", start="generalist-p70").validate()
    with pytest.raises(UserError, match="pruned start must be auto, surgery, a bundled name or a .keras file"):
        CompressOptions(rate=0.7, start=" ").validate()


def compress_from_start(cli_here, setup, start, out, *more):
    """`compress --rate 0.7` of the test model from the pruned start `start` into `out`, not retrained unless `more`
    says, the float16 file only, one thread: (status, stdout, stderr)."""
    root, data, base = setup
    return cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--start", start, "--retrain-epochs",
                    "0", "--quantize", "float16", "--out-dir", out, "--threads", "1", *more)


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_from_a_pruned_start_takes_its_weights_and_refuses_other_widths(setup, cli_here, tmp_path):
    """--start FILE: the network before retraining holds the file's weights (no ranking), the report, the recipe and
    the retrained model's record name it; a file of other widths is one error line, before any file is written."""
    from fcnpose_tf.training.model import build_fcn_pose, load_model

    root, data, base = setup
    start = tmp_path / "pruned.keras"
    randomize(build_fcn_pose(P70_WIDTHS, input_size=64), seed=5).save(start)
    out = tmp_path / "out"
    status, stdout, err = compress_from_start(cli_here, setup, start, out)
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "scoring filters" not in stdout
    for w0, w1 in zip(load_model(start).get_weights(), load_model(out / "base_p70.keras").get_weights()):
        np.testing.assert_array_equal(w0, w1)
    report = json.loads((out / "base_p70_report.json").read_text())
    assert report["pruning"]["start"] == str(start) == report["options"]["start"]
    assert report["recipe"].startswith(f"filter surgery's widths at 0.7 (no layer under 15 filters, same parameter "
                                       f"budget), the weights of {start}")
    refused = tmp_path / "refused"
    status, _, err = cli_here("compress", "--rate", "0.5", "--model", base, "--data", data, "--start", start,
                              "--retrain-epochs", "0", "--out-dir", refused)
    assert status == 2 and "Traceback" not in err
    assert f"--start {start}: its widths ({', '.join(map(str, P70_WIDTHS))}, 9) are not filter surgery's" in err
    assert not refused.exists()
    status, out_text, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--start", "nope",
                                     "--out-dir", refused)  # a start that names nothing: before the data is read
    assert status == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("error: nope: model file not found (or one of the bundled models: ")
    assert "loading" not in out_text.lower() and not refused.exists()


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_runs_at_the_height_its_pruned_start_was_retrained_at(setup, cli_here, tmp_path):
    """A pruned start retrained at another input size than the model's (the bundled generalist-p70 at 256 for the
    generalist at 224): the run rebuilds the model at the start's height, says why, and the recipe and the report's
    options record it; the files keep the names the command checked; --input-size keeps the user's height."""
    from fcnpose_tf.training.model import build_fcn_pose, load_model

    root, data, base = setup
    assert load_model(base).input_shape == (None, 64, 64, 3)
    start = tmp_path / "pruned96.keras"
    randomize(build_fcn_pose(P70_WIDTHS, input_size=96), seed=5).save(start)
    out = tmp_path / "out"
    status, stdout, err = compress_from_start(cli_here, setup, start, out)
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert f"96x96, rebuilt from its 64x64: the height {start} was retrained at" in stdout
    assert load_model(out / "base_p70.keras").input_shape == (None, 96, 96, 3)
    report = json.loads((out / "base_p70_report.json").read_text())
    assert report["options"]["input_size"] == 96 and report["recipe"].endswith("not retrained, at 96x96")
    mine = tmp_path / "mine"
    status, stdout, err = compress_from_start(cli_here, setup, start, mine, "--input-size", "64")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "rebuilt" not in stdout and load_model(mine / "base_p70_64.keras").input_shape == (None, 64, 64, 3)
    at_64 = json.loads((mine / "base_p70_64_report.json").read_text())
    assert report["base"]["macs"] == at_64["base"]["macs"] * 9 // 4  # the unpruned model measured at 96 too


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_keeps_a_pruned_start_that_no_retraining_epoch_beats(setup, cli_here, tmp_path):
    """A pruned start holds trained weights: its validation loss is epoch 0's, and when retraining only makes it worse
    (here a learning rate of 50 throws every weight far off) the start is what compress keeps, and says so."""
    from fcnpose_tf.training.model import build_fcn_pose, load_model

    start = tmp_path / "pruned.keras"
    randomize(build_fcn_pose(P70_WIDTHS, input_size=64), seed=5).save(start)
    out = tmp_path / "out"
    status, stdout, err = compress_from_start(cli_here, setup, start, out, "--retrain-epochs", "1",
                                              "--learning-rate", "50")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "the start is kept, unchanged" in stdout
    for w0, w1 in zip(load_model(start).get_weights(), load_model(out / "base_p70.keras").get_weights()):
        np.testing.assert_array_equal(w0, w1)
    report = json.loads((out / "base_p70_report.json").read_text())
    assert report["retraining"]["start_kept"] is True and report["retraining"]["best_epoch"] == 0


def test_a_model_rebuilt_at_another_input_size_keeps_its_layers_and_weights():
    """`at_input_size`: FCN-Pose (functional) and a Sequential chain at a new side compute what the network built at
    that side with the same weights computes; layer names and the input's name kept; a side the five poolings do not
    divide is refused."""
    import tf_keras as keras

    from fcnpose_tf.errors import UserError
    from fcnpose_tf.training.model import at_input_size, build_fcn_pose

    widths = (8, 8, 8, 8, 8, 8, 8, 8, 8)
    model = randomize(build_fcn_pose(widths, input_size=64), seed=3)
    assert at_input_size(model, 64) is model
    resized = at_input_size(model, 96)
    assert resized.input_shape == (None, 96, 96, 3) and resized.output_shape == (None, 96, 96, 9)
    assert [layer.name for layer in resized.layers] == [layer.name for layer in model.layers]
    built = build_fcn_pose(widths, input_size=96)
    built.set_weights(model.get_weights())
    image = np.random.default_rng(0).random((1, 96, 96, 3), dtype=np.float32)
    np.testing.assert_array_equal(resized(image).numpy(), built(image).numpy())
    chain = keras.Sequential([keras.Input((64, 64, 3)), keras.layers.Conv2D(4, 3, padding="same", name="c1"),
                              keras.layers.MaxPooling2D(name="p1"), keras.layers.UpSampling2D(name="u1"),
                              keras.layers.Conv2D(2, 3, padding="same", name="c2")])
    wider = at_input_size(chain, 96)
    assert wider.output_shape == (None, 96, 96, 2)
    for w0, w1 in zip(chain.get_weights(), wider.get_weights()):
        np.testing.assert_array_equal(w0, w1)
    with pytest.raises(UserError, match="multiple of 32"):
        at_input_size(model, 100)


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_at_another_input_size_names_and_exports_files_at_it(setup, cli_here, tmp_path):
    """--input-size 96 on a 64x64 model: the model is rebuilt at 96, retrained and exported at it; the files carry the
    size in their names, the recipe and the report say it."""
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.training.model import load_model

    root, data, base = setup
    out = tmp_path / "out"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", data, "--input-size", "96",
                                   "--retrain-epochs", "1", "--quantize", "float16", "--out-dir", out, "--threads", "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert "base model " in stdout and "(96x96, rebuilt from its 64x64)" in stdout
    assert load_model(out / "base_p70_96.keras").input_shape == (None, 96, 96, 3)
    assert KeypointModel(out / "base_p70_96_fp16.tflite").view.shape == (96, 96)
    report = json.loads((out / "base_p70_96_report.json").read_text())
    assert report["options"]["input_size"] == 96 and report["recipe"].endswith(", at 96x96")
    assert not (out / "base_p70.keras").exists()


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_keeps_the_base_models_crop_in_every_file(setup, cli_here, tmp_path):
    """A base model that reads a crop of the frame (train --input-size auto's workspace) is pruned, retrained and
    exported over the same crop: the .keras and every .tflite carry it, and the Pi runtime reads it back."""
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.training.model import load_model, save_for_inference, view_of, with_view

    root, data, base = setup
    view = FrameView(64, 64, crop=(8, 4, 72, 64), frame_size=(96, 72))
    cropped = tmp_path / "cropped.keras"
    save_for_inference(with_view(load_model(base), view), cropped)
    out = tmp_path / "out"
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", cropped, "--data", data, "--retrain-epochs",
                                   "1", "--quantize", "float16", "--out-dir", out, "--threads", "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert f"base model {cropped} ({view.describe()})" in stdout
    assert view_of(load_model(out / "cropped_p70.keras")) == view
    assert KeypointModel(out / "cropped_p70_fp16.tflite").view == view


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_several_rates_in_one_run_give_a_file_set_and_rows_each_and_name_the_best(setup, cli_here):
    root, data, base = setup
    out = root / "rates"
    status, stdout, err = cli_here("compress", "--rates", "0.7,0.3", "--model", base, "--data", data,
                                   "--retrain-epochs", "0", "--quantize", "float16", "--out-dir", out, "--threads", "1")
    assert status == 0, err
    assert {"base_p30_fp16.tflite", "base_p70_fp16.tflite", "base_p30_report.json",
            "base_p70_report.json"} <= {p.name for p in out.iterdir()}
    assert "Compression at rates 0.3, 0.7" in stdout
    assert "rate 0.3: float16 TFLite (.tflite)" in stdout and "rate 0.7: float16 TFLite (.tflite)" in stdout
    assert stdout.count("unpruned (Keras; size as .h5)") == 1
    note = next(line for line in stdout.splitlines() if "PCK@0.5 budget" in line or "no rate kept" in line)
    reports = {r: json.loads((out / f"base_p{r}_report.json").read_text()) for r in (30, 70)}
    # the scoring is shared: the base model measured and its filters scored by the first rate only
    assert stdout.count("scoring filters by taylor") == 1 and stdout.count("filters scored already") == 1
    assert stdout.count("measured already") == 1 and reports[30]["base"] == reports[70]["base"]
    base_pck = reports[30]["base"]["metrics"]["pck@0.5_bbox"]
    within = [r for r in (30, 70)
              if base_pck - reports[r]["quantized"]["metrics"]["pck@0.5_bbox"] <= 0.02]
    if within:
        assert note.startswith(f"Best rate within the 0.02 PCK@0.5 budget: {max(within) / 100:g}")
    else:
        assert note.startswith("note: no rate kept PCK@0.5 within 0.02")
    status, _, err = cli_here("compress", "--rate", "0.5", "--rates", "0.3,0.5", "--model", base, "--data", data)
    assert status == 2 and "--rate and --rates both given" in err


@pytest.mark.usefixtures("few_timed_frames")
def test_int8_is_calibrated_on_the_fold_the_base_model_was_trained_on_without_retraining(setup, tmp_path,
                                                                                          monkeypatch):
    """With --retrain-epochs 0 and no --fold, the run's fold is still the base model's own (its NAME_train.json,
    same data): the int8 file is calibrated on that fold's training frames, as its filters are scored and as a
    retraining would train, never on the hold-out split's."""
    import json
    import shutil

    from fcnpose_tf.compression import frames
    from fcnpose_tf.compression.compress import compress_model
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.records import file_sha256

    _, data, base_file = setup
    base = tmp_path / "base.keras"
    shutil.copy(base_file, base)
    dataset = load_dataset(data)
    (tmp_path / "base_train.json").write_text(json.dumps({"data": str(dataset.via_path), "fold": 1,
                                                          "data_sha256": file_sha256(dataset.via_path)}))
    _, eval_indices = dataset.split(None)  # the command's measured frames without --fold
    seen = []

    class Seen(Exception):
        pass

    def export_frames(quantize, input_size, train_dataset, train_indices, *rest, **more):
        seen.append(np.asarray(train_indices))
        raise Seen

    monkeypatch.setattr(frames, "export_frames", export_frames)
    options = CompressOptions(rate=0.5, retrain_epochs=0, quantize=("int8",), importance="l1", min_filters=0,
                              qat_epochs=0, threads=1).checked(base)
    with pytest.raises(Seen):
        compress_model(base, dataset, dataset, [int(i) for i in eval_indices], tmp_path / "out", options)
    expected = np.setdiff1d(dataset.split(1)[0], eval_indices)
    assert not np.array_equal(expected, np.setdiff1d(dataset.split(None)[0], eval_indices))  # the test can fail
    assert np.array_equal(seen[0], expected)


def test_a_runs_files_are_named_once_and_checked_before_any_work(tmp_path):
    """`check_outputs` refuses an existing file and returns the run's `OutputFiles`, which every step and the
    command's last lines read: the report's keys in order, each format's file, the retraining's side files."""
    from fcnpose_tf.compression.options import CompressOptions, check_outputs, output_files
    from fcnpose_tf.errors import UserError

    options = CompressOptions(rate=0.7, quantize=("float16", "int8"))
    files = check_outputs(tmp_path / "arm.keras", tmp_path / "out", options)
    assert files.stem == "arm_p70" and list(files.paths) == ["keras", "tflite_fp16", "tflite_int8", "report"]
    assert files.tflite == {"float16": tmp_path / "out/arm_p70_fp16.tflite", "int8": tmp_path / "out/arm_p70_int8.tflite"}
    assert {p.name for p in files.side} == {"arm_p70_train.json", "arm_p70_loss.csv", "arm_p70_loss.png"}
    assert output_files(tmp_path / "arm.keras", tmp_path / "out", options) == files  # the same names, unchecked
    unretrained = CompressOptions(rate=0.7, retrain_epochs=0, method="magnitude", quantize=("int8",))
    assert check_outputs(tmp_path / "arm.keras", tmp_path / "out", unretrained).every == [
        tmp_path / "out" / name for name in ("arm_m70.keras", "arm_m70_int8.tflite", "arm_m70_report.json")]
    (tmp_path / "out").mkdir(exist_ok=True)  # check_writable made it
    (tmp_path / "out/arm_p70_int8.tflite").write_bytes(b"")
    with pytest.raises(UserError, match="arm_p70_int8.tflite"):
        check_outputs(tmp_path / "arm.keras", tmp_path / "out", options)
    assert check_outputs(tmp_path / "arm.keras", tmp_path / "out", options, force=True) == files
