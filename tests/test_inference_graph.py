"""fold_upsampling: the rewritten network computes what the original computes, and exports as DEPTH_TO_SPACE."""

import numpy as np
import pytest
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.export import export_tflite
from fcnpose_tf.compression.verify import _interpreter, run_tflite
from fcnpose_tf.compression.inference_graph import (DepthToSpace, UnsupportedGraphError, describe_folds, fold_kernel,
                                                    fold_upsampling, foldable_pairs)
from fcnpose_tf.training.model import DEFAULT_WIDTHS, build_fcn_pose
from fcnpose_tf.compression.keep_rule import pruned_widths
from weights import randomize

L = keras.layers


def images(size, n=2, seed=1, channels=3):
    h, w = (size, size) if isinstance(size, int) else size
    return np.random.default_rng(seed).random((n, h, w, channels), dtype=np.float32)


def max_diff(a, b, x):
    return float(np.abs(np.asarray(a(x, training=False)) - np.asarray(b(x, training=False))).max())


@pytest.mark.slow
@pytest.mark.parametrize("widths,size", [
    (DEFAULT_WIDTHS, 64),                          # the full network
    (pruned_widths(DEFAULT_WIDTHS, 0.7), 64),      # 70% pruned: 39, 20, 10, 5, 3, 3, 5, 10, 20
    (pruned_widths(DEFAULT_WIDTHS, 0.9), 96),      # another width and input size
])
def test_folded_fcn_pose_equals_original(widths, size):
    model = randomize(build_fcn_pose(widths, input_size=size), seed=sum(widths))
    folded = fold_upsampling(model)
    assert not any(isinstance(layer, L.UpSampling2D) for layer in folded.layers)
    assert [layer.block_size for layer in folded.layers if isinstance(layer, DepthToSpace)] == [2, 2, 2, 4]
    assert folded.output_shape == model.output_shape and folded.input_shape == model.input_shape
    assert folded.layers[0].name == model.layers[0].name == "image"
    x = images(size)
    out = np.asarray(model(x))
    assert out.std() > 0.02 and 0.01 < out.min() < out.max() < 0.99  # varied, unsaturated maps
    assert max_diff(model, folded, x) <= 1e-5
    assert folded.get_layer("conv10").kernel.shape == (3, 3, widths[-1], 16 * 9)
    # the original is left as it was
    assert [type(layer).__name__ for layer in model.layers].count("UpSampling2D") == 4


def _pair(factor, kernel, activation="relu", size=(5, 7), cin=3, cout=4, use_bias=True):
    inputs = keras.Input((*size, cin), name="x")
    up = L.UpSampling2D(factor, name="up")(inputs)
    out = L.Conv2D(cout, kernel, padding="same", activation=activation, use_bias=use_bias, name="conv")(up)
    return randomize(keras.Model(inputs, out), seed=factor * 10 + kernel)


@pytest.mark.parametrize("factor,kernel", [(2, 3), (3, 3), (4, 3), (4, 1), (2, 5), (1, 3)])
@pytest.mark.parametrize("activation", ["linear", "softmax"])
def test_one_pair_exact_including_borders(factor, kernel, activation):
    # odd, non-square low-resolution map: every output pixel near a border reads zero padding
    model = _pair(factor, kernel, activation)
    folded = fold_upsampling(model)
    x = images((5, 7), 3, seed=factor)
    assert max_diff(model, folded, x) <= 1e-5
    if factor > 1:
        assert [type(layer).__name__ for layer in folded.layers][1:] == \
            ["Conv2D", "DepthToSpace"] + (["Activation"] if activation == "softmax" else [])
    else:
        assert folded is model  # nothing to fold


def test_without_bias_sequential_and_variable_size():
    seq = keras.Sequential([keras.Input((None, None, 2)), L.Conv2D(3, 3, padding="same"), L.UpSampling2D(2),
                            L.Conv2D(5, 3, padding="same", use_bias=False, activation="tanh")])
    randomize(seq, seed=4)
    folded = fold_upsampling(seq)
    for size in ((6, 6), (3, 5)):
        assert max_diff(seq, folded, images(size, 2, channels=2)) <= 1e-5


def test_fold_kernel_sums_the_taps_of_each_phase():
    kernel = np.arange(1, 10, dtype=np.float64).reshape(3, 3, 1, 1)  # rows (1 2 3), (4 5 6), (7 8 9)
    folded = fold_kernel(kernel, 4)  # 3 x 3 x 1 x 16, channels (py, px)
    phase = lambda py, px: folded[:, :, 0, 4 * py + px]  # noqa: E731
    # phases 1 and 2 of both axes read only the centre pixel: the sum of all taps
    np.testing.assert_array_equal(phase(1, 2), [[0, 0, 0], [0, 45, 0], [0, 0, 0]])
    # phase 0: tap -1 lands on low-res offset -1, taps 0 and +1 on offset 0 (rows and columns alike)
    np.testing.assert_array_equal(phase(0, 0), [[1, 2 + 3, 0], [4 + 7, 5 + 6 + 8 + 9, 0], [0, 0, 0]])
    # phase 3: taps -1 and 0 on offset 0, tap +1 on offset +1
    np.testing.assert_array_equal(phase(3, 3), [[0, 0, 0], [0, 1 + 2 + 4 + 5, 3 + 6], [0, 7 + 8, 9]])
    assert folded.sum() == 16 * kernel.sum()


@pytest.mark.parametrize("build,message", [
    (lambda i: L.Conv2D(2, 3, padding="same")(L.UpSampling2D(2, interpolation="bilinear")(i)), "'bilinear'"),
    (lambda i: L.Conv2D(2, 3, padding="same")(L.UpSampling2D((2, 3))(i)), "unequal factors 2 x 3"),
    (lambda i: L.Conv2D(2, 3, strides=2, padding="same")(L.UpSampling2D(2)(i)), r"strides \(2, 2\)"),
    (lambda i: L.Conv2D(2, 3, dilation_rate=2, padding="same")(L.UpSampling2D(2)(i)), r"dilation \(2, 2\)"),
    (lambda i: L.Conv2D(2, 3, padding="valid")(L.UpSampling2D(2)(i)), "'valid' padding"),
    (lambda i: L.Conv2D(2, 2, padding="same")(L.UpSampling2D(2)(i)), r"even kernel size \(2, 2\)"),
    (lambda i: L.Conv2D(4, 3, padding="same", groups=2)(L.UpSampling2D(2)(i)), "grouped"),
    (lambda i: (lambda shared: shared(shared(i)))(L.Conv2D(4, 3, padding="same", name="twice")),
     "layer twice is called more than once"),
])
def test_unsupported_structures_are_refused(build, message):
    inputs = keras.Input((8, 8, 4))
    model = keras.Model(inputs, build(inputs))
    with pytest.raises(UnsupportedGraphError, match=message) as error:
        fold_upsampling(model)
    assert isinstance(error.value, UserError)


def test_two_inputs_are_refused_and_plain_models_returned_unchanged():
    a, b = keras.Input((4, 4, 1)), keras.Input((4, 4, 1))
    with pytest.raises(UnsupportedGraphError, match="2 inputs and 1 outputs"):
        fold_upsampling(keras.Model([a, b], L.Add()([a, b])))
    inputs = keras.Input((8, 8, 3))
    plain = keras.Model(inputs, L.UpSampling2D(2)(L.Conv2D(2, 3, padding="same")(inputs)))  # conv, then up
    assert foldable_pairs(plain) == [] and fold_upsampling(plain) is plain


# ------------------------------------------------------------------------------------------
# export
# ------------------------------------------------------------------------------------------

def _op_names(data):
    """Operator names from the interpreter's op table (delegate nodes excluded)."""
    return [op["op_name"] for op in _interpreter(data)._get_ops_details() if op["op_name"] != "DELEGATE"]


@pytest.fixture(scope="module")
def p70_64():
    return randomize(build_fcn_pose(pruned_widths(DEFAULT_WIDTHS, 0.7), input_size=64), seed=5)


@pytest.mark.slow
def test_folded_export_runs_depth_to_space_and_matches_the_original(p70_64):
    export = export_tflite(p70_64, "float16", fold_upsampling=True)
    ops = _op_names(export.data)
    assert ops.count("DEPTH_TO_SPACE") == 4 and "RESIZE_NEAREST_NEIGHBOR" not in ops and ops.count("CONV_2D") == 10
    assert export.parity.max_abs_diff <= 1e-2  # verified against the original (unfolded) model
    assert export.graph_rewrites == tuple(describe_folds(p70_64))
    assert export.graph_rewrites[-1] == "up4 + conv10 -> conv10 at 1/4 size + depth_to_space(4)"
    assert export.to_dict()["graph_rewrites"] == list(export.graph_rewrites)
    # without float16 weights the file computes what the original Keras model computes
    f32 = export_tflite(p70_64, "float32", fold_upsampling=True)
    x = images(64, 3, seed=9)
    assert np.abs(run_tflite(_interpreter(f32.data), x) - np.asarray(p70_64(x))).max() <= 1e-5


@pytest.mark.slow
def test_runtime_counts_a_folded_file_as_the_original_network(p70_64, tmp_path):
    """The Pi runtime's parameter and MAC counts of a folded file are the Keras model's, not the phase kernels'."""
    from fcnpose_tf.runtime.estimator import KeypointModel

    path = tmp_path / "folded.tflite"
    path.write_bytes(export_tflite(p70_64, "float16", fold_upsampling=True).data)
    stats = KeypointModel(path, 1).stats()
    assert stats.params == p70_64.count_params()
    assert stats.conv_layers == 10


@pytest.mark.slow
def test_unfolded_export_keeps_resize_and_branched_models_export_unfolded(p70_64):
    plain = export_tflite(p70_64, "float32", fold_upsampling=False)
    ops = _op_names(plain.data)
    assert ops.count("RESIZE_NEAREST_NEIGHBOR") == 4 and "DEPTH_TO_SPACE" not in ops
    assert plain.graph_rewrites == ()
    inputs = keras.Input((16, 16, 3))
    up = L.UpSampling2D(2, interpolation="bilinear", name="up")(L.MaxPooling2D(2)(inputs))
    branched = randomize(keras.Model(inputs, L.Conv2D(3, 1, activation="sigmoid")(
        L.Add()([inputs, L.Conv2D(3, 3, padding="same")(up)]))), seed=6)
    export = export_tflite(branched, "float32", fold_upsampling=True)  # not foldable: converted as it is
    assert export.graph_rewrites == () and "RESIZE_BILINEAR" in _op_names(export.data)


# ------------------------------------------------------------------------------------------
# graphs that branch and merge
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("widths", [DEFAULT_WIDTHS, (16, 15, 15, 15, 8, 8, 15, 15, 15)])
def test_fcn_pose_with_its_skip_folds_the_merge_at_half_resolution(widths):
    """conv10(up4(x) + skip_up(s)) is conv10(up2(up2(x) + s)): the Add is computed at half resolution and conv10
    folds by 2; the file converts and computes what Keras computes."""
    model = randomize(build_fcn_pose(widths, input_size=(64, 96), skip=True), seed=7)
    folded = fold_upsampling(model)
    assert [layer.block_size for layer in folded.layers if isinstance(layer, DepthToSpace)] == [2, 2, 2, 2]
    assert [layer.name for layer in folded.layers if isinstance(layer, L.UpSampling2D)] == ["up4_x2"]
    assert describe_folds(model)[-1] == "skip_add + conv10 -> conv10 at 1/2 size + depth_to_space(2)"
    x = images((64, 96), seed=3)
    assert np.asarray(model(x)).std() > 0.02 and max_diff(model, folded, x) <= 1e-5
    f32 = export_tflite(model, "float32", fold_upsampling=True)
    assert np.abs(run_tflite(_interpreter(f32.data), x[:1]) - np.asarray(model(x[:1]))).max() <= 1e-5


def test_merges_of_unequal_factors_and_shared_reads_are_exact():
    """Upsamplings by 4 and 2 merge at half resolution, by 12, 8 and 6 at 2 (gcd); one upsampled tensor read by a
    convolution (folded) and by an activation (upsampled once, for it alone) stays exact."""
    inputs = keras.Input((24, 24, 3), name="x")
    a = L.Conv2D(4, 3, padding="same", name="a")(L.MaxPooling2D(12, name="p12")(inputs))  # 2 x 2
    b = L.Conv2D(4, 3, padding="same", name="b")(L.MaxPooling2D(8, name="p8")(inputs))  # 3 x 3
    c = L.Conv2D(4, 3, padding="same", name="c")(L.MaxPooling2D(6, name="p6")(inputs))  # 4 x 4
    ua, ub = L.UpSampling2D(12, name="ua")(a), L.UpSampling2D(8, name="ub")(b)  # 24 x 24, gcd 4
    uc = L.UpSampling2D(2, name="uc")(c)  # 8 x 8
    m1 = L.Add(name="m1")([L.UpSampling2D(2, name="ua2")(L.UpSampling2D(2, name="ua1")(a)), uc])  # 4*2 and 2: gcd 2
    m2 = L.Maximum(name="m2")([ua, ub, L.UpSampling2D(3, name="um1")(m1)])
    out = L.Add(name="out")([L.Conv2D(4, 3, padding="same", name="conv")(m2), L.Activation("tanh", name="t")(m2)])
    model = randomize(keras.Model(inputs, out), seed=11)
    folded = fold_upsampling(model)
    assert [fold[1:] for fold in foldable_pairs(model)] == [("conv", 2)]  # gcd(12, 8, 6): m2 at 12 x 12
    x = images(24, 3, seed=5)
    assert max_diff(model, folded, x) <= 1e-5
    # factors 2 and 3: nothing in common, both computed at full resolution before the merge; nothing folds
    inputs = keras.Input((12, 12, 2))
    two = L.UpSampling2D(2)(L.MaxPooling2D(2)(inputs))
    three = L.UpSampling2D(3)(L.MaxPooling2D(3)(inputs))
    coprime = randomize(keras.Model(inputs, L.Conv2D(2, 3, padding="same")(L.Subtract()([two, three]))), seed=2)
    assert foldable_pairs(coprime) == [] and fold_upsampling(coprime) is coprime
