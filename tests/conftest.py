import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


LONGEST_FILES_FIRST = ("test_sweep.py", "test_compress.py", "test_reliability.py", "test_qat.py",
                       "test_train_evaluate.py", "test_exit_path.py")
"""The test files that take longest (`--durations`), run first. The suite runs in two processes a file at a time
(setup.cfg: pytest-xdist, --dist loadfile), handed out in collection order: a long file handed out last ran alone
at the end (test_sweep.py's Ray smoke run, 95-531 s as the load varies), so the longest start first and the many
short files fill in around them."""


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's tests keep their order


PROCESS_TIMEOUT = 1800
"""Seconds a test gives a new process to start, to reach what it waits for or to end, before it fails: a machine
busy with other work may take minutes to import TensorFlow. Only a failure waits this long; a test that passes goes on
as soon as the process is there (it polls or blocks on the process, never sleeps a fixed time)."""


@pytest.fixture
def cli(tmp_path):
    """Run `python -m fcnpose_tf ARGS` in a subprocess; returns CompletedProcess with text output."""

    def run(*args, cwd=None, env=None, timeout=PROCESS_TIMEOUT):
        full_env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", **(env or {}))
        return subprocess.run([sys.executable, "-m", "fcnpose_tf", *map(str, args)], cwd=cwd or tmp_path,
                              env=full_env, capture_output=True, text=True, timeout=timeout)

    return run


FEW_TIMED_CLI = Path(__file__).with_name("cli_few_timed.py")


def run_cli_few_timed(*args, cwd, env=None, timeout=3600):  # 40 min seen for a sweep beside two trainings
    """`python -m fcnpose_tf ARGS` in a fresh process whose evaluations time a few frames (`cli_few_timed.py`)."""
    full_env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", **(env or {}))
    return subprocess.run([sys.executable, str(FEW_TIMED_CLI), *map(str, args)], cwd=cwd, env=full_env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def cli_few_timed(tmp_path):
    """`cli` for commands that evaluate a model (train, compress) in a test that asserts no timing beyond its
    presence: the same fresh process, its evaluations timing `FEW_TIMED_FRAMES` frames after one of warm-up."""

    def run(*args, cwd=None, env=None, timeout=PROCESS_TIMEOUT):
        return run_cli_few_timed(*args, cwd=cwd or tmp_path, env=env, timeout=timeout)

    return run


@pytest.fixture
def cli_here(capsys):
    """Run `fcnpose-tf ARGS` in this process through `fcnpose_tf.cli.main`: (status, stdout, stderr).

    The same parser, exit path and messages as `cli` without a new interpreter importing TensorFlow
    again (seconds per call): for checks that do not depend on a fresh process (thread settings,
    signals, what a process imports).
    """
    from fcnpose_tf.cli import main

    def run(*args):
        capsys.readouterr()
        try:
            status = main([str(a) for a in args])
        except SystemExit as exc:  # argparse's own errors and --help
            status = exc.code
        out, err = capsys.readouterr()
        return status, out, err

    return run


@pytest.fixture(scope="session")
def structured_tflite() -> bytes:
    """The float16 .tflite bytes of test_runtime's hand-set FCN-Pose (TensorFlow's plain converter), converted once
    per session: the model file of the run, bench, predict and camera CLI tests and of the exit-path and full-disk
    tests (each module writes its own copy)."""
    from test_runtime import _convert_plain, _structured_model

    return _convert_plain(_structured_model())


FEW_TIMED_FRAMES = 3
"""Frames an evaluation times under `few_timed_frames` (the package times at least 50 after 5 of warm-up)."""


def stop_after_first_epoch(monkeypatch) -> None:
    """Make `train.fit` stop like Ctrl-C once its first epoch is complete and checkpointed (`monkeypatch`: a
    MonkeyPatch; its undo ends it)."""
    from fcnpose_tf.training import train

    original = train._CheckpointAndStop.on_epoch_end

    def stop_after_first(self, epoch, logs=None):
        original(self, epoch, logs)
        if epoch == 0:
            raise KeyboardInterrupt

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", stop_after_first)


def cut_timed_frames(monkeypatch) -> None:
    """Make evaluations in this process time at most FEW_TIMED_FRAMES frames after one warm-up frame.

    Every frame of the evaluated split is still scored once; only the extra timing-only passes (50 frames after 5
    of warm-up: seconds of eager Keras calls per evaluation) are cut. `monkeypatch`: a MonkeyPatch (its undo ends it).
    """
    from fcnpose_tf.compression import steps
    from fcnpose_tf.training import evaluate

    real = evaluate.evaluate_predictor
    signature = inspect.signature(real)
    assert {"min_timed_frames", "warmup"} <= set(signature.parameters), signature

    def evaluate_predictor(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        bound.arguments["min_timed_frames"] = min(bound.arguments["min_timed_frames"], FEW_TIMED_FRAMES)
        bound.arguments["warmup"] = min(bound.arguments["warmup"], 1)
        return real(*bound.args, **bound.kwargs)

    monkeypatch.setattr(evaluate, "evaluate_predictor", evaluate_predictor)  # train, evaluate, sweep import it late
    monkeypatch.setattr(steps, "evaluate_predictor", evaluate_predictor)  # compress's steps import it with the module


@pytest.fixture
def few_timed_frames(monkeypatch):
    """`cut_timed_frames` for one test: for tests of what train, evaluate or compress write and say, not of how many
    frames they time (test_train_evaluate checks that count on a real evaluation)."""
    cut_timed_frames(monkeypatch)


def _conversion_key(model, quantize, input_shape, calibration=None, pixel_interface=True) -> str | None:
    """What `export._convert`'s flatbuffer depends on, hashed: the model's architecture (its JSON, names included),
    every weight, the format, the input shape, the calibration frames and the interface; None if unreadable."""
    import hashlib

    import numpy as np

    digest = hashlib.sha256()
    try:
        digest.update(type(model).__module__.encode() + model.to_json().encode())
        arrays = [*model.get_weights(), *([] if calibration is None else [np.asarray(calibration)])]
    except Exception:  # noqa: BLE001 - a model that cannot say what it is gets converted every time
        return None
    digest.update(repr((quantize, tuple(input_shape), calibration is None, bool(pixel_interface))).encode())
    for array in arrays:
        digest.update(repr((array.dtype.str, array.shape)).encode() + np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


@pytest.fixture(scope="module")
def convert_once():
    """Within a module: a TFLite conversion (`compression.export._convert`) of a model identical to one converted
    before (architecture, names, weights, format, input shape, calibration frames) returns the flatbuffer that
    conversion gave instead of converting again (seconds each; the converter is deterministic). What follows it
    (the view metadata, the verification against Keras, the keypoint gate, the files) runs every time.

    For modules whose tests export the same model again through other commands (test_qat: one faint model through
    compress and export, the same float16 and int8 files each time)."""
    from fcnpose_tf.compression import export

    real = export._convert
    converted = {}

    def convert(model, quantize, input_shape, calibration=None, pixel_interface=True):
        key = _conversion_key(model, quantize, input_shape, calibration, pixel_interface)
        if key is None:
            return real(model, quantize, input_shape, calibration, pixel_interface)
        if key not in converted:
            converted[key] = real(model, quantize, input_shape, calibration, pixel_interface)
        return converted[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(export, "_convert", convert)
        yield converted
