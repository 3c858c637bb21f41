"""Every command that takes a model takes the bundled models by name (fcnpose_tf.bundled.resolve_model)."""

import pytest

from fcnpose_tf import bundled
from fcnpose_tf.errors import UserError

KERAS_COMMANDS = {  # command line with MODEL where the model goes -> the parsed attribute
    "evaluate": (["evaluate", "MODEL", "--data", "d"], "model"),
    "predict": (["predict", "MODEL", "--source", "frames", "--via", "pre.json"], "model"),
    "export": (["export", "MODEL"], "model"),
    "summary": (["summary", "MODEL"], "model"),
    "compress": (["compress", "--rate", "0.7", "--model", "MODEL"], "model"),
}
TFLITE_COMMANDS = {
    "run": (["run", "MODEL", "--source", "frames"], "model"),
    "bench": (["bench", "MODEL"], "model"),
}


def _parse(argv, name):
    from fcnpose_tf.cli import build_parser

    return build_parser().parse_args([name if a == "MODEL" else a for a in argv])


@pytest.mark.parametrize("command", sorted(KERAS_COMMANDS))
@pytest.mark.parametrize("name", ["generalist", "generalist-p70", "workcell", "workcell-p70"])
def test_a_keras_model_argument_takes_the_bundled_names(command, name, capsys):
    argv, attribute = KERAS_COMMANDS[command]
    value = getattr(_parse(argv, name), attribute)
    expected = bundled.models_dir() / bundled.BUNDLED_MODELS[name][0]
    assert value == expected and value.is_file()
    assert f"{name}: the bundled model {expected}" in capsys.readouterr().out  # says which file it resolved


@pytest.mark.parametrize("command", sorted(TFLITE_COMMANDS))
def test_a_tflite_model_argument_takes_the_bundled_tflite_names(command, cli_here):
    argv, attribute = TFLITE_COMMANDS[command]
    value = getattr(_parse(argv, "workcell-p70-int8"), attribute)
    assert (value[0] if isinstance(value, list) else value) == bundled.models_dir() / "fcnpose_ur5_p70_int8.tflite"
    status, out, err = cli_here(*[("generalist" if a == "MODEL" else a) for a in argv])
    assert status == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert "generalist: the bundled .keras model; this command takes .tflite models (bundled: " \
           "workcell-p70-fp16, workcell-p70-int8, workcell-p70-fp16native)" in err


@pytest.mark.parametrize("command", ["evaluate", "predict", "export", "summary", "compress", "run", "bench", "train"])
def test_every_model_argument_lists_the_names_in_its_help(command, cli_here):
    status, out, _ = cli_here(command, "--help")
    text = " ".join(out.split())
    assert status == 0
    names = bundled.bundled_names(bundled.TFLITE_SUFFIXES if command in TFLITE_COMMANDS else bundled.KERAS_SUFFIXES)
    for name in names:
        assert f"{name}:" in text or (command == "train" and name == "workcell-p70"), (command, name)


def test_the_defaults_are_bundled_names_too():
    baseline = bundled.baseline_model()
    assert _parse(["evaluate", "--data", "d"], "").model == baseline
    assert _parse(["predict", "--source", "f", "--via", "p.json"], "").model == baseline
    assert _parse(["compress", "--rate", "0.7"], "").model == baseline


def test_train_init_takes_the_same_names():
    from fcnpose_tf.commands.train import initial_weights

    assert initial_weights("generalist") == bundled.generalist_model()
    assert initial_weights("workcell-p70") == bundled.models_dir() / "fcnpose_ur5_p70.keras"
    assert initial_weights("none") is None
    with pytest.raises(UserError, match="workcell-p70-int8: the bundled .tflite model"):
        initial_weights("workcell-p70-int8")


def test_a_missing_model_names_the_bundled_ones(tmp_path):
    with pytest.raises(UserError, match="nope.keras: model file not found \\(or one of the bundled models: generalist, "
                                        "generalist-p70, workcell, workcell-p70\\)"):
        bundled.resolve_model(tmp_path / "nope.keras", bundled.KERAS_SUFFIXES)
    with pytest.raises(UserError, match="init.keras: model file not found"):
        from fcnpose_tf.commands.train import initial_weights

        initial_weights(str(tmp_path / "init.keras"))
