"""A dataset on disk (VIA file + frames) and the training feed built from it.

`load_dataset(DATA, images)` follows the `--data` rule of every command: DATA
is a folder holding one VIA project file (*.json) and the images it names (in
the folder or an `images/` subfolder), or the path of a VIA file, optionally
with the images' folder. The result carries the schema, the kept frames, what
was dropped and why, and the splits stored beside the VIA file.

`TrainingData` turns dataset frames into model arrays at an input size:
frames resized by `fcnpose_tf.preprocess.preprocess_frame` (the function the Pi
runtime uses), keypoints scaled by `keypoints_to_input`, target maps drawn by
`masks.make_target_maps`, plus offline augmented copies for training frames.
Arrays are kept as uint8 (1,218 frames at 224 take ~0.7 GB) and served as
float32 batches by a tf_keras `Sequence`. Only `sequence()` imports tf_keras.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable

import numpy as np

from fcnpose_tf.data import augment as _augment
from fcnpose_tf.data.augment import AugmentConfig
from fcnpose_tf.data.masks import make_target_maps
from fcnpose_tf.data.splits import Splits, load_or_create_splits
from fcnpose_tf.data.via import read_via
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import special_file_kind
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.preprocess import FrameView, ViewLike, keypoints_to_input, preprocess_frame, read_image
from fcnpose_tf.progress import report_items


@dataclass
class Sample:
    """One usable frame: its VIA file name, image path, size and K x 2 (x, y) frame-pixel keypoints (NaN missing)."""

    filename: str
    image_path: Path
    width: int
    height: int
    keypoints: np.ndarray

    @property
    def num_visible(self) -> int:
        return int(np.isfinite(self.keypoints).all(axis=1).sum())


@dataclass(frozen=True)
class AddedFrames:
    """Frames added to every training split of a dataset (`with_training_frames`), as its records name them."""

    source: str
    """Where they came from (a video, an image folder, a VIA project), as the user named it."""
    labelled_by: str | None
    """What labelled them (a model's file); None: a project's own labels, as they are."""
    frames: int
    description: str
    """One line: how many, how chosen, how labelled."""

    def to_json(self) -> dict[str, str | int]:
        """The record's entry: {"source", "labelled_by", "frames", "description"}."""
        return {"source": self.source, "labelled_by": self.labelled_by, "frames": self.frames,
                "description": self.description}


@dataclass
class Dataset:
    """Annotated frames of one VIA file, with the drop counts and the stored splits.

    `dropped` maps a reason to a frame count; `splits_status` says whether the
    splits were "loaded" from `splits_path`, "created" there, or "not saved".
    `added` names frames of another project added to every training split (`with_training_frames`): the splits'
    validation frames are all of `via_path`.
    """

    via_path: Path
    schema: KeypointSchema
    samples: list[Sample]
    splits: Splits
    splits_path: Path
    splits_status: str
    dropped: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    attribute: str = "keypoint"
    min_visible: int = 1
    ignored_regions: int = 0
    added: AddedFrames | None = None

    def __len__(self) -> int:
        return len(self.samples)

    @property
    def names(self) -> list[str]:
        return [s.filename for s in self.samples]

    @property
    def num_dropped(self) -> int:
        return sum(self.dropped.values())

    def keypoints(self) -> np.ndarray:
        """N x K x 2 frame-pixel keypoints of all samples (NaN missing)."""
        return np.stack([s.keypoints for s in self.samples]) if self.samples else \
            np.zeros((0, self.schema.num_keypoints, 2))

    def load_image(self, index: int) -> np.ndarray:
        """Frame `index` as OpenCV reads it (H x W x 3 uint8, BGR); UserError if unreadable or resized."""
        sample = self.samples[index]
        image = read_image(sample.image_path)
        if image is None:
            raise UserError(f"{sample.image_path}: cannot read image (missing, not an image or corrupt)")
        if image.shape[:2] != (sample.height, sample.width):
            raise UserError(f"{sample.image_path}: image is {image.shape[1]}x{image.shape[0]}, but was "
                            f"{sample.width}x{sample.height} when the annotations were read")
        return image

    def split(self, fold: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(train, val) sample indices of K-fold fold `fold` (0-based), or the 80/20 hold-out split when None."""
        return self.splits.get(fold)


def with_training_frames(dataset: Dataset, extra: Dataset, added: AddedFrames) -> Dataset:
    """`dataset` with the frames of `extra` after its own, in the training split of its hold-out split and of every
    fold and never in a validation split: frames a model labelled (`correction.pseudolabel`) that validation must not
    be measured on.

    Args:
        dataset: the user's frames, with their splits (unchanged: `via_path`, its splits file and its frames' roles).
        extra: the frames to add (their own splits are not read).
        added: how the records name them.
    Returns:
        A new `Dataset`: `samples` the two lists, `splits` with the added indices in every training split, `added` set.
    Raises:
        UserError: the two keypoint schemas differ.
    """
    if extra.schema.to_dict() != dataset.schema.to_dict():
        raise UserError(f"{extra.via_path}: keypoint schema {extra.schema.name!r} "
                        f"({', '.join(extra.schema.keypoints)}) differs from {dataset.via_path}'s "
                        f"{dataset.schema.name!r} "
                        f"({', '.join(dataset.schema.keypoints)})")
    indices = np.arange(len(dataset), len(dataset) + len(extra), dtype=np.int64)
    return replace(dataset, samples=[*dataset.samples, *extra.samples], splits=dataset.splits.with_training(indices),
                   added=added)


def own_frames(dataset: Dataset) -> Dataset:
    """`dataset` without the frames `with_training_frames` added: the user's own, with their own splits.

    Args:
        dataset: a dataset, with frames added or not.
    Returns:
        The dataset of its own frames (`dataset` itself when none were added).
    """
    if dataset.added is None:
        return dataset
    count = len(dataset) - dataset.added.frames
    return replace(dataset, samples=dataset.samples[:count], splits=dataset.splits.before(count), added=None)


def resolve_data(data: str | os.PathLike, images: str | os.PathLike | None = None) -> tuple[Path, Path | None]:
    """(VIA file, images folder or None for the default search) for a `--data DATA [--images DIR]` pair."""
    data = Path(data)
    if images is not None and not Path(images).is_dir():
        raise UserError(f"{images}: images folder not found")
    if data.is_dir():
        candidates = sorted(p for p in data.glob("*.json")
                            if not p.name.startswith(".") and not p.name.endswith(".splits.json"))
        if not candidates:
            raise UserError(f"{data}: no VIA project file (*.json) in this folder; expected a folder with one "
                            "VIA .json file and its images (or an images/ subfolder), or a VIA file path")
        if len(candidates) > 1:
            names = ", ".join(p.name for p in candidates[:5]) + (", ..." if len(candidates) > 5 else "")
            raise UserError(f"{data}: several JSON files ({names}); pass the VIA file itself, e.g. "
                            f"--data {candidates[0]}")
        return candidates[0], Path(images) if images is not None else None
    if data.is_file():
        return data, Path(images) if images is not None else None
    kind = special_file_kind(data)
    if kind is not None:
        raise UserError(f"{data}: is {kind}; expected a dataset folder (one VIA .json file + images) or a VIA .json "
                        "file")
    raise UserError(f"{data}: not found; expected a dataset folder (one VIA .json file + images) or a VIA .json file")


def load_dataset(data: str | os.PathLike, images: str | os.PathLike | None = None, *, attribute: str = "keypoint",
                 schema: KeypointSchema | None = None, min_visible: int | None = None, skip_bad: bool = False,
                 folds: int | None = None, val_fraction: float = 0.2, split_seed: int | None = 0,
                 write_splits: bool = True,
                 resplit: bool = False) -> Dataset:
    """Load a dataset by the `--data` rule and attach its stored (or newly stored) splits.

    Args:
        data: a folder with one VIA .json file (images beside it or in images/), or a VIA file.
        images: the images' folder, when not beside the VIA file or in its images/ subfolder.
        attribute, schema, min_visible, skip_bad: as in `via.read_via`.
        folds, val_fraction, split_seed: K-fold count, hold-out validation fraction and seed. A K
            given is refused for fewer than K frames (`splits.check_fold_count`); None means
            the default 5, with no folds on a dataset too small for them. Seed None: the stored splits', else 0.
        write_splits: store new splits as `<VIA stem>.splits.json` (skipped silently when the
            folder is read-only).
        resplit: replace stored splits (needed after changing the frames or split options).

    Raises:
        UserError: for a missing or ambiguous VIA file, bad annotations (see `read_via`),
        no usable frames, or stored splits that do not match.
    """
    via_path, images_dir = resolve_data(data, images)
    ann = read_via(via_path, images_dir, attribute=attribute, schema=schema, min_visible=min_visible,
                   skip_bad=skip_bad)
    samples = [Sample(f.filename, f.image_path, f.width, f.height, f.keypoints) for f in ann.frames]
    if not samples:
        why = "; ".join(f"{n} {reason}" for reason, n in ann.dropped.items()) or "the file lists no frames"
        raise UserError(f"{via_path}: no usable frames ({why})")
    splits, spath, status = load_or_create_splits(via_path, [s.filename for s in samples], k=folds,
                                                  val_fraction=val_fraction, seed=split_seed,
                                                  write=write_splits, resplit=resplit,
                                                  roles=[f.split for f in ann.frames])
    return Dataset(via_path, ann.schema, samples, splits, spath, status, dict(ann.dropped), list(ann.problems),
                   attribute, ann.min_visible, ann.ignored_regions)


class TrainingData:
    """Model-ready arrays for some dataset frames at one input view (crop and size), with offline augmented copies.

    Rows are the frames of `indices` in the given order, then (when
    augment_copies > 0) `augment_copies` augmented copies of each of them, copy
    by copy. Pass only training indices with augment_copies > 0: validation data
    must not be augmented (`fold_data` does this for you). A frame's copies
    depend only on (seed, its dataset index), so they are the same in every fold.

    Attributes:
        images: N x H x W x 3 uint8 RGB (preprocess_frame's output times 255).
        maps: N x H x W x (K+1) uint8 in {0, 1}: keypoint discs, then the skeleton.
        keypoints: N x K x 2 float64 keypoints in input pixels (NaN missing).
        source: N dataset indices each row comes from.
        kinds: N strings: "original", or the augmentation kind of the copy.
        frame_sizes: N x 2 (width, height) of the source frames, to map keypoints back.
    """

    def __init__(self, dataset: Dataset, indices: Iterable[int], input_size: ViewLike, augment_copies: int = 0,
                 seed: int = 0, *, augment_config: AugmentConfig = AugmentConfig(), radius: float | None = None,
                 thickness: float | None = None, progress: bool = False):
        indices = np.asarray(list(indices), dtype=np.int64)
        view = FrameView.of(input_size)
        if augment_copies < 0:
            raise UserError(f"augmentation copies must be >= 0, got {augment_copies}")
        if indices.size and (indices.min() < 0 or indices.max() >= len(dataset)):
            raise UserError(f"sample indices must be between 0 and {len(dataset) - 1}")
        self.dataset = dataset
        self.schema = dataset.schema
        self.view = view
        self.input_size = view.shape
        self.augment_copies = int(augment_copies)
        self.seed = int(seed)
        n = len(indices) * (1 + self.augment_copies)
        (h, w), k = view.shape, self.schema.num_keypoints
        self.images = np.zeros((n, h, w, 3), np.uint8)
        self.maps = np.zeros((n, h, w, self.schema.num_maps), np.uint8)
        self.keypoints = np.full((n, k, 2), np.nan)
        self.source = np.zeros(n, np.int64)
        self.frame_sizes = np.zeros((n, 2), np.int64)
        self.kinds: list[str] = [""] * n
        buffer = np.empty((h, w, 3), np.float32)
        whole = FrameView(h, w)

        def put(row: int, index: int, frame: np.ndarray, kps: np.ndarray, kind: str) -> None:
            preprocess_frame(frame, whole, out=buffer)
            np.rint(buffer * 255.0, out=buffer)
            self.images[row] = buffer
            scaled = keypoints_to_input(kps, frame.shape, whole)
            self.keypoints[row] = scaled
            self.maps[row] = make_target_maps(scaled, whole, self.schema, radius, thickness)
            self.source[row] = index
            self.frame_sizes[row] = (frame.shape[1], frame.shape[0])
            self.kinds[row] = kind

        for j, index in enumerate(report_items(indices, progress, f"frames at {view.describe(whole='')}")):
            # the view's crop first, then the frame as the paper's whole frame: augmentation rotates and pads
            # the crop, which is what the model sees
            frame, kps = view.crop_sample(dataset.load_image(int(index)), dataset.samples[int(index)].keypoints)
            put(j, int(index), frame, kps, "original")
            if self.augment_copies:
                rng = np.random.default_rng([self.seed, int(index)])
                for c, aug in enumerate(_augment.augment_copies(frame, kps, self.augment_copies, rng, augment_config)):
                    put(len(indices) * (1 + c) + j, int(index), aug.image, aug.keypoints, aug.kind)

    def __len__(self) -> int:
        return len(self.images)

    def describe(self) -> str:
        """What one epoch shows, for progress lines."""
        frames = len(self) // (1 + self.augment_copies)
        return f"{len(self)} samples ({frames} frames + {self.augment_copies} augmented copies each)"

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """All rows as float32 (images in [0, 1], maps in {0, 1}); for small sets such as validation."""
        return _to_float(self.images), self.maps.astype(np.float32)

    def sequence(self, batch_size: int = 8, shuffle: bool = True, seed: int = 0):
        """A tf_keras `Sequence` of float32 (images, maps) batches, reshuffled every epoch when `shuffle`.

        The order of every epoch depends only on `seed`. Pass it to `model.fit`
        (and validation data to `validation_data=`).
        """
        if batch_size < 1:
            raise UserError(f"batch size must be positive, got {batch_size}")
        return _sequence_class()(self, batch_size, shuffle, seed)


def fold_data(dataset: Dataset, fold: int | None, input_size: ViewLike, augment_copies: int = 2, seed: int = 0,
              augment: str = "paper", *, progress: bool = False, **kwargs):
    """(training data, validation data without augmentation) for a fold.

    `fold` is a K-fold index (0-based) or None for the 80/20 hold-out split. `augment` "paper":
    `augment_copies` fixed offline copies per training frame (with the paper's 508 frames and 2
    copies: 406 + 812 = 1,218 training rows and 102 validation rows); "online": the training
    frames drawn with fresh random transforms every epoch (`data.online.OnlineTrainingData`).
    Extra keyword arguments (augment_config, radius, thickness) go to TrainingData.
    """
    train_idx, val_idx = dataset.split(fold)
    if len(train_idx) == 0 or len(val_idx) == 0:
        raise UserError(f"{dataset.via_path}: {len(dataset)} usable frame{'s' if len(dataset) != 1 else ''}; training "
                        "needs at least 2, one to learn from and one held out for validation (annotate more frames)")
    if augment == "online":
        from fcnpose_tf.data.online import OnlineTrainingData

        train = OnlineTrainingData(dataset, train_idx, input_size, seed, radius=kwargs.get("radius"),
                                   thickness=kwargs.get("thickness"), progress=progress)
    elif augment == "paper":
        train = TrainingData(dataset, train_idx, input_size, augment_copies, seed, progress=progress, **kwargs)
    else:
        raise UserError(f"augmentation must be online or paper, got {augment!r}")
    return train, TrainingData(dataset, val_idx, input_size, 0, seed, progress=progress, **kwargs)


def _to_float(images: np.ndarray) -> np.ndarray:
    # the same float32 values as preprocess_frame (uint8 times float32(1/255))
    out = np.empty(images.shape, np.float32)
    np.multiply(images, np.float32(1.0 / 255.0), out=out, casting="unsafe")
    return out


@functools.lru_cache(maxsize=None)
def _sequence_class():
    import tf_keras as keras

    class MapSequence(keras.utils.Sequence):
        """Float32 (images, maps) batches from a TrainingData's uint8 arrays; reshuffled per epoch."""

        def __init__(self, data: TrainingData, batch_size: int, shuffle: bool, seed: int):
            super().__init__()
            self.data = data
            self.batch_size = int(batch_size)
            self.shuffle = bool(shuffle)
            self._rng = np.random.default_rng(seed)
            n = len(data)
            self.order = self._rng.permutation(n) if self.shuffle else np.arange(n)

        def __len__(self) -> int:
            return math.ceil(len(self.data) / self.batch_size)

        def rows(self, batch: int) -> np.ndarray:
            """The TrainingData rows of batch `batch` of the current epoch."""
            if not 0 <= batch < len(self):
                raise IndexError(f"batch {batch} out of range (0..{len(self) - 1})")
            return self.order[batch * self.batch_size:(batch + 1) * self.batch_size]

        def __getitem__(self, batch: int):
            rows = self.rows(batch)
            return _to_float(self.data.images[rows]), self.data.maps[rows].astype(np.float32)

        def on_epoch_end(self) -> None:
            if self.shuffle:
                self.order = self._rng.permutation(len(self.data))

    return MapSequence
