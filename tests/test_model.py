import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.metrics import conv_macs
from fcnpose_tf.training.model import build_fcn_pose, conv_widths, describe

# The paper's table "FCN-Pose Structure": (layer, output shape, parameters).
PAPER_TABLE = [
    ("conv1", (224, 224, 128), 3584), ("pool1", (112, 112, 128), 0),
    ("conv2", (112, 112, 64), 73792), ("pool2", (56, 56, 64), 0),
    ("conv3", (56, 56, 32), 18464), ("pool3", (28, 28, 32), 0),
    ("conv4", (28, 28, 16), 4624), ("pool4", (14, 14, 16), 0),
    ("conv5", (14, 14, 8), 1160), ("pool5", (7, 7, 8), 0),
    ("conv6", (7, 7, 8), 584), ("up1", (14, 14, 8), 0),
    ("conv7", (14, 14, 16), 1168), ("up2", (28, 28, 16), 0),
    ("conv8", (28, 28, 32), 4640), ("up3", (56, 56, 32), 0),
    ("conv9", (56, 56, 64), 18496), ("up4", (224, 224, 64), 0),
    ("conv10", (224, 224, 9), 5193),
]


def test_matches_paper_table():
    model = build_fcn_pose()
    rows = describe(model)
    assert rows[0].output_shape == (224, 224, 3)
    assert [(r.name, r.output_shape, r.params) for r in rows[1:]] == PAPER_TABLE
    assert model.count_params() == 131705
    assert conv_widths(model) == (128, 64, 32, 16, 8, 8, 16, 32, 64, 9)


def test_activations_and_no_batchnorm():
    model = build_fcn_pose(input_size=64)
    convs = [layer for layer in model.layers if type(layer).__name__ == "Conv2D"]
    assert [c.activation.__name__ for c in convs] == ["relu"] * 9 + ["sigmoid"]
    assert all(c.kernel_size == (3, 3) and c.padding == "same" for c in convs)
    assert not any("BatchNormalization" in type(layer).__name__ for layer in model.layers)
    assert [layer.size for layer in model.layers if type(layer).__name__ == "UpSampling2D"] == \
        [(2, 2), (2, 2), (2, 2), (4, 4)]


def test_macs_equal_numpy_reference():
    model = build_fcn_pose(input_size=64)
    expected = 0
    for layer in model.layers:
        if type(layer).__name__ == "Conv2D":
            h, w, cout = layer.output_shape[1:]
            kh, kw, cin, _ = layer.kernel.shape
            expected += h * w * kh * kw * cin * cout
    assert sum(r.macs for r in describe(model)) == expected
    assert conv_macs(224, 224, 3, 3, 3, 128) == 173_408_256


@pytest.mark.parametrize("size", [32, 64, 96, 320])
def test_any_multiple_of_32_maps_to_same_size(size):
    model = build_fcn_pose(input_size=size)
    out = model(np.zeros((1, size, size, 3), np.float32))
    assert out.shape == (1, size, size, 9)
    assert model.count_params() == 131705  # parameters do not depend on the input size


@pytest.mark.parametrize("size", [0, -32, 100, 225, 48, 64.0, "224"])
def test_bad_input_size_is_rejected_with_rule(size):
    with pytest.raises(UserError, match="multiple of 32"):
        build_fcn_pose(input_size=size)


def test_custom_widths_and_maps():
    model = build_fcn_pose(widths=(39, 20, 10, 5, 3, 3, 5, 10, 20), input_size=64, num_maps=7)
    assert conv_widths(model)[-1] == 7
    with pytest.raises(UserError, match="9 positive"):
        build_fcn_pose(widths=(8, 8))


def test_the_skip_architecture_starts_as_the_model_it_is_given():
    """fcn-pose-skip adds conv2's half-resolution block before conv10 through a 1x1 convolution at zero: an FCN-Pose
    given the skip computes exactly what it computed; conv1..conv10 keep their widths; a trained skip is not dropped."""
    import tf_keras as keras

    from fcnpose_tf.training.model import SKIP_LAYERS, architecture_of, as_architecture

    keras.utils.set_random_seed(5)
    plain = build_fcn_pose(input_size=(64, 96))
    skipped = as_architecture(plain, "fcn-pose-skip")
    for layer in plain.layers:  # every weight copied (a fresh build would draw others)
        for mine, copied in zip(layer.get_weights(), skipped.get_layer(layer.name).get_weights()):
            np.testing.assert_array_equal(mine, copied)
    assert (architecture_of(plain), architecture_of(skipped)) == ("fcn-pose", "fcn-pose-skip")
    assert as_architecture(skipped, "fcn-pose-skip") is skipped and as_architecture(plain, "fcn-pose") is plain
    assert conv_widths(skipped) == conv_widths(plain) and skipped.input_shape == plain.input_shape
    x = np.random.default_rng(1).random((2, 64, 96, 3), dtype=np.float32)
    np.testing.assert_allclose(np.asarray(skipped(x)), np.asarray(plain(x)), rtol=0, atol=1e-6)
    rows = {r.name: r for r in describe(skipped)}
    assert rows["skip2"].output_shape == (32, 48, 64) and rows["skip_add"].output_shape == (64, 96, 64)
    assert rows["skip2"].macs == conv_macs(32, 48, 1, 1, 64, 64)
    assert skipped.count_params() - plain.count_params() == 64 * 64 + 64
    kernel = skipped.get_layer(SKIP_LAYERS[0])
    kernel.set_weights([np.full_like(w, 0.01) for w in kernel.get_weights()])
    assert np.abs(np.asarray(skipped(x)) - np.asarray(plain(x))).max() > 1e-4  # the skip reaches conv10
    assert isinstance(skipped.get_layer(SKIP_LAYERS[2]), keras.layers.Add)
    with pytest.raises(UserError, match="would drop its trained skip"):
        as_architecture(skipped, "fcn-pose")
    with pytest.raises(UserError, match="architecture must be one of"):
        as_architecture(plain, "unet")
