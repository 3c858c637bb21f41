"""Filter importance criteria: a score for every output filter of every Conv2D, higher = keep.

Filter surgery (`fcnpose_tf.compression.prune`) keeps, in each Conv2D but the output layer, the filters a
criterion scores highest; the criterion is a callable object kept apart from the surgery (as in
Torch-Pruning's ``importance=`` and keras-surgeon), so every criterion goes through the same surgery:

    l1          sum of |w| of the filter's kernel (Li et al. 2017; the paper's)
    l2          sqrt of the sum of w**2 of the filter's kernel
    activation  mean |output| of the filter over training frames (data-aware)
    taylor      mean over frames of |spatial mean of output x d loss / d output| (first-order
                Taylor expansion of the loss, Molchanov et al. 2017; data-aware)

The weight criteria look at the kernel only and can rank a layer without the input channels the
previous layer lost (the greedy strategy). The data-aware criteria run the unpruned model on a
few hundred frames once (taylor also back-propagates the training loss), then rank every layer; the model may
branch and merge (FCN-Pose with its skip), every Conv2D's output read where the model computes it.
"""

from __future__ import annotations

from typing import Any, NotRequired, Protocol, Sequence, TypedDict

import numpy as np
import tf_keras as keras

from fcnpose_tf.errors import UserError

CRITERIA = ("l1", "l2", "activation", "taylor")
DATA_AWARE = ("activation", "taylor")
"""Criteria that need frames (and, for taylor, their target maps)."""


class CriterionFacts(TypedDict):
    """What reports record about a criterion (`Importance.describe`)."""

    importance: str
    """The criterion's name (CRITERIA)."""
    importance_frames: NotRequired[int]
    """The frames a data-aware criterion scored the filters on."""


class Importance(Protocol):
    """A filter importance criterion."""

    name: str

    def __call__(self, model: keras.Model) -> dict[str, np.ndarray]:
        """Layer name -> float64 score of each output filter, for every Conv2D of `model` in order (the output
        layer, which surgery never prunes, may be left out)."""

    def describe(self) -> CriterionFacts:
        """What reports record about the criterion.

        Returns:
            {"importance": name[, "importance_frames": N for a data-aware one]}.
        """


def _convolutions(model: keras.Model) -> list[keras.layers.Layer]:
    return [layer for layer in model.layers if type(layer) is keras.layers.Conv2D]


class WeightNorm:
    """The Lp norm of each filter's kernel over height, width and input channels (bias excluded).

    Args:
        p: 1 (L1, the paper's criterion) or 2 (L2).
    """

    def __init__(self, p: int = 1) -> None:
        if p not in (1, 2):
            raise UserError(f"weight norm order must be 1 or 2, got {p!r}")
        self.p = p
        self.name = f"l{p}"

    def filter_scores(self, kernel: np.ndarray, input_channels: Sequence[int] | None = None) -> np.ndarray:
        """Scores of a kernel's filters.

        Args:
            kernel: a Conv2D kernel, (kh, kw, cin, cout).
            input_channels: only these input channels count (the greedy strategy's kept inputs); None: all.
        Returns:
            cout float64 scores.
        Raises:
            UserError: a kernel of another rank.
        """
        kernel = np.asarray(kernel)
        if kernel.ndim != 4:
            raise UserError(f"expected a Conv2D kernel of shape (kh, kw, cin, cout), got shape {kernel.shape}")
        if input_channels is not None:
            kernel = kernel[:, :, np.asarray(input_channels, dtype=np.int64), :]
        kernel = kernel.astype(np.float64)
        if self.p == 1:
            return np.abs(kernel).sum(axis=(0, 1, 2))
        return np.sqrt(np.square(kernel).sum(axis=(0, 1, 2)))

    def __call__(self, model: keras.Model) -> dict[str, np.ndarray]:
        return {conv.name: self.filter_scores(conv.get_weights()[0]) for conv in _convolutions(model)}

    def describe(self) -> CriterionFacts:
        """What the report records about the criterion: {"importance": "l1" or "l2"}.

        Returns:
            The `CriterionFacts`.
        """
        return {"importance": self.name}


class _DataAware:
    """Shared part of the criteria that run the model on frames, a batch at a time."""

    name = ""

    def __init__(self, images: np.ndarray, batch_size: int = 8) -> None:
        images = np.asarray(images)
        if images.ndim != 4 or len(images) == 0:
            raise UserError(f"the {self.name} criterion needs frames (N x H x W x C), got shape {images.shape}")
        if batch_size < 1:
            raise UserError(f"batch size must be positive, got {batch_size}")
        self.images = images
        self.batch_size = int(batch_size)

    def _probe(self, model: keras.Model) -> tuple[keras.Model, list[str]]:
        """A model of `model`'s own layers giving its output and every Conv2D's output, and those Conv2Ds' names."""
        if not isinstance(model, keras.Model) or not getattr(model, "inputs", None):
            raise UserError(f"the {self.name} importance criterion needs a built tf_keras model")
        if len(model.inputs) != 1 or len(model.outputs) != 1:
            raise UserError(f"model {model.name} has {len(model.inputs)} inputs and {len(model.outputs)} outputs; "
                            f"the {self.name} importance criterion scores a single-input, single-output model")
        convs = _convolutions(model)
        if not convs:
            raise UserError(f"model {model.name} has no Conv2D layer to score")
        probe = keras.Model(model.inputs, [model.outputs[0], *(conv.output for conv in convs)])
        return probe, [conv.name for conv in convs]

    def _batches(self):
        for start in range(0, len(self.images), self.batch_size):
            yield slice(start, start + self.batch_size)

    def describe(self) -> CriterionFacts:
        """What the report records about the criterion."""
        return {"importance": self.name, "importance_frames": int(len(self.images))}


def _forward(probe: tuple[keras.Model, list[str]], x: Any) -> tuple[Any, dict[str, Any]]:
    """Run the model on `x` (inference mode); its output and every Conv2D's output by layer name (`_probe`)."""
    model, names = probe
    output, *convs = model(x, training=False)
    return output, dict(zip(names, convs))


def _compiled(function, *arrays: np.ndarray):
    """`function` as one TensorFlow graph for batches shaped like `arrays` (any batch size): a data-aware
    criterion's batches run 1.7x faster than eagerly (docs/results.md, "Taylor ranking as one graph")."""
    import tensorflow as tf

    return tf.function(function, input_signature=[tf.TensorSpec((None, *a.shape[1:]), tf.float32) for a in arrays])


def _summed(batch_scores, batches) -> dict[str, np.ndarray]:
    """Per-filter scores summed over batches: `batch_scores(batch)` gives {layer name: K per-filter sums}."""
    sums: dict[str, np.ndarray] = {}
    for batch in batches:
        for name, scores in batch_scores(batch).items():
            sums[name] = sums.get(name, 0.0) + scores.numpy().astype(np.float64)
    return sums


class MeanActivation(_DataAware):
    """Mean absolute output of each filter (after the layer's own activation) over frames and positions.

    score_k = (1 / (N H W)) * sum over frames n and positions (h, w) of |a[n, h, w, k]|.

    Args:
        images: N x H x W x 3 float32 frames as the model takes them (preprocessed, in [0, 1]).
        batch_size: frames per forward pass.
    """

    name = "activation"

    def __call__(self, model: keras.Model) -> dict[str, np.ndarray]:
        import tensorflow as tf

        probe = self._probe(model)

        def batch_sums(x):
            _, outputs = _forward(probe, x)
            return {name: tf.reduce_sum(tf.reduce_mean(tf.abs(a), axis=[1, 2]), axis=0) for name, a in outputs.items()}

        compiled = _compiled(batch_sums, self.images)
        sums = _summed(lambda batch: compiled(tf.convert_to_tensor(self.images[batch], tf.float32)), self._batches())
        return {name: total / len(self.images) for name, total in sums.items()}


class FirstOrderTaylor(_DataAware):
    """First-order Taylor importance of each filter for the training loss (Molchanov et al. 2017).

    With L the sum over frames of each frame's training loss (so the batch size does not matter),
    a the filter's output and g = dL/da:

        score_k = (1 / N) * sum over frames n of |mean over positions (h, w) of a[n, h, w, k] * g[n, h, w, k]|

    the first-order estimate of how much the loss changes when the filter's output is removed. Every
    Conv2D but the output layer is scored (surgery never prunes that one).

    Args:
        images: N x H x W x 3 float32 frames as the model takes them.
        maps: N x H x W x C float32 target maps of those frames.
        loss: the training loss (`train.training_loss`); its per-pixel values (`loss.call`) are averaged per frame.
        batch_size: frames per forward and backward pass.
    """

    name = "taylor"

    def __init__(self, images: np.ndarray, maps: np.ndarray, loss: keras.losses.Loss, batch_size: int = 8) -> None:
        super().__init__(images, batch_size)
        maps = np.asarray(maps)
        if len(maps) != len(self.images):
            raise UserError(f"the taylor criterion needs one target map per frame, got {len(maps)} maps for "
                            f"{len(self.images)} frames")
        self.maps = maps
        self.loss = loss

    def __call__(self, model: keras.Model) -> dict[str, np.ndarray]:
        import tensorflow as tf

        probe = self._probe(model)
        final = {tensor._keras_history[0].name for tensor in model.outputs}

        def batch_sums(x, y):
            with tf.GradientTape() as tape:
                prediction, outputs = _forward(probe, x)
                per_pixel = self.loss.call(y, prediction)  # N x H x W
                loss = tf.reduce_sum(tf.reduce_mean(per_pixel, axis=list(range(1, len(per_pixel.shape)))))
            names = [name for name in outputs if name not in final]  # not the output layer: never pruned, and
            # the loss may read its logits
            grads = tape.gradient(loss, [outputs[name] for name in names])
            return {name: tf.reduce_sum(tf.abs(tf.reduce_mean(outputs[name] * g, axis=[1, 2])), axis=0)
                    for name, g in zip(names, grads)}

        compiled = _compiled(batch_sums, self.images, self.maps)
        sums = _summed(lambda batch: compiled(tf.convert_to_tensor(self.images[batch], tf.float32),
                                              tf.convert_to_tensor(self.maps[batch], tf.float32)), self._batches())
        return {name: total / len(self.images) for name, total in sums.items()}


def make_importance(name: str, *, images: np.ndarray | None = None, maps: np.ndarray | None = None,
                    loss: keras.losses.Loss | None = None, batch_size: int = 8) -> Importance:
    """The criterion `name` names (one of CRITERIA).

    Args:
        name: l1, l2, activation or taylor.
        images: the frames the data-aware criteria (activation, taylor) run the model on.
        maps: the frames' target maps (taylor).
        loss: the training loss whose gradient taylor takes.
        batch_size: frames per forward pass.
    Returns:
        The criterion.
    Raises:
        UserError: an unknown name, or a data-aware criterion without its frames.
    """
    if name == "l1":
        return WeightNorm(1)
    if name == "l2":
        return WeightNorm(2)
    if name in DATA_AWARE and images is None:
        raise UserError(f"the {name} importance criterion needs training frames")
    if name == "activation":
        return MeanActivation(images, batch_size)
    if name == "taylor":
        if maps is None or loss is None:
            raise UserError("the taylor importance criterion needs the frames' target maps and the training loss")
        return FirstOrderTaylor(images, maps, loss, batch_size)
    raise UserError(f"importance criterion must be one of {', '.join(CRITERIA)}, got {name!r}")
