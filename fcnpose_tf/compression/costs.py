"""What a Keras model costs: its widths, parameters and MACs (`model_facts`) and its file sizes (`file_sizes`), the
facts every measured step of a compression report starts from (`report.ModelStep.of`).
"""

from __future__ import annotations

import gzip
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import tf_keras as keras


@dataclass(frozen=True)
class ModelFacts:
    """What a Keras model costs (`model_facts`): the conv widths, parameters and MACs (FLOPs = 2 x MACs)."""

    widths: list[int]
    params: int
    macs: int
    flops: int
    nonzero_weights: int
    """Weights that are not zero (magnitude pruning zeroes weights without removing them)."""


def file_sizes(model: keras.Model, keras_path: Path | None = None) -> dict[str, int]:
    """Bytes of the model as .keras and .h5 (no optimizer state), and gzip-compressed .h5.

    Args:
        model: a tf_keras model.
        keras_path: its .keras file when written (its size is read; None: the model is saved to a temporary one).
    Returns:
        {"h5_size_bytes", "h5_gzip_size_bytes", "keras_size_bytes"}.
    """
    from fcnpose_tf.training.model import h5_bytes, inference_copy, save_for_inference

    with warnings.catch_warnings():  # the paper's size is the .h5; Keras calls the format legacy
        warnings.simplefilter("ignore", UserWarning)
        h5 = h5_bytes(inference_copy(model))
    sizes = {"h5_size_bytes": len(h5), "h5_gzip_size_bytes": len(gzip.compress(h5, 9))}
    with tempfile.TemporaryDirectory() as tmp:
        if keras_path is None:
            keras_path = Path(tmp) / "m.keras"
            save_for_inference(model, keras_path)
        sizes["keras_size_bytes"] = keras_path.stat().st_size
    return sizes


def model_facts(model: keras.Model) -> ModelFacts:
    """Widths, parameters and MACs (FLOPs = 2 x MACs) of a model.

    Args:
        model: a tf_keras model.
    Returns:
        Its facts, the weights that are not zero among them.
    """
    from fcnpose_tf.training.model import conv_widths, describe

    rows = describe(model)
    macs = sum(r.macs for r in rows)
    return ModelFacts(widths=list(conv_widths(model)), params=int(model.count_params()), macs=int(macs),
                      flops=int(2 * macs),
                      nonzero_weights=int(sum(np.count_nonzero(w) for w in model.get_weights())))
