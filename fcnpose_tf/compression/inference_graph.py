"""Exact inference-time rewrites of a trained network, applied before TFLite conversion.

`fold_upsampling` removes FCN-Pose's nearest-neighbour upsampling layers from the graph without
changing what the network computes. In the decoder, ``conv10(up4(x))`` runs a 3x3 convolution over
a 224 x 224 x C map that is a 56 x 56 one with every pixel repeated 4 x 4 times. The same result
comes from one convolution at 56 x 56 with 16 x as many filters, one per output phase, followed by
``depth_to_space(4)``, which interleaves the 16 phases back into 224 x 224 (see `fold_upsampling`
for why this is exact). The multiply-accumulate count is unchanged, but the 224 x 224 x C
upsampled tensor is never built, and the folded convolution has 16 x the output channels, which
the TFLite CPU kernels (XNNPACK) vectorise far better than FCN-Pose's 9 maps.
``tools/bench_speedup.py`` and docs/runtime.md have the measured effect.

`fcnpose_tf.compression.export` applies it per format (`settings.TFLITE_FORMATS`' fold_upsampling: on for int8,
whose forward pass it speeds up; off for the float formats, whose files it would make larger; docs/runtime.md;
`fold_upsampling=` overrides it) and verifies the file against the original Keras model. The
rewritten model is for inference only: train and save the original.
"""

from __future__ import annotations

import math

import numpy as np
import tensorflow as tf
import tf_keras as keras

from fcnpose_tf.errors import UserError

__all__ = ["DepthToSpace", "UnsupportedGraphError", "describe_folds", "fold_and_describe", "fold_kernel",
           "fold_upsampling", "foldable_pairs"]

# Conv2D activations that act on each value alone, so they commute with depth_to_space and can stay
# fused in the folded convolution. Any other (softmax over channels, custom) is applied after it.
_ELEMENTWISE_ACTIVATIONS = frozenset({
    "linear", "relu", "relu6", "sigmoid", "hard_sigmoid", "tanh", "elu", "selu", "softplus", "softsign",
    "swish", "silu", "gelu", "exponential", "mish", "leaky_relu"})


class UnsupportedGraphError(UserError):
    """The model (or one upsampling + convolution pair in it) cannot be rewritten exactly."""


@keras.saving.register_keras_serializable(package="fcnpose_tf")
class DepthToSpace(keras.layers.Layer):
    """``tf.nn.depth_to_space``: (H, W, b*b*C) -> (b*H, b*W, C), channel blocks ordered (row, column, C).

    Converts to TFLite's DEPTH_TO_SPACE built-in op.
    """

    def __init__(self, block_size: int, **kwargs):
        super().__init__(**kwargs)
        self.block_size = int(block_size)

    def call(self, inputs):
        """Keras's forward pass.

        Args:
            inputs: N x H x W x (C * block_size**2).
        Returns:
            N x (H * block_size) x (W * block_size) x C.
        """
        return tf.nn.depth_to_space(inputs, self.block_size)

    def compute_output_shape(self, input_shape):
        """Keras's shape inference.

        Args:
            input_shape: N x H x W x C (sides may be None).
        Returns:
            N x (H * block_size) x (W * block_size) x (C / block_size**2).
        """
        b = self.block_size
        n, h, w, c = tf.TensorShape(input_shape).as_list()
        return tf.TensorShape([n, None if h is None else h * b, None if w is None else w * b, c // (b * b)])

    def get_config(self):
        return {**super().get_config(), "block_size": self.block_size}


def _phase_taps(factor: int, size: int) -> np.ndarray:
    """M[p, a, d] = 1 where tap d of a 'same' kernel of `size` taps, at output phase p of a `factor`-fold
    nearest upsampling, reads low-resolution offset a - R (R = ceil((size // 2) / factor))."""
    r = size // 2
    reach = -(-r // factor)
    taps = np.zeros((factor, 2 * reach + 1, size))
    for p in range(factor):
        for d in range(size):
            taps[p, (p + d - r) // factor + reach, d] = 1.0
    return taps


def fold_kernel(kernel: np.ndarray, factor: int) -> np.ndarray:
    """The low-resolution kernel equivalent to `kernel` applied after nearest upsampling by `factor`.

    Args:
        kernel: kh x kw x Cin x Cout, odd kh and kw (a 'same', stride-1 Conv2D's kernel).
        factor: the upsampling factor of both axes.
    Returns:
        A (2*ceil((kh//2)/factor)+1) x (2*ceil((kw//2)/factor)+1) x Cin x (factor*factor*Cout) kernel
        (3 x 3 for a 3 x 3 kernel and any factor >= 1) in `kernel`'s dtype, whose output channels
        are ordered (row phase, column phase, Cout) as `tf.nn.depth_to_space` expects. Each entry is
        the sum of the original taps that land on that low-resolution pixel (computed in float64).
    """
    kernel = np.asarray(kernel)
    kh, kw, cin, cout = kernel.shape
    rows, cols = _phase_taps(factor, kh), _phase_taps(factor, kw)
    folded = np.einsum("pay,qbx,yxic->abipqc", rows, cols, kernel.astype(np.float64))
    return folded.reshape(rows.shape[1], cols.shape[1], cin, factor * factor * cout).astype(kernel.dtype)


_MERGES = (keras.layers.Add, keras.layers.Subtract, keras.layers.Multiply, keras.layers.Average,
           keras.layers.Maximum, keras.layers.Minimum)
"""Elementwise merges: nearest upsampling commutes with them, so inputs upsampled by f and g merge at gcd(f, g)."""


def _wiring(model: keras.Model) -> list[tuple[keras.layers.Layer, list[str]]]:
    """The layers after the input in an order where every source comes first, each with the layers it reads."""
    if not isinstance(model, keras.Model) or not getattr(model, "inputs", None):
        raise UnsupportedGraphError(f"expected a built tf_keras model, got {type(model).__name__}")
    if len(model.inputs) != 1 or len(model.outputs) != 1:
        raise UnsupportedGraphError(f"model {model.name} has {len(model.inputs)} inputs and {len(model.outputs)} "
                                    "outputs; folding the upsampling handles a single-input, single-output model")
    layers = [layer for layer in model.layers if not isinstance(layer, keras.layers.InputLayer)]
    for layer in layers:
        if isinstance(layer, keras.Model):
            raise UnsupportedGraphError(f"layer {layer.name} is a nested model; folding the upsampling handles a "
                                        "flat graph of layers")
    if isinstance(model, keras.Sequential):
        names = [_input_name(model)] + [layer.name for layer in layers]
        return [(layer, [previous]) for layer, previous in zip(layers, names)]
    entries = {entry["name"]: entry for entry in model.get_config()["layers"]}
    wiring = []
    for layer in layers:
        nodes = entries[layer.name]["inbound_nodes"]
        if len(nodes) != 1 or any(inbound[1] != 0 or inbound[2] != 0 for inbound in nodes[0]):
            raise UnsupportedGraphError(f"layer {layer.name} is called more than once or reads a layer that is (a "
                                        "shared layer); folding the upsampling handles layers called once")
        wiring.append((layer, [inbound[0] for inbound in nodes[0]]))
    return wiring


def _input_name(model: keras.Model) -> str:
    first = model.layers[0] if model.layers and isinstance(model.layers[0], keras.layers.InputLayer) else None
    return first.name if first is not None else model.inputs[0].name.split(":")[0]


def _fold_factor(source: str, up: keras.layers.Layer | None, conv: keras.layers.Layer, factor: int) -> int:
    """`factor` if `conv` reading `source` upsampled by it can be folded exactly, else UnsupportedGraphError.
    `up` is the UpSampling2D `conv` reads directly (its interpolation and factors are checked), if any."""
    kind = type(up).__name__ if up is not None and up.name == source else "upsampled"

    def refuse(why: str) -> UnsupportedGraphError:
        return UnsupportedGraphError(f"cannot fold {source} ({kind}) into {conv.name} (Conv2D): {why}")

    if up is not None:
        fy, fx = (int(s) for s in up.size)
        if up.interpolation != "nearest":
            raise refuse(f"{up.interpolation!r} interpolation (only 'nearest' repeats pixels)")
        if up.data_format != "channels_last":
            raise refuse("channels_first data format")
        if fy != fx:
            raise refuse(f"unequal factors {fy} x {fx} (depth_to_space needs square blocks)")
    if conv.data_format != "channels_last":
        raise refuse("channels_first data format")
    if tuple(conv.strides) != (1, 1) or tuple(conv.dilation_rate) != (1, 1):
        raise refuse(f"strides {tuple(conv.strides)} and dilation {tuple(conv.dilation_rate)} (needs 1, 1)")
    if conv.padding != "same":
        raise refuse(f"{conv.padding!r} padding (needs 'same')")
    if getattr(conv, "groups", 1) != 1:
        raise refuse(f"grouped convolution (groups={conv.groups})")
    if any(k % 2 == 0 for k in conv.kernel_size):
        raise refuse(f"even kernel size {tuple(conv.kernel_size)} ('same' padding is then asymmetric)")
    return factor


def _nearest_square(layer: keras.layers.Layer) -> int | None:
    """The factor of a nearest, square, channels-last UpSampling2D (the kind that is carried to a convolution)."""
    if type(layer) is not keras.layers.UpSampling2D or layer.interpolation != "nearest" or \
            layer.data_format != "channels_last" or len(set(layer.size)) != 1:
        return None
    return int(layer.size[0])


class _Value:
    """A tensor of the original graph as the rewrite holds it: `tensor` (in the new graph) upsampled by `factor`,
    the upsampling not yet computed. `source` names the layer that made it (an UpSampling2D, or a merge of
    upsampled tensors); `layer` is that UpSampling2D when the value is exactly its output."""

    def __init__(self, tensor, factor: int = 1, source: str = "", layer: keras.layers.Layer | None = None):
        self.tensor, self.factor, self.source, self.layer = tensor, factor, source, layer
        self._full = tensor if factor == 1 else None

    def full(self, rewrite: "_Rewrite"):
        """The tensor at its own resolution (the upsampling computed once, however many layers read it)."""
        if self._full is None:
            if self.layer is not None:
                self._full = rewrite.add(_clone(self.layer), self.layer.get_weights())(self.tensor)
            else:
                self._full = rewrite.upsample(self.tensor, self.factor, self.source)
        return self._full


class _Rewrite:
    """The new graph being built: layer names in use and the weights to set once every layer is built."""

    def __init__(self, model: keras.Model) -> None:
        self.names = {layer.name for layer in model.layers}
        self.assignments: list[tuple[keras.layers.Layer, list[np.ndarray]]] = []
        self.folds: list[tuple[str, str, int]] = []

    def add(self, layer: keras.layers.Layer, weights: list[np.ndarray]) -> keras.layers.Layer:
        self.assignments.append((layer, weights))
        return layer

    def upsample(self, tensor, factor: int, source: str):
        name, n = f"{source}_x{factor}", 1
        while name in self.names:
            n += 1
            name = f"{source}_x{factor}_{n}"
        self.names.add(name)
        return keras.layers.UpSampling2D(factor, name=name)(tensor)

    def fold(self, conv: keras.layers.Layer, value: _Value):
        factor = value.factor
        weights = conv.get_weights()
        kernel = fold_kernel(weights[0], factor)
        activation = _activation_name(conv.activation)
        fused = activation if activation in _ELEMENTWISE_ACTIVATIONS else "linear"
        folded = keras.layers.Conv2D(kernel.shape[-1], kernel.shape[:2], padding="same", activation=fused,
                                     use_bias=conv.use_bias, dtype=conv.dtype, name=conv.name)
        x = folded(value.tensor)
        self.add(folded, [kernel] + ([np.tile(weights[1], factor * factor)] if conv.use_bias else []))
        x = DepthToSpace(factor, name=f"{conv.name}_depth_to_space")(x)
        if fused != activation:
            x = keras.layers.Activation(conv.activation, name=f"{conv.name}_activation")(x)
        self.folds.append((value.source, conv.name, factor))
        return x


def _rewrite(model: keras.Model) -> tuple[keras.Model, list[tuple[str, str, int]]]:
    """`fold_upsampling`'s model and the (source, convolution, factor) of every fold made."""
    wiring = _wiring(model)
    inputs = keras.Input(batch_shape=tuple(model.inputs[0].shape), dtype=model.inputs[0].dtype,
                         name=_input_name(model))
    rewrite = _Rewrite(model)
    values = {_input_name(model): _Value(inputs)}
    for layer, sources in wiring:
        ins = [values[name] for name in sources]
        factor = _nearest_square(layer)
        if factor is not None and len(ins) == 1:  # carried, not computed
            (value,) = ins
            values[layer.name] = _Value(value.tensor, value.factor * factor, layer.name,
                                        layer if value.factor == 1 else None)
            continue
        if type(layer) is keras.layers.Conv2D and len(ins) == 1:
            read = model.get_layer(sources[0]) if sources[0] in rewrite.names else None
            up = read if type(read) is keras.layers.UpSampling2D else None
            if ins[0].factor > 1:
                _fold_factor(ins[0].source, up, layer, ins[0].factor)
                values[layer.name] = _Value(rewrite.fold(layer, ins[0]))
                continue
            if up is not None:  # an upsampling that is not carried (bilinear, unequal factors): refused here
                _fold_factor(up.name, up, layer, 1)
        if isinstance(layer, _MERGES) and any(value.factor > 1 for value in ins):
            common = math.gcd(*(value.factor for value in ins))
            parts = [value.tensor if value.factor == common else
                     (value.full(rewrite) if common == 1 else rewrite.upsample(value.tensor, value.factor // common,
                                                                                value.source))
                     for value in ins]
            merged = rewrite.add(_clone(layer), layer.get_weights())(parts)
            values[layer.name] = _Value(merged, common, layer.name) if common > 1 else _Value(merged)
            continue
        clone = rewrite.add(_clone(layer), layer.get_weights())
        tensors = [value.full(rewrite) for value in ins]
        values[layer.name] = _Value(clone(tensors if len(tensors) > 1 else tensors[0]))
    output = values[model.outputs[0]._keras_history[0].name].full(rewrite)
    for layer, weights in rewrite.assignments:
        if weights:
            layer.set_weights(weights)
    return keras.Model(inputs, output, name=model.name), rewrite.folds


def foldable_pairs(model: keras.Model) -> list[tuple[str, str, int]]:
    """The folds `fold_upsampling` makes: the UpSampling2D layer, or the merge of upsampled tensors, that a
    convolution reads.

    Args:
        model: a tf_keras model.
    Returns:
        (what is upsampled, convolution layer, factor) of every fold.
    Raises:
        UnsupportedGraphError: as `fold_upsampling`.
    """
    return _rewrite(model)[1]


def _activation_name(activation) -> str | None:
    try:
        name = keras.activations.serialize(activation)
    except Exception:  # a custom callable
        return None
    return name if isinstance(name, str) else None


def _clone(layer: keras.layers.Layer) -> keras.layers.Layer:
    try:
        return layer.__class__.from_config(layer.get_config())
    except Exception as exc:
        raise UnsupportedGraphError(f"layer {layer.name} ({type(layer).__name__}) cannot be rebuilt from its "
                                    f"config ({type(exc).__name__}: {exc})") from exc


def fold_upsampling(model: keras.Model) -> keras.Model:
    """The same network with every nearest upsampling that a 'same' Conv2D reads computed at low resolution.

    Each ``conv(up_f(x))`` becomes ``depth_to_space_f(conv'(x))``, where conv' has the same
    (odd) kernel reach at x's resolution and f*f times the filters: one set per output phase
    (py, px) of an f x f block (`fold_kernel`). Nearest upsampling commutes with elementwise merges, so
    ``conv(up_4(x) + up_2(s))`` (FCN-Pose's skip) is ``conv(up_2(up_2(x) + s))`` and folds at factor 2; consecutive
    upsamplings multiply. The rest of the graph is rebuilt unchanged, with the same layer names and weights (the
    folded convolution keeps its name; the new layers are named ``<conv>_depth_to_space`` and, for an upsampling
    left to do before a merge, ``<upsampling>_x<factor>``), so the model takes and returns the same tensors.

    Why it is exact: nearest upsampling gives U[y, x] = x[y // f, x // f]. Output pixel
    (f*Y + py, f*X + px) of a stride-1 'same' convolution with taps dy, dx in [-r, r] reads
    U[f*Y + py + dy, ...] = x[Y + (py + dy) // f, ...]: for each phase, every tap lands on a fixed
    low-resolution offset (for a 3x3 kernel and f = 4: phases 1 and 2 of a row on row Y only,
    phase 0 on rows Y-1 and Y, phase 3 on rows Y and Y+1), so summing the taps that land on the same
    offset gives a convolution over x itself with per-phase kernels. Zero padding is preserved:
    f*Y + py + dy lies outside [0, f*H) exactly when Y + (py + dy) // f lies outside [0, H), so a
    tap that reads padding in the original reads padding in the folded convolution. The bias is
    the same for every phase, and the activation is applied per value, before or after
    depth_to_space alike (a channel-mixing activation such as softmax is moved after it). The
    result equals the original up to float rounding of the summed taps (~1e-7 relative).

    The multiply-accumulates are the same; what changes is that the f*f times larger upsampled
    tensor is never written or read, and the convolution has f*f times more output channels,
    which TFLite's XNNPACK kernels run at a much higher rate. The folded kernels hold f*f times
    more weights (for a 3x3 kernel and f >= 2, 3x3 per phase, most of them zero), so the
    .tflite file grows accordingly.

    Works for any widths and any input size (also a variable one): the rewrite does not depend on
    the spatial size.

    Args:
        model: a built tf_keras model (functional or Sequential), single input and output, each layer called
            once, e.g. FCN-Pose pruned or not, with or without its skip.
    Returns:
        A new functional tf_keras model (inference only; not compiled), or `model` itself when no Conv2D reads
        an upsampled tensor.
    Raises:
        UnsupportedGraphError (a UserError): several inputs or outputs, nested models, shared layers, a layer
            that cannot be rebuilt from its config, or an upsampling a Conv2D reads that cannot be folded
            exactly: bilinear interpolation, unequal factors, channels_first, strides or dilation other than 1,
            padding other than 'same', grouped, or even-sized kernels.
    Example:
        >>> from fcnpose_tf.training.model import build_fcn_pose
        >>> folded = fold_upsampling(build_fcn_pose(input_size=64))
        >>> [layer.name for layer in folded.layers][-2:]
        ['conv10', 'conv10_depth_to_space']
    """
    folded, folds = _rewrite(model)
    return folded if folds else model


def describe_folds(model: keras.Model) -> list[str]:
    """One line per pair `fold_upsampling` folds, e.g. ``up4 + conv10 -> conv10 at 1/4 size + depth_to_space(4)``.

    Args:
        model: a tf_keras model.
    Returns:
        The lines (none for a model without a fold).
    """
    return fold_and_describe(model)[1]


def fold_and_describe(model: keras.Model) -> tuple[keras.Model, list[str]]:
    """`fold_upsampling(model)` and `describe_folds(model)`, the graph rewritten once.

    Args:
        model: a tf_keras model.
    Returns:
        (the folded model, or `model` itself without a fold; one line per fold).
    """
    folded, folds = _rewrite(model)
    lines = [f"{up} + {conv} -> {conv} at 1/{factor} size + depth_to_space({factor})" for up, conv, factor in folds]
    return (folded if folds else model), lines

