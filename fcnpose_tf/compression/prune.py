"""Filter pruning with layer surgery (Li et al. 2017, as FCN-Pose applies it), and unstructured
magnitude pruning with tensorflow-model-optimization for comparison.

Structured pruning (`prune_model`) removes whole filters: every Conv2D except the output layer
keeps its ``n - floor(n * rate)`` filters that an importance criterion scores highest (default:
the L1 norm of the kernel, the paper's; `fcnpose_tf.compression.importance` holds the others), the network is rebuilt with
the narrower layers (``from_config`` plus sliced weights, as keras-surgeon does), and the next
Conv2D's kernel loses the matching input channels. Parameters, MACs, file size and latency all
shrink. Before retraining, the pruned model computes exactly what the original computes with the
removed channels deleted from the graph.

Unstructured pruning (`magnitude_prune`) zeroes the smallest weights of every kernel instead. The
tensors keep their shapes, so the parameter count and the latency stay the same; only a
compressed file (gzip) gets smaller. It exists so reports can show the two side by side.

Rates are fractions in [0, 1) of the filters to *remove*. The keep rule is the paper's (and
NNI's), ``n - floor(n * rate)``, which always keeps at least one filter; Torch-Pruning's
``floor(n * (1 - rate))`` keeps one fewer whenever ``n * rate`` is not a whole number.
"""

from __future__ import annotations

import math
import numbers
from decimal import Decimal
from fractions import Fraction
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence, Union

import numpy as np
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.importance import Importance, WeightNorm
from fcnpose_tf.training.model import chain_layers

Rate = Union[float, int, Fraction, Decimal, str]

STRATEGIES = ("independent", "greedy")

# Slack added to n * rate before flooring, for rates computed in floating point (0.1 * 7 and the
# like). Rates are first read exactly as the shortest decimal that prints as the float (0.29 ->
# 29/100), so a typed rate never needs it.
_RATE_SLACK = Fraction(1, 10**9)

# Layers the surgery understands. Channel-wise layers pass the kept-channel set through unchanged.
_CHANNELWISE = (
    keras.layers.MaxPooling2D,
    keras.layers.AveragePooling2D,
    keras.layers.UpSampling2D,
    keras.layers.ZeroPadding2D,
    keras.layers.Cropping2D,
    keras.layers.ReLU,
    keras.layers.LeakyReLU,
    keras.layers.ELU,
    keras.layers.Dropout,  # also SpatialDropout2D; identity at inference, channel-wise in training
)
# Activation functions that mix channels: allowed only where no channel has been removed.
_CHANNEL_MIXING_ACTIVATIONS = ("softmax", "log_softmax")

_SUPPORTED_NAMES = ("Conv2D, MaxPooling2D, AveragePooling2D, UpSampling2D, ZeroPadding2D, Cropping2D, "
                    "Activation, ReLU, LeakyReLU, ELU, Softmax, BatchNormalization and Dropout")


# --------------------------------------------------------------------------------------------
# The keep rule and the ranking
# --------------------------------------------------------------------------------------------

def _exact_rate(rate: Rate) -> Fraction:
    """The rate as an exact fraction, validated to lie in [0, 1)."""
    if isinstance(rate, bool):
        raise UserError(f"pruning rate must be a number in [0, 1), got {rate!r}")
    try:
        if isinstance(rate, str):
            value = Fraction(rate.strip())
        elif isinstance(rate, (Fraction, int)):
            value = Fraction(rate)
        elif isinstance(rate, Decimal):
            if not rate.is_finite():
                raise ValueError
            value = Fraction(rate)
        elif isinstance(rate, numbers.Real):
            if not math.isfinite(float(rate)):
                raise ValueError
            # repr of a float is the shortest decimal that reads back as it: 0.29 -> "0.29" -> 29/100.
            value = Fraction(repr(float(rate)))
        else:
            raise ValueError
    except (ValueError, ZeroDivisionError):
        raise UserError(f"pruning rate must be a number in [0, 1), got {rate!r}") from None
    if not 0 <= value < 1:
        raise UserError(f"pruning rate must be in [0, 1) (the fraction of filters removed), got {rate!r}")
    return value


def keep_count(n: int, rate: Rate) -> int:
    """Filters a layer of `n` filters keeps at `rate`: ``n - floor(n * rate)``, at least 1.

    The product is computed exactly (the rate is read as the decimal it prints as), so
    ``keep_count(100, 0.29) == 71`` although ``100 * 0.29`` is 28.999999999999996 in floating point.

    Args:
        n: the layer's filter count (positive).
        rate: fraction of filters to remove, in [0, 1); a float, int, Fraction, Decimal or a
            decimal string such as ``"0.7"``.
    Returns:
        The number of filters kept.
    Raises:
        UserError: if the rate is outside [0, 1) or not a number, or n is not positive.
    Example:
        >>> keep_count(128, 0.7), keep_count(8, 0.7), keep_count(64, 0.5)
        (39, 3, 32)
    """
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise UserError(f"filter count must be a positive integer, got {n!r}")
    removed = math.floor(int(n) * _exact_rate(rate) + _RATE_SLACK)
    return int(n) - min(int(removed), int(n) - 1)


def pruned_widths(widths: Iterable[int], rate: Rate) -> tuple[int, ...]:
    """The keep rule applied to each width, e.g. FCN-Pose's conv1..conv9 (not the output layer).

    Args:
        widths: filter counts of the layers that are pruned.
        rate: fraction of filters to remove, in [0, 1).
    Returns:
        The kept filter counts, in the same order.
    Raises:
        UserError: for a rate outside [0, 1) or a non-positive width.
    Example:
        >>> pruned_widths((128, 64, 32, 16, 8, 8, 16, 32, 64), 0.7)
        (39, 20, 10, 5, 3, 3, 5, 10, 20)
    """
    _exact_rate(rate)
    return tuple(keep_count(int(w), rate) for w in widths)


def filter_l1_norms(kernel: np.ndarray, input_channels: Sequence[int] | None = None) -> np.ndarray:
    """L1 norm of every filter of a Conv2D kernel (kh, kw, cin, cout): sum of |w| over kh, kw and cin.

    Args:
        kernel: the Conv2D kernel, shape (kh, kw, cin, cout).
        input_channels: if given, only these input channels count (the greedy strategy leaves out
            the channels the previous layer lost).
    Returns:
        A float64 array of length cout.
    """
    return WeightNorm(1).filter_scores(kernel, input_channels)


def kept_filters(kernel: np.ndarray, rate: Rate, input_channels: Sequence[int] | None = None) -> np.ndarray:
    """Indices of the filters a Conv2D keeps at `rate`: the largest L1 norms, in their original order.

    Ties in the norm go to the lower index, so the choice is deterministic.

    Args:
        kernel: the Conv2D kernel, shape (kh, kw, cin, cout).
        rate: fraction of filters to remove, in [0, 1).
        input_channels: rank only on these input channels (the greedy strategy); all if None.
    Returns:
        Sorted int64 indices, ``keep_count(cout, rate)`` of them.
    Raises:
        UserError: for a rate outside [0, 1) or a kernel that is not 4-D.
    Example:
        >>> k = np.zeros((1, 1, 1, 4)); k[..., :] = [3.0, -5.0, 1.0, 3.0]
        >>> kept_filters(k, 0.5).tolist()
        [0, 1]
    """
    return kept_by_score(filter_l1_norms(kernel, input_channels), rate)


def kept_by_score(scores: np.ndarray, rate: Rate) -> np.ndarray:
    """Indices of the ``keep_count(len(scores), rate)`` highest scores, in their original order.

    Ties go to the lower index, so the choice is deterministic.

    Example:
        >>> kept_by_score(np.array([0.2, 0.9, 0.2, 0.5]), 0.5).tolist()
        [1, 3]
    """
    return kept_top(scores, keep_count(len(np.atleast_1d(scores)), rate))


def kept_top(scores: np.ndarray, count: int) -> np.ndarray:
    """Indices of the `count` highest scores, in their original order; ties go to the lower index.

    Example:
        >>> kept_top(np.array([0.2, 0.9, 0.2, 0.5]), 3).tolist()
        [0, 1, 3]
    """
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 1 or not np.all(np.isfinite(scores)):
        raise UserError(f"filter scores must be a finite 1-D array, got shape {scores.shape}")
    if not 1 <= count <= len(scores):
        raise UserError(f"a layer of {len(scores)} filters cannot keep {count}")
    # Stable sort on the negated scores: largest first, equal scores in index order.
    order = np.argsort(-scores, kind="stable")
    return np.sort(order[:count]).astype(np.int64)


def floored_widths(widths: Sequence[int], rate: Rate, min_filters: int,
                   param_count: Callable[[tuple[int, ...]], int]) -> tuple[tuple[int, ...], int]:
    """Kept filter counts that leave no layer narrower than `min_filters`, at no more parameters than the keep rule's.

    The keep rule at `rate` leaves the narrow layers of an hourglass network (FCN-Pose's conv5 and conv6: 8
    filters) with 3 filters at 0.7, through which every keypoint's position has to pass. Here every layer keeps
    at least ``min(n, min_filters)`` filters and the others are pruned at the smallest rate >= `rate` at which the
    whole network has no more parameters than ``pruned_widths(widths, rate)`` gives it: the budget moves from the
    wide, high-resolution layers to the bottleneck. If no rate fits the budget with that floor (high rates), the
    floor is lowered one filter at a time; a floor of 1 is the keep rule itself.

    Args:
        widths: filter counts of the layers that are pruned, in order.
        rate: fraction of filters to remove, in [0, 1); sets the parameter budget.
        min_filters: the narrowest a layer may become (0 or 1: the plain keep rule).
        param_count: the network's parameter count for a tuple of kept counts (`chain_param_count`).
    Returns:
        (kept counts, the floor used).
    Example:
        >>> count = lambda kept: sum(kept)  # a toy cost: one parameter per filter
        >>> floored_widths((128, 64, 8), 0.7, 4, count)
        ((38, 19, 4), 4)
    """
    uniform = pruned_widths(widths, rate)
    if isinstance(min_filters, bool) or not isinstance(min_filters, numbers.Integral) or min_filters < 0:
        raise UserError(f"the narrowest layer width must be a whole number >= 0, got {min_filters!r}")
    if all(k >= min(n, min_filters) for n, k in zip(widths, uniform)):  # always so for a floor of 0 or 1
        return uniform, int(min_filters)
    budget = param_count(uniform)
    start = _exact_rate(rate)
    # Keep counts only change at rates m/n, so these are all the rates worth trying, in increasing order.
    rates = sorted({start} | {Fraction(m, n) for n in set(widths) for m in range(1, n) if Fraction(m, n) > start})
    for floor in range(int(min_filters), 1, -1):
        for candidate in rates:
            kept = tuple(max(keep_count(n, candidate), min(n, floor)) for n in widths)
            if param_count(kept) <= budget:
                return kept, floor
    return uniform, 1


# --------------------------------------------------------------------------------------------
# The chain of layers
# --------------------------------------------------------------------------------------------

def _unsupported(layer: keras.layers.Layer, why: str = "") -> UserError:
    return UserError(f"unsupported layer {layer.name} ({type(layer).__name__}){': ' + why if why else ''}; "
                     f"filter pruning handles a plain chain of {_SUPPORTED_NAMES} layers")


def _chain(model: keras.Model) -> list[keras.layers.Layer]:
    """The model's layers after its input, checked to form one unbranched chain of supported layers."""
    layers = chain_layers(model, "filter pruning", check_layer=_check_supported)
    if not any(type(layer) is keras.layers.Conv2D for layer in layers):
        raise UserError(f"model {model.name} has no Conv2D layer to prune")
    return layers


def check_chain(model: keras.Model) -> None:
    """UserError unless `model` is one chain of the layers filter surgery understands with a Conv2D to prune."""
    _chain(model)


def _check_supported(layer: keras.layers.Layer) -> None:
    if type(layer) is keras.layers.Conv2D:
        if layer.data_format != "channels_last":
            raise _unsupported(layer, "channels_first data format")
        if getattr(layer, "groups", 1) != 1:
            raise _unsupported(layer, f"grouped convolution (groups={layer.groups})")
        return
    if isinstance(layer, keras.layers.BatchNormalization):
        axis = layer.axis if isinstance(layer.axis, (list, tuple)) else [layer.axis]
        if [a % 4 for a in axis] != [3]:
            raise _unsupported(layer, f"normalises axis {layer.axis}, not the channel axis")
        return
    if isinstance(layer, (keras.layers.Activation, keras.layers.Softmax)):
        return
    if isinstance(layer, _CHANNELWISE):
        if getattr(layer, "data_format", "channels_last") != "channels_last":
            raise _unsupported(layer, "channels_first data format")
        return
    raise _unsupported(layer)


def _mixes_channels(layer: keras.layers.Layer) -> bool:
    if isinstance(layer, keras.layers.Softmax):
        return True
    if isinstance(layer, keras.layers.Activation):
        name = getattr(layer.activation, "__name__", str(layer.activation))
        return name in _CHANNEL_MIXING_ACTIVATIONS
    return False


def chain_param_count(model: keras.Model, kept: Sequence[int]) -> int:
    """Parameters of `model` after its Conv2D layers but the last keep `kept` filters (no surgery done).

    Counts what the surgery leaves: each Conv2D's kernel (and bias) on the channels that reach it, and a
    BatchNormalization's per-channel weights on the channels that pass it; other layers have none here.
    """
    return _counter(model)(kept)[0]


def _counter(model: keras.Model) -> Callable[[Sequence[int]], tuple[int, int]]:
    """(parameters, MACs) of `model` after its Conv2D layers but the last keep the given counts; its chain read once.

    MACs are the convolutions' (`metrics.conv_macs`, as `model_facts` counts them): a layer's output size does not
    change with its width."""
    from fcnpose_tf.metrics import conv_macs

    layers = _chain(model)
    pruned = sum(type(layer) is keras.layers.Conv2D for layer in layers) - 1
    steps = []  # (kernel area, bias?, filters, output pixels) of a Conv2D; (None, .., .., weights per channel) of BN
    for layer in layers:
        if type(layer) is keras.layers.Conv2D:
            height, width = layer.output_shape[1:3]
            steps.append((layer.kernel_size[0] * layer.kernel_size[1], layer.use_bias, layer.filters,
                          conv_macs(height, width, 1, 1, 1, 1)))
        elif isinstance(layer, keras.layers.BatchNormalization):
            steps.append((None, False, None, len(layer.get_weights())))
    channels_in = int(model.inputs[0].shape[-1])

    def count(kept: Sequence[int]) -> tuple[int, int]:
        if len(kept) != pruned:
            raise UserError(f"model {model.name} prunes {pruned} Conv2D layers, got {len(kept)} widths")
        widths, channels, params, macs = iter(kept), channels_in, 0, 0
        for area, bias, filters, extra in steps:
            if area is None:
                params += extra * channels
                continue
            width = next(widths, filters)  # the output layer keeps its filters
            params += area * channels * width + (width if bias else 0)
            macs += extra * area * channels * width
            channels = width
        return params, macs

    return count


@dataclass(frozen=True)
class WidthPlan:
    """How wide every Conv2D of a chain becomes at a rate, computed once (`plan_widths`) and read by every step that
    needs it (the surgery, a pruned start's check, magnitude pruning's sparsity, the recipe, the report).

    Attributes:
        rate: the fraction of filters to remove asked for.
        min_filters: the narrowest layer asked for (0: the paper's keep rule).
        floor: the narrowest layer the parameter budget allowed (`floored_widths`; below min_filters only at high
            rates).
        widths: filters of every Conv2D after pruning, the output layer's (never pruned) last.
        params: parameters of the pruned network.
        macs: multiply-accumulates of its convolutions for one frame at the model's input size.
    """

    rate: float
    min_filters: int
    floor: int
    widths: tuple[int, ...]
    params: int
    macs: int

    @property
    def pruned_widths(self) -> tuple[int, ...]:
        """The widths of the layers that are pruned (every Conv2D but the output layer)."""
        return self.widths[:-1]


def plan_widths(model: keras.Model, rate: Rate, min_filters: int = 0) -> WidthPlan:
    """How many filters each Conv2D keeps at `rate`, with no layer under `min_filters` (`floored_widths`; 0: every
    layer keeps ``n - floor(n * rate)``), and what the pruned network costs; the model is not changed.

    Raises:
        UserError: a bad rate or floor, or a model that is not a plain chain of supported layers.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose
        >>> plan = plan_widths(build_fcn_pose(), 0.7, 15)
        >>> plan.widths, plan.floor, plan.params
        ((15, 15, 15, 15, 8, 8, 15, 15, 15, 9), 15, 14611)
    """
    counter = _counter(model)
    convs = [layer for layer in _chain(model) if type(layer) is keras.layers.Conv2D]
    kept, floor = floored_widths([conv.filters for conv in convs[:-1]], rate, min_filters,
                                 lambda counts: counter(counts)[0])
    params, macs = counter(kept)
    return WidthPlan(float(rate), int(min_filters), floor, (*kept, int(convs[-1].filters)), params, macs)


def prune_plan(model: keras.Model, rate: Rate, *, strategy: str = "independent",
               importance: Importance | None = None, min_filters: int = 0,
               widths: WidthPlan | None = None) -> dict[str, np.ndarray]:
    """Which filters every Conv2D keeps at `rate`, without changing the model.

    Args:
        model: a built tf_keras model whose layers form one chain (see `prune_model`).
        rate: fraction of filters to remove per layer, in [0, 1).
        strategy: ``"independent"`` ranks each layer on its whole kernel; ``"greedy"`` ranks a layer
            after taking the input channels the previous Conv2D lost out of its kernel
            (Li et al. 2017, section 3.2; weight criteria only).
        importance: the criterion scoring each filter (`fcnpose_tf.compression.importance`); default the L1 norm.
        min_filters: no layer narrower than this (all its filters if it has fewer), the parameter budget
            of `rate` kept by pruning the other layers harder (`floored_widths`); 0 is the paper's rule.
        widths: the model's `plan_widths` at `rate` and `min_filters` when the caller has it (not computed again).
    Returns:
        Layer name -> sorted kept filter indices, for every Conv2D in order. The output layer (the
        last Conv2D) keeps all its filters.
    Raises:
        UserError: for a bad rate or strategy, a greedy strategy with a data-aware criterion, or a
            model that is not a plain chain of supported layers.
    """
    if strategy not in STRATEGIES:
        raise UserError(f"pruning strategy must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
    importance = importance if importance is not None else WeightNorm(1)
    greedy = strategy == "greedy"
    if greedy and not hasattr(importance, "filter_scores"):
        raise UserError(f"the greedy strategy ranks kernels without the removed input channels; the "
                        f"{importance.name} criterion does not rank kernels (use --strategy independent)")
    counts = (widths or plan_widths(model, rate, min_filters)).pruned_widths
    layers = _chain(model)
    convs = [layer for layer in layers if type(layer) is keras.layers.Conv2D]
    scores = None if greedy else importance(model)
    plan: dict[str, np.ndarray] = {}
    kept_in: np.ndarray | None = None  # input channels of the next Conv2D that survive
    for i, conv in enumerate(convs):
        if i == len(convs) - 1:
            kept = np.arange(conv.filters, dtype=np.int64)
        elif greedy:
            kept = kept_top(importance.filter_scores(conv.get_weights()[0], kept_in), counts[i])
        else:
            kept = kept_top(scores[conv.name], counts[i])
        plan[conv.name] = kept
        kept_in = kept
    return plan


# --------------------------------------------------------------------------------------------
# Surgery
# --------------------------------------------------------------------------------------------

def prune_model(model: keras.Model, rate: Rate, *, strategy: str = "independent",
                importance: Importance | None = None, min_filters: int = 0,
                widths: WidthPlan | None = None) -> keras.Model:
    """Remove the least important filters (default: smallest L1 norms) from every Conv2D but the output layer.

    Every Conv2D except the last keeps ``n - floor(n * rate)`` filters (the highest scores of
    `importance`, by default the L1 norms of their kernels, ties to the lower index, in their
    original order). The network is rebuilt with
    narrower layers and the kept weights: each Conv2D's kernel and bias lose the removed filters,
    the next Conv2D's kernel loses the matching input channels, and a BatchNormalization between
    them loses the same channels. Layer names, activations and all other settings are kept; the
    output layer keeps all its maps. The original model is not modified.

    The model must be one chain (functional or Sequential) of Conv2D, MaxPooling2D,
    AveragePooling2D, UpSampling2D, ZeroPadding2D, Cropping2D, Activation, ReLU, LeakyReLU, ELU,
    BatchNormalization and Dropout layers (softmax only where no channel was removed).

    Args:
        model: a built tf_keras model, e.g. from `fcnpose_tf.training.model.build_fcn_pose`.
        rate: fraction of filters to remove per layer, in [0, 1); 0 returns an identical copy.
        strategy: ``"independent"`` (default; each layer ranked on its original kernel) or
            ``"greedy"`` (a layer ranked without the input channels the previous layer lost),
            the two strategies Li et al. 2017 compare.
        importance: the criterion ranking the filters (`fcnpose_tf.compression.importance.make_importance`);
            None is the L1 norm, the paper's.
        min_filters: the narrowest a layer may become, the parameter budget of `rate` kept
            (`floored_widths`); 0 (default) is the paper's keep rule.
        widths: the model's `plan_widths` at `rate` and `min_filters` when the caller has it (not computed again).
    Returns:
        A new, uncompiled tf_keras model (Sequential if the input was) with the same layer names.
    Raises:
        UserError: for a rate outside [0, 1), an unknown strategy, or a model with a branch or an
            unsupported layer ("unsupported layer NAME (TYPE)").
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose, conv_widths
        >>> small = prune_model(build_fcn_pose(), 0.7)
        >>> conv_widths(small), small.count_params()
        ((39, 20, 10, 5, 3, 3, 5, 10, 20, 9), 14668)
    """
    plan = prune_plan(model, rate, strategy=strategy, importance=importance, min_filters=min_filters, widths=widths)
    layers = _chain(model)
    source = model.inputs[0]
    new_layers: list[keras.layers.Layer] = []
    new_weights: list[list[np.ndarray]] = []
    channels: np.ndarray | None = None  # kept channels of the tensor flowing; None = all of them
    for layer in layers:
        config = layer.get_config()
        config.pop("batch_input_shape", None)  # the rebuilt model gets its own Input
        weights = layer.get_weights()
        if type(layer) is keras.layers.Conv2D:
            kept = plan[layer.name]
            kernel = weights[0]
            if channels is not None:
                kernel = kernel[:, :, channels, :]
            weights = [kernel[..., kept]] + [w[kept] for w in weights[1:]]  # bias, if any
            config["filters"] = int(len(kept))
            channels = None if len(kept) == layer.filters else kept
        elif isinstance(layer, keras.layers.BatchNormalization):
            if channels is not None:
                weights = [w[channels] for w in weights]  # gamma, beta, moving mean and variance
        elif _mixes_channels(layer) and channels is not None:
            raise _unsupported(layer, "it mixes channels after some were pruned")
        try:
            new_layer = type(layer).from_config(config)
        except Exception as exc:  # a custom activation or regularizer that cannot be re-created
            raise UserError(f"layer {layer.name} ({type(layer).__name__}) cannot be rebuilt from its config: "
                            f"{type(exc).__name__}: {exc}") from exc
        new_layers.append(new_layer)
        new_weights.append(weights)

    shape = tuple(source.shape)
    inputs = keras.Input(batch_shape=shape, dtype=source.dtype, name=_input_name(model))
    if isinstance(model, keras.Sequential):
        pruned: keras.Model = keras.Sequential([inputs] + new_layers, name=model.name)
    else:
        x = inputs
        for new_layer in new_layers:
            x = new_layer(x)
        pruned = keras.Model(inputs, x, name=model.name)
    for new_layer, weights in zip(new_layers, new_weights):
        new_layer.set_weights(weights)
    return pruned


def _input_name(model: keras.Model) -> str:
    first = model.layers[0] if model.layers else None
    if isinstance(first, keras.layers.InputLayer):
        return first.name
    return model.inputs[0].name.split(":")[0]


# --------------------------------------------------------------------------------------------
# Unstructured magnitude pruning (tensorflow-model-optimization)
# --------------------------------------------------------------------------------------------

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
        include_output: also prune the output layer (the last Conv2D); off by default, as in
            `prune_model`. Biases are never pruned.
    Returns:
        A plain tf_keras model (wrappers stripped) with the same layers and names.
    Raises:
        UserError: for a sparsity outside [0, 1) or a model without a Conv2D to prune.
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
    convs = [layer.name for layer in model.layers if type(layer) is keras.layers.Conv2D]
    targets = set(convs if include_output else convs[:-1])
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
    return sparsity_api.strip_pruning(wrapped)


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
    """
    wanted = None if layer_names is None else set(layer_names)
    result = {}
    for layer in model.layers:
        if type(layer) is keras.layers.Conv2D and (wanted is None or layer.name in wanted):
            kernel = layer.get_weights()[0]
            result[layer.name] = float(np.count_nonzero(kernel == 0) / kernel.size)
    return result
