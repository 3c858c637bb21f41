"""How wide every layer becomes at a rate, planned once per model before any surgery: the run's `WidthPlan`.

How many filters each Conv2D keeps is the paper's keep rule (`fcnpose_tf.compression.keep_rule`), with a floor
(`--min-filters`) at the same parameter budget; `plan_widths` computes the widths, the floor used, the parameters and
the MACs of the pruned network without building it, and every later step reads them (the surgery,
`fcnpose_tf.compression.prune`; a pruned start's check; magnitude pruning's sparsity; the recipe; the report). A plain
chain of layers is checked here, once (`check_chain`); a model with branches (FCN-Pose's skip, residual,
concatenating, depthwise) is planned per group of coupled channels (`fcnpose_tf.compression.depgraph`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.keep_rule import Rate, floored_widths
from fcnpose_tf.training.model import chain_layers

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

_SUPPORTED_NAMES = ("Conv2D, MaxPooling2D, AveragePooling2D, UpSampling2D, ZeroPadding2D, Cropping2D, "
                    "Activation, ReLU, LeakyReLU, ELU, Softmax, BatchNormalization and Dropout")


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
    """Refuse a model filter surgery cannot prune.

    Args:
        model: a tf_keras model.
    Raises:
        UserError: `model` is not one chain of the layers filter surgery understands with a Conv2D to prune.
    """
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


def chain_param_count(model: keras.Model, kept: Sequence[int]) -> int:
    """Parameters of `model` after its Conv2D layers but the last keep `kept` filters (no surgery done).

    Counts what the surgery leaves: each Conv2D's kernel (and bias) on the channels that reach it, and a
    BatchNormalization's per-channel weights on the channels that pass it; other layers have none here.

    Args:
        model: a plain chain (`check_chain`).
        kept: filters kept per Conv2D but the last, in order.
    Returns:
        The parameter count.
    """
    return _counter(model)(kept)[0]


def _counter(model: keras.Model, layers: Sequence[keras.layers.Layer] | None = None
             ) -> Callable[[Sequence[int]], tuple[int, int]]:
    """(parameters, MACs) of `model` after its Conv2D layers but the last keep the given counts; its chain read once
    (`layers`: the chain `_chain` read already).

    MACs are the convolutions' (`metrics.conv_macs`, as `model_facts` counts them): a layer's output size does not
    change with its width."""
    from fcnpose_tf.metrics import conv_macs

    layers = _chain(model) if layers is None else layers
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
    """How wide every Conv2D (every group of coupled channels, for a model that branches) becomes at a rate, computed
    once (`plan_widths`) and read by every step that needs it (the surgery, a pruned start's check, magnitude
    pruning's sparsity, the recipe, the report).

    Attributes:
        rate: the fraction of filters to remove asked for.
        min_filters: the narrowest layer asked for (0: the paper's keep rule).
        floor: the narrowest layer the parameter budget allowed (`floored_widths`; below min_filters only at high
            rates).
        widths: filters of every Conv2D after pruning, the output layer's (never pruned) last.
        params: parameters of the pruned network.
        macs: multiply-accumulates of its convolutions for one frame at the model's input size.
        group_counts: for a model that branches, what every prunable group keeps (`graph_prune.prunable_groups`
            order; None for a chain).
    """

    rate: float
    min_filters: int
    floor: int
    widths: tuple[int, ...]
    params: int
    macs: int
    group_counts: tuple[int, ...] | None = None

    @property
    def pruned_widths(self) -> tuple[int, ...]:
        """The widths of the layers that are pruned (every Conv2D but the output layer)."""
        return self.widths[:-1]


def plan_widths(model: keras.Model, rate: Rate, min_filters: int = 0, *, branches: bool = True) -> WidthPlan:
    """How many filters each Conv2D keeps at `rate`, with no layer under `min_filters` (`floored_widths`; 0: every
    layer keeps ``n - floor(n * rate)``), and what the pruned network costs; the model is not changed.

    A model that branches and merges (FCN-Pose with its skip, a residual block) is planned per group of coupled
    channels (`graph_prune.prunable_groups`): a group is one "layer" of the keep rule and of the floor, and
    `widths` holds one count per group of layer outputs, in the graph's order (for FCN-Pose-skip: conv1..conv9,
    skip2 sharing conv9's group, then conv10).

    Args:
        model: a tf_keras model.
        rate: the pruning rate, in [0, 1).
        min_filters: the floor (0: the paper's rule).
        branches: plan a model that branches per group of coupled channels; False refuses any model that is not
            one chain of the layers filter surgery understands (`check_chain`), as FCN-Pose without its skip is.
    Returns:
        The plan: rate, floor asked and used, widths, parameters and MACs.
    Raises:
        UserError: a bad rate or floor, or a model neither a plain chain of supported layers nor (with `branches`)
            a graph `depgraph.dependency_graph` understands.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose
        >>> plan = plan_widths(build_fcn_pose(), 0.7, 15)
        >>> plan.widths, plan.floor, plan.params
        ((15, 15, 15, 15, 8, 8, 15, 15, 15, 9), 15, 14611)
    """
    if branches and not is_chain(model):
        return _plan_graph_widths(model, rate, min_filters)
    layers = _chain(model)  # the chain checked once, here
    counter = _counter(model, layers)
    convs = [layer for layer in layers if type(layer) is keras.layers.Conv2D]
    kept, floor = floored_widths([conv.filters for conv in convs[:-1]], rate, min_filters,
                                 lambda counts: counter(counts)[0])
    params, macs = counter(kept)
    return WidthPlan(float(rate), int(min_filters), floor, (*kept, int(convs[-1].filters)), params, macs)


def is_chain(model: keras.Model) -> bool:
    """Whether `model` is wired as one unbranched chain (its layers are checked later, by the chain's planner).

    Args:
        model: a tf_keras model.
    Returns:
        True for one chain, False for a model that branches.
    """
    try:
        chain_layers(model, "filter pruning")
    except UserError:
        return False
    return True


def _plan_graph_widths(model: keras.Model, rate: Rate, min_filters: int) -> WidthPlan:
    from fcnpose_tf.compression.depgraph import dependency_graph
    from fcnpose_tf.compression.graph_prune import group_cost, prunable_groups

    graph = dependency_graph(model)
    groups = prunable_groups(graph)
    if not groups:
        raise UserError(f"model {model.name} has no channels to prune (every group is kept whole)")
    cost = group_cost(graph)
    kept, floor = floored_widths([group.width for group in groups], rate, min_filters, lambda c: cost(c)[0])
    params, macs = cost(kept)
    counts = dict(zip((group.index for group in groups), kept))
    widths = tuple(counts.get(group.index, group.width) for group in graph.groups
                   if not set(group.producers) & {key[0] for key in graph.inputs})
    return WidthPlan(float(rate), int(min_filters), floor, widths, params, macs if macs is not None else 0,
                     tuple(kept))
