"""`fcnpose-tf prune`: graph pruning of any Keras CNN file, tf_keras or Keras 3, surgery only."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest


def _residual(K, name="small"):
    """A small residual CNN classifier: c1 and c2 meet in an Add (one group), c3 its own group, fc the output."""
    inp = K.Input((32, 32, 3))
    x = K.layers.Conv2D(16, 3, padding="same", activation="relu", name="c1")(inp)
    y = K.layers.Conv2D(16, 3, padding="same", name="c2")(x)
    y = K.layers.BatchNormalization(name="bn")(y)
    x = K.layers.Add(name="add")([x, y])
    x = K.layers.Conv2D(24, 3, strides=2, padding="same", activation="relu", name="c3")(x)
    x = K.layers.GlobalAveragePooling2D(name="gap")(x)
    return K.Model(inp, K.layers.Dense(5, activation="softmax", name="fc")(x), name=name)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    import keras
    import tf_keras

    folder = tmp_path_factory.mktemp("prune_cli")
    paths = {"keras": folder / "k3.keras", "tf_keras": folder / "tk.keras", "tf_keras_h5": folder / "tk.h5"}
    _residual(keras).save(paths["keras"])
    model = _residual(tf_keras)
    model.save(paths["tf_keras"])
    model.save(paths["tf_keras_h5"])
    return paths


def _widths(model):
    return {layer.name: int(layer.get_weights()[0].shape[-1]) for layer in model.layers
            if type(layer).__name__ in ("Conv2D", "Dense")}


@pytest.mark.parametrize("which, package", [("keras", "keras"), ("tf_keras", "tf_keras"), ("tf_keras_h5", "tf_keras")])
def test_prune_writes_a_model_of_the_same_keras_with_the_plans_widths(cli_here, saved, tmp_path, which, package):
    from fcnpose_tf.compression.keras_file import load_any, saved_by

    suffix = saved[which].suffix
    out, plan = tmp_path / f"p50{suffix}", tmp_path / "plan.json"
    status, stdout, err = cli_here("prune", saved[which], "--rate", "0.5", "--out", out, "--json", plan)
    assert status == 0, err
    assert saved_by(out) == package
    pruned = load_any(out)
    assert type(pruned).__module__.split(".")[0] == package
    assert _widths(pruned) == {"c1": 8, "c2": 8, "c3": 12, "fc": 5}
    assert "c1, c2" in stdout and "reaches output fc" in stdout and f"wrote {out}" in stdout
    assert "\nparameters " in stdout and "\nMACs " in stdout  # the totals under the groups table
    facts = json.loads(plan.read_text())
    assert facts["keras"] == package and facts["rate"] == 0.5
    assert [(g["channels"], g["kept"]) for g in facts["groups"]][0] == (3, 3)  # the input, frozen
    assert [(g["producers"], g["channels"], g["kept"]) for g in facts["groups"]][1:] == [
        (["c1", "c2"], 16, 8), (["c3"], 24, 12), (["fc"], 5, 5)]
    assert facts["layers"]["c3"]["in_channels_kept"] == [8] and facts["layers"]["c3"]["out_channels_kept"] == 12
    assert facts["params"]["before"] > facts["params"]["after"] == pruned.count_params()
    x = np.random.default_rng(0).random((2, 32, 32, 3), dtype=np.float32)
    assert np.asarray(pruned(x)).shape == (2, 5)


def test_round_to_min_filters_and_keep(cli_here, saved, tmp_path):
    from fcnpose_tf.compression.keras_file import load_any

    out = tmp_path / "p.keras"
    status, stdout, err = cli_here("prune", saved["keras"], "--rate", "0.7", "--out", out, "--round-to", "8",
                                   "--keep", "c3", "--importance", "l2", "--aggregate", "max")
    assert status == 0, err
    assert _widths(load_any(out)) == {"c1": 8, "c2": 8, "c3": 24, "fc": 5}  # 16 - 11 = 5, rounded up to 8
    assert "c3 kept whole" in stdout
    status, _, err = cli_here("prune", saved["keras"], "--rate", "0.9", "--out", out, "--min-filters", "6",
                              "--force")
    assert status == 0, err
    assert _widths(load_any(out))["c1"] == 6


@pytest.mark.parametrize("args, message", [
    (["--rate", "1.0"], "pruning rate must be in [0, 1)"),
    (["--rate", "-0.1"], "pruning rate must be in [0, 1)"),
    (["--rate", "0.5", "--keep", "c33"], "no layer named c33 to keep whole (did you mean c3?)"),
    (["--rate", "0.5", "--keep", "zzz"], "its layers: c1, c2, bn, add, c3, gap, fc"),
    (["--rate", "0.5", "--round-to", "0"], "--round-to must be at least 1"),
])
def test_bad_input_is_one_line_and_nothing_written(cli_here, saved, tmp_path, args, message):
    out, plan = tmp_path / "p.keras", tmp_path / "plan.json"
    status, _, err = cli_here("prune", saved["keras"], "--out", out, "--json", plan, *args)
    assert status == 2 and message in err and "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("error:")]
    assert not out.exists() and not plan.exists() and list(tmp_path.iterdir()) == []


def test_an_existing_out_is_refused_without_force(cli_here, saved, tmp_path):
    out = tmp_path / "p.keras"
    out.write_bytes(b"earlier")
    status, _, err = cli_here("prune", saved["keras"], "--rate", "0.5", "--out", out)
    assert status == 2 and "already exists; pass --force" in err and out.read_bytes() == b"earlier"


def test_files_that_are_not_models_and_unsupported_layers_are_refused(cli_here, tmp_path):
    import keras

    missing, junk, other = tmp_path / "missing.keras", tmp_path / "junk.keras", tmp_path / "notes.txt"
    junk.write_bytes(b"not a zip")
    other.write_text("hello")
    for path, message in ((missing, "model file not found"), (junk, "not a Keras model file"),
                          (other, "expected a Keras model file")):
        status, _, err = cli_here("prune", path, "--rate", "0.5", "--out", tmp_path / "p.keras")
        assert status == 2 and message in err, err
    inp = keras.Input((16, 3))
    x = keras.layers.Conv1D(8, 3, name="conv1d")(inp)
    seq = tmp_path / "seq.keras"
    keras.Model(inp, keras.layers.Dense(2, name="fc")(x)).save(seq)
    status, _, err = cli_here("prune", seq, "--rate", "0.5", "--out", tmp_path / "p.keras")
    assert status == 2 and "conv1d (Conv1D)" in err and "Traceback" not in err
    assert not (tmp_path / "p.keras").exists()


@pytest.mark.parametrize("suffix", [".keras", ".h5"])
def test_a_tf_keras_convnext_file_is_read_back(cli_here, tmp_path, suffix):
    """tf_keras does not register ConvNeXt's LayerScale and StochasticDepth; its own ConvNeXt files still load."""
    import tf_keras
    from tf_keras.src.applications import convnext

    inp = tf_keras.Input((16, 16, 3))
    x = tf_keras.layers.Conv2D(8, 3, padding="same", activation="relu", name="c1")(inp)
    x = convnext.StochasticDepth(0.1, name="drop_path")(convnext.LayerScale(0.5, 8, name="scale")(x))
    path, out = tmp_path / f"cnx{suffix}", tmp_path / f"p50{suffix}"
    tf_keras.Model(inp, tf_keras.layers.Conv2D(2, 1, name="head")(x)).save(path)
    status, _, err = cli_here("prune", path, "--rate", "0.5", "--out", out)
    assert status == 0, err
    from fcnpose_tf.compression.keras_file import load_any

    pruned = load_any(out)
    assert pruned.get_layer("c1").filters == 4 and pruned.get_layer("scale").get_weights()[0].shape == (4,)


def test_saved_by_reads_the_keras_version(saved, tmp_path):
    from fcnpose_tf.compression.keras_file import saved_by

    assert saved_by(saved["keras"]) == "keras" and saved_by(saved["tf_keras"]) == "tf_keras"
    assert json.loads(zipfile.ZipFile(saved["keras"]).read("metadata.json"))["keras_version"].startswith("3.")
