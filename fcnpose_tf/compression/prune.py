"""Filter pruning with layer surgery (Li et al. 2017, as FCN-Pose applies it): the plan, and the chain's ranking.

Structured pruning (`prune_model`) removes whole filters: every Conv2D except the output layer
keeps its ``n - floor(n * rate)`` filters that an importance criterion scores highest (default:
the L1 norm of the kernel, the paper's; `fcnpose_tf.compression.importance` holds the others), the network is rebuilt with
the narrower layers (``from_config`` plus sliced weights, as keras-surgeon does), and the next
Conv2D's kernel loses the matching input channels. Parameters, MACs, file size and latency all
shrink. Before retraining, the pruned model computes exactly what the original computes with the
removed channels deleted from the graph.

How many filters each layer keeps is the paper's keep rule (`fcnpose_tf.compression.keep_rule`), planned once per
model and rate (`plan_widths`: a `WidthPlan`). A model with branches (FCN-Pose's skip, residual, concatenating,
depthwise) is planned the same way per group of coupled channels (`fcnpose_tf.compression.depgraph`) and cut by the
same rebuild; tensorflow-model-optimization's unstructured pruning is `fcnpose_tf.compression.magnitude`'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.importance import Importance, WeightNorm
from fcnpose_tf.compression.keep_rule import Rate, floored_widths, kept_top
from fcnpose_tf.training.model import chain_layers

STRATEGIES = ("independent", "greedy")

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
    if branches and not _is_chain(model):
        return _plan_graph_widths(model, rate, min_filters)
    layers = _chain(model)  # the chain checked once, here
    counter = _counter(model, layers)
    convs = [layer for layer in layers if type(layer) is keras.layers.Conv2D]
    kept, floor = floored_widths([conv.filters for conv in convs[:-1]], rate, min_filters,
                                 lambda counts: counter(counts)[0])
    params, macs = counter(kept)
    return WidthPlan(float(rate), int(min_filters), floor, (*kept, int(convs[-1].filters)), params, macs)


def _is_chain(model: keras.Model) -> bool:
    """Whether `model` is wired as one unbranched chain (its layers are checked later, by the chain's planner)."""
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
        widths: the model's `plan_widths` at `rate` and `min_filters` when the caller has it (not computed again, and
            the chain it checked not checked again).
    Returns:
        Layer name -> sorted kept filter indices, for every Conv2D in order. The output layer (the
        last Conv2D) keeps all its filters.
    Raises:
        UserError: for a bad rate or strategy, a greedy strategy with a data-aware criterion, or a
            model that is not a plain chain of supported layers.
        ValueError: `widths` planned for a model with another number of Conv2D layers.
    """
    if strategy not in STRATEGIES:
        raise UserError(f"pruning strategy must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
    importance = importance if importance is not None else WeightNorm(1)
    greedy = strategy == "greedy"
    if greedy and not hasattr(importance, "filter_scores"):
        raise UserError(f"the greedy strategy ranks kernels without the removed input channels; the "
                        f"{importance.name} criterion does not rank kernels (use --strategy independent)")
    # the chain is checked once, by its plan: the caller's (`plan_widths` of this model), or the one made here
    counts = (widths or plan_widths(model, rate, min_filters, branches=False)).pruned_widths
    convs = [layer for layer in model.layers if type(layer) is keras.layers.Conv2D]
    if len(convs) != len(counts) + 1:
        raise ValueError(f"a plan of {len(counts) + 1} Conv2D layers for model {model.name}, which has {len(convs)}")
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

    A chain (functional or Sequential) of Conv2D, MaxPooling2D, AveragePooling2D, UpSampling2D, ZeroPadding2D,
    Cropping2D, Activation, ReLU, LeakyReLU, ELU, BatchNormalization and Dropout layers (softmax only where no
    channel was removed) is ranked layer by layer. A model that branches and merges (FCN-Pose with its skip)
    is ranked per group of coupled channels (`graph_prune.plan_graph`: the group's producers' scores summed),
    each group keeping the `plan_widths` count, with the independent strategy only.

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
        UserError: for a rate outside [0, 1), an unknown strategy, or a model with an unsupported layer
            ("unsupported layer NAME (TYPE)") or wiring (a shared layer, a nested model).
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose, conv_widths
        >>> small = prune_model(build_fcn_pose(), 0.7)
        >>> conv_widths(small), small.count_params()
        ((39, 20, 10, 5, 3, 3, 5, 10, 20, 9), 14668)
    """
    from fcnpose_tf.compression.graph_prune import plan_graph, plan_kept, rebuild

    branching = widths.group_counts is not None if widths is not None else not _is_chain(model)  # the plan knows
    if branching:  # a branching model: the plan's counts per group of coupled channels
        if strategy != "independent":
            raise UserError(f"the {strategy} strategy ranks a chain of layers; model {model.name} branches "
                            "(use --strategy independent)")
        widths = widths or plan_widths(model, rate, min_filters)
        return rebuild(plan_graph(model, rate, importance=importance or WeightNorm(1), counts=widths.group_counts))
    plan = prune_plan(model, rate, strategy=strategy, importance=importance, min_filters=min_filters, widths=widths)
    return rebuild(plan_kept(model, plan))  # the one surgery (graph_prune), on the filters the chain's plan keeps
