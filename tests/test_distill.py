"""Distillation while retraining: the loss at W = 0 is exactly today's, W = 1 the loss against the teacher's maps,
and the training batches carry the teacher's maps of the same frames."""

import numpy as np
import pytest
import tf_keras as keras

from fcnpose_tf.training.model import build_fcn_pose
from fcnpose_tf.training.train import (DistillationLoss, FitConfig, KeypointBinaryCrossentropy, compile_for_training, fit,
                                       training_loss)
from fcnpose_tf.progress import SILENT
from weights import randomize


def _batch(size=32, n=4, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.random((n, size, size, 3), dtype=np.float32)
    y = (rng.random((n, size, size, 9)) < 0.1).astype(np.float32)
    return x, y


def _today(positive_weight):
    """The loss compile_for_training built before distillation existed."""
    return keras.losses.BinaryCrossentropy() if positive_weight == 1 else KeypointBinaryCrossentropy(positive_weight)


@pytest.fixture(scope="module")
def models():
    student = randomize(build_fcn_pose((8, 8, 8, 4, 4, 4, 4, 8, 8), input_size=32), seed=1)
    teacher = randomize(build_fcn_pose(input_size=32), seed=2)
    return student, teacher


@pytest.mark.parametrize("positive_weight", [1.0, 20.0])
def test_weight_zero_is_exactly_todays_loss(models, positive_weight):
    student, teacher = models
    x, y = _batch()
    p, t = student(x), teacher(x)
    loss = training_loss(positive_weight, 0.0)
    assert type(loss) is type(_today(positive_weight))
    assert float(loss(y, p)) == float(_today(positive_weight)(y, p))
    # the distillation formula itself at W = 0, on targets that carry the teacher's maps: the same value
    both = np.concatenate([y, t], axis=-1)
    assert float(DistillationLoss(0.0, positive_weight)(both, p)) == float(_today(positive_weight)(y, p))

    # in a compiled training step (graph mode, the loss read from the sigmoid's logits): the same loss values
    losses = []
    for distill, targets in ((None, y), (0.0, y), ("formula", both)):
        model = keras.models.clone_model(student)
        model.set_weights(student.get_weights())
        if distill is None:
            model.compile(keras.optimizers.Adam(1e-3), _today(positive_weight))
        elif distill == "formula":
            model.compile(keras.optimizers.Adam(1e-3), DistillationLoss(0.0, positive_weight))
        else:
            compile_for_training(model, 1e-3, positive_weight, distill)
        losses.append([float(model.train_on_batch(x, targets)) for _ in range(2)])
    assert losses[0] == losses[1] == losses[2]


@pytest.mark.parametrize("positive_weight", [1.0, 20.0])
def test_weight_one_is_the_loss_against_the_teachers_maps(models, positive_weight):
    student, teacher = models
    x, y = _batch(seed=3)
    p = student(x)
    t = np.asarray(teacher.predict(x, verbose=0))  # the teacher's maps, computed independently
    both = np.concatenate([y, t], axis=-1)
    truth, against_teacher = float(_today(positive_weight)(y, p)), float(_today(positive_weight)(t, p))
    assert abs(truth - against_teacher) > 1e-3  # the two targets differ, so the test can tell them apart
    assert float(DistillationLoss(1.0, positive_weight)(both, p)) == pytest.approx(against_teacher, rel=1e-6)
    previous = truth
    for w in (0.25, 0.5, 0.75):  # W moves the loss from the truth's towards the teacher's, linearly
        value = float(DistillationLoss(w, positive_weight)(both, p))
        assert value == pytest.approx((1 - w) * truth + w * against_teacher, rel=1e-6)
        assert (value - previous) * (against_teacher - truth) > 0
        previous = value
    # validation targets without the teacher's channels: the ground-truth term alone, at every W
    assert float(DistillationLoss(0.5, positive_weight)(y, p)) == pytest.approx(truth, rel=1e-7)


def test_distillation_loss_survives_a_checkpoint(models, tmp_path):
    student, _ = models
    model = keras.models.clone_model(student)
    compile_for_training(model, 1e-3, 20.0, 0.3)
    model.save(tmp_path / "ckpt.keras")
    loss = keras.models.load_model(tmp_path / "ckpt.keras").loss
    assert isinstance(loss, DistillationLoss) and (loss.weight, loss.positive_weight) == (0.3, 20.0)


def _training_data(tmp_path, copies=1):
    from fcnpose_tf.data.dataset import TrainingData, load_dataset
    from test_train_evaluate import make_via_folder

    dataset = load_dataset(make_via_folder(tmp_path / "frames", n=6))
    return dataset, TrainingData(dataset, range(6), 32, copies, seed=0)


def test_fixed_rows_carry_the_teachers_maps_in_the_same_order(models, tmp_path):
    from fcnpose_tf.training.distill import with_teacher_maps

    _, teacher = models
    dataset, data = _training_data(tmp_path)
    plain = data.sequence(4, seed=5)
    wrapped, facts = with_teacher_maps(data, data.sequence(4, seed=5), teacher, batch_size=3)
    assert facts["teacher_maps"] == "cached" and wrapped.carries_teacher_maps and not hasattr(wrapped, "epoch")
    for epoch in range(2):  # reshuffled per epoch, the same way as without distillation
        assert len(wrapped) == len(plain) == 3
        for b in range(len(plain)):
            x, y = plain[b]
            wx, wy = wrapped[b]
            np.testing.assert_array_equal(wx, x)
            np.testing.assert_array_equal(wy[..., :9], y)
            np.testing.assert_allclose(wy[..., 9:], teacher.predict(x, verbose=0), atol=1e-3)  # float16 cache
        plain.on_epoch_end()
        wrapped.on_epoch_end()


def test_online_rows_get_the_teachers_maps_per_batch(models, tmp_path):
    from fcnpose_tf.data.online import OnlineTrainingData
    from fcnpose_tf.training.distill import with_teacher_maps

    _, teacher = models
    dataset, _ = _training_data(tmp_path, copies=0)
    online = OnlineTrainingData(dataset, range(6), 32, seed=0, samples_per_epoch=6)
    wrapped, facts = with_teacher_maps(online, online.sequence(4), teacher)
    assert facts == {"teacher_maps": "per batch"} and wrapped.epoch == 0
    wrapped.epoch = 3  # what fit sets on resume reaches the online data's epoch
    assert wrapped.sequence.epoch == 3
    x, y = wrapped[0]
    want_x, want_y = online.batch(3, range(4))
    np.testing.assert_array_equal(x, want_x)
    np.testing.assert_array_equal(y[..., :9], want_y)
    np.testing.assert_allclose(y[..., 9:], teacher.predict(x, verbose=0), atol=1e-5)


@pytest.mark.slow
def test_fit_with_distillation_runs_and_records_it(models, tmp_path):
    import json

    from fcnpose_tf.training.distill import with_teacher_maps

    student, teacher = models
    dataset, data = _training_data(tmp_path)
    _, val = _training_data(tmp_path / "val", copies=0)
    config = FitConfig(epochs=1, batch_size=4, distill=0.5)
    with pytest.raises(ValueError, match="teacher's maps"):
        fit(keras.models.clone_model(student), data.sequence(4), val.arrays(), tmp_path / "m.keras", config)
    sequence, _ = with_teacher_maps(data, data.sequence(4), teacher)
    result = fit(keras.models.clone_model(student), sequence, val.arrays(), tmp_path / "m.keras", config, reporter=SILENT)
    assert result.epochs_run == 1 and np.isfinite(result.best_val_loss)
    assert json.loads((tmp_path / "m_train.json").read_text())["config"]["distill"] == 0.5
