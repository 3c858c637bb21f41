"""Filter surgery for any Keras CNN: a dependency graph of coupled channels (as Torch-Pruning's DepGraph).

`fcnpose_tf.compression.prune` removes filters from a plain chain of layers. Here the model may branch and merge:
the channels a model computes are traced through its graph (`dependency_graph`) and gathered into *groups* of
channels that must go together. The filters of every layer whose outputs meet in an elementwise merge (Add,
Subtract, Multiply, ...) form one group, coupled channel by channel; a Concatenate on the channel axis puts its
inputs' channels side by side, each keeping its own group, and its consumers read them at their offsets; a
Flatten before a Dense repeats the channels at every spatial position (the Dense loses rows ``c + C * k``).
`fcnpose_tf.compression.layer_rules` holds what each layer type does to channels (`channel_rules`: what a rule is).

Every group of n channels keeps ``n - floor(n * rate)`` of them (the paper's keep rule, `keep_rule.keep_count`), the
ones whose importance is highest: the importance of a channel is the aggregate (sum, mean or max) over the layers
producing it of their filter's score (L1 or L2 norm of the filter's kernel slice, bias excluded). Per-channel
layers (BatchNormalization, DepthwiseConv2D, PReLU) do not score: they are not producers, their weights are
sliced with their channel. A group is not pruned (it is *frozen*) if its channels reach a model output, come
from a model input, pass a layer that mixes channels (Softmax or a softmax activation over channels,
LayerNormalization over channels), or belong to a layer the caller keeps whole (``keep=``).

`fcnpose_tf.compression.graph_prune` plans on this graph: `plan_graph` chooses the kept channels and counts
parameters and multiply-accumulates before and after without touching the model; `prune_graph` rebuilds the model
with the narrower layers (``from_config`` plus sliced weights), in the Keras it was built with (tf_keras in, tf_keras
out; Keras 3 in, Keras 3 out). Before retraining, the pruned model computes exactly what the original computes with
the removed channels deleted.

For a plain chain (FCN-Pose) every Conv2D is its own group and the output layer is frozen, so `prune_graph` with
the L1 importance gives `prune.prune_model`'s result. Unlike `plan.plan_widths`' ``min_filters``, which keeps the
parameter budget of the rate by pruning other groups harder (what `prune.prune_model` and `compress` use on a
branching model too), ``min_filters`` of `graph_prune.plan_graph` only floors each group's width.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Iterable

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.channel_rules import Context, Rule
from fcnpose_tf.compression.layer_rules import rule_for
from fcnpose_tf.tables import format_table



# --------------------------------------------------------------------------------------------
# The model's graph, whichever Keras built it
# --------------------------------------------------------------------------------------------

def keras_of(model: Any) -> ModuleType:
    """The Keras module `model` was built with: ``tf_keras`` (Keras 2) or ``keras`` (Keras 3).

    Args:
        model: a built Keras model.
    Returns:
        The module.
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
class TracedOp:
    """One call of a layer in the model: the tensors it reads and the one it makes (keys), with their shapes, and
    the arguments it was called with (its input tensors among them), to call the rebuilt layer the same way."""

    layer: Any
    rule: Rule
    inputs: list[tuple]
    output: tuple
    in_shapes: list[tuple]
    out_shape: tuple
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)


def tensor_key(tensor: Any) -> tuple:
    """Where a symbolic tensor comes from, the same for every reference to it.

    Args:
        tensor: a Keras tensor of a functional model.
    Returns:
        (producing layer's name, node index, tensor index).
    """
    layer, node_index, tensor_index = tensor._keras_history
    return (layer.name, int(node_index), int(tensor_index))


def _listed(value: Any) -> list:
    return list(value) if isinstance(value, (list, tuple)) else [value]


def call_arguments(node: Any) -> tuple[tuple, dict]:
    """The positional and keyword arguments of a layer's call in a functional model, as Keras recorded them.

    Args:
        node: the call's node (Keras 3 `Node` with ``arguments``, tf_keras `Node` with ``call_args``).
    Returns:
        (args, kwargs), with the symbolic input tensors in place.
    """
    if hasattr(node, "arguments"):  # Keras 3
        return tuple(node.arguments.args), dict(node.arguments.kwargs)
    return tuple(node.call_args), dict(node.call_kwargs)


def _trace(model: Any, keras: ModuleType) -> tuple[dict[tuple, Any], list[TracedOp], dict[tuple, tuple]]:
    """The model's input tensors by key, its layer calls in an order where every input comes first, and the aliases:
    the key of a nested model's output (or of its inputs) -> the key of the inner (or outer) tensor it is. A nested
    model is traced through: its layers become the flat model's."""
    inputs: dict[tuple, Any] = {}
    ops: dict[tuple, TracedOp] = {}
    order: list[TracedOp] = []
    aliases: dict[tuple, Any] = {}  # tensor key -> the tensor it stands for
    calls: dict[str, tuple] = {}  # layer name -> (the layer's id, its node), to refuse shared layers
    training: dict[int, Any] = {}  # id of a layer in a nested model called with training= -> that value
    stack = [(tensor, False) for tensor in reversed(model.outputs)]
    while stack:
        tensor, ready = stack.pop()
        key = tensor_key(tensor)
        if key in ops or key in inputs:
            continue
        if key in aliases:  # a nested model's input or output: trace the tensor it is
            stack.append((aliases[key], ready))
            continue
        layer = tensor._keras_history[0]
        if isinstance(layer, keras.layers.InputLayer):
            inputs[key] = tensor
            continue
        node = layer._inbound_nodes[key[1]]
        # every symbolic tensor of the call (tf_keras' input_tensors is its first argument only: `x + y` reads y too)
        sources = list(node.keras_inputs) if hasattr(node, "keras_inputs") else _listed(node.input_tensors)
        _check_single_use(layer, key, calls)
        if _is_graph_model(layer, keras):
            inner_inputs, inner_outputs = list(getattr(layer, "inputs", None) or []), list(layer.outputs or [])
            if len(inner_inputs) != len(sources):
                raise UserError(f"layer {layer.name} ({type(layer).__name__}) is a nested model called on "
                                f"{len(sources)} tensors for its {len(inner_inputs)} inputs; graph pruning traces "
                                "a nested model called on its inputs")
            aliases.update((tensor_key(inner), source) for inner, source in zip(inner_inputs, sources))
            aliases[key] = inner_outputs[key[2]]
            mode = call_arguments(node)[1].get("training")
            if mode is not None:  # base(x, training=False) keeps its BatchNormalization in inference mode
                training.update((id(inner), mode) for inner in _sublayers(layer))
            stack.append((inner_outputs[key[2]], False))
            continue
        if not ready:
            stack.append((tensor, True))
            stack.extend((source, False) for source in reversed(sources))
            continue
        if len(_listed(node.output_tensors)) != 1:
            raise UserError(f"layer {layer.name} ({type(layer).__name__}) has several outputs; graph pruning "
                            "handles layers with one output")
        in_shapes = [tuple(source.shape) for source in sources]
        out_shape = tuple(tensor.shape)
        rule = rule_for(layer, keras)
        rule.check(layer, in_shapes, out_shape)
        args, kwargs = call_arguments(node)
        rule.check_call(layer, args, kwargs)
        if id(layer) in training and "training" not in kwargs and _takes_training(layer):
            kwargs = {**kwargs, "training": training[id(layer)]}
        op = TracedOp(layer, rule, [_resolved(tensor_key(source), aliases) for source in sources], key, in_shapes,
                      out_shape, args, kwargs)
        ops[key] = op
        order.append(op)
    return inputs, order, {key: _resolved(key, aliases) for key in aliases}


def _is_graph_model(layer: Any, keras: ModuleType) -> bool:
    """A nested functional or Sequential model (its graph can be traced), not a subclassed one."""
    return isinstance(layer, keras.Model) and type(layer).__name__ in ("Functional", "Sequential") and \
        type(layer).__module__.startswith(keras.__name__ + ".")


def _sublayers(model: Any) -> list:
    """The layers of a nested model and of the models nested in it."""
    return [inner for layer in model.layers for inner in ([layer] + (_sublayers(layer) if hasattr(layer, "layers")
                                                                    else []))]


def _takes_training(layer: Any) -> bool:
    import inspect

    try:
        return "training" in inspect.signature(layer.call).parameters
    except (TypeError, ValueError):
        return False


def _check_single_use(layer: Any, key: tuple, calls: dict[str, tuple]) -> None:
    seen = calls.setdefault(layer.name, (id(layer), key[1]))
    if seen[0] != id(layer):
        raise UserError(f"model has two layers named {layer.name} (a nested model's and another); graph pruning "
                        "needs unique layer names")
    if seen[1] != key[1]:
        raise UserError(f"layer {layer.name} ({type(layer).__name__}) is used more than once (a shared "
                        "layer); graph pruning handles layers called once")


def _resolved(key: tuple, aliases: dict[tuple, Any]) -> tuple:
    while key in aliases:
        key = tensor_key(aliases[key])
    return key


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
        block_of: for channels a grouped convolution makes or reads, the block (its group) of each group channel;
            every block keeps as many channels as the others. None: no such constraint.
    """

    index: int
    producers: tuple[str, ...]
    width: int
    channel_of: dict[str, np.ndarray] = field(repr=False)
    frozen: str = ""
    block_of: np.ndarray | None = field(default=None, repr=False)

    @property
    def blocks(self) -> int:
        """How many equal blocks the group's kept channels come in (1 without a grouped convolution)."""
        return 1 if self.block_of is None else int(self.block_of.max()) + 1


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
        self.inputs, self.ops, self.aliases = _trace(model, self.keras)
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
            self._freeze(self.maps[self.key(tensor)], f"reaches output {self.key(tensor)[0]}")
        self._keep(keep)
        for op in self.ops:
            if op.rule.mixes_channels(op.layer, op.in_shapes):
                self._freeze(self.maps[op.output], f"{op.layer.name} mixes channels")
        self.groups = self._groups()

    def key(self, tensor: Any) -> tuple:
        """The key of the traced tensor a symbolic tensor of the model is (a nested model's output: the inner one).

        Args:
            tensor: a Keras tensor of the model or of a model nested in it.
        Returns:
            The key of `maps` and of the ops' inputs and outputs.
        """
        key = tensor_key(tensor)
        return self.aliases.get(key, key)

    # Context, for the rules
    def new_channels(self, layer: Any, count: int) -> np.ndarray:
        """Number `count` new channels made by `layer` (a rule's producer); returns their graph-wide numbers.

        Args:
            layer: the layer making them.
            count: how many.
        Returns:
            Their numbers (`Context.new_channels`).
        """
        return self._new(layer.name, count)

    def couple(self, first: np.ndarray, second: np.ndarray) -> None:
        """Join the channels of `first` and `second` pairwise into the same groups (a merge's inputs).

        Args:
            first, second: two channel maps of the same length.
        """
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
        """The channels a layer makes.

        Args:
            owner: the name of a producer or a model input.
        Returns:
            Its channels' graph-wide numbers, one per filter.
        Raises:
            KeyError: a layer that makes no channels of its own.
        """
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
                f"; its layers: {short_list(tuple(op.layer.name for op in self.ops), shown=12)}"
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
        return tuple(self._with_blocks(groups, roots))

    def _with_blocks(self, groups: list[ChannelGroup], roots: np.ndarray) -> list[ChannelGroup]:
        """The groups with the blocks of the grouped convolutions reading or making their channels."""
        group_of = {}  # root channel -> (group index, position)
        for group in groups:
            for producer, positions in group.channel_of.items():
                for channel, position in zip(self._blocks[producer].tolist(), positions.tolist()):
                    group_of[int(roots[channel])] = (group.index, position)
        for op in self.ops:
            count = op.rule.channel_blocks(op.layer)
            if count == 1:
                continue
            for channels in [self.maps[key] for key in op.inputs] + [self.maps[op.output]]:
                places = [group_of[int(roots[c])] for c in channels.tolist()]
                index = places[0][0]
                group = groups[index]
                positions = np.array([p for _, p in places], dtype=np.int64)
                if group.frozen:
                    continue
                if any(i != index for i, _ in places) or sorted(positions.tolist()) != list(range(group.width)):
                    raise UserError(f"layer {op.layer.name} ({type(op.layer).__name__}): a grouped convolution "
                                    f"(groups={count}) whose channels are not one whole group of channels; graph "
                                    "pruning handles a grouped convolution reading and making whole groups")
                block_of = np.empty(group.width, dtype=np.int64)
                block_of[positions] = np.arange(len(positions)) // (len(positions) // count)
                if group.block_of is not None and not np.array_equal(group.block_of, block_of):
                    raise UserError(f"layer {op.layer.name} ({type(op.layer).__name__}): its groups split channels "
                                    f"{short_list(group.producers)} differently from another grouped convolution")
                groups[index] = ChannelGroup(group.index, group.producers, group.width, group.channel_of,
                                             group.frozen, block_of)
        return groups

    def layer(self, name: str) -> Any:
        """The model's layer called `name` (a producer of a group), in a nested model too.

        Args:
            name: the layer's name.
        Returns:
            The layer.
        Raises:
            ValueError: no such layer (Keras' `get_layer`).
        """
        for op in self.ops:
            if op.layer.name == name:
                return op.layer
        return self.model.get_layer(name)

    def describe(self) -> str:
        """The graph for reading.

        Returns:
            A plain-text table of the groups: producers, width and whether they may be pruned.
        """
        rows = [[g.index, short_list(g.producers), g.width, g.frozen or "prunable"] for g in self.groups]
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
            subclassed nested model (a functional or Sequential one is traced through), a layer name used twice,
            or an unknown name in `keep`.
    """
    return DependencyGraph(model, keep)


def short_list(names: tuple[str, ...], shown: int = 3) -> str:
    """The first `shown` names, then "+k more".

    Args:
        names: layer names.
        shown: how many to name.
    Returns:
        The names, comma-separated.
    """
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" +{more} more" if more > 0 else "")
