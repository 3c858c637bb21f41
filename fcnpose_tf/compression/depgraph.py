"""Filter surgery for any Keras CNN: a dependency graph of coupled channels (as Torch-Pruning's DepGraph).

`fcnpose_tf.compression.prune` removes filters from a plain chain of layers. Here the model may branch and merge:
the channels a model computes are traced through its graph (`dependency_graph`) and gathered into *groups* of
channels that must go together. The filters of every layer whose outputs meet in an elementwise merge (Add,
Subtract, Multiply, ...) form one group, coupled channel by channel; a Concatenate on the channel axis puts its
inputs' channels side by side, each keeping its own group, and its consumers read them at their offsets; a
Flatten before a Dense repeats the channels at every spatial position (the Dense loses rows ``c + C * k``).
`fcnpose_tf.compression.channel_rules` holds what each layer type does to channels.

Every group of n channels keeps ``n - floor(n * rate)`` of them (the paper's keep rule, `keep_rule.keep_count`), the
ones whose importance is highest: the importance of a channel is the aggregate (sum, mean or max) over the layers
producing it of their filter's score (L1 or L2 norm of the filter's kernel slice, bias excluded). Per-channel
layers (BatchNormalization, DepthwiseConv2D, PReLU) do not score: they are not producers, their weights are
sliced with their channel. A group is not pruned (it is *frozen*) if its channels reach a model output, come
from a model input, pass a layer that mixes channels (Softmax or a softmax activation over channels,
LayerNormalization over channels), or belong to a layer the caller keeps whole (``keep=``).

`plan_graph` chooses the kept channels and counts parameters and multiply-accumulates before and after without
touching the model; `prune_graph` rebuilds the model with the narrower layers (``from_config`` plus sliced
weights), in the Keras it was built with (tf_keras in, tf_keras out; Keras 3 in, Keras 3 out). Before
retraining, the pruned model computes exactly what the original computes with the removed channels deleted.

For a plain chain (FCN-Pose) every Conv2D is its own group and the output layer is frozen, so `prune_graph` with
the L1 importance gives `prune.prune_model`'s result. Unlike `prune.prune_model`'s ``min_filters``, which keeps the
parameter budget of the rate by pruning other layers harder, ``min_filters`` here only floors each group's width.
"""

from __future__ import annotations

import copy
import importlib
import math
import numbers
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable, Iterable, Mapping, Union

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.channel_rules import Context, Rule, rule_for
from fcnpose_tf.compression.importance import WeightNorm
from fcnpose_tf.compression.keep_rule import Rate, keep_count, kept_top
from fcnpose_tf.tables import format_table

AGGREGATES: dict[str, Callable[[np.ndarray], float]] = {"sum": np.sum, "mean": np.mean, "max": np.max}
ImportanceLike = Union[str, WeightNorm, Callable[[Any], Mapping[str, np.ndarray]]]


# --------------------------------------------------------------------------------------------
# The model's graph, whichever Keras built it
# --------------------------------------------------------------------------------------------

def keras_of(model: Any) -> ModuleType:
    """The Keras module `model` was built with: ``tf_keras`` (Keras 2) or ``keras`` (Keras 3).

    Raises:
        UserError: for an object that is not a model of either, or a model without inputs (not built).
    """
    package = type(model).__module__.split(".")[0]
    if package not in ("tf_keras", "keras"):
        raise UserError(f"expected a tf_keras or Keras 3 model, got {type(model).__name__} from {package}")
    keras = importlib.import_module(package)
    if not isinstance(model, keras.Model):
        raise UserError(f"expected a Keras model, got {type(model).__name__}")
    if not getattr(model, "inputs", None) or not getattr(model, "outputs", None):
        raise UserError(f"model {model.name} is not built: give it an input shape (keras.Input) first")
    return keras


@dataclass
class _Op:
    """One call of a layer in the model: the tensors it reads and the one it makes (keys), with their shapes."""

    layer: Any
    rule: Rule
    inputs: list[tuple]
    output: tuple
    in_shapes: list[tuple]
    out_shape: tuple


def _key(tensor: Any) -> tuple:
    layer, node_index, tensor_index = tensor._keras_history
    return (layer.name, int(node_index), int(tensor_index))


def _listed(value: Any) -> list:
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _trace(model: Any, keras: ModuleType) -> tuple[dict[tuple, Any], list[_Op]]:
    """The model's input tensors by key, and its layer calls in an order where every input comes first."""
    inputs: dict[tuple, Any] = {}
    ops: dict[tuple, _Op] = {}
    order: list[_Op] = []
    calls: dict[str, tuple] = {}  # layer name -> its node, to refuse shared layers
    stack = [(tensor, False) for tensor in reversed(model.outputs)]
    while stack:
        tensor, ready = stack.pop()
        key = _key(tensor)
        if key in ops or key in inputs:
            continue
        layer = tensor._keras_history[0]
        if isinstance(layer, keras.layers.InputLayer):
            inputs[key] = tensor
            continue
        node = layer._inbound_nodes[key[1]]
        sources = _listed(node.input_tensors)
        if not ready:
            stack.append((tensor, True))
            stack.extend((source, False) for source in reversed(sources))
            continue
        if calls.setdefault(layer.name, key[:2]) != key[:2]:
            raise UserError(f"layer {layer.name} ({type(layer).__name__}) is used more than once (a shared "
                            "layer); graph pruning handles layers called once")
        if len(_listed(node.output_tensors)) != 1:
            raise UserError(f"layer {layer.name} ({type(layer).__name__}) has several outputs; graph pruning "
                            "handles layers with one output")
        in_shapes = [tuple(source.shape) for source in sources]
        out_shape = tuple(tensor.shape)
        rule = rule_for(layer, keras)
        rule.check(layer, in_shapes, out_shape)
        op = _Op(layer, rule, [_key(source) for source in sources], key, in_shapes, out_shape)
        ops[key] = op
        order.append(op)
    return inputs, order


# --------------------------------------------------------------------------------------------
# Channels and their groups
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ChannelGroup:
    """Channels that are removed together, and the layers that produce them.

    Attributes:
        index: the group's number, in the order its first producer runs.
        producers: names of the layers (or model inputs) making the group's channels.
        width: the number of channels, n (coupled channels of several producers count once).
        channel_of: producer name -> the group channel (0..n-1) of each of its filters.
        frozen: why the group is not pruned ("" if it may be).
    """

    index: int
    producers: tuple[str, ...]
    width: int
    channel_of: dict[str, np.ndarray] = field(repr=False)
    frozen: str = ""


class DependencyGraph(Context):
    """The channels of a model traced through its layers, and their groups (`dependency_graph` builds it).

    Attributes:
        keras: the Keras module of the model (tf_keras or keras).
        groups: the `ChannelGroup`s, in the order their first producer runs.
        maps: tensor key -> channel map (the channel of each element of its last axis).
    """

    def __init__(self, model: Any, keep: Iterable[str] = ()) -> None:
        self.model = model
        self.keras = keras_of(model)
        self.inputs, self.ops = _trace(model, self.keras)
        self._parent: list[int] = []
        self._owner: list[str] = []  # channel -> the layer (or model input) making it
        self._blocks: dict[str, np.ndarray] = {}  # layer (or model input) -> the channels it makes
        self._frozen: dict[int, str] = {}  # channel -> why it may not be removed
        self.maps: dict[tuple, np.ndarray] = {}
        for key, tensor in self.inputs.items():
            channels = self._new(key[0], int(tensor.shape[-1]))
            self._freeze(channels, f"model input {key[0]}")
            self.maps[key] = channels
        for op in self.ops:
            in_maps = [self.maps[key] for key in op.inputs]
            self.maps[op.output] = op.rule.output_map(op.layer, in_maps, op.in_shapes, op.out_shape, self)
        # The first reason given is the one a group reports.
        for tensor in model.outputs:
            self._freeze(self.maps[_key(tensor)], f"reaches output {_key(tensor)[0]}")
        self._keep(keep)
        for op in self.ops:
            if op.rule.mixes_channels(op.layer, op.in_shapes):
                self._freeze(self.maps[op.output], f"{op.layer.name} mixes channels")
        self.groups = self._groups()

    # Context, for the rules
    def new_channels(self, layer: Any, count: int) -> np.ndarray:
        return self._new(layer.name, count)

    def couple(self, first: np.ndarray, second: np.ndarray) -> None:
        for a, b in zip(first.tolist(), second.tolist()):
            ra, rb = self._root(a), self._root(b)
            if ra != rb:
                self._parent[max(ra, rb)] = min(ra, rb)

    def _new(self, owner: str, count: int) -> np.ndarray:
        start = len(self._parent)
        self._parent.extend(range(start, start + count))
        self._owner.extend([owner] * count)
        self._blocks[owner] = np.arange(start, start + count, dtype=np.int64)
        return self._blocks[owner]

    @property
    def size(self) -> int:
        """The number of channels made in the model (model inputs included), before any coupling."""
        return len(self._parent)

    def channels_of(self, owner: str) -> np.ndarray:
        """The channels (graph-wide numbers) a producer or model input makes, one per filter."""
        return self._blocks[owner]

    def _root(self, channel: int) -> int:
        parent = self._parent
        while parent[channel] != channel:
            parent[channel] = parent[parent[channel]]
            channel = parent[channel]
        return channel

    def _freeze(self, channels: np.ndarray, why: str) -> None:
        for channel in channels.tolist():
            self._frozen.setdefault(channel, why)

    def _keep(self, keep: Iterable[str]) -> None:
        names = [keep] if isinstance(keep, str) else list(keep)
        outputs = {op.layer.name: op.output for op in self.ops}
        outputs.update({key[0]: key for key in self.inputs})
        unknown = [name for name in names if name not in outputs]
        if unknown:
            import difflib

            close = difflib.get_close_matches(str(unknown[0]), list(outputs), n=1)
            hint = f" (did you mean {close[0]}?)" if close else \
                f"; its layers: {_names(tuple(op.layer.name for op in self.ops), shown=12)}"
            raise UserError(f"model {self.model.name} has no layer named {', '.join(map(str, unknown))} to keep "
                            f"whole{hint}")
        for name in names:
            self._freeze(self.maps[outputs[name]], f"{name} kept whole")

    def _groups(self) -> tuple[ChannelGroup, ...]:
        roots = np.array([self._root(c) for c in range(len(self._parent))], dtype=np.int64)
        # Producers sharing a coupled channel belong to one group (a small union-find over their names).
        producer_parent: dict[str, str] = {}

        def find(name: str) -> str:
            while producer_parent.setdefault(name, name) != name:
                name = producer_parent[name]
            return name

        first_owner: dict[int, str] = {}
        for channel, root in enumerate(roots.tolist()):
            owner = self._owner[channel]
            a, b = find(first_owner.setdefault(root, owner)), find(owner)
            if a != b:
                producer_parent[b] = a
        members: dict[str, list[str]] = {}
        for owner in self._blocks:  # in order of creation
            members.setdefault(find(owner), []).append(owner)
        groups = []
        for producers in members.values():
            channels = np.sort(np.concatenate([self._blocks[p] for p in producers]))
            classes = list(dict.fromkeys(roots[channels].tolist()))  # the group's channels, first-seen order
            position = {root: i for i, root in enumerate(classes)}
            channel_of = {p: np.array([position[r] for r in roots[self._blocks[p]].tolist()], dtype=np.int64)
                          for p in producers}
            frozen = next((self._frozen[c] for c in channels.tolist() if c in self._frozen), "")
            groups.append(ChannelGroup(len(groups), tuple(producers), len(classes), channel_of, frozen))
        return tuple(groups)

    def layer(self, name: str) -> Any:
        """The model's layer called `name` (a producer of a group)."""
        return self.model.get_layer(name)

    def describe(self) -> str:
        """A table of the groups: producers, width and whether they may be pruned."""
        rows = [[g.index, _names(g.producers), g.width, g.frozen or "prunable"] for g in self.groups]
        return format_table(["group", "producers", "channels", "status"], rows)


def dependency_graph(model: Any, keep: Iterable[str] = ()) -> DependencyGraph:
    """Trace `model`'s channels and group the coupled ones.

    Args:
        model: a built tf_keras or Keras 3 model (functional or Sequential, channels_last, single-use layers).
        keep: names of layers whose output channels are all kept (their groups are frozen).
    Returns:
        The `DependencyGraph`, with its `groups`.
    Raises:
        UserError: for a layer the surgery does not handle, one line naming it and its type; a shared layer, a
            nested model, or an unknown name in `keep`.
    """
    return DependencyGraph(model, keep)


def _names(names: tuple[str, ...], shown: int = 3) -> str:
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" +{more} more" if more > 0 else "")


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
        """The kept filter indices of one of the group's producers."""
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
        """Producer name -> its kept filter indices, for every layer making channels (model inputs left out)."""
        result = {}
        for plan in self.groups:
            for producer in plan.group.producers:
                if producer in self.layers:
                    result[producer] = plan.filters(producer)
        return result

    def describe(self) -> str:
        """The groups (producers, channels before and after, status) and the totals, as a plain-text table."""
        rows = [[p.group.index, _names(p.group.producers), p.group.width, int(len(p.kept)),
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


def _group_keep_count(width: int, rate: Rate, min_filters: int, round_to: int) -> int:
    count = max(keep_count(width, rate), min(width, min_filters))
    return min(width, math.ceil(count / round_to) * round_to)


def plan_graph(model: Any, rate: Rate, *, importance: ImportanceLike = "l1", aggregate: str = "sum",
               min_filters: int = 0, round_to: int = 1, keep: Iterable[str] = ()) -> GraphPlan:
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
    Returns:
        The `GraphPlan`.
    Raises:
        UserError: for a bad rate, importance, aggregate, min_filters or round_to, or a model
            `dependency_graph` refuses.
    """
    keep_count(1, rate)  # validates the rate
    if aggregate not in AGGREGATES:
        raise UserError(f"aggregate must be one of {', '.join(AGGREGATES)}, got {aggregate!r}")
    min_filters = _check_count(min_filters, "min_filters", 0)
    round_to = _check_count(round_to, "round_to", 1)
    scorer = _scorer(importance)
    graph = dependency_graph(model, keep)
    plans = []
    for group in graph.groups:
        if group.frozen:
            plans.append(GroupPlan(group, np.arange(group.width, dtype=np.int64)))
            continue
        scores = _group_scores(graph, group, scorer, AGGREGATES[aggregate])
        kept = kept_top(scores, _group_keep_count(group.width, rate, min_filters, round_to))
        plans.append(GroupPlan(group, kept, scores))
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
        weights = op.layer.get_weights()
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
        for op, (layer, _) in zip(graph.ops, new_layers):
            sources = [tensors[key] for key in op.inputs]
            tensors[op.output] = layer(sources if op.rule.kind in ("merge", "concatenate") else sources[0])
        inputs = [tensors[_key(t)] for t in model.inputs]
        outputs = [tensors[_key(t)] for t in model.outputs]
        pruned = keras.Model(inputs if len(inputs) > 1 else inputs[0],
                             outputs if len(outputs) > 1 else outputs[0], name=model.name)
    for layer, weights in new_layers:
        layer.set_weights(weights)
    return pruned


def _narrowed(op: _Op, entry: LayerChannels) -> tuple[Any, list[np.ndarray]]:
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
    weights = op.rule.slice_weights(op.layer, op.layer.get_weights(), list(entry.kept_in), entry.kept_out)
    return layer, weights
