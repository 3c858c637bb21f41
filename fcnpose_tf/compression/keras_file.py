"""Model files of either Keras: which one saved a .keras/.h5 file, loading it with that one, saving atomically.

A .keras file is a zip whose ``metadata.json`` holds ``keras_version``; an .h5 file holds a ``keras_version``
attribute. Version 3 and later: saved by Keras 3 (the ``keras`` package); earlier: by tf_keras (Keras 2), which
FCN-Pose is built with. `fcnpose-tf prune` loads a model with the Keras that saved it and saves the pruned model
with the same one; `fcnpose-tf export` converts either.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

from fcnpose_tf.errors import UserError

KERAS_3 = "keras"
TF_KERAS = "tf_keras"


def saved_by(path: str | os.PathLike) -> str:
    """The package that saved a .keras or .h5 model file.

    Args:
        path: the model file.
    Returns:
        "keras" (Keras 3) or "tf_keras" (Keras 2).
    Raises:
        UserError: for a missing file, another suffix, or a file that is not a Keras model file.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: model file not found")
    if path.suffix not in (".keras", ".h5"):
        raise UserError(f"{path}: expected a Keras model file (.keras or .h5)"
                        + ("; a .tflite is already converted" if path.suffix == ".tflite" else ""))
    version = None
    try:
        if path.suffix == ".keras":
            with zipfile.ZipFile(path) as archive:
                version = json.loads(archive.read("metadata.json")).get("keras_version")
        else:
            import h5py

            with h5py.File(path, "r") as h5:
                version = h5.attrs.get("keras_version")
                version = version.decode() if isinstance(version, bytes) else version
    except (zipfile.BadZipFile, KeyError, ValueError, OSError) as exc:
        raise UserError(f"{path}: not a Keras model file ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from exc
    if not isinstance(version, str) or not version[:1].isdigit():
        raise UserError(f"{path}: not a Keras model file (no keras_version in it)")
    return KERAS_3 if int(version.split(".")[0]) >= 3 else TF_KERAS


def load_any(path: str | os.PathLike) -> Any:
    """The model in a .keras/.h5 file, loaded uncompiled with the Keras that saved it (`saved_by`).

    A tf_keras file is loaded as every command loads FCN-Pose (`fcnpose_tf.training.model.load_model`: its stored
    view kept, a variable input size refused); a Keras 3 file with ``keras.saving.load_model(compile=False)``.

    Args:
        path: the model file.
    Returns:
        The model, a tf_keras or a Keras 3 one.
    Raises:
        UserError: one line, for a file that is missing or cannot be read as a model.
    """
    from fcnpose_tf.fileio import native_name

    path = Path(path)
    if saved_by(path) == TF_KERAS:
        from fcnpose_tf.training.model import load_model

        return load_model(path)
    import keras

    try:
        return keras.saving.load_model(native_name(path), compile=False)
    except Exception as exc:  # Keras raises many types for a broken file or an unknown layer
        raise UserError(f"{path}: cannot be read as a Keras 3 model ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from exc


def save_to(model: Any, path: str | os.PathLike) -> None:
    """Save `model` (uncompiled, no optimizer state) to a .keras or .h5 file with the Keras it was built with, at
    once (`save_atomically` is the safe one; this writes a temporary of `fileio.atomic_paths`). A tf_keras model
    keeps its view and keypoint schema (`fcnpose_tf.training.model.save_for_inference`).

    Args:
        model: a tf_keras or Keras 3 model.
        path: the file (its suffix chooses the format).
    """
    from fcnpose_tf.compression.depgraph import keras_of

    if keras_of(model).__name__ == TF_KERAS:
        from fcnpose_tf.training.model import save_for_inference

        save_for_inference(model, path)
    else:
        model.save(os.fspath(path))


def save_atomically(model: Any, path: str | os.PathLike, force: bool = False) -> Path:
    """`save_to` a file that appears only once complete (`fileio.atomic_path`).

    Args:
        model: a tf_keras or Keras 3 model.
        path: the file, .keras or .h5.
        force: replace an existing file.
    Returns:
        `path`.
    Raises:
        UserError: another suffix, or an existing file without `force`.
    """
    from fcnpose_tf import fileio

    path = Path(path)
    if path.suffix not in (".keras", ".h5"):
        raise UserError(f"{path}: a Keras model file should end in .keras or .h5")
    with fileio.atomic_path(path, force) as tmp:
        save_to(model, tmp)
    return path
