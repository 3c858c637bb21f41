"""Filter pruning: the keep rule, the L1 ranking, exact surgery, unsupported layers, magnitude pruning."""

import functools
import gzip
import io
import math
from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.training.model import DEFAULT_WIDTHS, build_fcn_pose, conv_widths
from fcnpose_tf.compression.costs import model_facts
from fcnpose_tf.compression.keep_rule import filter_l1_norms, floored_widths, keep_count, kept_filters, pruned_widths
from fcnpose_tf.compression.plan import chain_param_count, plan_widths
from fcnpose_tf.compression.prune import prune_model, prune_plan
from fcnpose_tf.compression.magnitude import magnitude_prune, weight_sparsity

# tfmot 0.8.1 still imports distutils' LooseVersion
pytestmark = pytest.mark.filterwarnings("ignore:distutils Version classes are deprecated:DeprecationWarning")

SWEEP = [1, 2, 3, 4, 5, 6, 7, 8, 9]  # tenths: the paper's 10%..90% sweep


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------

def randomize(model, seed=0, bias_scale=0.1):
    """Random kernels (He-like), non-zero biases and BatchNormalization statistics."""
    rng = np.random.default_rng(seed)
    for layer in model.layers:
        if isinstance(layer, keras.layers.BatchNormalization):
            layer.set_weights([rng.uniform(0.5, 2.0, w.shape).astype(np.float32) if i == len(layer.get_weights()) - 1
                               else rng.normal(0, 0.5, w.shape).astype(np.float32)
                               for i, w in enumerate(layer.get_weights())])
        elif layer.get_weights():
            weights = layer.get_weights()
            fan_in = np.prod(weights[0].shape[:-1])
            layer.set_weights([rng.normal(0, math.sqrt(2 / fan_in), weights[0].shape).astype(np.float32)]
                              + [rng.normal(0, bias_scale, w.shape).astype(np.float32) for w in weights[1:]])
    return model


def zeroed_reference(model, plan):
    """Copy of `model` whose removed filters output exactly 0: kernel and bias zeroed, and where a
    BatchNormalization follows, its moving mean and beta zeroed for those channels, so BN maps the
    0 to 0 whatever gamma and the variance are. Activations here map 0 to 0 (ReLU), so every later
    layer sees zeros in those channels, which is what deleting them means."""
    copy = keras.models.clone_model(model)
    copy.set_weights(model.get_weights())
    removed = np.array([], np.int64)
    for layer in copy.layers:
        if type(layer) is keras.layers.Conv2D:
            weights = layer.get_weights()
            removed = np.setdiff1d(np.arange(layer.filters), plan[layer.name])
            weights[0][..., removed] = 0
            if layer.use_bias:
                weights[1][removed] = 0
            layer.set_weights(weights)
        elif isinstance(layer, keras.layers.BatchNormalization) and len(removed):
            weights = layer.get_weights()  # [gamma], [beta], moving_mean, moving_variance
            weights[-2][removed] = 0
            if layer.center:
                weights[1 if layer.scale else 0][removed] = 0
            layer.set_weights(weights)
    return copy


def frames(size, n=2, seed=1):
    return np.random.default_rng(seed).random((n, size, size, 3), dtype=np.float32)


def bn_chain(size=32, order="conv-bn-relu", sequential=False, scale=True, center=True, use_bias=True):
    """A plain chain with BatchNormalization, Dropout, average pooling and Activation layers."""
    def block(filters, name):
        conv = keras.layers.Conv2D(filters, 3, padding="same", use_bias=use_bias, name=name)
        bn = keras.layers.BatchNormalization(scale=scale, center=center, name=f"{name}_bn")
        relu = keras.layers.ReLU(name=f"{name}_relu")
        return [conv, bn, relu] if order == "conv-bn-relu" else [conv, relu, bn]

    body = (block(12, "conv1") + [keras.layers.MaxPooling2D(2, name="pool1")]
            + block(10, "conv2") + [keras.layers.Dropout(0.3, name="drop"),
                                    keras.layers.AveragePooling2D(2, name="pool2")]
            + [keras.layers.Conv2D(8, 3, padding="same", name="conv3"), keras.layers.Activation("relu", name="act3"),
               keras.layers.UpSampling2D(4, name="up"),
               keras.layers.Conv2D(3, 1, activation="sigmoid", name="out")])
    inputs = keras.Input((size, size, 3), name="image")
    if sequential:
        return randomize(keras.Sequential([inputs] + body, name="seq"))
    x = inputs
    for layer in body:
        x = layer(x)
    return randomize(keras.Model(inputs, x, name="bnnet"))


# ------------------------------------------------------------------------------------------
# the keep rule
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("width", sorted(set(DEFAULT_WIDTHS)))
@pytest.mark.parametrize("tenths", SWEEP)
def test_keep_rule_every_width_every_rate(width, tenths):
    expected = width - (width * tenths) // 10  # exact integer arithmetic: n - floor(n * r)
    for rate in (tenths / 10, tenths * 0.1, 1 - (10 - tenths) / 10, f"0.{tenths}", Decimal(f"0.{tenths}"),
                 Fraction(tenths, 10)):
        assert keep_count(width, rate) == expected, rate


def test_keep_rule_floating_point_traps():
    assert 100 * 0.29 < 29  # the trap
    assert keep_count(100, 0.29) == 71
    assert keep_count(100, 0.57) == 43  # 100 * 0.57 = 56.99999999999999
    assert keep_count(10, 0.7) == 3 and keep_count(10, 0.1 * 7) == 3
    assert keep_count(3, 1 / 3) == 2  # 3 * (1/3) rounds to exactly 1.0
    # ours is n - floor(n r); Torch-Pruning's floor(n (1 - r)) keeps one fewer here
    assert keep_count(128, 0.7) == 39 and math.floor(128 * (1 - 0.7)) == 38
    assert all(keep_count(n, 0.999) >= 1 for n in range(1, 200))


@pytest.mark.slow
def test_pruned_widths_reproduce_paper_parameter_counts():
    assert pruned_widths(DEFAULT_WIDTHS, 0.7) == (39, 20, 10, 5, 3, 3, 5, 10, 20)
    for rate, params in [(0.7, 14_668), (0.5, 35_185), (0.9, 2_480), (0.0, 131_705)]:
        pruned = prune_model(build_fcn_pose(input_size=32), rate)
        assert pruned.count_params() == params, rate
        assert conv_widths(pruned) == pruned_widths(DEFAULT_WIDTHS, rate) + (9,)
        assert build_fcn_pose(pruned_widths(DEFAULT_WIDTHS, rate), input_size=32).count_params() == params


@pytest.mark.parametrize("rate", [-0.1, 1, 1.0, 1.2, float("nan"), float("inf"), "abc", "1/0", True, None, [0.5]])
def test_bad_rate_is_a_clear_error(rate):
    with pytest.raises(UserError, match="rate"):
        keep_count(8, rate)
    with pytest.raises(UserError, match="rate"):
        prune_model(build_fcn_pose(input_size=32), rate)


def test_bad_strategy():
    with pytest.raises(UserError, match="strategy must be one of independent, greedy"):
        prune_model(build_fcn_pose(input_size=32), 0.5, strategy="random")


# ------------------------------------------------------------------------------------------
# the ranking
# ------------------------------------------------------------------------------------------

def reference_kept(kernel, rate):
    """Slow reference: sort (−L1 norm, index) pairs, keep the first n − floor(n·rate), in index order."""
    n = kernel.shape[3]
    norms = [float(np.sum(np.abs(kernel[:, :, :, j].astype(np.float64)))) for j in range(n)]
    ranked = sorted(range(n), key=lambda j: (-norms[j], j))
    return sorted(ranked[:n - math.floor(Fraction(str(rate)) * n)])


@pytest.mark.parametrize("seed", range(5))
def test_kept_filters_match_reference_with_ties(seed):
    rng = np.random.default_rng(seed)
    # integer-valued kernels make exact ties in the L1 norm common
    kernel = rng.integers(-2, 3, size=(3, 3, 2, 16)).astype(np.float32)
    for rate in (0.1, 0.25, 0.5, 0.7, 0.9):
        assert kept_filters(kernel, rate).tolist() == reference_kept(kernel, rate)


def test_ties_go_to_lower_index_and_order_is_kept():
    kernel = np.zeros((1, 1, 1, 6), np.float32)
    kernel[0, 0, 0] = [1, 3, -3, 2, 3, 0]
    assert kept_filters(kernel, 0.5).tolist() == [1, 2, 4]  # the three 3s, in index order
    assert kept_filters(kernel, 0.7).tolist() == [1, 2]  # 6 - floor(4.2) = 2: ties to lower index
    assert filter_l1_norms(kernel).tolist() == [1, 3, 3, 2, 3, 0]
    assert filter_l1_norms(kernel, input_channels=[]).tolist() == [0] * 6


def test_plan_ranks_on_l1_norm_of_original_kernels():
    model = randomize(build_fcn_pose(input_size=32), seed=3)
    plan = prune_plan(model, 0.7)
    assert list(plan) == [f"conv{i}" for i in range(1, 11)]
    for name, kept in plan.items():
        kernel = model.get_layer(name).get_weights()[0]
        if name == "conv10":
            assert kept.tolist() == list(range(9))
        else:
            assert kept.tolist() == reference_kept(kernel, 0.7)


@pytest.mark.parametrize("norm", [None, 1, 2])  # the default (L1), and each weight norm given as importance=
def test_greedy_ranks_without_the_removed_input_channels(norm):
    from fcnpose_tf.compression.importance import WeightNorm

    extra = {} if norm is None else {"importance": WeightNorm(norm)}
    inputs = keras.Input((8, 8, 1))
    x = keras.layers.Conv2D(2, 1, name="a")(inputs)
    x = keras.layers.Conv2D(2, 1, name="b")(x)
    model = keras.Model(inputs, keras.layers.Conv2D(1, 1, name="out")(x))
    model.get_layer("a").set_weights([np.array([[[[5.0, 1.0]]]], np.float32), np.zeros(2, np.float32)])
    # b's filter 0 is heavy only on input channel 1, which `a` loses; filter 1 is moderate on channel 0
    model.get_layer("b").set_weights([np.array([[[[0.1, 2.0], [9.0, 0.0]]]], np.float32), np.zeros(2, np.float32)])
    assert prune_plan(model, 0.5, **extra)["b"].tolist() == [0]
    assert prune_plan(model, 0.5, strategy="greedy", **extra)["b"].tolist() == [1]
    assert prune_plan(model, 0.5, strategy="greedy", **extra)["a"].tolist() == [0]  # first layer: as independent
    assert prune_model(model, 0.5, strategy="greedy", **extra).get_layer("b").get_weights()[0].ravel().tolist() == \
        pytest.approx([2.0])


def test_greedy_matches_reference_on_fcn_pose():
    model = randomize(build_fcn_pose(input_size=32), seed=4)
    plan = prune_plan(model, 0.5, strategy="greedy")
    previous = None
    for i in range(1, 10):
        kernel = model.get_layer(f"conv{i}").get_weights()[0]
        if previous is not None:
            kernel = kernel[:, :, previous, :]
        assert plan[f"conv{i}"].tolist() == reference_kept(kernel, 0.5)
        previous = plan[f"conv{i}"]


# ------------------------------------------------------------------------------------------
# the narrowest layer (--min-filters): the same parameter budget, moved to the bottleneck
# ------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def built_params(widths):
    return build_fcn_pose(widths, input_size=32).count_params()


def reference_floored_widths(rate, floor):
    """An independent reading of the rule on FCN-Pose: try every rate k/128 >= rate (FCN-Pose's widths all divide
    128, so these are all the rates at which a keep count changes) with integer arithmetic, count parameters by
    building the network, and lower the floor until one fits the keep rule's budget."""
    budget = built_params(pruned_widths(DEFAULT_WIDTHS, rate))
    first = math.ceil(Fraction(str(rate)) * 128)
    for f in range(floor, 1, -1):
        for k in range(first, 128):
            widths = tuple(max(n - (n * k) // 128, min(n, f)) for n in DEFAULT_WIDTHS)
            if built_params(widths) <= budget:
                return widths, f
    return pruned_widths(DEFAULT_WIDTHS, rate), 1


@pytest.mark.slow
@pytest.mark.parametrize("rate", [0.5, 0.7, 0.8, 0.9])
@pytest.mark.parametrize("floor", [6, 8, 12])
def test_min_filters_widths_match_an_independent_search(rate, floor):
    model = build_fcn_pose(input_size=32)
    widths, used = prune_widths(model, rate, floor)
    plan = plan_widths(model, rate, floor)
    pruned = prune_model(model, rate, min_filters=floor, widths=plan)
    assert (plan.params, plan.macs) == (model_facts(pruned).params, model_facts(pruned).macs)
    assert (widths, used) == reference_floored_widths(rate, floor)
    assert all(w >= min(n, used) for n, w in zip(DEFAULT_WIDTHS, widths))
    assert chain_param_count(model, widths) == built_params(widths) <= built_params(pruned_widths(DEFAULT_WIDTHS, rate))


def prune_widths(model, rate, floor):
    """The pruned layers' widths and the floor used, as `plan_widths` plans them."""
    plan = plan_widths(model, rate, floor)
    return plan.pruned_widths, plan.floor


def test_min_filters_known_widths():
    model = build_fcn_pose(input_size=32)
    assert prune_widths(model, 0.7, 12) == ((30, 15, 12, 12, 8, 8, 12, 12, 15), 12)  # 14,344 parameters
    assert prune_widths(model, 0.7, 8) == ((36, 18, 9, 8, 8, 8, 8, 9, 18), 8)
    assert prune_widths(model, 0.9, 8)[1] == 5  # 2,480 parameters cannot hold five layers of 8: floor lowered
    for floor in (0, 1, 3):  # a floor the keep rule already meets changes nothing
        assert prune_widths(model, 0.7, floor) == (pruned_widths(DEFAULT_WIDTHS, 0.7), floor)
    assert floored_widths((128, 64, 8), 0.7, 4, sum) == ((38, 19, 4), 4)


@pytest.mark.parametrize("floor", [-1, 1.5, True, "8"])
def test_bad_min_filters(floor):
    with pytest.raises(UserError, match="narrowest layer width"):
        prune_widths(build_fcn_pose(input_size=32), 0.7, floor)


def test_chain_param_count_counts_batchnorm_and_biases():
    for use_bias in (True, False):
        model = bn_chain(use_bias=use_bias)
        for rate, floor in ((0.5, 0), (0.5, 5), (0.7, 0)):
            plan = prune_plan(model, rate, min_filters=floor)
            kept = [len(plan[name]) for name in ("conv1", "conv2", "conv3")]
            pruned = prune_model(model, rate, min_filters=floor)
            assert chain_param_count(model, kept) == pruned.count_params()
            widths = plan_widths(model, rate, floor)  # what the surgery builds, costed without building it
            assert widths.widths == conv_widths(pruned)
            assert (widths.params, widths.macs) == (model_facts(pruned).params, model_facts(pruned).macs)


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["independent", "greedy"])
def test_surgery_with_min_filters_is_exact(strategy):
    model = randomize(build_fcn_pose(input_size=32), seed=8)
    pruned = prune_model(model, 0.7, strategy=strategy, min_filters=12)
    assert conv_widths(pruned) == (30, 15, 12, 12, 8, 8, 12, 12, 15, 9) and pruned.count_params() == 14_344
    plan = prune_plan(model, 0.7, strategy=strategy, min_filters=12)
    uniform = prune_plan(model, 0.7, strategy=strategy)
    # the kept filters are the best-ranked ones: a layer kept wider keeps everything the keep rule kept
    assert set(uniform["conv4"].tolist()) <= set(plan["conv4"].tolist())
    reference = zeroed_reference(model, plan)
    x = frames(32)
    got, want, original = (np.asarray(m(x, training=False)) for m in (pruned, reference, model))
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    assert np.abs(got - original).max() > 1e-3


# ------------------------------------------------------------------------------------------
# surgery is exact
# ------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["independent", "greedy"])
@pytest.mark.parametrize("rate", [0.3, 0.7, 0.9])
def test_surgery_equals_original_with_removed_filters_zeroed(strategy, rate):
    model = randomize(build_fcn_pose(input_size=32), seed=5)
    pruned = prune_model(model, rate, strategy=strategy)
    reference = zeroed_reference(model, prune_plan(model, rate, strategy=strategy))
    x = frames(32)
    got, want, original = (np.asarray(m(x, training=False)) for m in (pruned, reference, model))
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    assert np.abs(got - original).max() > 1e-3  # the removed filters did matter: the test can fail


@pytest.mark.parametrize("strategy", ["independent", "greedy"])
@pytest.mark.parametrize("order", ["conv-bn-relu", "conv-relu-bn"])
@pytest.mark.parametrize("sequential", [False, True])
def test_surgery_exact_with_batchnorm(strategy, order, sequential):
    model = bn_chain(order=order, sequential=sequential)
    pruned = prune_model(model, 0.5, strategy=strategy)
    assert isinstance(pruned, keras.Sequential) == sequential
    assert [layer.name for layer in pruned.layers] == [layer.name for layer in model.layers]
    assert conv_widths(pruned) == (6, 5, 4, 3)
    assert pruned.get_layer("conv1_bn").get_weights()[0].shape == (6,)
    reference = zeroed_reference(model, prune_plan(model, 0.5, strategy=strategy))
    x = frames(32)
    got, want, original = (np.asarray(m(x, training=False)) for m in (pruned, reference, model))
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    assert np.abs(got - original).max() > 1e-3


@pytest.mark.parametrize("scale,center,use_bias", [(False, True, True), (True, False, False), (False, False, False)])
def test_surgery_exact_with_batchnorm_variants(scale, center, use_bias):
    model = bn_chain(scale=scale, center=center, use_bias=use_bias)
    pruned = prune_model(model, 0.7)
    reference = zeroed_reference(model, prune_plan(model, 0.7))
    x = frames(32)
    np.testing.assert_allclose(pruned(x, training=False), reference(x, training=False), atol=1e-5, rtol=0)


def test_weights_are_the_kept_slices_and_original_untouched():
    model = randomize(build_fcn_pose(input_size=32), seed=6)
    before = [w.copy() for w in model.get_weights()]
    plan = prune_plan(model, 0.7)
    pruned = prune_model(model, 0.7)
    k2, b2 = model.get_layer("conv2").get_weights()
    new_k2, new_b2 = pruned.get_layer("conv2").get_weights()
    np.testing.assert_array_equal(new_k2, k2[:, :, plan["conv1"], :][..., plan["conv2"]])
    np.testing.assert_array_equal(new_b2, b2[plan["conv2"]])
    assert pruned.get_layer("conv10").get_weights()[0].shape == (3, 3, 20, 9)
    for a, b in zip(before, model.get_weights()):
        np.testing.assert_array_equal(a, b)
    assert pruned.name == model.name and pruned.get_layer("conv10").activation.__name__ == "sigmoid"
    assert [layer.name for layer in pruned.layers] == [layer.name for layer in model.layers]


def test_rate_zero_is_an_identical_copy():
    model = randomize(build_fcn_pose(input_size=32), seed=7)
    copy = prune_model(model, 0.0)
    assert copy is not model and copy.count_params() == model.count_params()
    x = frames(32)
    np.testing.assert_array_equal(copy(x), model(x))


@pytest.mark.slow
def test_pruned_model_trains_and_saves(tmp_path):
    pruned = prune_model(randomize(build_fcn_pose(input_size=32)), 0.7)
    pruned.compile("adam", "binary_crossentropy")
    pruned.fit(frames(32, 2), np.zeros((2, 32, 32, 9), np.float32), epochs=1, verbose=0)
    path = tmp_path / "p70.keras"
    pruned.save(path)
    loaded = keras.models.load_model(path)
    assert loaded.count_params() == 14_668
    assert prune_model(loaded, 0.5).count_params() == build_fcn_pose(pruned_widths((39, 20, 10, 5, 3, 3, 5, 10, 20),
                                                                                   0.5), input_size=32).count_params()


# ------------------------------------------------------------------------------------------
# what is not a plain chain
# ------------------------------------------------------------------------------------------

def _functional(*layers, size=16):
    inputs = keras.Input((size, size, 3))
    x = inputs
    for layer in layers:
        x = layer(x)
    return keras.Model(inputs, x)


@pytest.mark.parametrize("make,message", [
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.Flatten(name="flat"),
                         keras.layers.Dense(2, name="fc")), r"unsupported layer flat \(Flatten\)"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.GlobalAveragePooling2D(name="gap"),
                         keras.layers.Dense(2, name="fc")), r"unsupported layer gap \(GlobalAveragePooling2D\)"),
    (lambda: _functional(keras.layers.DepthwiseConv2D(3, name="dw"), keras.layers.Conv2D(2, 1)),
     r"unsupported layer dw \(DepthwiseConv2D\)"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.Conv2DTranspose(2, 3, name="tconv")),
     r"unsupported layer tconv \(Conv2DTranspose\)"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.PReLU(name="prelu"),
                         keras.layers.Conv2D(2, 1)), r"unsupported layer prelu \(PReLU\)"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, groups=1, name="c"), keras.layers.Conv2D(4, 1, groups=2, name="g"),
                         keras.layers.Conv2D(2, 1)), r"unsupported layer g \(Conv2D\): grouped"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.Softmax(name="sm"),
                         keras.layers.Conv2D(2, 1)), r"layers c cannot lose channels: sm mixes channels"),
    (lambda: _functional(keras.layers.Conv2D(4, 3, name="c"), keras.layers.BatchNormalization(axis=1, name="bn1"),
                         keras.layers.Conv2D(2, 1)), r"unsupported layer bn1 \(BatchNormalization\)"),
    (lambda: _functional(keras.layers.Dense(4, name="fc"), keras.layers.Conv2D(2, 1)),
     r"unsupported layer fc \(Dense\)"),
    (lambda: _functional(keras.layers.Activation("relu")), "no Conv2D layer"),
])
def test_unsupported_models_are_clear_errors(make, message):
    with pytest.raises(UserError, match=message):
        prune_model(make(), 0.5)


def test_a_branching_model_is_pruned_per_group_of_coupled_channels():
    """A model that is not a chain goes to the graph surgery with the same plan (keep rule, floor at the parameter
    budget): channels meeting in an Add are one group, kept or removed together; greedy ranking is chain-only."""
    from fcnpose_tf.compression.graph_prune import prune_graph

    inputs = keras.Input((16, 16, 3))
    a = keras.layers.Conv2D(8, 3, padding="same", name="c1")(inputs)
    b = keras.layers.Conv2D(8, 3, padding="same", name="c2")(a)
    c = keras.layers.Conv2D(4, 3, padding="same", name="c3")(keras.layers.Add(name="skip")([a, b]))
    model = randomize(keras.Model(inputs, keras.layers.Conv2D(2, 1, name="out")(c)))
    plan = plan_widths(model, 0.5)
    assert plan.widths == (4, 2, 2) and plan.group_counts == (4, 2)  # {c1, c2}, c3, then the output
    pruned = prune_model(model, 0.5)
    assert [pruned.get_layer(n).filters for n in ("c1", "c2", "c3", "out")] == [4, 4, 2, 2]
    reference = prune_graph(model, 0.5)
    x = np.random.default_rng(0).random((2, 16, 16, 3)).astype("float32")
    np.testing.assert_array_equal(pruned(x).numpy(), reference(x).numpy())
    assert pruned.count_params() == plan.params
    with pytest.raises(UserError, match="greedy strategy ranks a chain"):
        prune_model(model, 0.5, strategy="greedy")
    # a floor keeps the narrow layer and pays for it in the coupled group, within the rate's parameter budget
    floored = plan_widths(model, 0.5, min_filters=4)
    assert floored.widths[1] == floored.floor == 3 and floored.params <= plan.params  # 4 exceeds the budget


def test_branch_without_merge_keeps_both_outputs():
    inputs = keras.Input((16, 16, 3))
    a = keras.layers.Conv2D(4, 3, padding="same", name="c1")(inputs)
    b = keras.layers.Conv2D(4, 3, padding="same", name="c2")(a)
    c = keras.layers.Conv2D(2, 1, name="c3")(a)
    pruned = prune_model(randomize(keras.Model(inputs, [b, c])), 0.5)
    assert [pruned.get_layer(n).filters for n in ("c1", "c2", "c3")] == [2, 4, 2]


def test_shared_layer_is_refused():
    inputs = keras.Input((16, 16, 3))
    shared = keras.layers.Conv2D(3, 3, padding="same", name="shared")
    x = shared(shared(inputs))  # one layer applied twice: its filters cannot be cut for one use only
    model = keras.Model(inputs, keras.layers.Conv2D(2, 1, name="out")(x))
    with pytest.raises(UserError, match="layer shared .* is used more than once"):
        prune_model(model, 0.5)


def test_softmax_on_the_output_is_fine():
    model = randomize(_functional(keras.layers.Conv2D(6, 3, padding="same", name="c1", activation="relu"),
                                  keras.layers.Conv2D(3, 1, name="out"), keras.layers.Softmax(name="sm")))
    pruned = prune_model(model, 0.5)
    assert conv_widths(pruned) == (3, 3)


def test_unbuilt_and_non_keras_models():
    with pytest.raises(UserError, match="not built"):
        prune_model(keras.Sequential([keras.layers.Conv2D(4, 3), keras.layers.Conv2D(2, 1)]), 0.5)
    with pytest.raises(UserError, match="expected a tf_keras"):
        prune_model(object(), 0.5)


# ------------------------------------------------------------------------------------------
# unstructured magnitude pruning
# ------------------------------------------------------------------------------------------

def _gzip_size(model):
    buffer = io.BytesIO()
    for w in model.get_weights():
        buffer.write(w.tobytes())
    return len(gzip.compress(buffer.getvalue()))


def test_magnitude_prune_zeroes_the_smallest_weights():
    model = randomize(build_fcn_pose(input_size=32), seed=8)
    before = [w.copy() for w in model.get_weights()]
    sparse = magnitude_prune(model, 0.7)
    assert [layer.name for layer in sparse.layers] == [layer.name for layer in model.layers]
    assert sparse.count_params() == model.count_params()  # shapes unchanged
    fractions = weight_sparsity(sparse)
    for name, fraction in fractions.items():
        original = model.get_layer(name).get_weights()[0]
        new = sparse.get_layer(name).get_weights()[0]
        if name == "conv10":
            assert fraction == 0.0
            np.testing.assert_array_equal(new, original)
            continue
        # numpy reference: keep the k = round(size * (1 - s)) largest magnitudes, ties at the threshold kept
        k = round(original.size * 0.3)
        threshold = np.sort(np.abs(original).ravel())[::-1][k - 1]
        assert np.count_nonzero(new == 0) == np.count_nonzero(np.abs(original) < threshold), name
        assert abs(fraction - 0.7) < 1e-3
        kept = new != 0
        np.testing.assert_array_equal(new[kept], original[kept])  # survivors untouched
        assert np.abs(original[~kept]).max() <= np.abs(original[kept]).min()  # the smallest went
        np.testing.assert_array_equal(sparse.get_layer(name).get_weights()[1], model.get_layer(name).get_weights()[1])
    for a, b in zip(before, model.get_weights()):
        np.testing.assert_array_equal(a, b)  # caller's model untouched
    assert _gzip_size(sparse) < 0.6 * _gzip_size(model)


@pytest.mark.slow
def test_magnitude_prune_keeps_masks_while_retraining():
    model = randomize(build_fcn_pose(input_size=32), seed=9)
    seen = {}

    def train(wrapped, callbacks):
        seen["callbacks"] = [type(c).__name__ for c in callbacks]
        wrapped.compile(keras.optimizers.Adam(1e-2), "binary_crossentropy")
        wrapped.fit(frames(32, 4), np.full((4, 32, 32, 9), 0.2, np.float32), batch_size=2, epochs=2,
                    callbacks=callbacks, verbose=0)

    sparse = magnitude_prune(model, 0.5, train_fn=train, frequency=1, include_output=True)
    assert seen["callbacks"] == ["UpdatePruningStep"]
    assert not np.allclose(sparse.get_layer("conv10").get_weights()[1], model.get_layer("conv10").get_weights()[1])
    for name, fraction in weight_sparsity(sparse).items():
        size = sparse.get_layer(name).get_weights()[0].size
        assert abs(fraction - 0.5) <= 1 / size + 1e-9, name


@pytest.mark.parametrize("sparsity", [-0.1, 1.0, "0.5", True])
def test_magnitude_prune_bad_sparsity(sparsity):
    with pytest.raises(UserError, match="sparsity"):
        magnitude_prune(build_fcn_pose(input_size=32), sparsity)


def test_magnitude_prune_spares_only_a_conv_that_is_the_models_output():
    """A classifier's last Conv2D feeds a Dense head: it is pruned like the others (it was left dense as "the output
    layer"); Keras 3 models and unknown layer names are refused in one line."""
    import tf_keras as keras

    inputs = keras.Input((16, 16, 3))
    x = keras.layers.Conv2D(8, 3, name="c1")(inputs)
    x = keras.layers.Conv2D(8, 3, name="c2")(x)
    x = keras.layers.GlobalAveragePooling2D()(x)
    classifier = keras.Model(inputs, keras.layers.Dense(4, name="fc")(x))
    sparse = weight_sparsity(magnitude_prune(classifier, 0.5))
    assert sparse == pytest.approx({"c1": 0.5, "c2": 0.5}, abs=0.01)
    assert weight_sparsity(magnitude_prune(build_fcn_pose(input_size=32), 0.5))["conv10"] == 0.0
    with pytest.raises(UserError, match="no Conv2D layer named fc, nope"):
        weight_sparsity(classifier, ["nope", "fc"])
    with pytest.raises(UserError, match="not a tf_keras model"):
        magnitude_prune(object(), 0.5)


def test_the_examples_in_the_docstrings_hold():
    import doctest

    from fcnpose_tf.compression import keep_rule, magnitude, prune

    for module in (keep_rule, prune, magnitude):
        assert doctest.testmod(module).failed == 0, module.__name__
