"""Distillation while retraining: the unpruned model's maps as a second target of every training batch.

`with_teacher_maps(data, sequence, teacher)` wraps a training Sequence so that each batch's targets
are the ground-truth maps followed by the teacher's maps of the same augmented frames (C + C
channels), which `train.DistillationLoss` reads; the teacher is frozen (run in inference mode,
never trained).

- Fixed training rows (the paper's offline copies, `TrainingData`): every epoch shows the same
  rows, so the teacher runs once over all of them before training and its maps are kept as
  float16; an epoch then costs what it costs without distillation (plus the copy of the maps).
- Fresh rows every epoch (online augmentation): the teacher runs on each batch as it is drawn,
  one forward pass of the unpruned model per training step.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import tf_keras as keras

CACHE_DTYPE = np.float16
"""Teacher maps of fixed rows are stored as float16 (half the memory; maps are probabilities in [0, 1],
kept to about 3 significant digits)."""


def _predictor(teacher: keras.Model):
    import tensorflow as tf

    shape = (None, *teacher.input_shape[1:])

    @tf.function(input_signature=[tf.TensorSpec(shape, tf.float32)])
    def predict(x):
        return teacher(x, training=False)

    return predict


def teacher_maps(teacher: keras.Model, sequence: Any) -> np.ndarray:
    """The teacher's maps of every row of a training Sequence iterated in row order.

    Args:
        teacher: the model whose maps are learnt from.
        sequence: a training Sequence (batches of (frames, targets), rows in order).
    Returns:
        N x H x W x C maps, float16 (the cache's dtype).
    """
    predict = _predictor(teacher)
    parts = [np.asarray(predict(np.asarray(sequence[b][0], np.float32))).astype(CACHE_DTYPE)
             for b in range(len(sequence))]
    return np.concatenate(parts, axis=0)


class TeacherTargets(keras.utils.Sequence):
    """A training Sequence whose targets carry the teacher's maps after the ground truth's (see module doc)."""

    carries_teacher_maps = True

    def __init__(self, sequence: Any, teacher: keras.Model, cache: np.ndarray | None = None) -> None:
        super().__init__()
        self.sequence = sequence
        self.cache = cache
        self._predict = None if cache is not None else _predictor(teacher)

    def __len__(self) -> int:
        return len(self.sequence)

    def __getitem__(self, batch: int):
        images, maps = self.sequence[batch]
        if self.cache is not None:
            teacher = self.cache[self.sequence.rows(batch)].astype(np.float32)
        else:
            teacher = np.asarray(self._predict(np.asarray(images, np.float32)), np.float32)
        return images, np.concatenate([np.asarray(maps, np.float32), teacher], axis=-1)

    def on_epoch_end(self) -> None:
        self.sequence.on_epoch_end()

    @property
    def epoch(self) -> int:
        """The wrapped Sequence's epoch (online augmentation; `fit` sets it on resume)."""
        return self.sequence.epoch  # AttributeError when it has none, so hasattr() tells

    @epoch.setter
    def epoch(self, value: int) -> None:
        self.sequence.epoch = value


def with_teacher_maps(data: Any, sequence: Any, teacher: keras.Model, batch_size: int = 8) -> tuple[Any, dict]:
    """`sequence` (batches of `data`) with the teacher's maps added to every batch's targets, and what it cost.

    Args:
        data: the training data `sequence` draws from: a `TrainingData` (fixed rows: the teacher's maps
            are computed once, here) or an online-augmented set (computed per batch while training).
        sequence: `data.sequence(...)`, the batches training would use without distillation.
        teacher: the unpruned model, same input size and maps as the student.
        batch_size: frames per teacher forward pass while caching.
    Returns:
        (the wrapped Sequence, {"teacher_maps": "cached" | "per batch", "teacher_seconds": ...}).
    """
    from fcnpose_tf.data.dataset import TrainingData

    if isinstance(data, TrainingData) and hasattr(sequence, "rows"):
        start = time.perf_counter()
        cache = teacher_maps(teacher, data.sequence(batch_size, shuffle=False))
        seconds = time.perf_counter() - start
        return TeacherTargets(sequence, teacher, cache), {"teacher_maps": "cached", "teacher_seconds": round(seconds, 1)}
    return TeacherTargets(sequence, teacher), {"teacher_maps": "per batch"}
