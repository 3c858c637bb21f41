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
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.training.train import FitConfig

    monkeypatch.setattr(settings.BATCH_SIZE, "default", 3)
    monkeypatch.setattr(settings.BATCH_SIZE, "paper", 3)
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
        assert "(default: 7;" in text or command in ("train", "compress")  # their own variants (below)
    for command in ("compress", "sweep"):
        assert "(default: 11;" in " ".join(_help(command).split())
    assert "patience help changed in one place" in _help("sweep")  # train has its own variant (TRAIN_PATIENCE)
    assert FitConfig().batch_size == CompressOptions(rate=0.5).batch_size == SweepConfig("o", "d").batch_size == 3
    assert CompressOptions(rate=0.5).retrain_epochs == SweepConfig("o", "d").retrain_epochs == 11
    assert SweepConfig("o", "d").lr_patience == 7 and FitConfig().lr_patience is CompressOptions(rate=0.5).lr_patience \
        is None  # resolved per run (FitConfig.resolved, CompressOptions.resolved)


@pytest.mark.parametrize("trained_start, augment, weight", [(True, "paper", 8.0), (True, "online", 20.0),
                                                           (False, "paper", 20.0), (False, "online", 20.0)])
def test_train_weights_keypoints_less_when_fine_tuning_on_one_fixed_camera(trained_start, augment, weight):
    assert settings.train_positive_weight(trained_start=trained_start, augment=augment) == weight


def test_commands_that_differ_use_their_own_variant():
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.training.train import FitConfig

    train, compress, sweep = _parsed(*TRAIN), _parsed("compress", "--rate", "0.5"), _parsed("sweep")
    assert (train.epochs, sweep.epochs) == (FitConfig().epochs, SweepConfig("o", "d").epochs) == (500, 60)
    assert (train.patience, compress.retrain_patience, sweep.patience, sweep.retrain_patience) == (12, 10, 20, 5)
    assert (CompressOptions(rate=0.5).patience, SweepConfig("o", "d").retrain_patience) == (10, 5)
    assert CompressOptions.preset("paper", rate=0.5).patience == 5
    # train serves a user's frames; compress and sweep reproduce the paper's tables
    assert compress.positive_weight is None and (train.positive_weight, sweep.positive_weight) == (None, 1.0)
    # train resolves its weight per run from its start and augmentation (settings.train_positive_weight, above)
    # compress retrains at 3e-3 halved after 3 stale epochs (0 on the cosine schedule); the sweep keeps the paper's
    assert compress.lr_patience is None and settings.DEFAULT_COMPRESS_LR_PATIENCE == 3
    assert (compress.learning_rate, train.learning_rate, sweep.learning_rate) == (3e-3, None, 1e-3)
    # train resolves its rate and frozen layers per run (settings.train_recipe): the skip on one fixed camera keeps
    # conv1 fixed and trains the rest at 3e-3; other trained starts keep conv1-2 fixed at 1e-3; random weights train all at 1e-3
    assert settings.train_recipe(True, "paper", "fcn-pose-skip") == (1, 3e-3)
    assert settings.train_recipe(True, "paper", "fcn-pose") == settings.train_recipe(True, "online", "fcn-pose-skip") \
        == (2, 1e-3)
    assert settings.train_recipe(False, "paper", "fcn-pose-skip") == (0, 1e-3)
    # and its copies of each frame (settings.train_augment_copies): 4 for the skip on one fixed camera, else the paper's 2
    assert settings.train_augment_copies(True, "paper", "fcn-pose-skip") == 4
    assert settings.train_augment_copies(True, "paper", "fcn-pose") == settings.train_augment_copies(
        False, "paper", "fcn-pose-skip") == settings.train_augment_copies(True, "online", "fcn-pose-skip") == 2
    assert CompressOptions(rate=0.5).learning_rate == 3e-3 and CompressOptions(rate=0.5).lr_patience is None
    assert (train.lr_patience, settings.DEFAULT_TRAIN_LR_PATIENCE, sweep.lr_patience) == (None, 4, 0)
    assert (train.max_minutes, sweep.max_minutes) == (30.0, None)
    assert (train.augment, compress.augment) == ("auto", None)  # train picks per dataset (data.views)
    # compress retrains as its base model was trained: test_compress_inherits_the_base_models_augmentation
    # compress resolves its criterion per run (taylor for independent filter surgery); the sweep keeps the paper's
    assert compress.importance is None and sweep.importance == settings.IMPORTANCE.default == "l1"
    assert compress.distill == sweep.distill == 0.0 and compress.freeze == 0  # compress retrains every layer
    assert settings.TRAIN_PATIENCE.check is settings.PATIENCE.check  # a variant shares its check and message
    assert train.folds is None and sweep.folds == 5


def _config(kind, **values):
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.training.train import FitConfig

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


def test_the_cli_refuses_with_the_settings_message(cli_here, tmp_path):
    status, _, err = cli_here("train", "--data", tmp_path, "--out", tmp_path / "m.keras", "--input-size", "100")
    assert status == 2 and "input size must be auto, S or HxW" in err
    status, _, err = cli_here("sweep", "--out", tmp_path / "res", "--learning-rate", "0")
    assert status == 2 and "learning rate must be a positive number, got 0.0" in err
    assert not (tmp_path / "res").exists()


def _cli_configs(preset):
    """Each command's configs as its parser leaves them with no option but --preset (and what it requires)."""
    from fcnpose_tf.commands.sweep import config_from_args
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.compression.export import ExportOptions
    from fcnpose_tf.training.train import FitConfig

    flag = [] if preset is None else ["--preset", preset]
    train, compress = _parsed(*TRAIN, *flag), _parsed("compress", "--rate", "0.7", *flag)
    sweep = _parsed("sweep", "--out", "o", "--data", "d", "--threads", "1", *flag)
    return {"train": settings.from_args(train, FitConfig),
            "compress": settings.from_args(compress, CompressOptions, renamed={"patience": "retrain_patience"}),
            "export": settings.from_args(_parsed("export", "m.keras"), ExportOptions),
            "sweep": config_from_args(sweep)}


def _api_configs(preset):
    """The same configs from the library: the class's defaults, or its `preset`."""
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.compression.export import ExportOptions
    from fcnpose_tf.sweep.jobs import SweepConfig
    from fcnpose_tf.training.train import FitConfig

    def make(cls, **values):
        return cls(**values) if preset is None else cls.preset(preset, **values)

    return {"train": make(FitConfig), "compress": make(CompressOptions, rate=0.7), "export": ExportOptions(),
            "sweep": make(SweepConfig, out="o", data="d")}


@pytest.mark.parametrize("preset", [None, "recommended", "paper"])
def test_the_api_and_the_cli_mean_the_same_with_no_options(preset):
    import dataclasses

    cli, api = _cli_configs(preset), _api_configs(preset)
    for kind in ("train", "compress", "export"):
        assert cli[kind] == api[kind], kind
    ignored = {"out", "data", "reporter"}  # paths as given; where the jobs report
    for f in dataclasses.fields(api["sweep"]):
        if f.name not in ignored:
            assert getattr(cli["sweep"], f.name) == getattr(api["sweep"], f.name), f.name
    # and once the settings left None are chosen for a run, as the library chooses them
    assert cli["compress"].resolved() == api["compress"].resolved()
    assert cli["train"].resolved(trained_start=True) == api["train"].resolved(trained_start=True)


def test_compress_options_mean_what_compress_means():
    from fcnpose_tf.compression.options import CompressOptions

    recommended = CompressOptions(rate=0.7).resolved()
    assert (recommended.importance, recommended.min_filters, recommended.learning_rate, recommended.lr_patience) == \
        ("taylor", 15, 3e-3, 3)
    assert recommended.quantize == ("float16", "int8")
    paper = CompressOptions.preset("paper", rate=0.7).resolved()
    assert (paper.importance, paper.min_filters, paper.learning_rate, paper.lr_patience, paper.positive_weight) == \
        ("l1", 0, 1e-3, 0, 1.0)
    assert (paper.retrain_epochs, paper.quantize) == (100, ("float16",))
    assert paper.input_size is None  # the paper's protocol runs the files at the model's own size
    for options in (recommended, paper):  # what compress_model retrains with passes fit's checks
        options.validate()
        options.fit_config().validate()
    greedy = CompressOptions(rate=0.7, strategy="greedy").resolved()
    assert greedy.importance == "l1"  # greedy ranking reads kernels only
    assert CompressOptions(rate=0.7, method="magnitude").resolved().min_filters == 0
    for options, minutes in ((recommended, 10.0), (paper, None)):  # an epoch budget, and a time budget but the
        fit_config = options.fit_config()                               # paper's: a valid FitConfig
        fit_config.validate()  # what fit() checks first
        assert fit_config.max_minutes == minutes and fit_config.epochs == options.retrain_epochs


def test_train_preset_paper_is_the_papers_recipe():
    from fcnpose_tf.training.train import FitConfig

    args = _parsed(*TRAIN, "--preset", "paper")
    assert (args.init, args.augment, args.folds) == ("none", "paper", None)
    config = FitConfig.preset("paper").resolved(trained_start=False)
    config.validate()  # no time budget is a value the paper's recipe may have
    assert (config.positive_weight, config.lr_patience, config.patience, config.max_minutes, config.freeze) == \
        (1.0, 0, 20, None, 0)
    recommended = FitConfig().resolved(trained_start=True)
    assert (recommended.positive_weight, recommended.lr_patience, recommended.freeze, recommended.max_minutes) == \
        (8.0, 4, 2, 30.0)
    given = _parsed(*TRAIN, "--preset", "paper", "--patience", "12")  # an option given beats the preset
    assert given.patience == 12 and given.given_settings >= {"patience"}


def test_the_sweep_passes_every_setting_on_to_its_runs():
    import dataclasses

    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.sweep.jobs import SWEEP_FIXED, Job, SweepConfig
    from fcnpose_tf.training.train import FitConfig

    config = SweepConfig("o", "d", lr_schedule="cosine", freeze=2, max_minutes=5.0, learning_rate=2e-3)
    fit = config.fit_config()
    assert (fit.lr_schedule, fit.max_minutes, fit.learning_rate, fit.freeze) == ("cosine", 5.0, 2e-3, 0)
    options = config.compress_options(Job(1, 0.7))
    assert (options.lr_schedule, options.freeze, options.learning_rate, options.fold) == ("cosine", 2, 2e-3, 1)
    assert SweepConfig("o", "d", input_size=160).compress_options(Job(0, 0.7)).input_size is None  # the base's own
    held = {f.name for f in dataclasses.fields(SweepConfig)}
    for f in dataclasses.fields(CompressOptions):  # none dropped: the sweep's own, fixed, or the job's
        assert f.name in held | set(SWEEP_FIXED) | {"rate", "fold", "patience", "total_minutes"}, f.name
    assert (options.max_minutes, options.total_minutes) == (None, None)  # rates compared at equal epochs
    assert {f.name for f in dataclasses.fields(FitConfig)} <= held | set(SWEEP_FIXED)
    assert (fit.keep_best, options.keep_best) == ("loss", "loss")  # fixed: the paper's rule, base and retraining


@pytest.mark.parametrize("rate, params", [(0.5, 35185), (0.7, 14668)])
def test_the_sweeps_paper_preset_keeps_the_papers_parameter_counts(rate, params):
    from fcnpose_tf.training.model import build_fcn_pose
    from fcnpose_tf.compression.prune import prune_model
    from fcnpose_tf.sweep.jobs import Job, SweepConfig

    config = SweepConfig.preset("paper", out="o", data="d")
    assert config.centroid == "plain"  # the paper's Algorithm 1, as under the sweep's recommended preset
    options = config.compress_options(Job(0, rate))
    assert (options.min_filters, options.importance, options.retrain_epochs) == (0, "l1", 100)
    pruned = prune_model(build_fcn_pose(input_size=64), options.rate, min_filters=options.min_filters)
    assert pruned.count_params() == params


def test_the_librarys_decoders_default_to_the_commands_decoding():
    """A decoder called without --centroid/--threshold reads maps as `evaluate`, `predict`, `run` and `bench` do."""
    import inspect

    from fcnpose_tf import postprocess
    from fcnpose_tf.compression.options import CompressOptions
    from fcnpose_tf.runtime import bench, estimator
    from fcnpose_tf.training import evaluate, train

    for decoder in (postprocess.maps_to_keypoints, postprocess.decode):  # the functions the Decoding calls
        parameters = inspect.signature(decoder).parameters
        assert parameters["centroid"].default == settings.CENTROID.default, decoder
        assert parameters["threshold"].default == settings.THRESHOLD.default, decoder
    default = postprocess.Decoding()
    assert (default.threshold, default.fallback, default.centroid) == (
        settings.THRESHOLD.default, settings.FALLBACK.default, settings.CENTROID.default)
    for predictor in (estimator.KeypointModel, evaluate.KerasKeypointModel, evaluate.open_model, bench.benchmark,
                      train.train_fold, train.keep_start_if_better):  # a Decoding, default None: the one above
        assert inspect.signature(predictor).parameters["decoding"].default is None, predictor
    assert estimator.KeypointPredictor.decoding == default
    assert CompressOptions(rate=0.5).centroid == settings.CENTROID.default == "weighted"
    assert _parsed("evaluate", "m.keras", "--data", "d").centroid == "weighted"
    assert _parsed("sweep").centroid == "plain"  # the paper's tables (settings.SWEEP_CENTROID)


def test_compress_time_budgets_reach_the_retraining_and_a_bad_one_is_refused(cli_here):
    from fcnpose_tf.cli import build_parser
    from fcnpose_tf.compression.options import CompressOptions

    assert CompressOptions(rate=0.7).fit_config().max_minutes == 10.0
    assert CompressOptions(rate=0.7, max_minutes=2.5).fit_config().max_minutes == 2.5
    assert CompressOptions.preset("paper", rate=0.7).fit_config().max_minutes is None
    parser = build_parser()
    for flag, name, label in (("--max-minutes", "max_minutes", "time budget"),
                              ("--total-minutes", "total_minutes", "total time budget")):
        assert getattr(parser.parse_args(["compress", "--rate", "0.7", flag, "none"]), name) is None
        assert getattr(parser.parse_args(["compress", "--rate", "0.7", flag, "7.5"]), name) == 7.5
        for bad in ("0", "-3", "inf"):
            status, _, err = cli_here("compress", "--rate", "0.7", flag, bad)
            assert status == 2 and err.strip().splitlines()[-1].startswith(
                f"error: {label} must be a positive number of minutes, or none"), err
        status, _, err = cli_here("compress", "--rate", "0.7", flag, "soon")
        assert status == 2 and "expected minutes or none, got 'soon'" in err


def test_compress_total_budget_leaves_the_retraining_what_the_other_steps_do_not_need():
    from dataclasses import replace

    from fcnpose_tf.compression.options import CompressOptions

    options = CompressOptions(rate=0.7)
    assert (options.total_minutes, options.max_minutes) == (15.0, 10.0)
    assert options.retraining_minutes(1.0) == 10.0  # 12 left: --max-minutes caps it
    assert options.retraining_minutes(3.0) == 6.0  # 15 - 3 spent - twice 3 kept for the steps after
    assert options.retraining_minutes(6.0, ranking_minutes=5.0) == 7.0  # 15 - 6 spent - twice the 1 not ranking
    assert options.retraining_minutes(5.0) == 2.0  # 0 left: the least a retraining gets
    assert replace(options, total_minutes=None).retraining_minutes(7.0) == 10.0
    assert replace(options, max_minutes=None).retraining_minutes(1.5) == 10.5
    assert replace(options, max_minutes=None, total_minutes=None).retraining_minutes(4.0) is None
    assert CompressOptions.preset("paper", rate=0.7).total_minutes is None


COMMON_OPTIONS = {"threads": settings.THREADS, "max_frames": settings.MAX_FRAMES, "by": settings.SELECT_BY,
                  "force": settings.FORCE}
"""Options several commands share, each declared once in settings (a command's variant names its own help)."""


def _declared(setting):
    """The setting `setting` is a variant of (itself when it is no variant)."""
    while "_base" in setting.__dict__:
        setting = setting.__dict__["_base"]
    return setting


def test_every_commands_threads_max_frames_by_and_force_are_the_settings_ones():
    import argparse

    from fcnpose_tf.cli import build_parser
    from fcnpose_tf.correction.selection import DEFAULT_STRATEGY, STRATEGIES

    found = {}

    def walk(parser, name):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for command, sub in action.choices.items():
                    walk(sub, f"{name} {command}".strip())
            elif action.dest in COMMON_OPTIONS:
                setting = getattr(action, "setting", None)
                assert setting is not None and _declared(setting) is COMMON_OPTIONS[action.dest], (name, action.dest)
                found.setdefault(action.dest, set()).add(name)

    walk(build_parser(), "")
    assert found["threads"] >= {"train", "compress", "export", "sweep", "evaluate", "run", "predict", "bench"}
    assert found["max_frames"] == {"run", "predict"} and found["by"] == {"predict"}
    assert found["force"] >= {"train", "compress", "export", "prune", "sweep", "evaluate", "run", "predict", "bench",
                              "synth", "data inspect", "data merge"}
    assert (settings.SELECT_BY.choices, settings.SELECT_BY.default) == (STRATEGIES, DEFAULT_STRATEGY)
    # left out, each is its setting's default, as the library's
    args = _parsed("predict", "--source", "frames", "--via", "out.json")
    assert (args.threads, args.max_frames, args.by, args.force) == (None, None, "uniform", False)
    assert _parsed("predict", "--source", "f", "--via", "o.json", "--force", "--by", "jump", "--max-frames", "3",
                   "--threads", "2").force is True
    assert _parsed("bench", "m.tflite", "--threads", "1,2").threads == (1, 2)
    with pytest.raises(UserError, match="--max-frames must be at least 1, got 0"):
        settings.MAX_FRAMES.validate(0)
