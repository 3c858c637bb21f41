"""Filter importance criteria: each ranks filters as an independent numpy reference does, and surgery with
each keeps the remaining filters' outputs exact."""

import math
from fractions import Fraction

import numpy as np
import pytest
import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.compression.importance import CRITERIA, FirstOrderTaylor, MeanActivation, WeightNorm, make_importance
from fcnpose_tf.compression.keep_rule import kept_by_score
from fcnpose_tf.compression.prune import prune_model, prune_plan
from fcnpose_tf.training.train import ground_truth_loss
from test_prune import bn_chain, frames, zeroed_reference


def reference_ranking(scores, rate):
    """Slow reference: sort (-score, index), keep the first n - floor(n·rate), in index order."""
    n = len(scores)
    ranked = sorted(range(n), key=lambda j: (-scores[j], j))
    return sorted(ranked[:n - math.floor(Fraction(str(rate)) * n)])


# ------------------------------------------------------------------------------------------
# weight criteria on a hand-built layer
# ------------------------------------------------------------------------------------------

def _layer_kernel(seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(-3, 4, size=(3, 3, 4, 12)).astype(np.float32)  # integers: ties are common


@pytest.mark.parametrize("seed", range(3))
def test_l1_and_l2_scores_and_rankings_match_a_loop_reference(seed):
    kernel = _layer_kernel(seed)
    l1 = [sum(abs(float(kernel[i, j, c, k])) for i in range(3) for j in range(3) for c in range(4)) for k in range(12)]
    l2 = [math.sqrt(sum(float(kernel[i, j, c, k]) ** 2 for i in range(3) for j in range(3) for c in range(4)))
          for k in range(12)]
    np.testing.assert_allclose(WeightNorm(1).filter_scores(kernel), l1, rtol=1e-12)
    np.testing.assert_allclose(WeightNorm(2).filter_scores(kernel), l2, rtol=1e-12)
    for rate in (0.25, 0.5, 0.7):
        assert kept_by_score(WeightNorm(1).filter_scores(kernel), rate).tolist() == reference_ranking(l1, rate)
        assert kept_by_score(WeightNorm(2).filter_scores(kernel), rate).tolist() == reference_ranking(l2, rate)


def test_l1_and_l2_rank_differently_where_they_should():
    kernel = np.zeros((1, 1, 4, 2), np.float32)
    kernel[0, 0, :, 0] = [1, 1, 1, 1]  # L1 4, L2 2
    kernel[0, 0, :, 1] = [3, 0, 0, 0]  # L1 3, L2 3
    assert kept_by_score(WeightNorm(1).filter_scores(kernel), 0.5).tolist() == [0]
    assert kept_by_score(WeightNorm(2).filter_scores(kernel), 0.5).tolist() == [1]
    assert WeightNorm(2).filter_scores(kernel, input_channels=[1, 2]).tolist() == [math.sqrt(2), 0.0]


# ------------------------------------------------------------------------------------------
# data-aware criteria on a hand-built tiny model, against numpy
# ------------------------------------------------------------------------------------------

def tiny_model(seed=0, maps=3):
    """conv3x3 (relu) -> conv1x1 (relu) -> conv1x1 (sigmoid): small enough for a numpy forward and backward."""
    inputs = keras.Input((8, 8, 3))
    x = keras.layers.Conv2D(6, 3, padding="same", activation="relu", name="a")(inputs)
    x = keras.layers.Conv2D(5, 1, activation="relu", name="b")(x)
    model = keras.Model(inputs, keras.layers.Conv2D(maps, 1, activation="sigmoid", name="out")(x))
    rng = np.random.default_rng(seed)
    for layer in model.layers[1:]:
        kernel, bias = layer.get_weights()
        layer.set_weights([rng.normal(0, 0.6, kernel.shape).astype(np.float32),
                           rng.normal(0.05, 0.1, bias.shape).astype(np.float32)])
    return model


def numpy_forward(model, x):
    """Activations a (after relu), b (after relu), logits z and maps p, in float64."""
    (ka, ba), (kb, bb), (ko, bo) = (
        [w.astype(np.float64) for w in model.get_layer(n).get_weights()] for n in ("a", "b", "out"))
    x = x.astype(np.float64)
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    za = np.zeros(x.shape[:3] + (ka.shape[3],))
    for i in range(3):
        for j in range(3):  # Keras' Conv2D is a cross-correlation
            za += padded[:, i:i + 8, j:j + 8, :] @ ka[i, j]
    a = np.maximum(za + ba, 0)
    zb = a @ kb[0, 0] + bb
    b = np.maximum(zb, 0)
    z = b @ ko[0, 0] + bo
    return a, zb, b, z, 1 / (1 + np.exp(-z))


def numpy_taylor(model, x, y, positive_weight):
    """Taylor scores with the gradient of L = sum over frames of each frame's mean BCE, derived by hand."""
    (kb, _), (ko, _) = ([w.astype(np.float64) for w in model.get_layer(n).get_weights()] for n in ("b", "out"))
    a, zb, b, z, p = numpy_forward(model, x)
    h, w, c = p.shape[1:]
    weight = np.ones(c)
    weight[:-1] = positive_weight  # keypoint maps weighted, the last (skeleton) map not
    # d/dz of -(w y log p + (1 - y) log(1 - p)) = p (w y + 1 - y) - w y, averaged over h, w and c
    dz = (p * (weight * y + 1 - y) - weight * y) / (h * w * c)
    db = dz @ ko[0, 0].T
    da = (db * (zb > 0)) @ kb[0, 0].T
    return {"a": np.abs((a * da).mean(axis=(1, 2))).mean(axis=0),
            "b": np.abs((b * db).mean(axis=(1, 2))).mean(axis=0)}


@pytest.fixture(scope="module")
def tiny():
    model = tiny_model()
    rng = np.random.default_rng(1)
    x = rng.random((5, 8, 8, 3), dtype=np.float32)
    y = (rng.random((5, 8, 8, 3)) < 0.3).astype(np.float32)
    return model, x, y


def test_activation_scores_equal_numpy_mean_absolute_activation(tiny):
    model, x, _ = tiny
    a, _, b, _, p = numpy_forward(model, x)
    want = {"a": np.abs(a).mean(axis=(0, 1, 2)), "b": np.abs(b).mean(axis=(0, 1, 2)), "out": p.mean(axis=(0, 1, 2))}
    for batch_size in (2, 5):  # the frames split into batches (2 + 2 + 1) or not: the same scores
        got = MeanActivation(x, batch_size=batch_size)(model)
        assert list(got) == ["a", "b", "out"]
        for name in want:
            np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-7)
    plan = prune_plan(model, 0.5, importance=MeanActivation(x))
    assert plan["a"].tolist() == reference_ranking(want["a"].tolist(), 0.5)
    assert plan["b"].tolist() == reference_ranking(want["b"].tolist(), 0.5)
    assert plan["out"].tolist() == [0, 1, 2]  # the output layer keeps every map


@pytest.mark.parametrize("positive_weight", [1.0, 20.0])
def test_taylor_scores_equal_the_hand_derived_numpy_gradient(tiny, positive_weight):
    model, x, y = tiny
    want = numpy_taylor(model, x, y, positive_weight)
    for batch_size in (2, 5):
        got = FirstOrderTaylor(x, y, ground_truth_loss(positive_weight), batch_size=batch_size)(model)
        assert list(got) == ["a", "b"]  # the output layer is never pruned
        for name in want:
            np.testing.assert_allclose(got[name], want[name], rtol=1e-4, atol=1e-9)
    plan = prune_plan(model, 0.5, importance=FirstOrderTaylor(x, y, ground_truth_loss(positive_weight)))
    assert plan["a"].tolist() == reference_ranking(want["a"].tolist(), 0.5)
    assert plan["b"].tolist() == reference_ranking(want["b"].tolist(), 0.5)


def test_criteria_disagree_on_the_tiny_model(tiny):
    """The four criteria are not one ranking under four names (else the tests above could not tell them apart)."""
    model, x, y = tiny
    plans = {name: prune_plan(model, 0.5, importance=make_importance(name, images=x, maps=y,
                                                                      loss=ground_truth_loss()))
             for name in CRITERIA}
    kept = {name: (plan["a"].tolist(), plan["b"].tolist()) for name, plan in plans.items()}
    assert len({str(v) for v in kept.values()}) >= 3, kept


# ------------------------------------------------------------------------------------------
# surgery with every criterion is exact
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", CRITERIA)
def test_surgery_with_each_criterion_equals_the_original_with_removed_filters_zeroed(name):
    model = bn_chain()
    x = frames(32, n=6, seed=2)
    y = (np.random.default_rng(3).random((6, 32, 32, 3)) < 0.2).astype(np.float32)
    importance = make_importance(name, images=x, maps=y, loss=ground_truth_loss(), batch_size=4)
    plan = prune_plan(model, 0.5, importance=importance)
    pruned = prune_model(model, 0.5, importance=importance)
    reference = zeroed_reference(model, plan)
    probe = frames(32, n=2, seed=4)
    got, want, original = (np.asarray(m(probe, training=False)) for m in (pruned, reference, model))
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    assert np.abs(got - original).max() > 1e-3
    scores = importance(model)
    for layer in ("conv1", "conv2", "conv3"):  # the criterion's own ranking, not L1's
        assert plan[layer].tolist() == reference_ranking(scores[layer].tolist(), 0.5)


def test_bad_criteria_and_combinations_are_clear_errors(tiny):
    model, x, y = tiny
    with pytest.raises(UserError, match="importance criterion must be one of l1, l2, activation, taylor"):
        make_importance("l3")
    with pytest.raises(UserError, match="activation importance criterion needs training frames"):
        make_importance("activation")
    with pytest.raises(UserError, match="taylor importance criterion needs the frames' target maps"):
        make_importance("taylor", images=x)
    with pytest.raises(UserError, match="one target map per frame"):
        FirstOrderTaylor(x, y[:2], ground_truth_loss())
    with pytest.raises(UserError, match="the activation criterion does not rank kernels"):
        prune_plan(model, 0.5, strategy="greedy", importance=MeanActivation(x))
    with pytest.raises(UserError, match="finite 1-D"):
        kept_by_score(np.array([1.0, np.nan]), 0.5)


@pytest.mark.parametrize("name", ["activation", "taylor"])
def test_data_aware_criteria_score_a_branching_model_where_it_computes(name):
    """FCN-Pose with its skip added at zero computes plain FCN-Pose: every shared Conv2D scores as in the plain
    model, the zero skip scores 0, and surgery ranks conv9 and skip2 as one group (their sum)."""
    from fcnpose_tf.training.model import as_architecture, build_fcn_pose, conv_widths
    from weights import randomize

    plain = randomize(build_fcn_pose((8, 8, 8, 8, 8, 8, 8, 8, 8), input_size=32, num_maps=3), seed=3)
    skip = as_architecture(plain, "fcn-pose-skip")
    rng = np.random.default_rng(2)
    x = rng.random((3, 32, 32, 3), dtype=np.float32)
    y = (rng.random((3, 32, 32, 3)) < 0.2).astype(np.float32)
    criterion = make_importance(name, images=x, maps=y, loss=ground_truth_loss())
    plain_scores, skip_scores = criterion(plain), criterion(skip)
    assert set(skip_scores) == set(plain_scores) | {"skip2"}
    for layer, scores in plain_scores.items():
        np.testing.assert_allclose(skip_scores[layer], scores, rtol=1e-5, atol=1e-9)
    assert not skip_scores["skip2"].any()
    assert conv_widths(prune_model(skip, 0.5, importance=criterion)) == (4, 4, 4, 4, 4, 4, 4, 4, 4, 3)
