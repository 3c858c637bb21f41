"""Training settings are defined once (fcnpose_tf.settings): every command and config follows that one place."""

import pytest

from fcnpose_tf import settings
from fcnpose_tf.errors import UserError


def _parsed(*argv):
    from fcnpose_tf.cli import build_parser

    return build_parser().parse_args(list(argv))


def _help(parser_args):
    from fcnpose_tf.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices[parser_args]
    return sub.format_help()


TRAIN = ["train", "--data", "d", "--out", "m.keras"]


def test_a_default_changed_in_settings_reaches_every_command_and_config(monkeypatch):
    from fcnpose_tf.compress import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.train import FitConfig

    monkeypatch.setattr(settings.BATCH_SIZE, "default", 3)
    monkeypatch.setattr(settings.LR_PATIENCE, "default", 7)
    monkeypatch.setattr(settings.RETRAIN_EPOCHS, "default", 11)
    monkeypatch.setattr(settings.PATIENCE, "help", "patience help changed in one place")
    train, compress, sweep = _parsed(*TRAIN), _parsed("compress", "--rate", "0.5"), _parsed("sweep")
    for args in (train, compress, sweep):
        assert args.batch_size == 3
    assert sweep.lr_patience == 7 and train.lr_patience is None  # resolved per run (DEFAULT_TRAIN_LR_PATIENCE)
    assert compress.lr_patience is None  # resolved per run (COMPRESS_LR_PATIENCE, below)
    assert compress.retrain_epochs == sweep.retrain_epochs == 11  # the sweep's per-rate form shares the default
    for command in ("train", "compress", "sweep"):
        text = " ".join(_help(command).split())
        assert "--batch-size BATCH_SIZE training batch size (default: 3)" in text
        assert "(default: 7)" in text or command in ("train", "compress")  # their own variants (below)
    for command in ("compress", "sweep"):
        assert "(default: 11)" in " ".join(_help(command).split())
    assert "patience help changed in one place" in _help("sweep")  # train has its own variant (TRAIN_PATIENCE)
    assert FitConfig().batch_size == CompressOptions(rate=0.5).batch_size == SweepConfig("o", "d").batch_size == 3
    assert CompressOptions(rate=0.5).retrain_epochs == SweepConfig("o", "d").retrain_epochs == 11
    assert FitConfig().lr_patience == CompressOptions(rate=0.5).lr_patience == SweepConfig("o", "d").lr_patience == 7


@pytest.mark.parametrize("trained_start, augment, weight", [(True, "paper", 8.0), (True, "online", 20.0),
                                                           (False, "paper", 20.0), (False, "online", 20.0)])
def test_train_weights_keypoints_less_when_fine_tuning_on_one_fixed_camera(trained_start, augment, weight):
    assert settings.train_positive_weight(trained_start=trained_start, augment=augment) == weight


def test_commands_that_differ_use_their_own_variant():
    from fcnpose_tf.compress import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.train import FitConfig

    train, compress, sweep = _parsed(*TRAIN), _parsed("compress", "--rate", "0.5"), _parsed("sweep")
    assert (train.epochs, sweep.epochs) == (FitConfig().epochs, SweepConfig("o", "d").epochs) == (500, 60)
    assert (train.patience, compress.retrain_patience, sweep.patience, sweep.retrain_patience) == (12, 5, 20, 5)
    assert CompressOptions(rate=0.5).patience == SweepConfig("o", "d").retrain_patience == 5
    # train serves a user's frames; compress and sweep reproduce the paper's tables
    assert compress.positive_weight is None and (train.positive_weight, sweep.positive_weight) == (None, 1.0)
    # train resolves its weight per run from its start and augmentation (settings.train_positive_weight, above)
    # compress retrains at 3e-3 halved after 3 stale epochs (0 on the cosine schedule); the sweep keeps the paper's
    assert compress.lr_patience is None and settings.DEFAULT_COMPRESS_LR_PATIENCE == 3
    assert (compress.learning_rate, train.learning_rate, sweep.learning_rate) == (3e-3, 1e-3, 1e-3)
    assert CompressOptions(rate=0.5).learning_rate == 1e-3 and CompressOptions(rate=0.5).lr_patience == 0
    assert (train.lr_patience, settings.DEFAULT_TRAIN_LR_PATIENCE, sweep.lr_patience) == (None, 4, 0) and (train.max_minutes, sweep.__dict__.get("max_minutes")) == (30.0, None)
    assert (train.augment, compress.augment) == ("auto", "paper")  # train picks per dataset (data.views)
    # compress resolves its criterion per run (taylor for independent filter surgery); the sweep keeps the paper's
    assert compress.importance is None and sweep.importance == settings.IMPORTANCE.default == "l1"
    assert compress.distill == sweep.distill == 0.0 and compress.freeze == 0  # compress retrains every layer
    assert settings.TRAIN_PATIENCE.check is settings.PATIENCE.check  # a variant shares its check and message
    assert train.folds is None and sweep.folds == 5


def _config(kind, **values):
    from fcnpose_tf.compress import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.train import FitConfig

    if kind == "fit":
        return FitConfig(**values)
    if kind == "compress":
        return CompressOptions(rate=0.5, **values)
    return SweepConfig("o", "d", **values)


@pytest.mark.parametrize("kind, values, message", [
    ("fit", {"epochs": 0}, "epochs must be at least 1, got 0"),
    ("sweep", {"epochs": 0}, "epochs must be at least 1, got 0"),
    ("compress", {"batch_size": 0}, "batch size must be at least 1, got 0"),
    ("sweep", {"input_size": 100}, "input size must be a positive multiple of 32"),
    ("sweep", {"retrain_patience": 0}, "retraining patience must be at least 1, got 0"),
    ("compress", {"patience": 0}, "retraining patience must be at least 1, got 0"),
    ("fit", {"learning_rate": float("nan")}, "learning rate must be a positive number, got nan"),
    ("compress", {"method": "x"}, "method must be one of l1, magnitude"),
])
def test_one_message_per_setting_from_every_config(kind, values, message):
    with pytest.raises(UserError, match=message):
        _config(kind, **values).validate()


def test_the_cli_refuses_with_the_settings_message(cli, tmp_path):
    proc = cli("train", "--data", tmp_path, "--out", tmp_path / "m.keras", "--input-size", "100")
    assert proc.returncode == 2 and "input size must be a positive multiple of 32" in proc.stderr
    proc = cli("sweep", "--out", tmp_path / "res", "--learning-rate", "0")
    assert proc.returncode == 2 and "learning rate must be a positive number, got 0.0" in proc.stderr
    assert not (tmp_path / "res").exists()
