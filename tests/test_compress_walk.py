"""The rate's walk through `fcnpose-tf compress`, measured on the package's own calls: every check runs once per run
(the settings once per command, the rate's range once per rate, an explicit --start found once), and the stages are
entered in the order the data flows: command -> options -> plan -> surgery -> retraining -> export -> report."""

import functools
import importlib
import inspect
import sys
from pathlib import Path

import numpy as np
import pytest

from test_train_evaluate import make_via_folder
from weights import randomize

WALKED = ("fcnpose_tf.commands.compress", "fcnpose_tf.settings", "fcnpose_tf.bundled", "fcnpose_tf.compression.options",
          "fcnpose_tf.compression.compress", "fcnpose_tf.compression.plan", "fcnpose_tf.compression.keep_rule",
          "fcnpose_tf.compression.methods", "fcnpose_tf.compression.steps", "fcnpose_tf.compression.prune",
          "fcnpose_tf.compression.graph_prune", "fcnpose_tf.compression.export_steps",
          "fcnpose_tf.compression.report", "fcnpose_tf.compression.summary")
"""The modules whose functions the walk follows: the command, the settings, the bundled models' names, the pipeline."""

STAGES = (("command", "fcnpose_tf.commands.compress", "run"),
          ("options", "fcnpose_tf.compression.options", "CompressOptions.checked"),
          ("plan", "fcnpose_tf.compression.plan", "plan_widths"),
          ("surgery", "fcnpose_tf.compression.methods", "FilterPruning.prune"),
          ("retraining", "fcnpose_tf.compression.steps", "retrain_step"),
          ("export", "fcnpose_tf.compression.export_steps", "export_formats"),
          ("report", "fcnpose_tf.compression.report", "CompressReport.to_json"))
"""Each stage of a run and the function that begins it, in data order."""

CHECKS = {("fcnpose_tf.settings", "validate_fields"): "config",
          ("fcnpose_tf.settings", "Setting.validate"): "self",
          ("fcnpose_tf.compression.keep_rule", "exact_rate"): "rate",
          ("fcnpose_tf.bundled", "resolve_model"): "value"}
"""The checks counted, with the argument each call is told apart by: the settings check (of `CompressOptions`), one
setting's check (the rate's), the rate's exact reading and range check, a model argument found (the --start)."""


class Calls:
    """From its making, every call of a function or method defined in a `WALKED` module, in order: (module, qualified
    name, the counted argument of a `CHECKS` function, else None).

    Each function is wrapped (`monkeypatch`, undone after the test) wherever a module of the package holds it, so a
    call costs nothing more outside them; a global trace function (`sys.settrace`) made the same run take 1.8x the
    CPU, every TensorFlow call going through it. Dunder methods, properties and nested functions are not followed."""

    def __init__(self, monkeypatch):
        self.seen = []
        wrappers = {}
        for name in WALKED:
            module = importlib.import_module(name)
            for cls in [v for v in vars(module).values() if inspect.isclass(v) and v.__module__ == name]:
                for attr, member in list(vars(cls).items()):
                    if inspect.isfunction(member) and not attr.startswith("__"):
                        monkeypatch.setattr(cls, attr, self._wrapped(member, wrappers))
        for module in [m for name, m in list(sys.modules.items()) if name.startswith("fcnpose_tf") and m]:
            for attr, value in list(vars(module).items()):
                if inspect.isfunction(value) and value.__module__ in WALKED and value.__name__ != "<lambda>":
                    monkeypatch.setattr(module, attr, self._wrapped(value, wrappers))

    def _wrapped(self, function, wrappers):
        if function not in wrappers:
            key = (function.__module__, function.__qualname__)
            counted = CHECKS.get(key)
            signature = inspect.signature(function) if counted else None

            @functools.wraps(function)
            def call(*args, **kwargs):
                value = signature.bind(*args, **kwargs).arguments.get(counted) if counted else None
                self.seen.append((*key, value))
                return function(*args, **kwargs)

            wrappers[function] = call
        return wrappers[function]

    def count(self, module: str, name: str, argument=lambda value: True) -> int:
        """Calls of module.name whose counted argument passes `argument`."""
        return sum(1 for m, n, value in self.seen if (m, n) == (module, name) and argument(value))

    def first(self, module: str, name: str) -> int:
        """Where module.name was first called (a failure if never)."""
        return next(i for i, (m, n, _) in enumerate(self.seen) if (m, n) == (module, name))


def _model(path: Path, skip: bool) -> Path:
    """A seeded 64 x 64 FCN-Pose (with its skip or not) whose maps start below the threshold (see test_compress)."""
    from fcnpose_tf.training.model import build_fcn_pose

    model = randomize(build_fcn_pose(input_size=64, skip=skip), seed=0)
    kernel, bias = model.get_layer("conv10").get_weights()
    model.get_layer("conv10").set_weights([kernel, np.full_like(bias, -2.0)])
    model.save(path)
    return path


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    return make_via_folder(tmp_path_factory.mktemp("walk") / "frames", n=20)


def _is_rate(setting) -> bool:
    return getattr(setting, "name", None) == "rate"


def _compress_options(config) -> bool:
    return type(config).__name__ == "CompressOptions"


@pytest.mark.slow  # two compress runs' worth: 14 s of CPU, the tracing itself next to nothing
@pytest.mark.usefixtures("few_timed_frames")
def test_two_rates_are_each_checked_once_and_walk_the_stages_in_data_order(frames, cli_here, tmp_path,
                                                                            monkeypatch):
    """`--rates` on a model with the skip (the graph surgery): the settings checked once for both rates, each rate's
    range once (its setting) and read exactly once (its plan; never again by the surgery), every stage entered after
    the one before it, and the options never asked again once the plan is made but for the retraining's settings."""
    base = _model(tmp_path / "skip.keras", skip=True)
    calls = Calls(monkeypatch)
    status, stdout, err = cli_here("compress", "--rates", "0.5,0.7", "--model", base, "--data", frames, "--importance",
                                   "l1", "--retrain-epochs", "0", "--quantize", "float16", "--out-dir",
                                   tmp_path / "out", "--threads", "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert calls.count("fcnpose_tf.settings", "validate_fields", _compress_options) == 1
    assert calls.count("fcnpose_tf.settings", "Setting.validate", _is_rate) == 2
    assert [value for m, n, value in calls.seen if (m, n) == ("fcnpose_tf.compression.keep_rule", "exact_rate")] == [
        0.5, 0.7]
    assert calls.count("fcnpose_tf.compression.graph_prune", "plan_graph") == 2  # the surgery ran, at each plan
    order = [calls.first(module, name) for _, module, name in STAGES]
    assert order == sorted(order), [stage for (stage, _, _), _ in sorted(zip(STAGES, order), key=lambda p: p[1])]
    planned = calls.first("fcnpose_tf.compression.plan", "plan_widths")
    asked_again = {n for m, n, _ in calls.seen[planned:] if n.startswith(("CompressOptions.", "CheckedOptions."))}
    assert asked_again <= {"CompressOptions.retraining_minutes", "CompressOptions.fit_config"}, asked_again


@pytest.mark.slow
@pytest.mark.usefixtures("few_timed_frames")
def test_an_explicit_start_is_found_once(frames, cli_here, tmp_path, monkeypatch):
    """--start FILE: found when the options are checked (before the data), then its weights taken without finding it
    again."""
    from fcnpose_tf.training.model import build_fcn_pose

    base = _model(tmp_path / "base.keras", skip=False)
    start = tmp_path / "pruned.keras"
    randomize(build_fcn_pose((15, 15, 15, 15, 8, 8, 15, 15, 15), input_size=64), seed=5).save(start)
    calls = Calls(monkeypatch)
    status, stdout, err = cli_here("compress", "--rate", "0.7", "--model", base, "--data", frames, "--start", start,
                                   "--retrain-epochs", "0", "--quantize", "float16", "--out-dir", tmp_path / "out",
                                   "--threads", "1")
    assert status == 0, stdout[-3000:] + err[-3000:]
    assert calls.count("fcnpose_tf.bundled", "resolve_model", lambda value: str(value) == str(start)) == 1
    assert calls.count("fcnpose_tf.settings", "validate_fields", _compress_options) == 1
    assert calls.count("fcnpose_tf.compression.keep_rule", "exact_rate") == 1
    assert calls.first("fcnpose_tf.compression.methods", "FilterPruning._from_start") > calls.first(
        "fcnpose_tf.compression.plan", "plan_widths")
