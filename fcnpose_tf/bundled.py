"""Where the bundled models (saved_models/) are: a source checkout, or the installed data files.

`pip install .` copies saved_models/ to <prefix>/share/fcnpose-tf/saved_models (setup.cfg
data_files); an editable install or a checkout uses the folder beside the package.
FCNPOSE_MODELS_DIR overrides both. numpy-free, TensorFlow-free.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable

from fcnpose_tf import progress
from fcnpose_tf.errors import UserError
from fcnpose_tf.progress import Reporter

BASELINE_NAME = "fcnpose_ur5"
"""Stem of the bundled baseline: fcnpose_ur5.keras, its card, and compressed exports."""

GENERALIST_NAME = "fcnpose_ur5_generalist"
"""Stem of the bundled generalist: the baseline fine-tuned on domain-randomised scenes (random cells,
cameras, arm looks, tools, light and clutter), a starting point for `train` on a user's own frames."""


def models_dir() -> Path:
    """The first existing bundled-models folder (environment, checkout, installed data files)."""
    candidates = []
    if os.environ.get("FCNPOSE_MODELS_DIR"):
        candidates.append(Path(os.environ["FCNPOSE_MODELS_DIR"]))
    candidates += [Path(__file__).resolve().parent.parent / "saved_models",
                   Path(sys.prefix) / "share" / "fcnpose-tf" / "saved_models"]
    for folder in candidates:
        if (folder / f"{BASELINE_NAME}.keras").is_file():
            return folder
    raise UserError("the bundled models were not found (looked in "
                    + ", ".join(str(c) for c in candidates) + "); pass a model file explicitly")


def baseline_model() -> Path:
    """Path of the bundled baseline FCN-Pose (.keras)."""
    return models_dir() / f"{BASELINE_NAME}.keras"


def generalist_model() -> Path:
    """Path of the bundled generalist FCN-Pose (.keras), `train`'s starting point for a user's frames."""
    return models_dir() / f"{GENERALIST_NAME}.keras"


KERAS_SUFFIXES = (".keras", ".h5")
TFLITE_SUFFIXES = (".tflite",)
ANY_MODEL = KERAS_SUFFIXES + TFLITE_SUFFIXES

BUNDLED_MODELS = {
    "generalist": (f"{GENERALIST_NAME}.keras", "the UR5 generalist, fine-tuned on domain-randomised scenes"),
    "generalist-p70": (f"{GENERALIST_NAME}_p70.keras", "the generalist pruned at rate 0.7 and retrained on "
                       "domain-randomised scenes: compress's start at 0.7 for a model fine-tuned from the generalist"),
    "workcell": (f"{BASELINE_NAME}.keras", "the paper-reproduction baseline of one UR5 workcell"),
    "workcell-p70": (f"{BASELINE_NAME}_p70.keras", "the workcell baseline pruned at rate 0.7 and retrained"),
    "workcell-p70-fp16": (f"{BASELINE_NAME}_p70_fp16.tflite", "workcell-p70 as float16 TFLite (the paper's format)"),
    "workcell-p70-int8": (f"{BASELINE_NAME}_p70_int8.tflite", "workcell-p70 as full-integer int8 TFLite (the Pi's)"),
    "workcell-p70-fp16native": (f"{BASELINE_NAME}_p70_fp16native.tflite",
                                "workcell-p70 as float16-native TFLite (a Pi 5 computes it in float16)"),
}
"""The names every command's model argument takes (`resolve_model`): name -> (file in models_dir(), what it is)."""


def bundled_names(suffixes: tuple[str, ...] = ANY_MODEL) -> list[str]:
    """The bundled models' names whose files have one of `suffixes`."""
    return [name for name, (file, _) in BUNDLED_MODELS.items() if Path(file).suffix in suffixes]


def names_help(suffixes: tuple[str, ...] = ANY_MODEL) -> str:
    """For a model argument's help: the bundled names it takes, each with what it is."""
    return "; ".join(f"{name}: {BUNDLED_MODELS[name][1]}" for name in bundled_names(suffixes))


def resolve_model(value: str | os.PathLike, suffixes: tuple[str, ...] = ANY_MODEL,
                  reporter: Reporter | None = None) -> Path:
    """The model file `value` names: an existing file as given, else a bundled model by name (BUNDLED_MODELS), whose
    file `reporter` names (default: the current reporter, `progress.current`).

    Raises:
        UserError: neither a file nor a bundled name, or a bundled model of another kind than `suffixes` allows.
    """
    text = os.fspath(value)
    if Path(text).is_file():
        return Path(text)
    names = bundled_names(suffixes)
    if text in BUNDLED_MODELS:
        file = BUNDLED_MODELS[text][0]
        if text not in names:
            raise UserError(f"{text}: the bundled {Path(file).suffix} model; this command takes "
                            f"{'/'.join(suffixes)} models (bundled: {', '.join(names)})")
        path = models_dir() / file
        if not path.is_file():
            raise UserError(f"{text}: the bundled model {path} is missing")
        say_bundled(text, path, reporter)
        return path
    raise UserError(f"{text}: model file not found (or one of the bundled models: {', '.join(names)})")


def say_bundled(value: str | os.PathLike, path: Path, reporter: Reporter | None = None) -> None:
    """Name the bundled file a model argument stands for, as `resolve_model` does when it finds it (nothing for a
    file given by its path): for a value found earlier and used later (compress's --start).

    Args:
        value: the argument as given.
        path: the file `resolve_model` found for it.
        reporter: where the line goes (default: the current reporter).
    """
    if Path(os.fspath(value)) != path:
        progress.resolve(reporter).say(f"{os.fspath(value)}: the bundled model {path}")


def model_argument(suffixes: tuple[str, ...] = ANY_MODEL) -> Callable[[str], Path]:
    """argparse type of a model argument: a bundled name resolved while parsing (`resolve_model`; a name of another
    kind is a one-line usage error), any other text the path it names (the command reads the file)."""
    def model(text: str) -> Path:
        if text not in BUNDLED_MODELS or Path(text).is_file():
            return Path(text)
        try:
            return resolve_model(text, suffixes)
        except UserError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return model
