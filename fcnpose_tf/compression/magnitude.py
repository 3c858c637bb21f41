"""Unstructured magnitude pruning with tensorflow-model-optimization, beside filter surgery for comparison.

`magnitude_prune` zeroes the smallest weights of every kernel instead of removing filters. The tensors keep their
shapes, so the parameter count and the latency stay the same; only a compressed file (gzip) gets smaller. It exists
so reports can show the two side by side (`compress --method magnitude`).
"""

from __future__ import annotations

import numbers
from typing import Callable, Iterable

import numpy as np
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.training.model import with_facts_of

TrainFn = Callable[[keras.Model, list], None]


def magnitude_prune(model: keras.Model, sparsity: float, *, train_fn: TrainFn | None = None,
                    frequency: int = 100, include_output: bool = False) -> keras.Model:
    """Zero the smallest-magnitude weights of every Conv2D kernel (unstructured pruning).

    Uses tensorflow-model-optimization's ``prune_low_magnitude`` with a ``ConstantSparsity``
    schedule: the masks are applied at once (so the result is sparse even without retraining),
    then `train_fn` may retrain the wrapped model while the masks are kept, and the wrappers are
    stripped. Tensor shapes do not change, so parameters, MACs and latency stay the same; only a
    compressed file gets smaller. For the ``--method magnitude`` comparison with `prune_model`.

    Args:
        model: a built tf_keras model; it is copied, not modified.
        sparsity: fraction of each pruned kernel's weights set to zero, in [0, 1).
        train_fn: called as ``train_fn(wrapped_model, callbacks)`` to retrain; it must compile the
            model and pass `callbacks` (tfmot's ``UpdatePruningStep``) to ``fit``. None skips it.
        frequency: training steps between mask updates while retraining.
        include_output: also prune a Conv2D that is the model's output layer (FCN-Pose's conv10); off by default,
            as in `prune_model`. Biases are never pruned.
    Returns:
        A plain tf_keras model (wrappers stripped) with the same layers and names, and `model`'s view and schema.
    Raises:
        UserError: for a sparsity outside [0, 1), a model that is not tf_keras (tfmot wraps tf_keras layers only), or
            one without a Conv2D to prune.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose
        >>> sparse = magnitude_prune(build_fcn_pose(input_size=64), 0.7)
        >>> round(weight_sparsity(sparse, ["conv2"])["conv2"], 3)
        0.7
    """
    import tensorflow_model_optimization as tfmot

    if isinstance(sparsity, bool) or not isinstance(sparsity, numbers.Real) or not 0 <= float(sparsity) < 1:
        raise UserError(f"sparsity must be a number in [0, 1), got {sparsity!r}")
    if isinstance(frequency, bool) or not isinstance(frequency, numbers.Integral) or frequency < 1:
        raise UserError(f"frequency must be a positive number of steps, got {frequency!r}")
    if not isinstance(model, keras.Model):
        raise UserError(f"model {getattr(model, 'name', model)!r} is not a tf_keras model: magnitude pruning (tfmot) "
                        "takes tf_keras models only")
    convs = [layer.name for layer in model.layers if type(layer) is keras.layers.Conv2D]
    outputs = set(model.output_names)  # the layers whose outputs are the model's
    targets = {name for name in convs if include_output or name not in outputs}
    if not targets:
        raise UserError(f"model {model.name} has no Conv2D layer to prune")
    sparsity_api = tfmot.sparsity.keras
    schedule = sparsity_api.ConstantSparsity(float(sparsity), begin_step=0, frequency=int(frequency))

    # tfmot wraps the layer objects it is given; clone first so the caller's weights stay intact.
    copy = keras.models.clone_model(model)
    copy.set_weights(model.get_weights())

    def wrap(layer):
        if layer.name in targets:
            return sparsity_api.prune_low_magnitude(layer, pruning_schedule=schedule)
        return layer

    wrapped = keras.models.clone_model(copy, clone_function=wrap)  # shares the copy's layers and weights
    with_facts_of(wrapped, model)  # the crop and keypoint names, for the file `train_fn` saves
    wrappers = [layer for layer in wrapped.layers if isinstance(layer, _prune_wrapper_type())]
    # Step 0 of the schedule: compute the masks from the current weights and apply them now.
    for layer in wrappers:
        layer.pruning_step.assign(0)
        layer.pruning_obj.conditional_mask_update()
        layer.pruning_obj.weight_mask_op()
    if train_fn is not None:
        train_fn(wrapped, [sparsity_api.UpdatePruningStep()])
        for layer in wrappers:  # the last optimizer step may have moved masked weights
            layer.pruning_obj.weight_mask_op()
    return with_facts_of(sparsity_api.strip_pruning(wrapped), model)


def _prune_wrapper_type() -> type:
    from tensorflow_model_optimization.python.core.sparsity.keras.pruning_wrapper import PruneLowMagnitude

    return PruneLowMagnitude


def weight_sparsity(model: keras.Model, layer_names: Iterable[str] | None = None) -> dict[str, float]:
    """Fraction of exactly-zero kernel weights of each Conv2D (or of the named layers).

    Args:
        model: a tf_keras model.
        layer_names: the Conv2D layers to measure; all of them if None.
    Returns:
        Layer name -> fraction of zeros in its kernel (biases are not counted), in layer order.
    Raises:
        UserError: a name that is no Conv2D layer of the model.
    """
    wanted = None if layer_names is None else set(layer_names)
    convs = {layer.name for layer in model.layers if type(layer) is keras.layers.Conv2D}
    if wanted is not None and wanted - convs:
        raise UserError(f"model {model.name} has no Conv2D layer named {', '.join(sorted(wanted - convs))}")
    result = {}
    for layer in model.layers:
        if type(layer) is keras.layers.Conv2D and (wanted is None or layer.name in wanted):
            kernel = layer.get_weights()[0]
            result[layer.name] = float(np.count_nonzero(kernel == 0) / kernel.size)
    return result
