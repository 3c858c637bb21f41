"""Training past a fixed prefix: with conv1..convN fixed (`train --freeze N`) and fixed training samples (the paper's
offline copies), the fixed layers compute the same outputs in every epoch. They are computed once, before the first
epoch, and each epoch trains a copy of the rest of the network (the head) from them: the same arithmetic as
training the whole network with those layers fixed, without their forward pass, the batches' images replaced by the
cut's features.

    whole network ──► prefix (fixed layers, and the parameter-free layers that only they feed) ──► features
                      head (a copy of every other layer) trained on the features; its weights copied back by name

The cut is where the prefix's tensors are read by the head: for FCN-Pose with conv1-2 fixed, pool2's output; with
its skip, conv2's output (the skip reads it; pool2 moves to the head, whose input it then is). Used by
`training.train.fit` when the features fit in memory (`FEATURE_MEMORY_SHARE` of what is available), else the whole
network trains as before (what it buys: docs/training.md, "Fixed layers computed once").
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import tf_keras as keras
import tensorflow as tf

from fcnpose_tf.system import memory_bytes

FEATURE_MEMORY_SHARE = 0.5
"""The most of the memory available when training starts that the prefix's features may take."""
_PREFIX_LAYERS = (keras.layers.InputLayer, keras.layers.Conv2D, keras.layers.MaxPooling2D,
                  keras.layers.AveragePooling2D, keras.layers.UpSampling2D, keras.layers.ZeroPadding2D,
                  keras.layers.Activation, keras.layers.ReLU, keras.layers.Add, keras.layers.Concatenate)
"""Layers whose output depends only on their inputs and weights, the same in training and inference: the only ones
a prefix holds (a Dropout or a BatchNormalization keeps everything after it in the head)."""


@dataclass
class FrozenPrefix:
    """A network cut after its fixed layers.

    Attributes:
        prefix: the image to the cut's tensors (the whole network's own layers, in inference).
        head: the cut's tensors to the maps: copies of the whole network's other layers, with their weights; the
            model that is trained.
        cut: names of the layers whose outputs are the head's inputs, in the head's input order.
    """

    prefix: keras.Model
    head: keras.Model
    cut: tuple[str, ...]

    def feature_bytes(self, rows: int) -> int:
        """Bytes of float32 features for `rows` samples."""
        return rows * 4 * sum(int(np.prod(shape[1:])) for shape in _shapes(self.prefix.output_shape))

    def features(self, images: np.ndarray, batch_size: int = 16) -> list[np.ndarray]:
        """The prefix's float32 outputs for RGB `images` (N x H x W x 3: uint8 as `TrainingData.images`, or float32
        in [0, 1] as its `arrays()`), one array per head input."""
        outputs = [np.empty((len(images), *shape[1:]), np.float32) for shape in _shapes(self.prefix.output_shape)]
        for start in range(0, len(images), batch_size):
            batch = images[start:start + batch_size]
            if batch.dtype == np.uint8:  # as `data.dataset._to_float`: the same float32 values
                batch = batch.astype(np.float32) * np.float32(1.0 / 255.0)
            values = self.prefix(batch, training=False)
            for out, value in zip(outputs, values if isinstance(values, (list, tuple)) else [values]):
                out[start:start + len(batch)] = value.numpy()
        return outputs

    def weights_into(self, whole: keras.Model, head: keras.Model | None = None) -> keras.Model:
        """`whole` with the weights of `head` (default: this one's) copied into its layers of the same names."""
        for layer in (head or self.head).layers:
            if layer.weights:
                whole.get_layer(layer.name).set_weights(layer.get_weights())
        return whole


def _shapes(shape: Any) -> list[tuple]:
    return list(shape) if isinstance(shape, list) else [shape]


def _single_node(model: keras.Model) -> bool:
    return all(len(layer._inbound_nodes) == 1 for layer in model.layers)  # noqa: SLF001 - tf_keras' graph


def split_frozen(model: keras.Model) -> FrozenPrefix | None:
    """`model` cut after its fixed layers (those with weights and none trainable), or None when nothing is worth
    cutting: no fixed layer with weights in front, or a network this cut does not follow (a layer called twice).

    The prefix takes every layer from the input whose inputs all come from the prefix and that has no trainable
    weights and behaves the same in training (`_PREFIX_LAYERS`); a parameter-free prefix layer whose inputs are all
    read by the head anyway moves to the head (its output would only add features to keep)."""
    if not _single_node(model):
        return None
    layers = model.layers
    producer = {id(layer.output): layer.name for layer in layers}

    def inputs_of(layer) -> list[str]:
        return [producer[id(t)] for t in tf.nest.flatten(layer.input)]

    prefix: list[str] = []
    for layer in layers:
        if isinstance(layer, keras.layers.InputLayer):
            prefix.append(layer.name)
        elif (type(layer) in _PREFIX_LAYERS and not layer.trainable_weights
              and all(name in prefix for name in inputs_of(layer))):
            prefix.append(layer.name)
    if not any(model.get_layer(name).weights for name in prefix):
        return None
    outputs = {producer[id(t)] for t in tf.nest.flatten(model.output)}

    def cut_of(names: list[str]) -> list[str]:
        read = {i for layer in layers if layer.name not in names for i in inputs_of(layer)}
        return [name for name in names if name in read or name in outputs]

    changed = True
    while changed:
        changed = False
        cut = cut_of(prefix)
        for name in reversed(prefix):
            layer = model.get_layer(name)
            if name in cut and not layer.weights and not isinstance(layer, keras.layers.InputLayer) and \
                    all(i in cut for i in inputs_of(layer)):
                prefix.remove(name)
                changed = True
                break
    cut = cut_of(prefix)
    if any(name in outputs for name in cut):
        return None  # the maps themselves come from fixed layers: nothing to train
    prefix_model = keras.Model(model.input, [model.get_layer(name).output for name in cut], name="frozen_prefix")
    tensors = {}
    head_inputs = []
    for name in cut:
        shape = model.get_layer(name).output_shape
        head_inputs.append(keras.Input(shape[1:], name=f"{name}_features"))
        tensors[name] = head_inputs[-1]
    for layer in layers:
        if layer.name in prefix:
            continue
        copy = layer.__class__.from_config(layer.get_config())
        arguments = tf.nest.map_structure(lambda t: tensors[producer[id(t)]], layer.input)
        tensors[layer.name] = copy(arguments)
        copy.set_weights(layer.get_weights())
        copy.trainable = layer.trainable
    head_outputs = tf.nest.map_structure(lambda t: tensors[producer[id(t)]], model.output)
    head = keras.Model(head_inputs, head_outputs, name=f"{model.name}_head")
    return FrozenPrefix(prefix_model, head, tuple(cut))


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable), None where unknown."""
    available = memory_bytes("MemAvailable")
    if available is not None:
        return available
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fits_in_memory(prefix: FrozenPrefix, rows: int, available: int | None = None) -> bool:
    """Whether the features of `rows` samples take at most FEATURE_MEMORY_SHARE of the memory available."""
    available = available_memory() if available is None else available
    return available is not None and prefix.feature_bytes(rows) <= FEATURE_MEMORY_SHARE * available


def feature_sequence(prefix: FrozenPrefix, sequence: Any) -> keras.utils.Sequence:
    """A keras Sequence of (features, maps) batches in `sequence`'s order (a `TrainingData.sequence`: the same rows
    per batch, reshuffled alike each epoch), the features computed once here."""
    return _FeatureSequence(prefix.features(sequence.data.images), sequence)


class _FeatureSequence(keras.utils.Sequence):
    """(features, maps) batches of a TrainingData's rows, in the order of the image sequence it replaces."""

    def __init__(self, features: Sequence[np.ndarray], rows: Any):
        super().__init__()
        self.features = list(features)
        self.rows = rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, batch: int):
        rows = self.rows.rows(batch)
        inputs = [f[rows] for f in self.features]
        return (inputs[0] if len(inputs) == 1 else tuple(inputs)), self.rows.data.maps[rows].astype(np.float32)

    def on_epoch_end(self) -> None:
        self.rows.on_epoch_end()
