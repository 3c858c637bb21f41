"""Graph pruning (`fcnpose_tf.compression.depgraph`): exact surgery on branching models in tf_keras and Keras 3.

Every architecture is built with either Keras and pruned at three rates; two checks say the surgery is right:

  (a) the original with the removed channels' *readers* zeroed (the consuming layers' input slices) computes
      what the pruned model computes;
  (b) the original with the removed filters made dead (zero kernel slice and bias, and beta and moving mean zero
      in a BatchNormalization after them, so they output exactly 0) computes what the pruned model computes.
"""

import doctest
import functools
import importlib

import keras as keras3
import numpy as np
import pytest
import tf_keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression import depgraph, graph_prune
from fcnpose_tf.compression.depgraph import dependency_graph
from fcnpose_tf.compression.graph_prune import plan_graph, prune_graph
from fcnpose_tf.compression.keep_rule import keep_count
from fcnpose_tf.compression.prune import prune_model
from fcnpose_tf.training.model import build_fcn_pose, conv_widths

FLAVOURS = {"tf_keras": tf_keras, "keras3": keras3}
RATES = (0.3, 0.5, 0.7)

# Keras 3 rebuilding FCN-Pose from its tf_keras config keeps the inputs as a list of one
pytestmark = pytest.mark.filterwarnings("ignore:The structure of `inputs` doesn't match:UserWarning")
TOLERANCE = 1e-5


# ------------------------------------------------------------------------------------------
# architectures, each built with the Keras module K
# ------------------------------------------------------------------------------------------

def conv(K, filters, name, kernel=3, strides=1, activation=None):
    return K.layers.Conv2D(filters, kernel, strides=strides, padding="same", activation=activation, name=name)


def residual_block(K):
    i = K.Input((32, 32, 3), name="image")
    x = K.layers.ReLU(name="stem_relu")(K.layers.BatchNormalization(name="stem_bn")(conv(K, 16, "stem")(i)))
    y = K.layers.ReLU(name="b1_relu")(K.layers.BatchNormalization(name="b1_bn")(conv(K, 16, "b1_conv")(x)))
    y = K.layers.BatchNormalization(name="b2_bn")(conv(K, 16, "b2_conv")(y))
    x = K.layers.ReLU(name="out_relu")(K.layers.Add(name="add")([x, y]))
    return K.Model(i, conv(K, 4, "head", 1)(x), name="residual")


def resnet_like(K):
    def block(x, filters, name, strides=1):
        y = K.layers.ReLU(name=f"{name}_r1")(K.layers.BatchNormalization(name=f"{name}_bn1")(
            conv(K, filters, f"{name}_c1", strides=strides)(x)))
        y = K.layers.BatchNormalization(name=f"{name}_bn2")(conv(K, filters, f"{name}_c2")(y))
        if strides != 1 or x.shape[-1] != filters:  # projection shortcut
            x = K.layers.BatchNormalization(name=f"{name}_pbn")(conv(K, filters, f"{name}_proj", 1, strides)(x))
        return K.layers.ReLU(name=f"{name}_out")(K.layers.Add(name=f"{name}_add")([x, y]))

    i = K.Input((32, 32, 3), name="image")
    x = K.layers.ReLU(name="stem_relu")(K.layers.BatchNormalization(name="stem_bn")(conv(K, 16, "stem")(i)))
    x = K.layers.MaxPooling2D(2, name="stem_pool")(x)
    x = block(block(x, 16, "l1a"), 16, "l1b")
    x = block(block(x, 24, "l2a", strides=2), 24, "l2b")
    x = K.layers.GlobalAveragePooling2D(name="gap")(x)
    return K.Model(i, K.layers.Dense(10, name="logits")(x), name="resnet")


def unet(K):
    i = K.Input((32, 32, 3), name="image")
    e1 = conv(K, 8, "e1", activation="relu")(i)
    e2 = conv(K, 16, "e2", activation="relu")(K.layers.MaxPooling2D(2, name="p1")(e1))
    b = conv(K, 24, "bottom", activation="relu")(K.layers.MaxPooling2D(2, name="p2")(e2))
    u2 = K.layers.Conv2DTranspose(16, 2, strides=2, name="up2")(b)
    d2 = conv(K, 16, "d2", activation="relu")(K.layers.Concatenate(name="cat2")([u2, e2]))
    u1 = K.layers.UpSampling2D(2, name="up1")(d2)
    d1 = conv(K, 8, "d1", activation="relu")(K.layers.Concatenate(name="cat1")([e1, u1]))
    return K.Model(i, conv(K, 3, "head", 1, activation="sigmoid")(d1), name="unet")


def densenet_block(K):
    i = K.Input((32, 32, 3), name="image")
    x = conv(K, 8, "stem")(i)
    for k in range(3):
        y = K.layers.ReLU(name=f"dl{k}_relu")(K.layers.BatchNormalization(name=f"dl{k}_bn")(x))
        y = conv(K, 6, f"dl{k}_conv")(y)
        x = K.layers.Concatenate(name=f"dl{k}_cat")([x, y])
    x = conv(K, 12, "transition", 1)(K.layers.BatchNormalization(name="tr_bn")(x))
    x = K.layers.AveragePooling2D(2, name="tr_pool")(x)
    x = K.layers.GlobalAveragePooling2D(name="gap")(x)
    return K.Model(i, K.layers.Dense(5, activation="softmax", name="probs")(x), name="densenet")


def mobilenet_v2(K):
    return K.applications.MobileNetV2(input_shape=(64, 64, 3), alpha=0.35, weights=None, classes=10)


def separable_stack(K):
    i = K.Input((32, 32, 3), name="image")
    x = conv(K, 8, "stem", activation="relu")(i)
    x = K.layers.DepthwiseConv2D(3, padding="same", name="dw1")(x)
    x = K.layers.ReLU(6.0, name="dw1_relu")(K.layers.BatchNormalization(name="dw1_bn")(x))
    x = conv(K, 16, "pw1", 1)(x)
    x = K.layers.SeparableConv2D(16, 3, padding="same", depth_multiplier=2, activation="relu", name="sep1")(x)
    x = K.layers.SeparableConv2D(12, 3, padding="same", name="sep2")(x)
    x = K.layers.DepthwiseConv2D(3, padding="same", activation="relu", name="dw2")(x)
    return K.Model(i, conv(K, 3, "head", 1)(x), name="separable")


def bn_everywhere(K):
    """A Sequential chain with BatchNormalization after every convolution (the Sequential path)."""
    layers = [K.Input((32, 32, 3))]
    for k, (filters, act) in enumerate([(12, K.layers.ReLU), (16, K.layers.LeakyReLU), (10, K.layers.ELU)]):
        layers += [conv(K, filters, f"c{k}"), K.layers.BatchNormalization(name=f"bn{k}"), act(name=f"act{k}")]
        if k == 1:
            layers += [K.layers.MaxPooling2D(2, name="pool"), K.layers.Dropout(0.3, name="drop")]
    layers += [conv(K, 4, "head", 1)]
    return K.Sequential(layers, name="bn_everywhere")


def encoder_decoder(K):
    i = K.Input((32, 32, 3), name="image")
    x = conv(K, 16, "enc1", strides=2, activation="relu")(i)
    x = conv(K, 24, "enc2", strides=2, activation="relu")(x)
    x = K.layers.Conv2DTranspose(16, 3, strides=2, padding="same", name="dec1")(x)
    x = K.layers.PReLU(shared_axes=[1, 2], name="dec1_prelu")(x)
    x = K.layers.Conv2DTranspose(8, 3, strides=2, padding="same", activation="relu", name="dec2")(x)
    x = K.layers.Cropping2D(1, name="crop")(K.layers.ZeroPadding2D(1, name="pad")(x))
    return K.Model(i, conv(K, 2, "head", 1)(x), name="encoder_decoder")


def classifier(K):
    i = K.Input((16, 16, 3), name="image")
    x = K.layers.MaxPooling2D(2, name="pool1")(conv(K, 8, "c1", activation="relu")(i))
    x = conv(K, 12, "c2", activation="relu")(x)
    flat = K.layers.Dense(16, activation="relu", name="fc_flat")(K.layers.Flatten(name="flatten")(x))
    pooled = K.layers.Dense(16, activation="relu", name="fc_gap")(K.layers.GlobalAveragePooling2D(name="gap")(x))
    x = K.layers.Add(name="fc_add")([flat, pooled])
    return K.Model(i, K.layers.Dense(5, name="logits")(x), name="classifier")


def fcn_pose(K):
    model = build_fcn_pose(input_size=64)
    return model if K is tf_keras else K.Model.from_config(model.get_config())


def merges_and_reshapes(K):
    """Every merge, a concatenation feeding an Add, reshapes, resizing, dropout and channel-mixing layers."""
    i = K.Input((16, 16, 3), name="image")
    a, b = conv(K, 8, "a", activation="relu")(i), conv(K, 8, "b", activation="relu")(i)
    c = conv(K, 16, "c")(i)
    m = K.layers.Concatenate(name="cat")([K.layers.Subtract(name="sub")([a, b]),
                                          K.layers.Multiply(name="mul")([a, b])])
    x = K.layers.Add(name="add")([m, c])
    x = K.layers.Maximum(name="max")([x, K.layers.Average(name="avg")([x, c])])
    x = K.layers.Resizing(24, 24, name="resize")(x)
    x = K.layers.Reshape((24 * 24, 16), name="rows")(x)
    x = K.layers.Reshape((24, 24, 16), name="back")(x)
    x = K.layers.SpatialDropout2D(0.2, name="sdrop")(K.layers.Dropout(0.1, name="drop")(x))
    d = K.layers.LayerNormalization(name="ln")(conv(K, 8, "d")(x))  # mixes channels: d is kept whole
    e = K.layers.Softmax(name="soft")(conv(K, 6, "e")(d))  # likewise
    x = K.layers.Concatenate(name="cat2")([conv(K, 10, "f", activation="relu")(x), e])
    return K.Model(i, conv(K, 3, "head", 1)(x), name="merges")


def preprocessing(K):
    """EfficientNet's and MobileNetV3's preprocessing layers at the input, a per-channel Rescaling inside."""
    i = K.Input((16, 16, 3), name="image")
    x = K.layers.Rescaling(1 / 127.5, offset=-1.0, name="rescale")(i)
    x = K.layers.Normalization(axis=-1, name="norm")(x)
    x = conv(K, 8, "c1", activation="relu")(x)
    x = K.layers.Rescaling([0.5 + k / 8 for k in range(8)], name="channel_scale")(x)
    x = conv(K, 6, "c2", activation="relu")(x)
    return K.Model(i, conv(K, 3, "head", 1)(x), name="preprocessing")


def squeeze_excite(K):
    """MobileNetV3's block: hard sigmoid as tensor arithmetic (``relu6(x + 3) * (1 / 6)``: Keras 3 operations,
    tf_keras TFOpLambda layers), hard swish as a Multiply, a squeeze-excite reading a GlobalAveragePooling2D with
    keepdims, and the residual written as ``x + y``."""
    def hard_sigmoid(x):
        return K.layers.ReLU(6.0)(x + 3.0) * (1.0 / 6.0)

    i = K.Input((16, 16, 3), name="image")
    x = K.layers.BatchNormalization(name="stem_bn")(conv(K, 16, "stem")(i))
    x = K.layers.Multiply(name="stem_hswish")([x, hard_sigmoid(x)])
    y = K.layers.DepthwiseConv2D(3, padding="same", name="dw")(x)
    y = K.layers.Activation("relu", name="dw_relu")(K.layers.BatchNormalization(name="dw_bn")(y))
    s = K.layers.GlobalAveragePooling2D(keepdims=True, name="se_pool")(y)
    s = conv(K, 16, "se_expand", 1)(conv(K, 4, "se_reduce", 1, activation="relu")(s))
    y = K.layers.Multiply(name="se_mul")([y, hard_sigmoid(s)])
    y = K.layers.BatchNormalization(name="project_bn")(conv(K, 16, "project", 1)(y))
    x = K.layers.Dropout(0.2, name="drop")(x + y)
    return K.Model(i, conv(K, 3, "head", 1)(x), name="squeeze_excite")


def convnext_block(K, nested=False):
    """ConvNeXt's pieces: a depthwise convolution written as Conv2D(groups=C), LayerNormalization, Dense on feature
    maps, LayerScale and StochasticDepth (keras.applications.convnext), the residual as ``x + y``; then a grouped
    depthwise convolution and a LayerScale on channels that can be pruned. ``nested``: the stem is a Sequential
    model inside the model, as ConvNeXt's is."""
    convnext = importlib.import_module(f"{K.__name__}.src.applications.convnext")
    i = K.Input((16, 16, 3), name="image")
    x = K.layers.Normalization(mean=[0.4, 0.5, 0.6], variance=[0.05, 0.06, 0.07], name="prestem")(i)
    stem = [conv(K, 16, "stem_conv", 2, strides=2), K.layers.LayerNormalization(epsilon=1e-6, name="stem_ln")]
    if nested:
        x = K.Sequential(stem, name="stem")(x)
    else:
        x = stem[1](stem[0](x))
    y = K.layers.Conv2D(16, 7, padding="same", groups=16, name="dw")(x)
    y = K.layers.Dense(64, name="pw1")(K.layers.LayerNormalization(epsilon=1e-6, name="ln")(y))
    y = K.layers.Dense(16, name="pw2")(K.layers.Activation("gelu", name="gelu")(y))
    y = convnext.StochasticDepth(0.1, name="drop_path")(convnext.LayerScale(0.5, 16, name="scale")(y))
    x = x + y
    z = K.layers.ReLU(name="z_relu")(K.layers.BatchNormalization(name="z_bn")(conv(K, 12, "z_conv")(x)))
    z = K.layers.Conv2D(12, 3, padding="same", groups=12, activation="relu", name="z_dw")(z)
    z = convnext.LayerScale(0.5, 12, name="z_scale")(z)
    return K.Model(i, conv(K, 3, "head", 1)(z), name="convnext")


def grouped(K, width=20, groups=2):
    """RegNetX's block: 1x1, a grouped 3x3 convolution (groups of width / groups channels), 1x1, a residual Add."""
    i = K.Input((16, 16, 3), name="image")
    x = K.layers.ReLU(name="stem_relu")(K.layers.BatchNormalization(name="stem_bn")(conv(K, width, "stem")(i)))
    y = K.layers.ReLU(name="a_relu")(K.layers.BatchNormalization(name="a_bn")(conv(K, width, "a", 1)(x)))
    y = K.layers.Conv2D(width, 3, padding="same", groups=groups, name="b")(y)
    y = K.layers.ReLU(name="b_relu")(K.layers.BatchNormalization(name="b_bn")(y))
    y = K.layers.BatchNormalization(name="c_bn")(conv(K, width, "c", 1)(y))
    x = K.layers.ReLU(name="out_relu")(K.layers.Add(name="add")([x, y]))
    return K.Model(i, conv(K, 3, "head", 1)(x), name="grouped")


ARCHITECTURES = {f.__name__: f for f in (residual_block, resnet_like, unet, densenet_block, mobilenet_v2,
                                         separable_stack, bn_everywhere, encoder_decoder, classifier, fcn_pose,
                                         merges_and_reshapes, preprocessing, squeeze_excite, convnext_block, grouped)}
SLOW = {"mobilenet_v2"}


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------

def randomize(model, seed=0):
    """Random kernels (He-like), non-zero biases, and random BatchNormalization gamma, beta, mean and variance."""
    rng = np.random.default_rng(seed)
    for layer in model.layers:
        weights = layer.get_weights()
        if not weights:
            continue
        if type(layer).__name__ == "BatchNormalization":
            new = [rng.normal(0, 0.5, w.shape) for w in weights]
            new[0] = rng.uniform(0.5, 1.5, weights[0].shape)  # gamma
            new[-1] = rng.uniform(0.5, 2.0, weights[-1].shape)  # moving variance
        elif type(layer).__name__ == "Normalization":  # mean, variance, count (an integer, kept)
            new = [rng.normal(0, 1, weights[0].shape), rng.uniform(0.5, 2.0, weights[1].shape)] + weights[2:]
        elif type(layer).__name__ in ("PReLU", "LayerNormalization"):
            new = [rng.uniform(0.1, 1.0, w.shape) for w in weights]
        else:
            new = []
            for w in weights:
                fan_in = np.prod(w.shape[:-1]) if w.ndim > 1 else 0
                new.append(rng.normal(0, np.sqrt(2 / fan_in), w.shape) if w.ndim > 1 else rng.normal(0, 0.1, w.shape))
        layer.set_weights([w if w.dtype.kind != "f" else w.astype(np.float32) for w in new])
    return model


@functools.lru_cache(maxsize=None)
def built(arch, flavour):
    return randomize(ARCHITECTURES[arch](FLAVOURS[flavour]))


@functools.lru_cache(maxsize=None)
def pruned(arch, flavour, rate):
    model = built(arch, flavour)
    return plan_graph(model, rate), prune_graph(model, rate)


def run_changed(model, changes, x, training=False):
    """`model`'s outputs on `x` with some layers' weights replaced (layer name -> weights), then put back
    (cheaper than a clone of the model)."""
    saved = {name: model.get_layer(name).get_weights() for name in changes}
    try:
        for name, weights in changes.items():
            model.get_layer(name).set_weights(weights)
        return run_training(model, x) if training else run(model, x)
    finally:
        for name, weights in saved.items():
            model.get_layer(name).set_weights(weights)


def run(model, x):
    out = model(x, training=False)
    return [np.asarray(o) for o in (out if isinstance(out, (list, tuple)) else [out])]


def run_training(model, x):
    return np.asarray(model(x, training=True))


def inputs_for(model, seed=1):
    shape = (2,) + tuple(model.inputs[0].shape[1:])
    return np.random.default_rng(seed).normal(0, 1, shape).astype(np.float32)


def assert_same(got, want):
    for g, w in zip(got, want):
        assert g.shape == w.shape
        scale = max(float(np.abs(w).max()), 1e-12)
        assert float(np.abs(g - w).max()) / scale <= TOLERANCE


def removed(count, kept):
    return np.setdiff1d(np.arange(count), kept)


def kind(layer):
    return type(layer).__name__


def zero_readers(model, plan):
    """(a): the weights zeroing the input slices of every layer that reads a removed channel (layer name -> weights)."""
    changes = {}
    for layer in model.layers:
        if layer.name not in plan.layers or kind(layer) not in ("Conv2D", "Conv2DTranspose", "SeparableConv2D",
                                                                 "Dense"):
            continue
        w = layer.get_weights()
        groups = getattr(layer, "groups", 1)
        if groups > 1:  # input channel c is row c % (cin / groups) of the filters of group c // (cin / groups)
            per_in, per_out = w[0].shape[2], w[0].shape[3] // groups
            for c in removed(per_in * groups, plan.layers[layer.name].kept_in[0]):
                w[0][:, :, c % per_in, (c // per_in) * per_out:(c // per_in + 1) * per_out] = 0
            changes[layer.name] = w
            continue
        in_axis = {"Conv2D": 2, "Conv2DTranspose": 3, "SeparableConv2D": 2, "Dense": 0}[kind(layer)]
        gone = removed(w[0].shape[in_axis], plan.layers[layer.name].kept_in[0])
        if kind(layer) == "Conv2DTranspose":
            w[0][..., gone] = 0
        elif kind(layer) == "Dense":
            w[0][gone, :] = 0
        else:  # Conv2D kernel, SeparableConv2D depthwise kernel: (kh, kw, cin, ...)
            w[0][:, :, gone, :] = 0
        changes[layer.name] = w
    return changes


def kill_removed_filters(model, plan):
    """(b): the weights making the filters to be removed output exactly 0 (zero kernel slice and bias; BN beta
    and moving mean zero), layer name -> weights."""
    changes = {}
    for layer in model.layers:
        entry = plan.layers.get(layer.name)
        if entry is None:
            continue
        w = layer.get_weights()
        if kind(layer) in ("Conv2D", "Conv2DTranspose", "SeparableConv2D", "Dense"):
            out_axis = {"Conv2DTranspose": 2}.get(kind(layer), -1)
            kernel = 1 if kind(layer) == "SeparableConv2D" else 0
            gone = removed(w[kernel].shape[out_axis], entry.kept_out)
            np.moveaxis(w[kernel], out_axis, -1)[..., gone] = 0
            for bias in w[kernel + 1:]:
                bias[gone] = 0
        elif kind(layer) == "BatchNormalization":
            gone = removed(w[0].shape[0], entry.kept_out)
            beta = 1 if layer.scale else 0
            if layer.center:
                w[beta][gone] = 0
            w[-2][gone] = 0  # moving mean
        elif kind(layer) == "DepthwiseConv2D" and len(w) > 1:
            w[1][removed(w[1].shape[0], entry.kept_out)] = 0
        else:
            continue
        changes[layer.name] = w
    return changes


def cases():
    for arch in ARCHITECTURES:
        marks = [pytest.mark.slow] if arch in SLOW else []
        for flavour in FLAVOURS:
            for rate in RATES:
                yield pytest.param(arch, flavour, rate, marks=marks, id=f"{arch}-{flavour}-{rate}")


# ------------------------------------------------------------------------------------------
# exactness on every architecture
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("arch, flavour, rate", list(cases()))
def test_pruned_model_equals_original_with_readers_zeroed(arch, flavour, rate):
    model = built(arch, flavour)
    plan, small = pruned(arch, flavour, rate)
    assert small.count_params() < model.count_params()
    x = inputs_for(model)
    assert_same(run(small, x), run_changed(model, zero_readers(model, plan), x))


@pytest.mark.parametrize("arch, flavour, rate", list(cases()))
def test_pruned_model_equals_original_with_dead_filters(arch, flavour, rate):
    model = built(arch, flavour)
    plan, small = pruned(arch, flavour, rate)
    x = inputs_for(model, seed=2)
    dead = run_changed(model, kill_removed_filters(model, plan), x)
    assert_same(run(small, x), dead)
    assert not np.allclose(dead[0], run(model, x)[0])  # the removed filters did matter


@pytest.mark.parametrize("arch, flavour, rate", list(cases()))
def test_plan_widths_and_counts(arch, flavour, rate):
    model = built(arch, flavour)
    plan, small = pruned(arch, flavour, rate)
    assert type(small).__module__.split(".")[0] == type(model).__module__.split(".")[0]
    assert [layer.name for layer in small.layers] == [layer.name for layer in model.layers]
    assert plan.params == (model.count_params(), small.count_params())
    assert plan.macs[1] < plan.macs[0]
    assert any(not p.group.frozen for p in plan.groups)
    for p in plan.groups:
        expected = p.group.width if p.group.frozen else keep_count(p.group.width, rate)
        assert len(p.kept) == expected, p.group
    for name, kept in plan.kept_filters().items():
        layer = small.get_layer(name)
        assert (layer.units if kind(layer) == "Dense" else layer.filters) == len(kept)


# ------------------------------------------------------------------------------------------
# groups
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("flavour", FLAVOURS)
def test_groups_of_a_residual_block(flavour):
    graph = dependency_graph(built("residual_block", flavour))
    producers = {g.producers: g for g in graph.groups}
    assert set(producers) == {("image",), ("stem", "b2_conv"), ("b1_conv",), ("head",)}
    assert producers[("image",)].frozen and producers[("head",)].frozen
    assert not producers[("stem", "b2_conv")].frozen and producers[("stem", "b2_conv")].width == 16
    assert "stem, b2_conv" in graph.describe()


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_concatenation_into_an_add_couples_by_offset(flavour):
    graph = dependency_graph(built("merges_and_reshapes", flavour))
    group = next(g for g in graph.groups if "c" in g.producers)
    assert set(group.producers) == {"a", "b", "c"} and group.width == 8
    assert group.channel_of["c"].tolist() == list(range(8)) * 2  # c's channel k and k + 8 meet a's k
    frozen = {p: g.frozen for g in graph.groups for p in g.producers}
    assert "ln mixes channels" in frozen["d"] and "soft mixes channels" in frozen["e"]
    assert not frozen["f"]


def test_fcn_pose_matches_prune_model():
    model = randomize(build_fcn_pose(input_size=64))
    for rate in (0.3, 0.5, 0.7, 0.9):
        want, got = prune_model(model, rate), prune_graph(model, rate)
        assert conv_widths(got) == conv_widths(want)
        for w, g in zip(want.get_weights(), got.get_weights()):
            np.testing.assert_array_equal(g, w)


# ------------------------------------------------------------------------------------------
# options
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("flavour", FLAVOURS)
def test_keep_is_honoured(flavour):
    model = built("resnet_like", flavour)
    small = prune_graph(model, 0.5, keep=["l1a_c1", "l2a_bn2"])
    assert small.get_layer("l1a_c1").filters == 16
    # l2a_bn2 carries the channels of l2a_c2, l2a_proj and l2b_c2 (coupled through the Adds)
    for name in ("l2a_c2", "l2a_proj", "l2b_c2"):
        assert small.get_layer(name).filters == 24
    assert small.get_layer("l2b_c1").filters == 12 and small.get_layer("l1b_c1").filters == 8
    with pytest.raises(UserError, match="no layer named nope"):
        prune_graph(model, 0.5, keep=["nope"])


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_round_to_and_min_filters(flavour):
    model = built("resnet_like", flavour)
    rounded = plan_graph(model, 0.3, round_to=8)
    for p in rounded.groups:
        if not p.group.frozen:
            assert len(p.kept) % 8 == 0 or len(p.kept) == p.group.width
            assert len(p.kept) >= keep_count(p.group.width, 0.3)
    assert any(len(p.kept) == 16 for p in rounded.groups if p.group.width == 16 and not p.group.frozen)  # 12 -> 16
    floored = plan_graph(model, 0.9, min_filters=4)
    widths = [len(p.kept) for p in floored.groups if not p.group.frozen]
    assert min(widths) == 4 and widths == [max(keep_count(p.group.width, 0.9), 4)
                                           for p in floored.groups if not p.group.frozen]
    for bad in ({"round_to": 0}, {"min_filters": -1}, {"aggregate": "median"}, {"importance": "l3"}):
        with pytest.raises(UserError):
            plan_graph(model, 0.5, **bad)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_importance_callable_and_aggregate(flavour):
    model = built("residual_block", flavour)

    def reverse(m):  # prefer low filter indices
        return {layer.name: -np.arange(layer.filters, dtype=float) for layer in m.layers if kind(layer) == "Conv2D"}

    plan = plan_graph(model, 0.5, importance=reverse)
    assert plan.kept_filters()["stem"].tolist() == list(range(8))
    l1 = plan_graph(model, 0.5)
    by_sum = next(p for p in l1.groups if "stem" in p.group.producers)
    stem, b2 = (np.abs(model.get_layer(name).get_weights()[0].astype(np.float64)).sum(axis=(0, 1, 2))
                for name in ("stem", "b2_conv"))
    np.testing.assert_allclose(by_sum.scores, stem + b2)
    by_max = next(p for p in plan_graph(model, 0.5, aggregate="max").groups if "stem" in p.group.producers)
    np.testing.assert_allclose(by_max.scores, np.maximum(stem, b2))
    with pytest.raises(UserError, match="no scores for layer"):
        plan_graph(model, 0.5, importance=lambda m: {})


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_original_unchanged_and_flavour_kept(flavour):
    model = built("unet", flavour)
    before = [w.copy() for w in model.get_weights()]
    small = prune_graph(model, 0.5)
    assert all(np.array_equal(a, b) for a, b in zip(before, model.get_weights()))
    assert isinstance(small, FLAVOURS[flavour].Model)
    assert small.name == model.name
    sequential = prune_graph(built("bn_everywhere", flavour), 0.5)
    assert isinstance(sequential, FLAVOURS[flavour].Sequential)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_per_channel_offsets_and_statistics_are_sliced(flavour):
    """A Rescaling's offset and a Normalization's mean map a removed (zero) channel to a non-zero value, so only the
    readers-zeroed check (a) applies; the pruned layers keep the kept channels' values."""
    K = FLAVOURS[flavour]
    scale, offset, mean, variance = (np.linspace(start, stop, 6) for start, stop in
                                     ((0.5, 2.0), (-0.3, 0.4), (-1.0, 1.0), (0.5, 3.0)))
    i = K.Input((8, 8, 3), name="image")
    x = K.layers.Rescaling(scale.tolist(), offset=offset.tolist(), name="rs")(conv(K, 6, "c1", activation="relu")(i))
    x = K.layers.Normalization(mean=mean.tolist(), variance=variance.tolist(), name="nm")(x)
    model = randomize(K.Model(i, conv(K, 2, "head", 1)(x), name="offsets"))
    plan, small = plan_graph(model, 0.5), prune_graph(model, 0.5)
    kept = plan.kept_filters()["c1"]
    assert len(kept) == 3
    np.testing.assert_allclose(small.get_layer("rs").get_config()["scale"], scale[kept])
    np.testing.assert_allclose(small.get_layer("rs").get_config()["offset"], offset[kept])
    np.testing.assert_allclose(small.get_layer("nm").get_config()["mean"], mean[kept])
    np.testing.assert_allclose(small.get_layer("nm").get_config()["variance"], variance[kept])
    x = inputs_for(model)
    assert_same(run(small, x), run_changed(model, zero_readers(model, plan), x))


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_a_grouped_convolution_keeps_as_many_channels_in_each_group(flavour):
    K = FLAVOURS[flavour]
    model = randomize(grouped(K, width=16, groups=4))
    plan = plan_graph(model, 0.7)  # keep rule: 16 - floor(11.2) = 5 channels, rounded up to 8 for 4 groups
    for name in ("a", "b"):
        kept = plan.kept_filters()[name]
        assert len(kept) == 8 and np.bincount(kept // 4, minlength=4).tolist() == [2, 2, 2, 2]
    assert len(plan.kept_filters()["stem"]) == 5  # not a grouped convolution's channels
    small = prune_graph(model, 0.7)
    assert small.get_layer("b").groups == 4 and small.get_layer("b").get_weights()[0].shape == (3, 3, 2, 8)
    x = inputs_for(model)
    assert_same(run(small, x), run_changed(model, zero_readers(model, plan), x))
    assert len(plan_graph(model, 0.7, round_to=8).kept_filters()["a"]) == 8
    with pytest.raises(UserError, match="multiple of 4"):
        plan_graph(model, 0.5, counts=[8, 6, 8])
    i = K.Input((8, 8, 3), name="image")
    both = K.layers.Concatenate(name="cat")([conv(K, 8, "p")(i), conv(K, 8, "q")(i)])
    split = K.Model(i, conv(K, 2, "head")(K.layers.Conv2D(8, 3, groups=4, name="g")(both)))
    assert "g (Conv2D): a grouped convolution (groups=4) whose channels are not one whole group" in _refusal(split)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_a_nested_model_prunes_as_its_flat_equivalent(flavour):
    """ConvNeXt's stem is a Sequential inside the model: traced through, its layers become the pruned model's."""
    K = FLAVOURS[flavour]
    flat, nested = built("convnext_block", flavour), convnext_block(K, nested=True)
    for layer in flat.layers:
        if layer.get_weights():
            (nested.get_layer("stem").get_layer(layer.name) if layer.name.startswith("stem_")
             else nested.get_layer(layer.name)).set_weights(layer.get_weights())
    want, got = prune_graph(flat, 0.5), prune_graph(nested, 0.5)
    named = [[layer.name for layer in m.layers if not layer.name.startswith("tf.")] for m in (got, want)]  # tf_keras
    assert named[0] == named[1] and len(got.layers) == len(want.layers)  # names its `x + y` in order of creation
    assert got.get_layer("pw1").units == 32 and got.get_layer("z_dw").filters == 6
    x = inputs_for(flat)
    np.testing.assert_array_equal(run(got, x)[0], run(want, x)[0])
    np.testing.assert_allclose(run(nested, x)[0], run(flat, x)[0], rtol=1e-6, atol=1e-6)
    i = K.Input((8, 8, 3), name="image")
    base = K.Sequential([K.Input((8, 8, 3)), conv(K, 8, "base_conv"), K.layers.BatchNormalization(name="base_bn"),
                         K.layers.ReLU(name="base_relu")], name="base")
    tuned = K.Model(i, conv(K, 2, "head", 1)(randomize(base)(i, training=False)))  # the fine-tuning idiom
    plan, small, x = plan_graph(tuned, 0.5), prune_graph(tuned, 0.5), inputs_for(tuned)
    assert small.get_layer("base_conv").filters == 4  # in training too, base_bn runs as the nested call says
    assert_same([run_training(small, x)], [run_changed(tuned, zero_readers(tuned, plan), x, training=True)])
    inner = K.Sequential([conv(K, 3, "inner_conv")], name="inner")
    twice = K.Model(i, conv(K, 2, "head")(K.layers.Add(name="sum")([inner(i), inner(i)])))
    assert "inner (Sequential) is used more than once" in _refusal(twice)
    dup = K.Sequential([K.Input((8, 8, 3)), conv(K, 4, "dup")], name="dup_inner")
    clash = K.Model(i, conv(K, 2, "head")(conv(K, 4, "dup", 1)(dup(i))))  # the flat model could not hold both
    assert "two layers named dup" in _refusal(clash)


# ------------------------------------------------------------------------------------------
# refusals
# ------------------------------------------------------------------------------------------

def _refusal(model):
    with pytest.raises(UserError) as info:
        prune_graph(model, 0.5)
    message = str(info.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_refusals_name_the_layer(flavour):
    K = FLAVOURS[flavour]
    i = K.Input((8, 8, 3), name="image")
    permuted = K.Model(i, conv(K, 2, "head")(K.layers.Permute((2, 1, 3), name="perm")(conv(K, 4, "c")(i))))
    assert "unsupported layer perm (Permute)" in _refusal(permuted)
    multiplied = K.Model(i, conv(K, 2, "head")(K.layers.DepthwiseConv2D(3, depth_multiplier=2, name="dw")(i)))
    assert "dw (DepthwiseConv2D)" in _refusal(multiplied) and "depth_multiplier 2" in _refusal(multiplied)
    shared = conv(K, 3, "shared")
    twice = K.Model(i, conv(K, 2, "head")(shared(shared(i))))
    assert "shared (Conv2D) is used more than once" in _refusal(twice)
    class Subclassed(K.Model):  # a nested model whose graph cannot be traced (a functional one is traced through)
        def __init__(self):
            super().__init__(name="inner")
            self.inner_conv = conv(K, 3, "inner_conv")

        def call(self, x):
            return self.inner_conv(x)

    j = K.Input((8, 8, 3), name="outer_image")
    nested = K.Model(j, conv(K, 2, "head")(Subclassed()(j)))
    assert "inner" in _refusal(nested) and "nested model" in _refusal(nested)
    broadcast = K.Model(i, K.layers.Multiply(name="scale")([conv(K, 4, "c4")(i), conv(K, 1, "c1")(i)]))
    assert "scale (Multiply)" in _refusal(broadcast)
    with pytest.raises(UserError, match="tf_keras or Keras 3 model"):
        prune_graph(object(), 0.5)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_operations_on_tensors(flavour):
    """Tensor arithmetic couples as a merge or passes with one number; other constants and functions are refused."""
    K = FLAVOURS[flavour]
    graph = dependency_graph(built("squeeze_excite", flavour))
    group = next(g for g in graph.groups if "stem" in g.producers)
    assert set(group.producers) == {"stem", "se_expand", "project"} and not group.frozen
    i = K.Input((8, 8, 3), name="image")
    c = conv(K, 4, "c")(i)
    constant = np.arange(4, dtype=np.float32)
    vector = K.Model(i, conv(K, 2, "head")(c * (constant if K is keras3 else tf_keras.backend.constant(constant))))
    assert "is not one number" in _refusal(vector)
    import tensorflow as tf

    mean = keras3.ops.mean(c, axis=-1, keepdims=True) if K is keras3 else tf.reduce_mean(c, axis=-1, keepdims=True)
    message = _refusal(K.Model(i, conv(K, 2, "head")(mean)))
    assert "unsupported" in message and ("Mean" in message or "reduce_mean" in message)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_two_inputs_two_outputs_and_a_dense_on_feature_maps(flavour):
    K = FLAVOURS[flavour]
    left, right = K.Input((16, 16, 3), name="left"), K.Input((16, 16, 1), name="right")
    a = conv(K, 8, "a", activation="relu")(left)
    b = K.layers.Dense(8, activation="relu", name="pixelwise")(conv(K, 6, "b", activation="relu")(right))
    x = conv(K, 12, "joint", activation="relu")(K.layers.Concatenate(name="cat")([a, b]))
    model = randomize(K.Model([left, right], [conv(K, 2, "out1", 1)(x), K.layers.Dense(3, name="out2")(x)]))
    plan, small = plan_graph(model, 0.5), prune_graph(model, 0.5)
    assert [small.get_layer(n).filters for n in ("a", "b", "joint", "out1")] == [4, 3, 6, 2]
    assert small.get_layer("pixelwise").units == 4 and small.get_layer("out2").units == 3
    x = [inputs_for(K.Model(left, a)), inputs_for(K.Model(right, b), seed=3)]
    assert_same(run(small, x), run_changed(model, zero_readers(model, plan), x))
    assert_same(run(small, x), run_changed(model, kill_removed_filters(model, plan), x))


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_an_unbuilt_model_is_refused(flavour):
    K = FLAVOURS[flavour]
    assert "not built" in _refusal(K.Sequential([K.layers.Conv2D(4, 3), K.layers.Conv2D(2, 1)]))


def test_docstring_examples():
    for module in (depgraph, graph_prune):
        assert doctest.testmod(module).failed == 0, module.__name__
