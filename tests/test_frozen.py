"""Training past a fixed prefix (`training.frozen`): the cut, the head's maps equal to the whole network's, and a
run that computes the fixed layers once trains the same weights as one that runs them every batch, resumed or not."""

import io
import json

import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from conftest import stop_after_first_epoch
from fcnpose_tf.progress import SILENT, Reporter
from test_train_evaluate import make_via_folder
from weights import randomize


def _model(skip: bool, frozen: int, size: int = 64):
    from fcnpose_tf.training.model import build_fcn_pose
    from fcnpose_tf.training.train import freeze_first_convolutions

    model = randomize(build_fcn_pose(input_size=size, skip=skip), seed=3)
    freeze_first_convolutions(model, frozen)
    return model


@pytest.mark.parametrize("skip, frozen, cut", [(False, 1, ("pool1",)), (False, 2, ("pool2",)), (False, 3, ("pool3",)),
                                               (True, 1, ("pool1",)), (True, 2, ("conv2",)),
                                               (True, 3, ("conv2", "pool3"))])
def test_the_head_on_the_prefix_computes_the_whole_networks_maps(skip, frozen, cut):
    """The cut is the prefix's last outputs the rest reads (with the skip and conv1-2 fixed, conv2's: the skip reads
    it, and pool2 moves to the head); the head trains exactly the layers the whole network trains."""
    from fcnpose_tf.training.frozen import split_frozen

    model = _model(skip, frozen)
    prefix = split_frozen(model)
    assert prefix.cut == cut
    images = (np.random.default_rng(0).random((3, 64, 64, 3)) * 255).astype(np.uint8)
    features = prefix.features(images, batch_size=2)
    assert features[0].dtype == np.float32 and len(features) == len(cut)
    head = prefix.head(features[0] if len(features) == 1 else features, training=False).numpy()
    whole = model(images.astype(np.float32) / 255, training=False).numpy()
    np.testing.assert_allclose(head, whole, atol=1e-5)
    assert sorted(w.name for w in prefix.head.trainable_weights) == sorted(w.name for w in model.trainable_weights)
    assert prefix.feature_bytes(10) == 10 * 4 * sum(f[0].size for f in features)


def test_nothing_fixed_nothing_cut():
    from fcnpose_tf.training.frozen import split_frozen

    assert split_frozen(_model(skip=True, frozen=0)) is None


def _fit(tmp_path, name, monkeypatch=None, *, cached=True, resume=False, interrupt=False, reporter=SILENT):
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.training import train

    folder = tmp_path / "frames"
    dataset = load_dataset(folder if folder.is_dir() else make_via_folder(folder, n=8))
    train_data, val_data = fold_data(dataset, None, 64, augment_copies=1)
    config = train.FitConfig(epochs=3, patience=5, batch_size=4, freeze=2, learning_rate=1e-3, positive_weight=8.0,
                             lr_patience=0)
    if not cached:
        monkeypatch.setattr(train, "_prefix_worth_keeping", lambda *args: None)
    if interrupt:
        stop_after_first_epoch(monkeypatch)
    out = tmp_path / f"{name}.keras"
    return train.fit(_model(skip=True, frozen=0), train_data.sequence(4, seed=0), val_data.arrays(), out, config,
                     resume=resume, reporter=reporter, start_is_candidate=True), out


def _weights(path):
    from fcnpose_tf.training.model import load_model

    model = load_model(path)
    return {layer.name: layer.get_weights() for layer in model.layers if layer.weights}


@pytest.mark.slow
def test_computing_the_fixed_layers_once_trains_the_same_network(tmp_path, monkeypatch):
    """conv1-2 fixed on the paper's copies: the run past the prefix and the run through the whole network end with the
    same weights and validation losses (to float rounding), the fixed layers the start's own, the view kept."""
    said = io.StringIO()
    cached, cached_path = _fit(tmp_path, "cached", reporter=Reporter(quiet=True, stream=said))
    assert "Fixed layers computed once: conv2's outputs for 14 samples (3.5 MB)" in said.getvalue(), said.getvalue()
    whole, whole_path = _fit(tmp_path, "whole", monkeypatch, cached=False)
    np.testing.assert_allclose([h["val_loss"] for h in cached.history], [h["val_loss"] for h in whole.history],
                               rtol=1e-3)
    a, b = _weights(cached_path), _weights(whole_path)
    assert a.keys() == b.keys()
    start = {layer.name: layer.get_weights() for layer in _model(skip=True, frozen=0).layers if layer.weights}
    for name in a:
        for x, y in zip(a[name], b[name]):
            np.testing.assert_allclose(x, y, atol=2e-4)
        if name in ("conv1", "conv2"):
            assert all(np.array_equal(x, s) for x, s in zip(a[name], start[name]))
    assert not any(np.array_equal(x, s) for x, s in zip(a["conv10"], start["conv10"]))
    record = json.loads((tmp_path / "cached_train.json").read_text())
    assert record["epochs_run"] == 3


@pytest.mark.slow
def test_a_run_past_the_prefix_resumes_where_it_stopped(tmp_path, monkeypatch):
    """Stopped after its first epoch, the run resumes from the head's checkpoint and the start's fixed layers (kept
    in the checkpoint), and ends with the weights of a run through the whole network stopped and resumed alike."""
    ends = {}
    for name, cached in (("whole", False), ("cached", True)):
        with pytest.raises(UserError, match="interrupted after 1 complete epochs"):
            _fit(tmp_path, name, monkeypatch, cached=cached, interrupt=True)
        state = json.loads((tmp_path / f"{name}.ckpt" / "state.json").read_text())
        assert state.get("frozen_prefix") == (["conv2"] if cached else None)
        monkeypatch.undo()
        result, path = _fit(tmp_path, name, monkeypatch, cached=cached, resume=True)
        monkeypatch.undo()
        assert [h["epoch"] for h in result.history] == [1, 2, 3]
        assert not (tmp_path / f"{name}.ckpt").exists()
        ends[name] = result, _weights(path)
    np.testing.assert_allclose([h["val_loss"] for h in ends["cached"][0].history],
                               [h["val_loss"] for h in ends["whole"][0].history], rtol=1e-3)
    for name, weights in ends["whole"][1].items():
        for x, y in zip(weights, ends["cached"][1][name]):
            np.testing.assert_allclose(x, y, atol=2e-4)


def test_features_that_do_not_fit_in_memory_leave_the_whole_network_to_train(monkeypatch):
    from fcnpose_tf.training import frozen, train

    prefix = frozen.split_frozen(_model(skip=True, frozen=2))
    rows = 100
    assert frozen.fits_in_memory(prefix, rows, available=2 * prefix.feature_bytes(rows))
    assert not frozen.fits_in_memory(prefix, rows, available=2 * prefix.feature_bytes(rows) - 1)

    class Rows:  # a TrainingData.sequence's shape
        class data:
            images = np.zeros((rows - 10, 64, 64, 3), np.uint8)

        def rows(self, batch):
            return np.arange(4)

    said = io.StringIO()
    monkeypatch.setattr(frozen, "available_memory", lambda: prefix.feature_bytes(rows))
    reporter = Reporter(quiet=True, stream=said)
    assert train._prefix_worth_keeping(_model(skip=True, frozen=2), Rows(), 10, reporter) is None
    assert said.getvalue().startswith("Fixed layers run every batch: their outputs for 100 samples"), said.getvalue()
    assert train._prefix_worth_keeping(_model(skip=True, frozen=2), object(), 10, reporter) is None
