"""What a result record states about where it came from: file hashes, a model's training record
(`TrainingRecord`), the host and the library versions. Standard library only (runtime/ uses it on a Pi).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import socket
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, TypedDict

from fcnpose_tf.measurements import Measurement
from fcnpose_tf.system import available_cores, memory_bytes

DISTRIBUTIONS: dict[str, tuple[str, ...]] = {
    "tensorflow": ("tensorflow", "tensorflow-cpu", "tensorflow-intel"),
    "tf_keras": ("tf-keras", "tf_keras"),
    "tensorflow_model_optimization": ("tensorflow-model-optimization",),
    "ai_edge_litert": ("ai-edge-litert", "ai-edge-litert-nightly"),
    "tflite_runtime": ("tflite-runtime",),
    "numpy": ("numpy",),
    "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless",
               "opencv-contrib-python"),
    "matplotlib": ("matplotlib",),
    "ray": ("ray",),
}
"""The libraries that shape results, each with the pip distributions that provide it."""

_IMPORT_NAMES = {"opencv": "cv2"}


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file: identifies the exact annotation file or model a record refers to."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _typed(value: Any, kind: type | tuple[type, ...]) -> Any:
    """`value` if it is a `kind` (a bool is no int here), else None."""
    return value if isinstance(value, kind) and not isinstance(value, bool) else None


DEPLOYED_RECORD_KEYS = ("data_sha256", "fold", "folds", "split", "split_seed")
"""What an exported .tflite keeps of its model's training record (`TrainingRecord.deployed`, the
`runtime.tflite_metadata.RECORD_METADATA` entry): which frames it was trained on, so that `evaluate` of the file
away from NAME_train.json (another folder, a Pi, `export --input-size`'s NAME_S_fp16.tflite) still takes the
validation frames. No paths: a file may be shared."""


@dataclass(frozen=True)
class TrainingRecord:
    """The NAME_train.json written beside a model by `fcnpose-tf train` (and by `compress` beside a retrained
    model), as the fields other modules read. A field the file lacks (an older record, a compressed model's)
    or holds with another type reads as None; `raw` keeps the whole file for anything else."""

    data: str | None = None
    """The annotation file trained on, as given (a path)."""
    data_absolute: str | None = None
    """The same file's absolute path (`train` since 2026-12-05; None in older records)."""
    images: str | None = None
    """The images' folder `train --images` gave (absolute), None when the images are where the VIA file says."""
    data_sha256: str | None = None
    """Hex SHA-256 of that annotation file: tells whether a dataset is the one trained on."""
    fold: int | None = None
    """The fold whose training frames were used; None for the hold-out 80/20 split (or not recorded)."""
    folds: int | None = None
    """How many folds the dataset's k-fold split has."""
    split: str | None = None
    """The split in words ("hold-out 80/20", "fold 2 of 5")."""
    split_seed: int | None = None
    """Seed of the dataset's split (which frames are validation frames)."""
    keypoints: tuple[str, ...] | None = None
    """The schema's keypoint names, in map order (the file's schema.keypoints)."""
    positive_weight: float | None = None
    """The keypoint maps' weight in the training loss (the file's config.positive_weight)."""
    input_size: int | None = None
    """The model's input size in pixels (the size it was kept at)."""
    augment: str | None = None
    """How its training frames were augmented: "paper" (fixed offline copies) or "online" (fresh every epoch)."""
    augment_copies: int | None = None
    """With augment "paper", the offline copies of each training frame (None: online, or not recorded)."""
    init: str | None = None
    """The model it started from, as `train --init` named it: a bundled name (generalist) or a path; None for a
    random start (--init none) or not recorded."""
    start_kept: bool = False
    """`train` kept its start's weights unchanged: no epoch beat the start (best epoch 0), or the start as saved
    measured better than the trained model (the file's start_as_saved.chose is "start")."""
    validation: Measurement | None = field(default=None, repr=False, hash=False, compare=False)
    """The kept model measured on its validation frames (`train_fold`'s "validation": metrics and timing); None in a
    compressed model's record (its NAME_pXX_report.json holds its measurements). Read from `raw`, so left out of
    comparisons."""
    raw: dict[str, Any] = field(default_factory=dict, repr=False, hash=False)
    """The whole JSON object, for keys without a field (config, epochs_run, validation...). Not to be changed."""

    def deployed(self) -> dict[str, Any]:
        """The keys of `DEPLOYED_RECORD_KEYS` this record holds, for an exported file's metadata."""
        return {key: self.raw[key] for key in DEPLOYED_RECORD_KEYS if key in self.raw}

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> TrainingRecord:
        """The record of a parsed NAME_train.json object; TypeError if it is no JSON object (dict)."""
        if not isinstance(record, dict):
            raise TypeError(f"a training record is a JSON object, not {type(record).__name__}")
        schema = record.get("schema")
        keypoints = schema.get("keypoints") if isinstance(schema, dict) else None
        if not (isinstance(keypoints, list) and all(isinstance(name, str) for name in keypoints)):
            keypoints = None
        config = record.get("config")
        positive_weight = _typed(config.get("positive_weight"), (int, float)) if isinstance(config, dict) else None
        init = _typed(record.get("init"), str)
        as_saved = record.get("start_as_saved")
        start_kept = init is not None and (_typed(record.get("best_epoch"), int) == 0 or (
            isinstance(as_saved, dict) and as_saved.get("chose") == "start"))
        return cls(data=_typed(record.get("data"), str), data_sha256=_typed(record.get("data_sha256"), str),
                   data_absolute=_typed(record.get("data_absolute"), str), images=_typed(record.get("images"), str),
                   fold=_typed(record.get("fold"), int), folds=_typed(record.get("folds"), int),
                   split=_typed(record.get("split"), str), split_seed=_typed(record.get("split_seed"), int),
                   keypoints=tuple(keypoints) if keypoints is not None else None,
                   positive_weight=float(positive_weight) if positive_weight is not None else None,
                   input_size=_typed(record.get("input_size"), int), augment=_typed(record.get("augment"), str),
                   augment_copies=_typed(record.get("augment_copies"), int),
                   init=init, start_kept=start_kept, validation=_measurement(record.get("validation")), raw=record)


def _measurement(value: Any) -> Measurement | None:
    """The `Measurement` of a record's "validation", or None (none, or not one: an older or hand-made record)."""
    try:
        return Measurement.from_json(value) if isinstance(value, dict) else None
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


def training_record(model_path: str | os.PathLike) -> TrainingRecord | None:
    """The NAME_train.json written beside a model by `fcnpose-tf train`, or None (none, unreadable, or no
    JSON object).

    An export or a compressed model (NAME_fp16.tflite, NAME_p70.keras: a format's file tag or a rate's pNN after the
    last underscore) finds NAME_train.json too; another model whose name only begins so (NAME_best.keras) does not.
    A .tflite exported since 2026-12-05 holds its own (`TrainingRecord.deployed`: the frames, no paths), which it
    reads first, wherever the file lies.
    """
    if Path(model_path).suffix == ".tflite" and (own := _record_in_metadata(model_path)) is not None:
        return own
    for candidate in _record_files(model_path):
        if candidate.is_file():
            record = _json_object(candidate)
            return TrainingRecord.from_json(record) if record is not None else None
    return None


def _json_object(path: Path) -> dict[str, Any] | None:
    """The JSON object in a record file; None when it is missing, no regular file (a folder; a named pipe, whose
    opening would wait for a writer), unreadable, not JSON (or nested beyond Python's parser) or no object."""
    try:
        if not path.is_file():
            return None
        record = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return record if isinstance(record, dict) else None


def _record_files(model_path: str | os.PathLike) -> list[Path]:
    """Where `training_record` looks: NAME_train.json, then for a derived file (a format's tag or a rate's pNN after
    the last underscore, repeatedly: NAME_p70_fp16 -> NAME_p70 -> NAME) its origins' records."""
    from fcnpose_tf.settings import QUANTIZE_FILE_TAGS

    stem = Path(model_path).with_suffix("")
    files = [Path(f"{stem}_train.json")]
    while True:
        base, _, tag = stem.name.rpartition("_")
        if not (base and (tag in QUANTIZE_FILE_TAGS.values() or re.fullmatch(r"p\d{1,2}", tag))):
            return files
        stem = stem.with_name(base)
        files.append(Path(f"{stem}_train.json"))


def recorded_schema(model_path: str | os.PathLike) -> dict[str, Any] | None:
    """The keypoint schema (`KeypointSchema.to_dict`) the nearest training record beside a model file holds
    (NAME_train.json, then its origins': a compressed model's record written before 2026-12-05 holds none, its base
    model's does), or None. (A .tflite's own schema is its `SCHEMA_METADATA` entry, not part of its record.)"""
    for candidate in _record_files(model_path):
        record = _json_object(candidate)
        if record is not None and isinstance(record.get("schema"), dict):
            return record["schema"]
    return None


def _record_in_metadata(path: str | os.PathLike) -> TrainingRecord | None:
    """The record a .tflite holds in its metadata (`runtime.tflite_metadata.RECORD_METADATA`), or None (none, an
    unreadable file or entry)."""
    from fcnpose_tf.runtime.tflite_metadata import RECORD_METADATA, read_metadata

    try:
        stored = read_metadata(path).get(RECORD_METADATA)
        record = json.loads(stored) if stored is not None else None
    except (OSError, ValueError, RecursionError):
        return None
    return TrainingRecord.from_json(record) if isinstance(record, dict) else None


def distribution_version(name: str) -> str | None:
    """Installed version of a library of DISTRIBUTIONS (package metadata, no import), or None.

    Without package metadata (e.g. OpenCV from the OS packages) the version of the already
    imported module is used.
    """
    from importlib import metadata

    for dist in DISTRIBUTIONS.get(name, (name,)):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    module = sys.modules.get(_IMPORT_NAMES.get(name, name))
    version = getattr(module, "__version__", None)
    return str(version) if version is not None else None


def library_versions(names: Iterable[str] | None = None) -> dict[str, str | None]:
    """fcnpose_tf's version and those of `names` (default: every library of DISTRIBUTIONS)."""
    from fcnpose_tf import __version__

    versions: dict[str, str | None] = {"fcnpose_tf": __version__}
    for name in DISTRIBUTIONS if names is None else names:
        versions[name] = distribution_version(name)
    return versions


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else platform's best guess."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "Hardware") and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


class MachineInfo(TypedDict, total=False):
    """A machine as a sweep's job records, retimings and results.json hold it (`machine_info`); a record written by
    another version may lack a key."""

    hostname: str
    cpu_model: str
    cpu_cores: int | None
    """os.cpu_count()."""
    cpu_cores_available: int
    """Cores this process may use (`system.available_cores`)."""
    memory_bytes: int
    """Left out where /proc/meminfo cannot be read."""
    platform: str
    python: str
    threads: int
    """The jobs' thread count, when given."""


def machine_info(threads: int | None = None) -> MachineInfo:
    """Host, CPU model, cores, memory, OS and Python (a sweep job's record); `threads` as used by the jobs."""
    info = MachineInfo(hostname=socket.gethostname(), cpu_model=cpu_model(), cpu_cores=os.cpu_count(),
                       cpu_cores_available=available_cores())
    total = memory_bytes("MemTotal")
    if total is not None:
        info["memory_bytes"] = total
    info.update(platform=platform.platform(), python=platform.python_version())
    if threads is not None:
        info["threads"] = threads
    return info


@dataclass(frozen=True)
class HostInfo:
    """The machine a benchmark ran on (its host line, and "host" of `bench --json`)."""

    machine: str
    """The CPU architecture (aarch64, x86_64)."""
    system: str
    """The OS, tersely."""
    cpu_count: int
    """Cores this process may use."""
    python: str
    numpy: str | None
    opencv: str | None

    def to_json(self) -> dict[str, Any]:
        """{"machine", "system", "cpu_count", "python", "numpy", "opencv"}."""
        return {"machine": self.machine, "system": self.system, "cpu_count": self.cpu_count, "python": self.python,
                "numpy": self.numpy, "opencv": self.opencv}


def host_info() -> HostInfo:
    """Machine, OS, usable cores, Python, numpy and OpenCV versions (a benchmark's host line)."""
    versions = library_versions(("numpy", "opencv"))
    return HostInfo(machine=platform.machine(), system=platform.platform(terse=True), cpu_count=available_cores(),
                    python=platform.python_version(), numpy=versions["numpy"], opencv=versions["opencv"])


def lineage(model_path: str | os.PathLike, max_depth: int = 16, kept_only: bool = False) -> list[str]:
    """What `model_path` was trained from, nearest first: each NAME_train.json's `init` (a bundled name or a path),
    followed through the records of the files it names (a second round of `train --init round1.keras` leads back
    to round 1's start). Stops at a random start, a model without a record, a path that is no file, a loop, or
    `max_depth` steps; with `kept_only`, also at a record whose run changed its start's weights
    (`TrainingRecord.start_kept` false): what is left names the files holding the same weights as `model_path`.

    Example: a model `train` fine-tuned from the generalist -> ["generalist"] ([] with `kept_only`).
    """
    chain: list[str] = []
    seen = {Path(model_path).resolve()}
    current: str | os.PathLike = model_path
    for _ in range(max_depth):
        record = training_record(current)
        if record is None or not record.init or (kept_only and not record.start_kept):
            break
        chain.append(record.init)
        path = Path(record.init)
        if not path.is_file() or path.resolve() in seen:
            break
        seen.add(path.resolve())
        current = path
    return chain
