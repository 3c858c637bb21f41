"""A model whose post-training int8 is refused by its keypoint gate: compress and export finish with the refusal in
their table, report and exit status, and compress's quantization-aware fallback gives an int8 file that passes."""

import json

import numpy as np
import pytest

from fcnpose_tf.progress import SILENT
from test_train_evaluate import make_via_folder
from weights import randomize

SIZE = 64

pytestmark = pytest.mark.usefixtures("convert_once")  # one faint model, its float16 and int8 files converted once


def faint_model(frames, seed=0, contrast=0.8, share=0.03, skeleton_offset=60.0):
    """A 64x64 FCN-Pose whose keypoint maps are faint and whose output logits span a wide range, as a model fine-tuned
    on a user's frames has them (docs/compression.md, "int8 on a user's model").

    Random (seeded) weights; conv10 is rescaled per map so that each keypoint map exceeds the threshold on the top
    `share` of its pixels on `frames` with logits up to `contrast` (map values up to 0.69), and the skeleton map
    (never decoded as a keypoint) is pushed down by `skeleton_offset`, so the int8 file's one scale for conv10's
    output spans about [-60, 1]: 0.24 logit per step, the keypoint blobs' whole contrast in three or four steps.
    """
    import tensorflow as tf
    import tf_keras as keras

    from fcnpose_tf.training.model import build_fcn_pose

    model = randomize(build_fcn_pose(input_size=SIZE), seed=seed)
    conv10 = model.get_layer("conv10")
    kernel, bias = conv10.get_weights()
    features = keras.Model(model.input, conv10.input)(frames)
    logits = (tf.nn.conv2d(features, kernel, 1, "SAME") + bias).numpy()
    top = np.quantile(logits, 1 - share, axis=(0, 1, 2))
    gain = contrast / (logits.max(axis=(0, 1, 2)) - top)
    gain[-1] = 1.0
    shift = (bias - top) * gain
    shift[-1] = -skeleton_offset
    conv10.set_weights([(kernel * gain).astype(np.float32), shift.astype(np.float32)])
    return model


@pytest.fixture(scope="module")
def faint(tmp_path_factory):
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.preprocess import preprocess_frame

    root = tmp_path_factory.mktemp("qat")
    data = make_via_folder(root / "frames", n=20)  # 16 training frames (calibration), 4 + 12 for the gate
    dataset = load_dataset(data)
    frames = np.stack([preprocess_frame(dataset.load_image(i), SIZE) for i in range(len(dataset))])
    model = faint_model(frames)
    path = root / "faint.keras"
    model.save(path)
    return root, data, path


def compress_args(data, model, out, *extra):
    # rate 0 without retraining: the exported model is the faint model itself, so its refusal does not depend on
    # a retraining run; l1 ranks filters without data (rate 0 keeps them all)
    return ("compress", "--rate", "0", "--retrain-epochs", "0", "--importance", "l1", "--model", model, "--data", data,
            "--out-dir", out, "--threads", "1", *extra)


def table_row(stdout, start):
    return next(line for line in stdout.splitlines() if line.startswith(start))


def test_post_training_int8_is_refused_and_float16_passes(faint):
    """The case itself: the gate refuses this model's post-training int8 file (a keypoint lost), not its float16."""
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.compression.export import export_tflite
    from fcnpose_tf.compression.frames import export_frames
    from fcnpose_tf.compression.verify import ExportVerificationError
    from fcnpose_tf.training.model import load_model

    root, data, path = faint
    model, dataset = load_model(path), load_dataset(data)
    train, val = dataset.split(None)
    samples, calibration = export_frames("int8", SIZE, dataset, train, dataset, val, 100)
    fp16 = export_tflite(model, "float16", sample_frames=samples)
    assert fp16.parity.keypoints_compared >= 100 and fp16.parity.keypoints_lost_or_gained == 0
    with pytest.raises(ExportVerificationError, match="lost or gained") as refused:
        export_tflite(model, "int8", sample_frames=samples, calibration_frames=calibration)
    assert refused.value.facts["keypoints_lost_or_gained"] >= 1 and refused.value.facts["frames"] == 16
    assert not refused.value.reason.endswith("nothing written") and str(refused.value).endswith("; nothing written")


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_without_qat_ends_with_its_table_and_the_refusal(faint, cli_here):
    """--qat-epochs 0: the float16 row, the int8 row marked REFUSED with the gate's reason, the report, exit 0
    (int8 was a default format, and a file was written)."""
    root, data, path = faint
    out = root / "no_qat"
    status, stdout, err = cli_here(*compress_args(data, path, out, "--qat-epochs", "0"))
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert not [line for line in err.splitlines() if line.startswith("error:")]
    fp16_row = table_row(stdout, "float16 TFLite (.tflite)")
    assert table_row(stdout, "int8 TFLite: REFUSED (gate)")
    report = json.loads((out / "faint_p00_report.json").read_text())
    assert f"{report['quantized']['metrics']['pck@0.5_bbox']:.3f}" in fp16_row
    assert report["quantized"]["quantize"] == "float16" and report["other_quantized"] == []
    (refused,) = report["refused"]
    assert refused["quantize"] == "int8" and refused["status"] == "refused" and "qat" not in refused
    assert refused["reason"].startswith("the int8 TFLite model decodes ")
    assert refused["post_training"]["keypoints_lost_or_gained"] >= 1
    assert f"int8: REFUSED, no file written: {refused['reason']}" in stdout
    assert not (out / "faint_p00_int8.tflite").exists()
    assert set(report["files"]) == {"keras", "tflite_fp16", "report"}
    for name in ("faint_p00.keras", "faint_p00_fp16.tflite", "faint_p00_report.json"):
        assert f"wrote {out / name}" in stdout
    assert "note: int8 refused by the keypoint gate" in stdout


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_with_int8_named_exits_2_after_writing_what_passed(faint, cli_here):
    root, data, path = faint
    out = root / "named"
    status, stdout, err = cli_here(*compress_args(data, path, out, "--qat-epochs", "0", "--quantize", "float16,int8"))
    assert status == 2 and "Traceback" not in err
    (error,) = [line for line in err.splitlines() if line.startswith("error:")]
    assert "int8 (named with --quantize) refused by the keypoint gate" in error
    assert f"kept {out / 'faint_p00.keras'}, {out / 'faint_p00_fp16.tflite'}, {out / 'faint_p00_report.json'}" in error
    assert table_row(stdout, "int8 TFLite: REFUSED (gate)") and table_row(stdout, "float16 TFLite (.tflite)")
    assert (out / "faint_p00_fp16.tflite").is_file() and (out / "faint_p00_report.json").is_file()


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_compress_falls_back_to_quantization_aware_int8_that_passes(faint, cli_here):
    """The default: post-training int8 refused, quantization-aware training's int8 file passes the same gate
    against the same Keras model, is written with the runtime's interface, and the report says how it was made."""
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.compression.frames import export_frames
    from fcnpose_tf.compression.verify import verify_tflite
    from fcnpose_tf.compression.tflite_file import inspect_tflite
    from fcnpose_tf.training.model import load_model

    root, data, path = faint
    out = root / "qat"
    status, stdout, err = cli_here(*compress_args(data, path, out))
    assert status == 0, stdout[-3000:] + err[-3000:]
    report = json.loads((out / "faint_p00_report.json").read_text())
    assert report["refused"] == []
    (int8,) = report["other_quantized"]
    assert int8["quantize"] == "int8" and int8["quantization"] == "quantization-aware training"
    qat = int8["qat"]
    assert qat["passed"] and qat["epochs"][-1]["passed"] and qat["minutes"] >= 0
    assert qat["post_training_refused"]["reason"].startswith("the int8 TFLite model decodes ")
    assert "post-training int8 refused: quantization-aware training" in stdout
    assert f"{qat['epochs_run']} QAT epoch(s)" in stdout and table_row(stdout, "int8 QAT TFLite (.tflite)")
    assert f"wrote {out / 'faint_p00_int8.tflite'}" in stdout
    # the written file: the runtime's int8 interface, folded upsampling, and it passes the gate here too
    tflite = (out / "faint_p00_int8.tflite").read_bytes()
    info = inspect_tflite(tflite)
    assert info["inputs"][0]["dtype"] == "UINT8" and info["outputs"][0]["dtype"] == "INT8"
    assert info["op_counts"].get("DEPTH_TO_SPACE") == 4 and "DEQUANTIZE" not in info["op_counts"]
    assert int8["export"]["graph_rewrites"] and int8["tflite_size_bytes"] == len(tflite)
    dataset = load_dataset(data)
    train, val = dataset.split(None)
    samples, _ = export_frames("int8", SIZE, dataset, train, dataset, val, 100)
    parity = verify_tflite(load_model(path), tflite, samples, map_atol=1.0, keypoint_px=2.0, keypoint_share=0.95,
                           pixel_input=True)
    assert parity.keypoints_lost_or_gained == 0 and parity.keypoints_within_px >= 0.95 * parity.keypoints_compared


@pytest.mark.slow
def test_export_refusal_is_a_row_and_the_exit_status_follows_what_was_named(faint, cli_here, tmp_path):
    """export: int8 refused, float16 written and named; exit 0 for the default formats, 2 when int8 was named."""
    import shutil

    root, data, path = faint
    model = tmp_path / "arm.keras"
    shutil.copy(path, model)
    status, stdout, err = cli_here("export", model, "--data", data, "--json", tmp_path / "export.json", "--threads",
                                   "1")
    assert status == 0, stdout + err
    assert table_row(stdout, "arm_int8.tflite: REFUSED")
    assert f"wrote {tmp_path / 'arm_fp16.tflite'}" in stdout and f"wrote {tmp_path / 'export.json'}" in stdout
    assert (tmp_path / "arm_fp16.tflite").is_file() and not (tmp_path / "arm_int8.tflite").exists()
    record = json.loads((tmp_path / "export.json").read_text())
    (fp16,) = record["files"]
    (refused,) = record["refused"]
    assert fp16["quantize"] == "float16" and refused["quantize"] == "int8" and refused["parity"]["frames"] == 16
    assert f"int8: REFUSED, no file written: {refused['reason']}" in stdout

    status, _, err = cli_here("export", model, "--data", data, "--quantize", "float16,int8", "--out-dir",
                              tmp_path / "named", "--threads", "1")
    assert status == 2 and "Traceback" not in err
    (error,) = [line for line in err.splitlines() if line.startswith("error:")]
    assert "int8 (named with --quantize) refused" in error and f"kept {tmp_path / 'named' / 'arm_fp16.tflite'}" in error
    assert (tmp_path / "named" / "arm_fp16.tflite").is_file()

    status, _, err = cli_here("export", model, "--data", data, "--quantize", "int8", "--out-dir", tmp_path / "only",
                              "--threads", "1")
    assert status == 2 and "no TFLite file written: int8 refused" in err
    assert not (tmp_path / "only").exists() or not any((tmp_path / "only").iterdir())


def test_calibrated_ranges_clamp_the_sigmoid_input(faint):
    """QAT starts from the calibration frames' ranges (tfmot's own start is [-6, 6]) with the logits on +-8."""
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.compression.export import _inference_graph
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.preprocess import preprocess_frame
    from fcnpose_tf.compression.qat import LOGIT_RANGE, calibrate_ranges, quantize_aware

    root, data, path = faint
    dataset = load_dataset(data)
    frames = np.stack([preprocess_frame(dataset.load_image(i), SIZE) for i in range(8)])
    graph, rewrites = _inference_graph(load_model(path))
    assert len(rewrites) == 4  # the four upsamplings folded, as the int8 export converts them
    qat = quantize_aware(graph)
    ranges = calibrate_ranges(qat, graph, frames)
    assert ranges["conv10"] == (-LOGIT_RANGE, LOGIT_RANGE)
    import tf_keras as keras

    conv1 = keras.Model(graph.input, graph.get_layer("conv1").output)(frames).numpy()
    assert ranges["conv1"] == (0.0, pytest.approx(float(conv1.max()), rel=1e-5))


def test_training_runs_epoch_by_epoch_until_the_gate_passes(faint):
    """train_until_gate: epoch 0 is the calibrated copy; each later epoch trains, pins the sigmoid's input range
    again and converts; it stops at the first file that passes and records every epoch's gate."""
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.compression.export import export_tflite
    from fcnpose_tf.compression.frames import export_frames
    from fcnpose_tf.compression.verify import ExportVerificationError
    from fcnpose_tf.training.model import load_model
    from fcnpose_tf.compression.qat import LOGIT_RANGE, train_until_gate

    root, data, path = faint
    model, dataset = load_model(path), load_dataset(data)
    train, val = dataset.split(None)
    samples, calibration = export_frames("int8", SIZE, dataset, train, dataset, val, 100)
    training, _ = fold_data(dataset, None, SIZE, 0, 0, "paper")
    seen = []

    def convert(qat):
        seen.append({v.name.split("/")[-1].split(":")[0]: float(v.numpy()) for v in qat.get_layer("quant_conv10")
                     .non_trainable_weights if "pre_activation" in v.name})
        # the mechanics only: the keypoint gate is off here (what training gives is measured on real models,
        # docs/compression.md); the file is still converted, loaded and checked for its interface
        export = export_tflite(qat, "int8", sample_frames=samples, calibration_frames=calibration,
                               fold_upsampling=False, reference=model, check_keypoints=False)
        if len(seen) < 2:  # refuse the untrained copy's file, as a model that needs training would be
            raise ExportVerificationError("held back for the test; nothing written", {"frames": 16})
        return export

    result = train_until_gate(model, training.sequence(8, seed=0), calibration, convert, epochs=3,
                              learning_rate=1e-4, seed=0, reporter=SILENT)
    assert result.export is not None and result.epochs_run == 1 and len(seen) == 2
    first, second = result.epochs
    assert first == {"epoch": 0, "passed": False, "reason": "held back for the test", "frames": 16}
    assert second["epoch"] == 1 and second["passed"] and second["loss"] > 0
    assert seen[1] == {"pre_activation_min": -LOGIT_RANGE, "pre_activation_max": LOGIT_RANGE}
    assert result.export.graph_rewrites and result.to_dict()["passed"] and result.reason == ""
