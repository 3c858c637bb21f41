"""Graph surgery on a dependency graph (`fcnpose_tf.compression.depgraph`): which channels every group keeps, and
the model rebuilt without the others.

`plan_graph` scores each group's channels (the aggregate over its producers of their filters' L1 or L2 norms, or a
caller's criterion), keeps ``n - floor(n * rate)`` of them per group (`keep_rule`; floored by ``min_filters``,
rounded up to ``round_to``) and counts parameters and MACs before and after; `rebuild` makes the narrower model in
the Keras it was built with; `prune_graph` is both.
"""

from __future__ import annotations

import copy
import math
import numbers
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any, Callable, Iterable, Mapping, Sequence, Union

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.keras_file import TF_KERAS
from fcnpose_tf.compression.layer_rules import rule_for
from fcnpose_tf.compression.depgraph import ChannelGroup, DependencyGraph, TracedOp, dependency_graph, short_list
from fcnpose_tf.compression.importance import WeightNorm
from fcnpose_tf.compression.keep_rule import Rate, exact_keep_count, exact_rate, kept_top
from fcnpose_tf.tables import format_table

AGGREGATES: dict[str, Callable[[np.ndarray], float]] = {"sum": np.sum, "mean": np.mean, "max": np.max}
"""How a group's channel importance is gathered from its producers' filter scores (`aggregate=`)."""
ImportanceLike = Union[str, WeightNorm, Callable[[Any], Mapping[str, np.ndarray]]]
"""l1, l2, a `WeightNorm`, or a callable(model) -> {layer name: filter scores}."""

# --------------------------------------------------------------------------------------------
# Importance and the plan
# --------------------------------------------------------------------------------------------

def _norm_scores(p: int) -> Callable[[DependencyGraph, str], np.ndarray]:
    def scores(graph: DependencyGraph, name: str) -> np.ndarray:
        layer = graph.layer(name)
        kernel = rule_for(layer, graph.keras).filter_kernel(layer.get_weights()).astype(np.float64)
        axes = tuple(range(kernel.ndim - 1))
        if p == 1:
            return np.abs(kernel).sum(axis=axes)
        return np.sqrt(np.square(kernel).sum(axis=axes))
    return scores


def _scorer(importance: ImportanceLike) -> Callable[[DependencyGraph, str], np.ndarray]:
    """Producer name -> its filters' scores, from "l1", "l2", a `WeightNorm` or a callable(model) -> {name: scores}."""
    if isinstance(importance, str):
        if importance not in ("l1", "l2"):
            raise UserError(f"importance must be l1, l2 or a callable giving each layer's filter scores, "
                            f"got {importance!r}")
        return _norm_scores(int(importance[1]))
    if isinstance(importance, WeightNorm):
        return _norm_scores(importance.p)
    if not callable(importance):
        raise UserError(f"importance must be l1, l2 or a callable giving each layer's filter scores, "
                        f"got {type(importance).__name__}")
    tables: dict[int, Mapping[str, np.ndarray]] = {}  # the criterion runs once per graph

    def scores(graph: DependencyGraph, name: str) -> np.ndarray:
        if id(graph) not in tables:
            tables[id(graph)] = importance(graph.model)
        table = tables[id(graph)]
        if name not in table:
            raise UserError(f"the importance criterion gave no scores for layer {name}")
        return np.asarray(table[name], dtype=np.float64)
    return scores


@dataclass(frozen=True)
class GroupPlan:
    """A group with the channels it keeps (positions 0..width-1, sorted) and their importance."""

    group: ChannelGroup
    kept: np.ndarray
    scores: np.ndarray | None = field(default=None, repr=False)

    def filters(self, producer: str) -> np.ndarray:
        """The kept filter indices of one of the group's producers.

        Args:
            producer: the name of a layer making the group's channels.
        Returns:
            Its kept output filters, sorted, int64.
        Raises:
            KeyError: not a producer of this group.
        """
        return np.flatnonzero(np.isin(self.group.channel_of[producer], self.kept)).astype(np.int64)


@dataclass(frozen=True)
class LayerChannels:
    """What one layer reads and writes after pruning: kept positions on each input's and the output's last axis."""

    kept_in: tuple[np.ndarray, ...]
    kept_out: np.ndarray
    params: tuple[int, int]  # before, after
    macs: tuple[int | None, int | None]  # before, after (None: unknown spatial size)


@dataclass(frozen=True)
class GraphPlan:
    """What `prune_graph` does to a model, computed without doing it (`plan_graph`).

    Attributes:
        graph: the `DependencyGraph`.
        groups: a `GroupPlan` per group, in the graph's order.
        layers: layer name -> its `LayerChannels`, for every layer after the inputs.
        params: parameters (trainable and not) before and after.
        macs: multiply-accumulates per sample of the convolutions and Dense layers before and after (None if a
            spatial size is unknown).
    """

    graph: DependencyGraph = field(repr=False)
    groups: tuple[GroupPlan, ...]
    layers: dict[str, LayerChannels] = field(repr=False)
    params: tuple[int, int]
    macs: tuple[int | None, int | None]

    def kept_filters(self) -> dict[str, np.ndarray]:
        """Which filters every layer making channels keeps.

        Returns:
            Producer name -> its kept filter indices (model inputs left out).
        """
        result = {}
        for plan in self.groups:
            for producer in plan.group.producers:
                if producer in self.layers:
                    result[producer] = plan.filters(producer)
        return result

    def describe(self) -> str:
        """The plan for reading.

        Returns:
            A plain-text table of the groups (producers, channels before and after, status), then the parameters
            and MACs before and after.
        """
        rows = [[p.group.index, short_list(p.group.producers), p.group.width, int(len(p.kept)),
                 p.group.frozen or "pruned"] for p in self.groups]
        table = format_table(["group", "producers", "channels", "kept", "status"], rows)
        return "\n".join([table, f"parameters {_change(*self.params)}", f"MACs {_change(*self.macs)}"])


def _change(before: int | None, after: int | None) -> str:
    if before is None or after is None:
        return "unknown (an input of unknown size)"
    share = f" ({after / before:.1%})" if before else ""
    return f"{before:,} -> {after:,}{share}"


def _check_count(value: Any, what: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise UserError(f"{what} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def _group_keep_count(width: int, rate: Fraction, min_filters: int, round_to: int, blocks: int = 1) -> int:
    count = max(exact_keep_count(int(width), rate), min(width, min_filters))
    step = math.lcm(round_to, blocks)  # a grouped convolution keeps as many channels in each block
    return min(width, math.ceil(count / step) * step)


def _kept_in_blocks(group: ChannelGroup, scores: np.ndarray, count: int) -> np.ndarray:
    """The `count` best channels of a group, as many from each block of a grouped convolution."""
    if group.block_of is None:
        return kept_top(scores, count)
    if count % group.blocks:
        raise UserError(f"layers {short_list(group.producers)} feed or form a grouped convolution of {group.blocks} "
                        f"groups: they keep a multiple of {group.blocks} channels, not {count}")
    kept = [np.flatnonzero(group.block_of == b)[kept_top(scores[group.block_of == b], count // group.blocks)]
            for b in range(group.blocks)]
    return np.sort(np.concatenate(kept)).astype(np.int64)


def plan_graph(model: Any, rate: Rate, *, importance: ImportanceLike = "l1", aggregate: str = "sum",
               min_filters: int = 0, round_to: int = 1, keep: Iterable[str] = (),
               counts: Sequence[int] | None = None) -> GraphPlan:
    """Which channels every group keeps at `rate`, and the parameters and MACs before and after; no surgery.

    Args:
        model: a built tf_keras or Keras 3 model (see `dependency_graph`).
        rate: fraction of each group's channels to remove, in [0, 1): a group of n keeps ``n - floor(n * rate)``.
        importance: "l1" (default) or "l2" (norm of each producer's filter, bias excluded), a `WeightNorm`, or a
            callable ``importance(model) -> {layer name: score per filter}`` covering every producer of a
            prunable group.
        aggregate: how a coupled channel's score is made from its producers' filter scores: "sum", "mean" or "max".
        min_filters: no group narrower than ``min(n, min_filters)`` (0: the keep rule alone).
        round_to: kept counts rounded up to a multiple of this (capped at n), e.g. 8 for SIMD-friendly widths.
        keep: names of layers whose channels are all kept.
        counts: how many channels each prunable group keeps, in the graph's order (`prunable_groups`), instead of
            the keep rule (rate, min_filters and round_to then unused): a plan made elsewhere, such as
            `plan.plan_widths`' parameter budget.
    Returns:
        The `GraphPlan`.
    Raises:
        UserError: for a bad rate (read only without `counts`), importance, aggregate, min_filters, round_to or
            counts, or a model `dependency_graph` refuses.
    """
    exact = exact_rate(rate) if counts is None else None  # read once, before every group's count; counts: read already
    if aggregate not in AGGREGATES:
        raise UserError(f"aggregate must be one of {', '.join(AGGREGATES)}, got {aggregate!r}")
    min_filters = _check_count(min_filters, "min_filters", 0)
    round_to = _check_count(round_to, "round_to", 1)
    scorer = _scorer(importance)
    graph = dependency_graph(model, keep)
    wanted = _checked_counts(graph, counts) if counts is not None else \
        [_group_keep_count(group.width, exact, min_filters, round_to, group.blocks) for group in prunable_groups(graph)]
    plans, wanted = [], iter(wanted)
    for group in graph.groups:
        if group.frozen:
            plans.append(GroupPlan(group, np.arange(group.width, dtype=np.int64)))
            continue
        scores = _group_scores(graph, group, scorer, AGGREGATES[aggregate])
        plans.append(GroupPlan(group, _kept_in_blocks(group, scores, next(wanted)), scores))
    return _finished(graph, plans)


def prunable_groups(graph: DependencyGraph) -> list[ChannelGroup]:
    """The groups a plan may narrow (not frozen), in the graph's order: what `counts=` lists.

    Args:
        graph: the model's dependency graph (`depgraph.dependency_graph`).
    Returns:
        The groups.
    """
    return [group for group in graph.groups if not group.frozen]


def _checked_counts(graph: DependencyGraph, counts: Sequence[int]) -> list[int]:
    groups = prunable_groups(graph)
    counts = [_check_count(count, "a group's kept count", 1) for count in counts]
    if len(counts) != len(groups) or any(count > group.width for count, group in zip(counts, groups)):
        raise UserError(f"counts must give each of the {len(groups)} prunable groups of model {graph.model.name} "
                        f"(widths {[group.width for group in groups]}) at most its width, got {counts}")
    return counts


def group_cost(graph: DependencyGraph) -> Callable[[Sequence[int]], tuple[int, int | None]]:
    """The cost of the graph's model at given counts, without choosing the channels: it does not depend on which are
    kept.

    Args:
        graph: the model's dependency graph.
    Returns:
        A function of the counts each prunable group keeps (in `prunable_groups` order) giving (parameters, MACs per
        sample; None for an unknown spatial size).
    """
    def cost(counts: Sequence[int]) -> tuple[int, int | None]:
        wanted = iter(_checked_counts(graph, counts))
        plans = [GroupPlan(group, np.arange(group.width, dtype=np.int64) if group.frozen else
                           _kept_in_blocks(group, np.zeros(group.width), next(wanted)))  # the first of each block
                 for group in graph.groups]
        plan = _finished(graph, plans)
        return plan.params[1], plan.macs[1]
    return cost


def plan_kept(model: Any, kept: Mapping[str, np.ndarray]) -> GraphPlan:
    """The plan that keeps the given filters of the named producers, and every channel of the others: how chain
    surgery (`prune.prune_model`, whose widths and ranking are its own) is carried out by the one rebuild.

    Args:
        model: the model to prune.
        kept: producer layer name -> the indices of its filters to keep (every producer of a coupled group named
            with the same channels, or only one of them).
    Returns:
        The plan (`rebuild` makes its model).
    Raises:
        UserError: a name that produces no group's channels, producers of one group kept apart, or a frozen group
            (an output, an input, a channel-mixing layer) asked to lose channels.
    """
    graph = dependency_graph(model)
    named = set(kept)
    plans = []
    for group in graph.groups:
        chosen = {tuple(np.sort(group.channel_of[p][np.asarray(kept[p], dtype=np.int64)]).tolist())
                  for p in group.producers if p in kept}
        named -= set(group.producers)
        if len(chosen) > 1:
            raise UserError(f"layers {', '.join(p for p in group.producers if p in kept)} share their channels "
                            "(one group) but were given different filters to keep")
        positions = np.array(next(iter(chosen)), dtype=np.int64) if chosen else np.arange(group.width, dtype=np.int64)
        if group.frozen and len(positions) < group.width:
            raise UserError(f"layers {short_list(group.producers)} cannot lose channels: {group.frozen}")
        if group.block_of is not None and len(set(np.bincount(group.block_of[positions],
                                                              minlength=group.blocks).tolist())) > 1:
            raise UserError(f"layers {short_list(group.producers)} feed or form a grouped convolution of "
                            f"{group.blocks} groups: they keep as many channels in each group")
        plans.append(GroupPlan(group, positions))
    if named:
        raise UserError(f"no layer of model {graph.model.name} makes channels named {', '.join(sorted(named))}")
    return _finished(graph, plans)


def _finished(graph: DependencyGraph, plans: list[GroupPlan]) -> GraphPlan:
    """The plan of these groups' kept channels: every layer's kept inputs and outputs, parameters and MACs."""
    layers = _layer_channels(graph, plans)
    totals = [sum(entry.params[i] for entry in layers.values()) for i in (0, 1)]
    macs = [[entry.macs[i] for entry in layers.values()] for i in (0, 1)]
    return GraphPlan(graph, tuple(plans), layers, (totals[0], totals[1]),
                     tuple(None if None in m else int(sum(m)) for m in macs))


def _group_scores(graph: DependencyGraph, group: ChannelGroup, scorer, reduce) -> np.ndarray:
    """Each group channel's score: `reduce` over the producers' filters that make it."""
    per_channel: list[list[float]] = [[] for _ in range(group.width)]
    for producer in group.producers:
        scores = scorer(graph, producer)
        positions = group.channel_of[producer]
        if scores.shape != positions.shape or not np.all(np.isfinite(scores)):
            raise UserError(f"the importance criterion gave {scores.shape} scores for layer {producer}, "
                            f"expected {len(positions)} finite ones")
        for position, score in zip(positions.tolist(), scores.tolist()):
            per_channel[position].append(score)
    return np.array([reduce(np.array(values, dtype=np.float64)) for values in per_channel])


def _layer_channels(graph: DependencyGraph, plans: list[GroupPlan]) -> dict[str, LayerChannels]:
    alive = np.ones(graph.size, dtype=bool)  # per graph-wide channel
    for plan in plans:
        for producer in plan.group.producers:
            channels = graph.channels_of(producer)
            alive[channels] = np.isin(np.arange(len(channels)), plan.filters(producer))
    layers = {}
    for op in graph.ops:
        kept_in = tuple(np.flatnonzero(alive[graph.maps[key]]).astype(np.int64) for key in op.inputs)
        kept_out = np.flatnonzero(alive[graph.maps[op.output]]).astype(np.int64)
        weights = weights_of(op.layer)
        sliced = op.rule.slice_weights(op.layer, weights, list(kept_in), kept_out)
        widths_in = [shape[-1] for shape in op.in_shapes]
        macs = (op.rule.macs(op.layer, op.in_shapes, op.out_shape, widths_in, op.out_shape[-1]),
                op.rule.macs(op.layer, op.in_shapes, op.out_shape, [len(k) for k in kept_in], len(kept_out)))
        layers[op.layer.name] = LayerChannels(kept_in, kept_out, (sum(int(w.size) for w in weights),
                                                                  sum(int(w.size) for w in sliced)), macs)
    return layers


# --------------------------------------------------------------------------------------------
# Surgery
# --------------------------------------------------------------------------------------------

def prune_graph(model: Any, rate: Rate, *, importance: ImportanceLike = "l1", aggregate: str = "sum",
                min_filters: int = 0, round_to: int = 1, keep: Iterable[str] = ()) -> Any:
    """Remove the least important channels of every prunable group and rebuild the model with narrower layers.

    Args:
        model: a built tf_keras or Keras 3 model (functional or Sequential, channels_last); not modified.
        rate, importance, aggregate, min_filters, round_to, keep: as in `plan_graph`.
    Returns:
        A new, uncompiled model of the same Keras (Sequential if the input was) with the same layer names.
    Raises:
        UserError: as `plan_graph`, or a layer that cannot be rebuilt from its config.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose, conv_widths
        >>> conv_widths(prune_graph(build_fcn_pose(), 0.7))
        (39, 20, 10, 5, 3, 3, 5, 10, 20, 9)
    """
    plan = plan_graph(model, rate, importance=importance, aggregate=aggregate, min_filters=min_filters,
                      round_to=round_to, keep=keep)
    return rebuild(plan)


def rebuild(plan: GraphPlan) -> Any:
    """The plan's model rebuilt with the kept channels only (what `prune_graph` returns).

    Args:
        plan: the channels each group keeps (`plan_graph`, `plan_kept`).
    Returns:
        The pruned model, of the Keras that built the original; a tf_keras model keeps the view and keypoint schema
        the original was given (`training.model.with_facts_of`).
    Raises:
        UserError: for a layer that cannot be re-created from its config.
    """
    graph = plan.graph
    keras, model = graph.keras, graph.model
    tensors: dict[tuple, Any] = {}
    for key, tensor in graph.inputs.items():
        tensors[key] = keras.Input(batch_shape=tuple(tensor.shape), dtype=tensor.dtype, name=key[0])
    new_layers = [_narrowed(op, plan.layers[op.layer.name]) for op in graph.ops]
    if isinstance(model, keras.Sequential):
        (first,) = tensors.values()
        pruned = keras.Sequential([first] + [layer for layer, _ in new_layers], name=model.name)
    else:
        for op, (layer, _) in zip(graph.ops, new_layers):  # called as the original was, on the new tensors
            tensors[op.output] = layer(*_substituted(op.args, tensors, graph), **_substituted(op.kwargs, tensors, graph))
        inputs = [tensors[graph.key(t)] for t in model.inputs]
        outputs = [tensors[graph.key(t)] for t in model.outputs]
        pruned = keras.Model(inputs if len(inputs) > 1 else inputs[0],
                             outputs if len(outputs) > 1 else outputs[0], name=model.name)
    for layer, weights in new_layers:
        if weights:
            layer.set_weights(weights)
    if keras.__name__ == TF_KERAS:  # an FCN-Pose's crop and keypoint names go with it
        from fcnpose_tf.training.model import with_facts_of

        with_facts_of(pruned, model)
    return pruned


def _narrowed(op: TracedOp, entry: LayerChannels) -> tuple[Any, list[np.ndarray]]:
    """A new layer like `op`'s for the kept channels, and its sliced weights (set once the layer is built)."""
    config = copy.deepcopy(op.layer.get_config())
    for name in ("batch_input_shape", "batch_shape", "input_shape"):
        config.pop(name, None)
    config = op.rule.new_config(op.layer, config, list(entry.kept_in), entry.kept_out)
    try:
        layer = type(op.layer).from_config(config)
    except Exception as exc:  # a custom activation or regularizer that cannot be re-created
        raise UserError(f"layer {op.layer.name} ({type(op.layer).__name__}) cannot be rebuilt from its "
                        f"config: {type(exc).__name__}: {exc}") from exc
    weights = op.rule.slice_weights(op.layer, weights_of(op.layer), list(entry.kept_in), entry.kept_out)
    return layer, weights


def weights_of(layer: Any) -> list[np.ndarray]:
    """A layer's weights (`get_weights()`); none for a Keras 3 operation on tensors (``x + 3.0``), not a layer.

    Args:
        layer: a layer or operation of a functional model.
    Returns:
        Its weights.
    """
    return layer.get_weights() if hasattr(layer, "get_weights") else []


def _substituted(value: Any, tensors: dict[tuple, Any], graph: DependencyGraph) -> Any:
    """A call's arguments with every symbolic tensor of the original model replaced by the rebuilt model's."""
    if hasattr(value, "_keras_history"):
        return tensors[graph.key(value)]
    if isinstance(value, tuple):
        return tuple(_substituted(item, tensors, graph) for item in value)
    if isinstance(value, list):
        return [_substituted(item, tensors, graph) for item in value]
    if isinstance(value, dict):
        return {key: _substituted(item, tensors, graph) for key, item in value.items()}
    return value
