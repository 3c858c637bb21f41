"""export of a model that is not a keypoint model (a pruned classifier, tf_keras or Keras 3): output parity."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.test_prune_command import _residual


@pytest.fixture(scope="module")
def pruned():
    """The small residual classifier of both Kerases, pruned at 0.5 by the dependency graph."""
    import keras
    import tf_keras

    from fcnpose_tf.compression.graph_prune import prune_graph

    models = {}
    for K in (keras, tf_keras):
        model = _residual(K)
        model(np.zeros((1, 32, 32, 3), np.float32))
        models[K.__name__] = prune_graph(model, 0.5)
    return models


def test_which_models_the_keypoint_gate_holds(pruned):
    from fcnpose_tf.compression.export import is_keypoint_model
    from fcnpose_tf.training.model import build_fcn_pose

    assert is_keypoint_model(build_fcn_pose(input_size=64))
    assert not is_keypoint_model(pruned["keras"]) and not is_keypoint_model(pruned["tf_keras"])


@pytest.mark.parametrize("package", ["keras", "tf_keras"])
@pytest.mark.parametrize("quantize", ["float16", "int8"])
def test_a_pruned_classifier_is_exported_and_verified_by_output_parity(pruned, package, quantize):
    from fcnpose_tf import settings
    from fcnpose_tf.compression.export import export_generic
    from fcnpose_tf.compression.tflite_file import inspect_tflite

    fmt = settings.TFLITE_FORMATS[quantize]
    export = export_generic(pruned[package], quantize, input_range=(-1.0, 1.0), calibration_count=20)
    parity = export.parity
    assert parity.frames == 16 and parity.relative_diff <= fmt.output_rtol == parity.output_rtol
    assert parity.output_scale == 1.0  # softmax probabilities
    assert parity.top1_compared is not None and parity.top1_agree >= fmt.top1_share * parity.top1_compared
    assert export.calibration_frames == (20 if quantize == "int8" else 0)
    facts = inspect_tflite(export.data)
    assert facts["inputs"][0]["shape"] == [1, 32, 32, 3] and facts["inputs"][0]["dtype"] == "FLOAT32"
    if quantize == "float16":
        assert parity.relative_diff < 1e-4


def test_a_broken_conversion_is_refused_and_nothing_written(pruned, cli_here, tmp_path, monkeypatch):
    import keras

    from fcnpose_tf.compression import export as export_module
    from fcnpose_tf.compression.verify import ExportVerificationError

    model = pruned["keras"]
    other = keras.models.clone_model(model)
    other.set_weights([w * 1.5 for w in model.get_weights()])
    convert = export_module._convert
    monkeypatch.setattr(export_module, "_convert", lambda m, *a, **k: convert(other, *a, **k))
    with pytest.raises(ExportVerificationError, match="disagrees with the Keras model"):
        export_module.export_generic(model, "float16")
    saved = tmp_path / "p.keras"
    model.save(saved)
    status, out, err = cli_here("export", saved, "--quantize", "float16", "--out-dir", tmp_path)
    assert status == 2 and "refused by the output-parity gate" in err and "REFUSED" in out
    assert not (tmp_path / "p_fp16.tflite").exists()


def test_export_command_of_a_keras3_classifier(pruned, cli_here, tmp_path):
    saved = tmp_path / "p.keras"
    pruned["keras"].save(saved)
    report = tmp_path / "export.json"
    status, out, err = cli_here("export", saved, "--quantize", "float16,int8", "--input-range=-1,1",
                                "--calibration-frames", "20", "--out-dir", tmp_path, "--json", report)
    assert status == 0, err
    assert "not a keypoint model" in out and "random inputs uniform in [-1, 1]" in out
    for name in ("p_fp16.tflite", "p_int8.tflite"):
        assert (tmp_path / name).is_file() and f"wrote {tmp_path / name}" in out
    facts = json.loads(report.read_text())
    assert facts["gate"] == "output parity" and [f["quantize"] for f in facts["files"]] == ["float16", "int8"]
    assert facts["files"][1]["calibration_frames"] == 20
    status, _, err = cli_here("export", saved, "--input-range", "1,0", "--out-dir", tmp_path)
    assert status == 2 and "LOW < HIGH" in err
