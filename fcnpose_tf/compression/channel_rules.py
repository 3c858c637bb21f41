"""What every supported Keras layer does to the channels it reads, for the dependency graph of `depgraph`.

A *channel map* is an int array, one entry per element of a tensor's last axis, naming the channel ("atom")
that element carries. A layer's rule says how its output's map follows from its inputs' maps, which of its
weights belong to which channels (so surgery can slice them), how its config changes when channels go, and how
many multiply-accumulates it costs. This module holds what a rule is (`Rule`, the pass-through, which the other
kinds override) and the refusal every rule gives; `layer_rules` holds each layer type's rule and finds it.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError

SUPPORTED = ("Conv2D, Conv2DTranspose, SeparableConv2D, DepthwiseConv2D, Dense, BatchNormalization, "
             "LayerNormalization, Normalization, Rescaling, activations, pooling, UpSampling2D, Resizing, "
             "ZeroPadding2D, Cropping2D, dropout, Add/Subtract/Multiply/Average/Maximum/Minimum, Concatenate, Flatten, "
             "Reshape and elementwise arithmetic or activations on tensors")


def unsupported(layer: Any, why: str = "") -> UserError:
    """The one-line refusal naming `layer` and its type (and why, if given).

    Args:
        layer: the layer graph pruning cannot handle.
        why: what about it is unsupported ("" says no more).
    Returns:
        The error, for the caller to raise.
    """
    what = "layer" if hasattr(layer, "get_weights") else "operation"  # Keras 3's ops on tensors are not layers
    return UserError(f"unsupported {what} {layer.name} ({type(layer).__name__}){': ' + why if why else ''}; "
                     f"graph pruning handles {SUPPORTED} layers")


def product(dims: Sequence, what: str | None, layer: Any) -> int | None:
    """The product of a shape's `dims`; with one of them unknown, None, or when `what` the layer does needs it (e.g.
    "flatten"), `unsupported`'s refusal."""
    if any(d is None for d in dims):
        if what is None:
            return None
        raise unsupported(layer, f"cannot {what} a tensor of unknown size {tuple(dims)}")
    return int(math.prod(int(d) for d in dims))


def area(shape: tuple) -> int | None:
    """The spatial positions of a (batch, ..., channels) shape; None when one is unknown."""
    return product(shape[1:-1], None, None)


class Context:
    """What a rule needs from the graph being built: new channels and the coupling of two maps."""

    def new_channels(self, layer: Any, count: int) -> np.ndarray:
        """A map of `count` new channels produced by `layer`.

        Args:
            layer: the layer making them (a `Producer`'s).
            count: how many.
        Returns:
            The map: one new channel id per position.
        """
        raise NotImplementedError

    def couple(self, first: np.ndarray, second: np.ndarray) -> None:
        """Channels at the same position of the two maps are removed together.

        Args:
            first, second: two channel maps of the same length (a merge's inputs).
        """
        raise NotImplementedError


class Rule:
    """The pass-through rule; the other kinds override what differs."""

    kind = "pass-through"

    def check(self, layer: Any, in_shapes: Sequence[tuple], out_shape: tuple) -> None:
        """Refuse a setting of the layer the rule cannot handle.

        Args:
            layer: the layer.
            in_shapes: its input shapes (batch axis first).
            out_shape: its output shape.
        Raises:
            UserError: `unsupported`'s, naming the layer and the setting.
        """
        if getattr(layer, "data_format", "channels_last") != "channels_last":
            raise unsupported(layer, "channels_first data format")
        if len(in_shapes) != 1:
            raise unsupported(layer, f"it reads {len(in_shapes)} tensors")

    def specialised(self, layer: Any) -> "Rule":
        """The rule for this particular layer of the rule's type (a setting may change its kind).

        Args:
            layer: the layer.
        Returns:
            This rule, unless a subclass says otherwise.
        """
        return self

    def channel_blocks(self, layer: Any) -> int:
        """Into how many equal blocks the layer splits its input and output channels, each output block reading its
        input block only (a grouped convolution's groups): each block must keep as many channels as the others.

        Args:
            layer: the layer.
        Returns:
            1 for a layer without groups.
        """
        return 1

    def check_call(self, layer: Any, args: tuple, kwargs: dict) -> None:
        """Refuse a call of the layer the rule cannot handle (an operation's constant operands).

        Args:
            layer: the layer (or Keras 3 operation).
            args, kwargs: the arguments it was called with, its input tensors among them.
        Raises:
            UserError: `unsupported`'s.
        """

    def output_map(self, layer: Any, in_maps: list[np.ndarray], in_shapes: Sequence[tuple],
                   out_shape: tuple, context: Context) -> np.ndarray:
        """The output's channel map: which channel every output position carries.

        Args:
            layer: the layer.
            in_maps: its inputs' channel maps.
            in_shapes: its input shapes.
            out_shape: its output shape.
            context: the graph being built (new channels, coupling).
        Returns:
            The output's map.
        """
        return in_maps[0]

    def mixes_channels(self, layer: Any, in_shapes: Sequence[tuple]) -> bool:
        """Whether the layer mixes its output channels (so none of them may be removed).

        Args:
            layer: the layer.
            in_shapes: its input shapes.
        Returns:
            True for a mixing layer (a softmax over the channels, for one).
        """
        return False

    def slice_weights(self, layer: Any, weights: list[np.ndarray], kept_in: list[np.ndarray],
                      kept_out: np.ndarray) -> list[np.ndarray]:
        """The layer's weights for the kept input positions and kept output positions.

        Args:
            layer: the layer.
            weights: its weights (`get_weights()`).
            kept_in: per input, the positions kept.
            kept_out: the output positions kept.
        Returns:
            The sliced weights, in `get_weights()` order.
        """
        return weights

    def new_config(self, layer: Any, config: dict, kept_in: list[np.ndarray], kept_out: np.ndarray) -> dict:
        """The layer's config after the surgery.

        Args:
            layer: the layer.
            config: its `get_config()` (changed in place).
            kept_in: per input, the positions kept.
            kept_out: the output positions kept.
        Returns:
            The config to rebuild it with.
        """
        return config

    def macs(self, layer: Any, in_shapes: Sequence[tuple], out_shape: tuple, widths_in: list[int],
             width_out: int) -> int | None:
        """Multiply-accumulates per sample at these widths.

        Args:
            layer: the layer.
            in_shapes: its input shapes.
            out_shape: its output shape.
            widths_in: channels of each input.
            width_out: channels of the output.
        Returns:
            The count, None if a spatial size is unknown.
        """
        return 0
