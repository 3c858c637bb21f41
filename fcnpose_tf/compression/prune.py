"""Filter pruning with layer surgery (Li et al. 2017, as FCN-Pose applies it): the chain's ranking, at a plan's widths.

Structured pruning (`prune_model`) removes whole filters: every Conv2D except the output layer
keeps its ``n - floor(n * rate)`` filters that an importance criterion scores highest (default:
the L1 norm of the kernel, the paper's; `fcnpose_tf.compression.importance` holds the others), the network is rebuilt with
the narrower layers (``from_config`` plus sliced weights, as keras-surgeon does), and the next
Conv2D's kernel loses the matching input channels. Parameters, MACs, file size and latency all
shrink. Before retraining, the pruned model computes exactly what the original computes with the
removed channels deleted from the graph.

How many filters each layer keeps is the paper's keep rule (`fcnpose_tf.compression.keep_rule`), planned once per
model and rate before any surgery (`fcnpose_tf.compression.plan`: a `WidthPlan`). A model with branches (FCN-Pose's
skip, residual, concatenating, depthwise) is planned the same way per group of coupled channels
(`fcnpose_tf.compression.depgraph`) and cut by the same rebuild; tensorflow-model-optimization's unstructured pruning
is `fcnpose_tf.compression.magnitude`'s.
"""

from __future__ import annotations

import numpy as np
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.importance import Importance, WeightNorm
from fcnpose_tf.compression.keep_rule import Rate, kept_top
from fcnpose_tf.compression.plan import WidthPlan, is_chain, plan_widths

STRATEGIES = ("independent", "greedy")


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
        widths: the model's `plan_widths` at `rate` and `min_filters` when the caller has it (not computed again, and
            the rate it read not read again).
    Returns:
        A new, uncompiled tf_keras model (Sequential if the input was) with the same layer names.
    Raises:
        UserError: for a rate outside [0, 1) (without `widths`), an unknown strategy, or a model with an unsupported
            layer ("unsupported layer NAME (TYPE)") or wiring (a shared layer, a nested model).
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose, conv_widths
        >>> small = prune_model(build_fcn_pose(), 0.7)
        >>> conv_widths(small), small.count_params()
        ((39, 20, 10, 5, 3, 3, 5, 10, 20, 9), 14668)
    """
    from fcnpose_tf.compression.graph_prune import plan_graph, plan_kept, rebuild

    branching = widths.group_counts is not None if widths is not None else not is_chain(model)  # the plan knows
    if branching:  # a branching model: the plan's counts per group of coupled channels
        if strategy != "independent":
            raise UserError(f"the {strategy} strategy ranks a chain of layers; model {model.name} branches "
                            "(use --strategy independent)")
        widths = widths or plan_widths(model, rate, min_filters)
        return rebuild(plan_graph(model, rate, importance=importance or WeightNorm(1), counts=widths.group_counts))
    plan = prune_plan(model, rate, strategy=strategy, importance=importance, min_filters=min_filters, widths=widths)
    return rebuild(plan_kept(model, plan))  # the one surgery (graph_prune), on the filters the chain's plan keeps
