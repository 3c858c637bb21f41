"""Where the bundled models (saved_models/) are: a source checkout, or the installed data files.

`pip install .` copies saved_models/ to <prefix>/share/fcnpose-tf/saved_models (setup.cfg
data_files); an editable install or a checkout uses the folder beside the package.
FCNPOSE_MODELS_DIR overrides both. numpy-free, TensorFlow-free.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from fcnpose_tf.errors import UserError

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
