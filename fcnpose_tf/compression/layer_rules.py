"""The channel rule of each supported Keras layer type (`channel_rules.Rule`), and `rule_for`, which finds it.

The rules work for tf_keras (Keras 2) and Keras 3 alike: `rule_for` is given the Keras module the model was built
with and matches the layer's exact class in it (a subclass of a supported layer may change its behaviour, so it is
refused).

Kinds of layers:

    producer     Conv2D, Conv2DTranspose, SeparableConv2D (its pointwise filters), Dense: new channels; a grouped
                 Conv2D keeps as many input channels and filters in each of its groups
    depthwise    DepthwiseConv2D (depth_multiplier 1), Conv2D with groups = its input channels = its filters:
                 per-channel weights, channels follow the input
    per-channel  BatchNormalization, Normalization (channel axis), PReLU, ConvNeXt's LayerScale: per-channel weights
                 sliced with their channel; Rescaling: its scale and offset, one number or one per channel (sliced in its config)
    mixing       LayerNormalization (channel axis), Softmax / softmax activations on the channel axis: they mix
                 channels, so the channels through them are never pruned (the dependency graph freezes them)
    pass-through activations, pooling, global pooling, UpSampling2D, Resizing, ZeroPadding2D, Cropping2D,
                 dropout and noise layers, ConvNeXt's StochasticDepth: the channels pass unchanged
    merge        Add, Subtract, Multiply, Average, Maximum, Minimum (and Concatenate off the channel axis):
                 all inputs carry one channel set, coupled channel by channel
    elementwise  operations written on tensors (Keras 3's ``x + 3.0`` or ``keras.ops.relu6(x)``, tf_keras'
                 TFOpLambda such as ``tf.math.multiply``): of several tensors a merge, of one tensor and numbers
                 (one number each) or of one tensor alone a pass-through
    concatenate  Concatenate on the channel axis: the inputs' channels side by side, at their offsets
    flatten      Flatten, and Reshape to one axis: every spatial position repeats the channel map
    reshape      Reshape that keeps the channel axis's length: the map passes unchanged
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Sequence

import numpy as np

from fcnpose_tf.compression.channel_rules import Rule, area, product, unsupported
from fcnpose_tf.errors import UserError

_MIXING_ACTIVATIONS = ("softmax", "log_softmax")


class Activation(Rule):
    """Activation, ReLU and the like; a softmax over the channel axis mixes channels."""

    def mixes_channels(self, layer: Any, in_shapes: Sequence[tuple]) -> bool:
        return _activation_mixes(getattr(layer, "activation", None))


class Softmax(Rule):
    """The Softmax layer: mixes channels when it normalises over the last axis."""

    def mixes_channels(self, layer: Any, in_shapes: Sequence[tuple]) -> bool:
        axes = layer.axis if isinstance(layer.axis, (list, tuple)) else [layer.axis]
        rank = len(in_shapes[0])
        return any(a % rank == rank - 1 for a in axes)


class PerChannel(Rule):
    """BatchNormalization, PReLU, LayerNormalization: weights whose last axis is the channel axis."""

    kind = "per-channel"

    def __init__(self, mixes: bool = False) -> None:
        self.mixes = mixes
        if mixes:
            self.kind = "mixing"

    def check(self, layer: Any, in_shapes: Sequence[tuple], out_shape: tuple) -> None:
        super().check(layer, in_shapes, out_shape)
        rank = len(in_shapes[0])
        if hasattr(layer, "axis"):  # the normalisations
            axes = layer.axis if isinstance(layer.axis, (list, tuple)) else [layer.axis]
            if sorted(a % rank for a in axes) != [rank - 1]:
                raise unsupported(layer, f"normalises axis {layer.axis}, not the channel axis only")

    def mixes_channels(self, layer: Any, in_shapes: Sequence[tuple]) -> bool:
        return self.mixes

    def slice_weights(self, layer, weights, kept_in, kept_out):
        # gamma, beta, moving statistics (C,); PReLU's alpha (..., C), or (..., 1) when shared over channels
        return [w[..., kept_in[0]] if w.ndim and w.shape[-1] != 1 else w for w in weights]


class LayerScale(PerChannel):
    """ConvNeXt's LayerScale (keras.applications): ``x * gamma``, one gamma per channel, its config's
    ``projection_dim`` the channel count."""

    def new_config(self, layer, config, kept_in, kept_out):
        config["projection_dim"] = int(len(kept_out))
        return config


class Normalization(PerChannel):
    """Normalization over the channel axis: its mean and variance (weights, or numbers in its config) per channel."""

    def new_config(self, layer, config, kept_in, kept_out):
        return _sliced_config(layer, config, ("mean", "variance"), kept_in[0])


class Rescaling(Rule):
    """Rescaling: ``x * scale + offset``, each one number or one per channel (sliced with the channels)."""

    def check(self, layer, in_shapes, out_shape):
        super().check(layer, in_shapes, out_shape)
        for key in ("scale", "offset"):
            size = np.size(getattr(layer, key))
            if size not in (1, in_shapes[0][-1]):
                raise unsupported(layer, f"its {key} has {size} values for {in_shapes[0][-1]} channels")

    def new_config(self, layer, config, kept_in, kept_out):
        return _sliced_config(layer, config, ("scale", "offset"), kept_in[0])


def _sliced_config(layer: Any, config: dict, keys: Sequence[str], kept: np.ndarray) -> dict:
    """`config` with the per-channel values under `keys` (one per channel of the layer's input) kept at `kept`."""
    channels = int(layer.input.shape[-1])
    for key in keys:
        value = config.get(key)
        if value is not None and np.size(value) == channels and channels > 1:
            config[key] = [float(v) for v in np.ravel(np.asarray(value, dtype=np.float64))[kept]]
    return config


class Merge(Rule):
    """Elementwise merges: every input carries the same channels, position by position."""

    kind = "merge"

    def check(self, layer, in_shapes, out_shape):
        if len({shape[-1] for shape in in_shapes}) != 1:
            raise unsupported(layer, f"its inputs have different channel counts {[s[-1] for s in in_shapes]} "
                                     "(broadcasting over channels)")

    def output_map(self, layer, in_maps, in_shapes, out_shape, context):
        for other in in_maps[1:]:
            context.couple(in_maps[0], other)
        return in_maps[0]


class Concatenate(Merge):
    """Concatenate: on the channel axis the maps go side by side; on another axis it couples like a merge."""

    kind = "concatenate"

    def _on_channels(self, layer, rank: int) -> bool:
        return layer.axis % rank == rank - 1

    def check(self, layer, in_shapes, out_shape):
        if not self._on_channels(layer, len(in_shapes[0])):
            super().check(layer, in_shapes, out_shape)

    def output_map(self, layer, in_maps, in_shapes, out_shape, context):
        if self._on_channels(layer, len(in_shapes[0])):
            return np.concatenate(in_maps)
        return super().output_map(layer, in_maps, in_shapes, out_shape, context)


class Elementwise(Merge):
    """An elementwise operation on tensors (Keras 3 ops, tf_keras TFOpLambda): several tensors of one channel count
    are coupled as a merge couples them; a constant operand must be one number (``x + 3.0`` in MobileNetV3's hard
    sigmoid), so the channels pass.

    Args:
        functions: for TFOpLambda, the TensorFlow functions (its config's ``function``) this rule handles; None for
            a Keras 3 operation class, which is the function.
    """

    kind = "elementwise"

    def __init__(self, functions: Sequence[str] | None = None) -> None:
        self.functions = functions

    def check(self, layer, in_shapes, out_shape):
        if self.functions is not None and layer.get_config().get("function") not in self.functions:
            raise unsupported(layer, f"TensorFlow function {layer.get_config().get('function')} (elementwise "
                                     f"{', '.join(self.functions)} are handled)")
        super().check(layer, in_shapes, out_shape)
        if out_shape[-1] != in_shapes[0][-1]:
            raise unsupported(layer, f"its output has {out_shape[-1]} channels for {in_shapes[0][-1]} in")

    def check_call(self, layer, args, kwargs):
        operands = list(args) + [value for key, value in kwargs.items() if key != "name"]
        for value in _leaves(operands):
            if value is None or hasattr(value, "_keras_history"):
                continue
            try:
                size = np.size(np.asarray(value))
            except Exception:  # an object numpy cannot read
                size = None
            if size != 1:
                raise unsupported(layer, f"its constant operand {type(value).__name__} of "
                                         f"{size if size is not None else 'unknown'} values is not one number")


def _leaves(value: Any) -> list:
    if isinstance(value, (list, tuple)):
        return [leaf for item in value for leaf in _leaves(item)]
    if isinstance(value, dict):
        return [leaf for item in value.values() for leaf in _leaves(item)]
    return [value]


class Flatten(Rule):
    """Flatten: position (spatial k, channel c) of the output is channel c, for every k."""

    kind = "flatten"

    def output_map(self, layer, in_maps, in_shapes, out_shape, context):
        return np.tile(in_maps[0], product(in_shapes[0][1:-1], "flatten", layer))


class Reshape(Rule):
    """Reshape keeping the channel axis's length (the map passes) or to one axis (as Flatten)."""

    kind = "reshape"

    def _flattens(self, layer, in_shapes, out_shape) -> bool:
        return len(out_shape) == 2 and len(in_shapes[0]) > 2

    def check(self, layer, in_shapes, out_shape):
        super().check(layer, in_shapes, out_shape)
        if not (out_shape[-1] == in_shapes[0][-1] or self._flattens(layer, in_shapes, out_shape)):
            raise unsupported(layer, f"reshapes {in_shapes[0]} to {out_shape}, moving the channel axis")

    def output_map(self, layer, in_maps, in_shapes, out_shape, context):
        if out_shape[-1] == in_shapes[0][-1]:
            return in_maps[0]
        return np.tile(in_maps[0], product(in_shapes[0][1:-1], "reshape", layer))

    def new_config(self, layer, config, kept_in, kept_out):
        target = list(config["target_shape"])
        if target[-1] != -1:
            target[-1] = int(len(kept_out))
        config["target_shape"] = tuple(target)
        return config


class Depthwise(Rule):
    """DepthwiseConv2D with depth_multiplier 1: kernel (kh, kw, C, 1) and bias (C,) follow the input channels."""

    kind = "depthwise"

    def check(self, layer, in_shapes, out_shape):
        super().check(layer, in_shapes, out_shape)
        if layer.depth_multiplier != 1:
            raise unsupported(layer, f"depth_multiplier {layer.depth_multiplier} (only 1 is handled)")

    def mixes_channels(self, layer, in_shapes):
        return _activation_mixes(layer.activation)

    def slice_weights(self, layer, weights, kept_in, kept_out):
        return [weights[0][:, :, kept_in[0], :]] + [b[kept_in[0]] for b in weights[1:]]

    def macs(self, layer, in_shapes, out_shape, widths_in, width_out):
        kh, kw = layer.kernel_size
        return area(out_shape) * kh * kw * widths_in[0] if area(out_shape) is not None else None


class GroupedDepthwise(Depthwise):
    """A Conv2D with ``groups`` equal to its input channels and its filters (ConvNeXt's depthwise convolution): kernel
    (kh, kw, 1, C) and bias (C,) follow the input channels, ``filters`` and ``groups`` the kept count."""

    def check(self, layer, in_shapes, out_shape):
        Rule.check(self, layer, in_shapes, out_shape)

    def slice_weights(self, layer, weights, kept_in, kept_out):
        return [w[..., kept_in[0]] for w in weights]

    def new_config(self, layer, config, kept_in, kept_out):
        config["filters"] = config["groups"] = int(len(kept_out))
        return config


class Producer(Rule):
    """A layer making new channels: its output axis is where its filters are, its input axis reads channels.

    Args:
        kind: "conv" (Conv2D), "transpose" (Conv2DTranspose), "separable" (SeparableConv2D) or "dense".
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind

    def specialised(self, layer: Any) -> Rule:
        """The rule for this layer: a Conv2D whose every group is one input channel making one filter is depthwise.

        Args:
            layer: a built layer of the rule's type.
        Returns:
            `GroupedDepthwise` for such a Conv2D, else this rule.
        """
        groups = getattr(layer, "groups", 1)
        if self.kind == "conv" and groups > 1 and groups == layer.filters and layer.kernel.shape[-2] == 1:
            return _GROUPED_DEPTHWISE
        return self

    def width(self, layer) -> int:
        """The layer's filter (unit) count.

        Args:
            layer: the layer.
        Returns:
            `units` for a Dense layer, else `filters`.
        """
        return int(layer.units if self.kind == "dense" else layer.filters)

    def check(self, layer, in_shapes, out_shape):
        super().check(layer, in_shapes, out_shape)
        if getattr(layer, "groups", 1) != 1 and self.kind != "conv":
            raise unsupported(layer, f"grouped convolution (groups={layer.groups})")

    def channel_blocks(self, layer):
        return int(getattr(layer, "groups", 1)) if self.kind == "conv" else 1

    def output_map(self, layer, in_maps, in_shapes, out_shape, context):
        return context.new_channels(layer, self.width(layer))

    def mixes_channels(self, layer, in_shapes):
        return _activation_mixes(layer.activation)

    def filter_kernel(self, weights: list[np.ndarray]) -> np.ndarray:
        """The kernel that holds the filters, with the filter axis last.

        Args:
            weights: the layer's weights (`get_weights()`).
        Returns:
            The kernel (a separable convolution's pointwise one).
        """
        if self.kind == "transpose":  # (kh, kw, filters, cin)
            return np.moveaxis(weights[0], 2, 3)
        if self.kind == "separable":  # depthwise (kh, kw, cin, dm), pointwise (1, 1, cin * dm, filters)
            return weights[1]
        return weights[0]

    def slice_weights(self, layer, weights, kept_in, kept_out):
        rows = kept_in[0]
        if self.kind == "conv" and self.channel_blocks(layer) > 1:
            kernels = [_grouped_kernel(weights[0], self.channel_blocks(layer), rows, kept_out)]
            rest = weights[1:]
        elif self.kind == "conv":
            kernels = [weights[0][:, :, rows, :][..., kept_out]]
            rest = weights[1:]
        elif self.kind == "transpose":
            kernels = [weights[0][:, :, kept_out, :][..., rows]]
            rest = weights[1:]
        elif self.kind == "separable":
            multiplier = weights[0].shape[-1]
            pointwise_rows = (rows[:, None] * multiplier + np.arange(multiplier)).ravel()
            kernels = [weights[0][:, :, rows, :], weights[1][:, :, pointwise_rows, :][..., kept_out]]
            rest = weights[2:]
        else:
            kernels = [weights[0][rows, :][:, kept_out]]
            rest = weights[1:]
        return kernels + [b[kept_out] for b in rest]

    def new_config(self, layer, config, kept_in, kept_out):
        config["units" if self.kind == "dense" else "filters"] = int(len(kept_out))
        return config

    def macs(self, layer, in_shapes, out_shape, widths_in, width_out):
        cin = widths_in[0]
        if self.kind == "dense":
            positions = product(out_shape[1:-1], None, layer)
            return None if positions is None else positions * cin * width_out
        kh, kw = layer.kernel_size
        if self.kind == "transpose":  # every input pixel scatters a kh x kw x filters patch
            pixels = area(in_shapes[0])
            return None if pixels is None else pixels * kh * kw * cin * width_out
        pixels = area(out_shape)
        if pixels is None:
            return None
        if self.kind == "separable":
            multiplier = layer.depth_multiplier
            return pixels * (kh * kw * cin * multiplier + cin * multiplier * width_out)
        return pixels * kh * kw * (cin // self.channel_blocks(layer)) * width_out


_GROUPED_DEPTHWISE = GroupedDepthwise()


def _grouped_kernel(kernel: np.ndarray, groups: int, rows: np.ndarray, kept_out: np.ndarray) -> np.ndarray:
    """A grouped convolution's kernel (kh, kw, cin / groups, filters) for the kept input channels and filters: the
    filters of group g read the kept channels of input block g, as many in every block."""
    per_in, per_out = kernel.shape[2], kernel.shape[3] // groups
    parts = []
    for g in range(groups):
        block_rows = rows[rows // per_in == g] - g * per_in
        parts.append(kernel[:, :, block_rows, :][..., kept_out[kept_out // per_out == g]])
    if len({part.shape[2] for part in parts}) != 1:
        raise UserError(f"a grouped convolution must keep as many input channels in each of its {groups} groups, "
                        f"got {[part.shape[2] for part in parts]}")
    return np.concatenate(parts, axis=-1)


def _activation_mixes(activation: Any) -> bool:
    name = getattr(activation, "__name__", str(activation))
    return name in _MIXING_ACTIVATIONS


def _rule_table(keras: ModuleType) -> dict[type, Rule]:
    layers = keras.layers
    table: dict[type, Rule] = {
        layers.Conv2D: Producer("conv"),
        layers.Conv2DTranspose: Producer("transpose"),
        layers.SeparableConv2D: Producer("separable"),
        layers.Dense: Producer("dense"),
        layers.DepthwiseConv2D: Depthwise(),
        layers.BatchNormalization: PerChannel(),
        layers.PReLU: PerChannel(),
        layers.Normalization: Normalization(),
        layers.Rescaling: Rescaling(),
        layers.LayerNormalization: PerChannel(mixes=True),
        layers.Softmax: Softmax(),
        layers.Concatenate: Concatenate(),
        layers.Flatten: Flatten(),
        layers.Reshape: Reshape(),
    }
    for name in ("Add", "Subtract", "Multiply", "Average", "Maximum", "Minimum"):
        table[getattr(layers, name)] = Merge()
    for name in ("Activation", "ReLU", "LeakyReLU", "ELU", "ThresholdedReLU"):
        if hasattr(layers, name):
            table[getattr(layers, name)] = Activation()
    for name in ("MaxPooling2D", "AveragePooling2D", "GlobalAveragePooling2D", "GlobalMaxPooling2D",
                 "UpSampling2D", "Resizing", "ZeroPadding2D", "Cropping2D", "Dropout", "SpatialDropout2D",
                 "GaussianDropout", "GaussianNoise"):
        table[getattr(layers, name)] = Rule()
    table.update(_operation_rules(keras))
    convnext = _private_module(f"{keras.__name__}.src.applications.convnext")
    if convnext is not None:
        table[convnext.LayerScale] = LayerScale()
        table[convnext.StochasticDepth] = Rule()  # the identity at inference; drops whole samples in training
    return table


def _private_module(name: str) -> ModuleType | None:
    """A module of a Keras's private tree (`keras.src...`), None if this version moved it: its layers are then
    refused as unknown rather than every model failing."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


# Elementwise TensorFlow functions of tf_keras' TFOpLambda (`x + y`, `x * 0.5`, `tf.nn.relu6(x)`) and Keras 3 ops
_TF_FUNCTIONS = ("__operators__.add", "math.add", "math.subtract", "math.multiply", "math.truediv", "math.divide",
                 "math.maximum", "math.minimum", "math.negative", "nn.relu", "nn.relu6", "math.sigmoid", "nn.silu",
                 "nn.swish", "math.tanh", "nn.gelu", "nn.elu", "nn.selu", "math.softplus", "nn.leaky_relu")
_KERAS_OPS = {"numpy": ("Add", "Subtract", "Multiply", "Divide", "TrueDivide", "Maximum", "Minimum", "Negative",
                        "Tanh"),
              "nn": ("Relu", "Relu6", "Sigmoid", "HardSigmoid", "Silu", "HardSilu", "Gelu", "Elu", "Selu",
                     "Softplus", "LeakyRelu")}


def _operation_rules(keras: ModuleType) -> dict[type, Rule]:
    """Rules for the elementwise operations written on tensors of this Keras's functional models."""
    if keras.__name__ == "tf_keras":
        module = _private_module("tf_keras.src.layers.core.tf_op_layer")
        return {module.TFOpLambda: Elementwise(_TF_FUNCTIONS)} if hasattr(module, "TFOpLambda") else {}
    rules: dict[type, Rule] = {}
    for module_name, names in _KERAS_OPS.items():
        module = _private_module(f"{keras.__name__}.src.ops.{module_name}")
        rules.update({getattr(module, name): Elementwise() for name in names if hasattr(module, name)})
    return rules


_TABLES: dict[str, dict[type, Rule]] = {}


def rule_for(layer: Any, keras: ModuleType) -> Rule:
    """The rule of `layer`'s exact class in the Keras module `keras` (tf_keras or keras).

    Args:
        layer: a layer of the model being pruned.
        keras: the Keras module the model was built with (`depgraph.keras_of`).
    Returns:
        How the layer's channels couple its inputs and outputs.
    Raises:
        UserError: for a nested model or a layer type without a rule ("unsupported layer NAME (TYPE)").
    """
    table = _TABLES.get(keras.__name__)
    if table is None:
        table = _TABLES[keras.__name__] = _rule_table(keras)
    rule = table.get(type(layer))
    if rule is not None:
        return rule.specialised(layer)
    if isinstance(layer, keras.Model):
        raise UserError(f"layer {layer.name} ({type(layer).__name__}) is a nested model; graph pruning "
                        "handles a flat model (rebuild it with the inner model's layers)")
    raise unsupported(layer)
