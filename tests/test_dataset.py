"""The --data rule, stored splits, the paper's counts, and the training feed."""

import json

import numpy as np
import pytest

from fcnpose_tf.data.dataset import TrainingData, fold_data, load_dataset, resolve_data
from fcnpose_tf.data.masks import make_target_maps
from fcnpose_tf.data.splits import holdout_split, kfold_split, make_splits, splits_path
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from fcnpose_tf.preprocess import keypoints_to_input, preprocess_frame
from test_via import write_dataset


# ------------------------------------------------------------------------------------------------ splits

def test_paper_counts_508_frames():
    splits = make_splits(508)
    train, val = splits.holdout
    assert (len(train), len(val)) == (406, 102)
    assert len(train) * (1 + 2) == 1218  # 406 originals + 2 augmented copies each
    assert [len(v) for _, v in splits.folds] == [102, 102, 102, 101, 101]
    np.testing.assert_array_equal(splits.holdout[1], splits.folds[0][1])  # 80/20 hold-out = fold 0 of 5


@pytest.mark.parametrize("n", [5, 10, 23, 508])
def test_kfold_partitions_and_is_deterministic(n):
    folds = kfold_split(n, 5, seed=3)
    vals = np.concatenate([v for _, v in folds])
    assert sorted(vals.tolist()) == list(range(n))
    for train, val in folds:
        assert not set(train) & set(val) and len(train) + len(val) == n
    again = kfold_split(n, 5, seed=3)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(folds, again))
    other = kfold_split(n, 5, seed=4)
    assert n < 6 or any(not np.array_equal(a[1], b[1]) for a, b in zip(folds, other))


def test_holdout_sizes():
    assert [len(x) for x in holdout_split(10)] == [8, 2]
    assert [len(x) for x in holdout_split(2)] == [1, 1]
    with pytest.raises(UserError, match="validation fraction"):
        holdout_split(10, val_fraction=1.0)


def test_too_few_frames_for_folds():
    splits = make_splits(3)
    assert splits.folds == () and len(splits.holdout[1]) == 1
    with pytest.raises(UserError, match="too few frames for 5 folds"):
        splits.get(0)


# ------------------------------------------------------------------------------------------ --data rule

def test_folder_with_images_subfolder_or_beside(tmp_path):
    write_dataset(tmp_path / "a", n=5)
    write_dataset(tmp_path / "b", n=5, images_subdir=None)
    assert len(load_dataset(tmp_path / "a")) == 5
    assert len(load_dataset(tmp_path / "b")) == 5


def test_via_file_plus_images_folder(tmp_path):
    via, _ = write_dataset(tmp_path / "labels", n=5, images_subdir="../frames")
    ds = load_dataset(via, tmp_path / "frames")
    assert len(ds) == 5 and ds.samples[0].image_path.parent == tmp_path / "frames"


def test_folder_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="empty: no VIA project file"):
        load_dataset(tmp_path / "empty")
    via, _ = write_dataset(tmp_path / "two", n=5)
    (tmp_path / "two" / "other.json").write_text("{}")
    with pytest.raises(UserError, match=r"several JSON files \(ann.json, other.json\)"):
        load_dataset(tmp_path / "two")
    with pytest.raises(UserError, match="nothing: not found"):
        load_dataset(tmp_path / "nothing")
    with pytest.raises(UserError, match="nope: images folder not found"):
        load_dataset(via, tmp_path / "nope")


def test_splits_file_is_not_taken_for_the_via_file(tmp_path):
    write_dataset(tmp_path, n=5)
    load_dataset(tmp_path)
    assert (tmp_path / "ann.splits.json").exists()
    assert load_dataset(tmp_path).splits_status == "loaded"  # not "several JSON files"


def test_empty_dataset_is_an_error(tmp_path):
    write_dataset(tmp_path, n=3, missing={i: range(6) for i in range(3)})
    with pytest.raises(UserError, match=r"no usable frames \(3 fewer than 4 visible keypoints\)"):
        load_dataset(tmp_path)


# --------------------------------------------------------------------------------------- stored splits

def test_splits_are_stored_and_reused_by_frame_name(tmp_path):
    via, _ = write_dataset(tmp_path, n=10)
    first = load_dataset(tmp_path)
    assert first.splits_status == "created" and first.splits_path == splits_path(via) == tmp_path / "ann.splits.json"
    stored = json.loads(first.splits_path.read_text())
    assert stored["kfold"]["k"] == 5 and len(stored["holdout"]["val"]) == 2
    # reorder the VIA file's frames: the same frames land in the same folds
    data = json.loads(via.read_text())
    data["_via_img_metadata"] = dict(reversed(list(data["_via_img_metadata"].items())))
    via.write_text(json.dumps(data))
    second = load_dataset(tmp_path)
    assert second.splits_status == "loaded"
    for fold in [None, 0, 4]:
        names_first = sorted(first.names[i] for i in first.split(fold)[1])
        names_second = sorted(second.names[i] for i in second.split(fold)[1])
        assert names_first == names_second


def test_changed_frames_or_options_need_resplit(tmp_path):
    write_dataset(tmp_path, n=10, missing={3: range(6)})
    load_dataset(tmp_path, min_visible=1)  # stores splits for 10 frames
    with pytest.raises(UserError, match=r"different frame list \(10 frames, now 9.*--resplit"):
        load_dataset(tmp_path)  # default threshold drops frame 3
    with pytest.raises(UserError, match="seed 0.*but seed 1"):
        load_dataset(tmp_path, min_visible=1, split_seed=1)
    ds = load_dataset(tmp_path, resplit=True)
    assert ds.splits_status == "created" and len(ds) == 9
    assert load_dataset(tmp_path).splits_status == "loaded"


def test_splits_can_be_left_unsaved(tmp_path):
    write_dataset(tmp_path, n=5)
    ds = load_dataset(tmp_path, write_splits=False)
    assert ds.splits_status == "not saved" and not ds.splits_path.exists()


# ------------------------------------------------------------------------------------------- training feed

def test_fold_data_follows_the_papers_scheme(tmp_path):
    write_dataset(tmp_path, n=10)
    ds = load_dataset(tmp_path)
    train, val = fold_data(ds, None, 64, augment_copies=2, seed=0)
    assert len(train) == 8 + 2 * 8 == 24 and len(val) == 2
    assert train.kinds[:8] == ["original"] * 8 and all(k != "original" for k in train.kinds[8:])
    assert val.kinds == ["original"] * 2
    train_idx, val_idx = ds.split(None)
    assert set(train.source) == set(train_idx) and not set(train.source) & set(val_idx)
    np.testing.assert_array_equal(train.source[8:16], train_idx)
    assert train.images.shape == (24, 64, 64, 3) and train.images.dtype == np.uint8
    assert train.maps.shape == (24, 64, 64, 9) and train.maps.dtype == np.uint8
    assert train.keypoints.shape == (24, 8, 2)
    # every augmented sample keeps its keypoints inside the input frame
    assert np.all((train.keypoints >= -0.5) & (train.keypoints <= 63.5))


def test_rows_match_preprocessing_and_maps(tmp_path):
    write_dataset(tmp_path, n=5, size=(96, 40), missing={2: [5]})
    ds = load_dataset(tmp_path, min_visible=1)
    data = TrainingData(ds, [2, 0], 32)
    frame = ds.load_image(2)
    np.testing.assert_array_equal(data.images[0], np.rint(preprocess_frame(frame, 32) * 255).astype(np.uint8))
    kps = keypoints_to_input(ds.samples[2].keypoints, frame.shape, 32)
    np.testing.assert_allclose(data.keypoints[0], kps)
    np.testing.assert_array_equal(data.maps[0], make_target_maps(kps, 32, UR5))
    assert data.maps[0, ..., 5].sum() == 0
    np.testing.assert_array_equal(data.frame_sizes[0], (96, 40))
    x, y = data.arrays()
    assert x.dtype == y.dtype == np.float32
    np.testing.assert_array_equal(x[0], preprocess_frame(frame, 32))  # bit-identical to the runtime input


def test_same_seed_same_training_data(tmp_path):
    write_dataset(tmp_path, n=6)
    ds = load_dataset(tmp_path)
    a = TrainingData(ds, [0, 1, 2], 48, augment_copies=2, seed=5)
    b = TrainingData(ds, [0, 1, 2], 48, augment_copies=2, seed=5)
    c = TrainingData(ds, [0, 1, 2], 48, augment_copies=2, seed=6)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.maps, b.maps)
    assert a.kinds == b.kinds
    assert not np.array_equal(a.images[3:], c.images[3:])
    # a frame's copies do not depend on which other frames are in the split
    d = TrainingData(ds, [2], 48, augment_copies=2, seed=5)
    np.testing.assert_array_equal(d.images[1], a.images[5])


def test_sequence_batches_and_per_epoch_shuffle(tmp_path):
    write_dataset(tmp_path, n=5)
    data = TrainingData(load_dataset(tmp_path), range(5), 32, augment_copies=1, seed=0)
    seq = data.sequence(batch_size=4, shuffle=True, seed=1)
    assert len(seq) == 3
    x, y = seq[0]
    assert x.shape == (4, 32, 32, 3) and y.shape == (4, 32, 32, 9) and x.dtype == y.dtype == np.float32
    assert 0.0 <= x.min() and x.max() <= 1.0 and set(np.unique(y)) <= {0.0, 1.0}
    assert seq[2][0].shape[0] == 2
    first = seq.order.copy()
    assert sorted(first) == list(range(10))
    seq.on_epoch_end()
    assert not np.array_equal(first, seq.order) and sorted(seq.order) == list(range(10))
    again = data.sequence(batch_size=4, shuffle=True, seed=1)
    np.testing.assert_array_equal(again.order, first)
    ordered = data.sequence(batch_size=4, shuffle=False)
    np.testing.assert_array_equal(ordered[0][1], data.maps[:4].astype(np.float32))
    with pytest.raises(IndexError):
        ordered[3]


def test_resolve_data_returns_the_via_file(tmp_path):
    via, _ = write_dataset(tmp_path, n=1)
    assert resolve_data(tmp_path) == (via, None)
    assert resolve_data(via, tmp_path / "images") == (via, tmp_path / "images")
