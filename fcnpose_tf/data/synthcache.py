"""Synthetic datasets generated once into a cache and reused (the defaults of `compress` and `sweep`).

The bundled baseline was trained on `fcnpose-tf synth --n 1200 --seed 0` (the default scene:
workcell 0, one fixed camera). Frame i of a set depends
only on (seed, i), so the first TRAINING_FRAMES of that set are a subset of the baseline's training
frames: `compress` and `sweep` retrain on them when given no --data (400 frames keep `compress
--rate 0.7` within about 10 minutes on 2 cores). Every default measurement uses a held-out set
from another seed. Both are generated on first use under $FCNPOSE_CACHE (default
~/.cache/fcnpose-tf), keyed by a hash of everything that shapes the generated files
(`generator_fingerprint`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

BASELINE_FRAMES = 1200
"""Frames of the synthetic set the bundled baseline was trained on (seed BASELINE_SEED)."""
BASELINE_SEED = 0
TRAINING_FRAMES = 400
"""Frames of the default training/retraining set: the first 400 of the baseline's set."""
HELDOUT_FRAMES = 100
HELDOUT_SEED = 1


def cache_dir() -> Path:
    """Root of fcnpose-tf's cache."""
    root = os.environ.get("FCNPOSE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "fcnpose-tf")
    return Path(root)


GENERATOR_MODULES = ("fcnpose_tf.data.synth", "fcnpose_tf.keypoints", "fcnpose_tf.data.via", "fcnpose_tf.fileio")
"""What shapes a generated dataset's bytes: the generator package (every module in it), the keypoint
schema, the VIA writer and the JSON writer it formats the VIA file with."""
NOT_SHAPING_MODULES = {
    "fcnpose_tf.errors": "error messages only",
    "fcnpose_tf.system": "the worker count; the files are the same for any",
    "fcnpose_tf.data.splits": "only removes the folds of a set being replaced",
    "fcnpose_tf.draw": "previews, which are not part of a dataset",
    "fcnpose_tf.preprocess": "data.via reads frames with it (read_via), never while a set is written",
    "fcnpose_tf.progress": "progress lines only",
    "fcnpose_tf.records": "keypoints.named_schema reads a model file's training record, never while a set is written",
}
"""First-party modules the generator imports that do not change the files (tests check that every
module the generator imports is in one of the two lists)."""


def generator_sources() -> list[Path]:
    """The source files of GENERATOR_MODULES (a package: all its .py files), in a stable order."""
    import importlib.util

    files: list[Path] = []
    for name in GENERATOR_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:  # pragma: no cover - the package is installed with its sources
            raise RuntimeError(f"cannot find the source of {name}")
        if spec.submodule_search_locations:
            files += sorted(Path(spec.origin).parent.rglob("*.py"))
        else:
            files.append(Path(spec.origin))
    return files


def generator_fingerprint(sources: Sequence[str | os.PathLike] | None = None) -> str:
    """First 12 hex digits of a hash over everything that shapes a generated dataset: a changed
    generator gets a fresh cache.

    Hashes each of `sources` (default: `generator_sources()`) by its path inside the package and its
    bytes, plus the numpy and OpenCV versions (random streams, resizing, blurring, PNG and JPEG coding).
    """
    import hashlib

    import cv2
    import numpy as np

    root = Path(__file__).resolve().parents[1]  # the package: names like data/via.py
    digest = hashlib.sha256()
    for source in generator_sources() if sources is None else sources:
        path = Path(source).resolve()
        name = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        data = path.read_bytes()
        digest.update(f"{name}\0{len(data)}\0".encode())
        digest.update(data)
    digest.update(f"numpy {np.__version__}\0opencv {cv2.__version__}".encode())
    return digest.hexdigest()[:12]


def synthetic_dataset(n: int, seed: int, width: int = 640, height: int = 480) -> Path:
    """Folder of a synthetic UR5 dataset (n frames, seed), generating it atomically on first use."""
    folder = cache_dir() / f"synth-{generator_fingerprint()}" / f"ur5_n{n}_seed{seed}_{width}x{height}"
    if (folder / "ur5_synth.json").is_file():
        return folder
    from fcnpose_tf.data.synth import generate

    folder.parent.mkdir(parents=True, exist_ok=True)
    from fcnpose_tf.progress import current

    current().say(f"generating {n} synthetic UR5 frames (seed {seed}) into the cache: {folder}")
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        generate(tmp, n=n, seed=seed, width=width, height=height, force=True)
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the cache is ordinary data
        try:
            os.replace(tmp, folder)
        except OSError:  # another process (a second compress) put the same set there first: theirs is as good
            if not (folder / "ur5_synth.json").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return folder


def default_training_data() -> Path:
    """The default data of `compress` and `sweep`: the first TRAINING_FRAMES frames of the baseline's set."""
    return synthetic_dataset(TRAINING_FRAMES, BASELINE_SEED)


def heldout_data() -> Path:
    """A synthetic set from another seed, never used for training: the default test set."""
    return synthetic_dataset(HELDOUT_FRAMES, HELDOUT_SEED)
