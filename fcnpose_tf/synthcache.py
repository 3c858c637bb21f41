"""Synthetic datasets generated once into a cache and reused (the defaults of `compress` and `sweep`).

The bundled baseline was trained on `fcnpose-tf synth --n 1200 --seed 0` (the default scene:
workcell 0, one fixed camera). Frame i of a set depends
only on (seed, i), so the first TRAINING_FRAMES of that set are a subset of the baseline's training
frames: `compress` and `sweep` retrain on them when given no --data (400 frames keep `compress
--rate 0.7` within about 10 minutes on 2 cores). Every default measurement uses a held-out set
from another seed. Both are generated on first use under $FCNPOSE_CACHE (default
~/.cache/fcnpose-tf), keyed by the generator's source hash.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

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


def generator_fingerprint() -> str:
    """First 12 hex digits of the generator's source hash: a changed generator gets a fresh cache."""
    import hashlib

    from fcnpose_tf.data import synth

    return hashlib.sha256(Path(synth.__file__).read_bytes()).hexdigest()[:12]


def synthetic_dataset(n: int, seed: int, width: int = 640, height: int = 480) -> Path:
    """Folder of a synthetic UR5 dataset (n frames, seed), generating it atomically on first use."""
    folder = cache_dir() / f"synth-{generator_fingerprint()}" / f"ur5_n{n}_seed{seed}_{width}x{height}"
    if (folder / "ur5_synth.json").is_file():
        return folder
    from fcnpose_tf.data.synth import generate

    folder.parent.mkdir(parents=True, exist_ok=True)
    print(f"generating {n} synthetic UR5 frames (seed {seed}) into the cache: {folder}")
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        generate(tmp, n=n, seed=seed, width=width, height=height, force=True)
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the cache is ordinary data
        os.replace(tmp, folder)
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
