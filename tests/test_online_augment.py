"""Online augmentation: keypoints follow the pixels through every geometric transform, seeds reproduce."""

import json

import numpy as np
import pytest

from fcnpose_tf.data.online import OnlineAugmentConfig, OnlineAugmenter, sample_rng, working_frame
from fcnpose_tf.errors import UserError

W, H, S = 120, 90, 64
NO_APPEARANCE = dict(color_p=0.0, gamma_p=0.0, shuffle_p=0.0, blur_p=0.0, noise_p=0.0, jpeg_p=0.0, dropout_p=0.0)


def dot_image(keypoints, width=W, height=H, sigma=1.5):
    """A black RGB frame with one bright blob per keypoint, keypoint c in channel c."""
    image = np.zeros((height, width, 3), np.uint8)
    yy, xx = np.mgrid[0:height, 0:width]
    for c, (x, y) in enumerate(keypoints):
        blob = np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))
        image[..., c] = np.round(255 * blob).astype(np.uint8)
    return image


def blob_centre(channel):
    weights = channel.astype(np.float64)
    weights[weights < 0.15 * weights.max()] = 0
    yy, xx = np.mgrid[0:channel.shape[0], 0:channel.shape[1]]
    return np.array([(xx * weights).sum() / weights.sum(), (yy * weights).sum() / weights.sum()])


GEOMETRY = {
    "flip": dict(flip_p=1.0, affine_p=0.0),
    "rotation": dict(flip_p=0.0, max_rotation_deg=30.0, min_scale=1.0, max_scale=1.0, max_shift=0.0),
    "zoom in": dict(flip_p=0.0, max_rotation_deg=0.0, min_scale=1.25, max_scale=1.3, max_shift=0.0),
    "zoom out": dict(flip_p=0.0, max_rotation_deg=0.0, min_scale=0.75, max_scale=0.8, max_shift=0.0),
    "shift": dict(flip_p=0.0, max_rotation_deg=0.0, min_scale=1.0, max_scale=1.0, max_shift=0.12),
    "all": dict(),
}


@pytest.mark.parametrize("name", list(GEOMETRY))
def test_dots_end_up_at_the_transformed_keypoints(name):
    kps = np.array([[40.0, 30.0], [80.5, 60.25], [60.0, 45.0]])
    image = dot_image(kps)
    augment = OnlineAugmenter(S, OnlineAugmentConfig(**GEOMETRY[name], **NO_APPEARANCE))
    moved_any = False
    for i in range(12):
        out, moved = augment(image, kps, sample_rng(0, 0, i))
        assert out.shape == (S, S, 3) and out.dtype == np.uint8
        expected_unmoved = (kps + 0.5) * np.array([S / W, S / H]) - 0.5
        moved_any |= not np.allclose(moved, expected_unmoved)
        for c in range(3):
            error = np.hypot(*(blob_centre(out[..., c]) - moved[c]))
            assert error < 0.35, (name, i, c, error)  # input pixels; the warp itself is exact
    assert moved_any, f"{name}: no sample was transformed"


def test_flip_keeps_identities_and_mirrors_x():
    kps = np.array([[20.0, 30.0], [100.0, 60.0]])
    augment = OnlineAugmenter(S, OnlineAugmentConfig(flip_p=1.0, affine_p=0.0, **NO_APPEARANCE))
    _, moved = augment(dot_image(kps), kps, sample_rng(0, 0, 0))
    scaled = (kps + 0.5) * np.array([S / W, S / H]) - 0.5
    np.testing.assert_allclose(moved[:, 0], S - 1 - scaled[:, 0], atol=1e-4)  # keypoint 0 stays keypoint 0
    np.testing.assert_allclose(moved[:, 1], scaled[:, 1], atol=1e-4)


def test_a_flip_swaps_the_labels_of_left_right_pairs():
    """A gripper's L and R fingers: flipped, the left finger is where a right finger is, and is labelled so (review:
    half the online-augmented targets swapped L and R); an unflipped sample keeps its labels."""
    from fcnpose_tf.correction.selection import flip_back
    from fcnpose_tf.keypoints import UR5, KeypointSchema, describe_mirror

    schema = KeypointSchema.chain("gripper", ("base", "finger L", "finger R"))
    assert schema.mirror == (0, 2, 1)
    assert KeypointSchema.chain("yaskawa", "SLURBT").mirror == tuple(range(6))  # axes named by a letter: no pair
    assert KeypointSchema.chain("axes", ("S-axis", "L-axis", "R-axis", "joint L", "joint R")).mirror == tuple(range(5))
    assert describe_mirror(schema) == "finger L <-> finger R" and describe_mirror(UR5) is None
    several = KeypointSchema.chain("hand", ("Gripper Left", "gripper right", "finger L1", "finger R1", "finger L2",
                                            "finger R2", "tip"))
    assert several.mirror == (1, 0, 3, 2, 5, 4, 6)  # case aside, and numbered pairs
    camel = KeypointSchema.chain("camel", ("leftFinger", "rightFinger", "RWrist", "LWrist", "wristRoll", "LAxis"))
    assert camel.mirror == (1, 0, 3, 2, 4, 5)  # camel-case words (OpenPose's RWrist) pair too; an axis stays
    for names, mirror in [(("finger L", "finger R", "finger r"), (1, 0, 2)),  # was (1, 0, 0): finger r lost its label
                          (("finger r", "finger L", "finger R"), (0, 2, 1)),  # the same spelling pairs first
                          (("base", "gripper L", "gripper R", "Gripper L"), (0, 2, 1, 3))]:
        assert KeypointSchema.chain("cased", names).mirror == mirror, names  # a permutation, whatever the names
    kps = np.array([[60.0, 80.0], [40.0, 30.0], [90.0, 30.0]])
    scaled = (kps + 0.5) * np.array([S / W, S / H]) - 0.5
    flipping = OnlineAugmenter(S, OnlineAugmentConfig(flip_p=1.0, affine_p=0.0, **NO_APPEARANCE), schema.mirror)
    _, moved = flipping(dot_image(kps), kps, sample_rng(0, 0, 0))
    assert moved[1, 0] < moved[2, 0]  # finger L still on the left of the picture
    np.testing.assert_allclose(moved[[0, 2, 1], 0], S - 1 - scaled[:, 0], atol=1e-4)
    still = OnlineAugmenter(S, OnlineAugmentConfig(flip_p=0.0, affine_p=0.0, **NO_APPEARANCE), schema.mirror)
    np.testing.assert_allclose(still(dot_image(kps), kps, sample_rng(0, 0, 0))[1], scaled, atol=1e-4)
    np.testing.assert_allclose(flip_back(kps, 160, schema.mirror), [[99.0, 80.0], [69.0, 30.0], [119.0, 30.0]])


def test_visible_keypoints_stay_in_the_frame_and_missing_ones_stay_missing():
    kps = np.array([[2.0, 2.0], [W - 3.0, H - 3.0], [np.nan, np.nan]])  # near corners: many draws rejected
    augment = OnlineAugmenter(S, OnlineAugmentConfig(max_rotation_deg=45, min_scale=1.3, max_scale=1.3))
    for i in range(20):
        _, moved = augment(dot_image(kps[:2]), kps, sample_rng(1, 2, i))
        assert np.isnan(moved[2]).all()
        assert np.all((moved[:2] >= -0.5) & (moved[:2] <= S - 0.5))


def test_same_seed_same_samples_other_seed_other_samples():
    kps = np.array([[40.0, 30.0], [80.0, 60.0], [60.0, 45.0]])
    image = dot_image(kps)
    augment = OnlineAugmenter(S)
    a = [augment(image, kps, sample_rng(7, 3, i)) for i in range(4)]
    b = [augment(image, kps, sample_rng(7, 3, i)) for i in reversed(range(4))][::-1]  # any order
    c = [augment(image, kps, sample_rng(8, 3, i)) for i in range(4)]
    for (ia, ka), (ib, kb) in zip(a, b):
        np.testing.assert_array_equal(ia, ib)
        np.testing.assert_array_equal(ka, kb)
    assert any(not np.array_equal(ia, ic) for (ia, _), (ic, _) in zip(a, c))


def test_working_frame_scales_keypoints_through_pixel_edges():
    frame = np.zeros((480, 640, 3), np.uint8)
    rgb, kps = working_frame(frame, np.array([[-0.5, -0.5], [639.5, 479.5]]), 64, 1.5)
    assert rgb.shape == (96, 128, 3)
    np.testing.assert_allclose(kps, [[-0.5, -0.5], [127.5, 95.5]])
    # a frame of another aspect than the input's: each side at least 1.5 x the input's, so none is enlarged later
    tall, _ = working_frame(np.zeros((640, 480, 3), np.uint8), np.zeros((2, 2)), (32, 96), 1.5)
    assert tall.shape[1] >= 1.5 * 96 and tall.shape[0] >= 1.5 * 32 and tall.shape[:2] == (192, 144)


def test_bad_ranges_are_refused():
    with pytest.raises(UserError, match="probability"):
        OnlineAugmentConfig(flip_p=1.5)
    with pytest.raises(UserError, match="min_scale"):
        OnlineAugmentConfig(min_scale=1.3, max_scale=1.0)


def test_online_training_data_follows_seed_and_epoch_and_keeps_keypoints_on_their_discs(tmp_path):
    from test_train_evaluate import make_via_folder

    from fcnpose_tf.data.dataset import fold_data, load_dataset

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    train, val = fold_data(ds, None, 64, seed=3, augment="online")
    again, _ = fold_data(ds, None, 64, seed=3, augment="online")
    other, _ = fold_data(ds, None, 64, seed=4, augment="online")
    assert len(train) == 3 * train.num_frames and len(val) == len(ds) - train.num_frames
    seq = train.sequence(4)
    first = seq[0]
    np.testing.assert_array_equal(first[0], again.sequence(4)[0][0])  # same seed, same batch
    assert not np.array_equal(first[0], other.sequence(4)[0][0])
    seq.on_epoch_end()
    assert not np.array_equal(first[0], seq[0][0])  # every epoch draws anew
    resumed = again.sequence(4)
    resumed.epoch = 1  # what `fit` sets when it resumes after one epoch
    np.testing.assert_array_equal(seq[1][1], resumed[1][1])
    images, maps = first
    assert images.dtype == maps.dtype == np.float32 and images.shape == (4, 64, 64, 3) and maps.shape[-1] == 9
    assert 0.0 <= images.min() and images.max() <= 1.0 and set(np.unique(maps)) <= {0.0, 1.0}


@pytest.mark.usefixtures("few_timed_frames")
def test_train_cli_paper_copies_by_default_and_online_on_request(tmp_path, cli_here):
    import json

    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=6)
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "p.keras", "--epochs", "1",
                                   "--input-size", "64", "--init", "none", "--augment-copies", "1", "--quiet")
    assert status == 0, err
    assert "10 samples (5 frames + 1 augmented copies each)" in stdout
    record = json.loads((tmp_path / "p_train.json").read_text())
    assert record["augment"] == "paper" and record["augment_copies"] == 1
    assert record["config"]["freeze"] == 0  # from scratch every layer trains
    assert record["config"]["positive_weight"] == 20.0  # random weights need the large keypoint weight
    assert (record["config"]["lr_schedule"], record["config"]["lr_patience"]) == ("plateau", 4)
    status, stdout, err = cli_here("train", "--data", data, "--out", tmp_path / "m.keras", "--epochs", "1",
                                   "--input-size", "64", "--init", "none", "--augment", "online", "--lr-schedule",
                                   "cosine", "--quiet")
    assert status == 0, err
    assert "15 freshly augmented samples an epoch from 5 frames" in stdout
    record = json.loads((tmp_path / "m_train.json").read_text())
    assert record["augment"] == "online" and record["augment_copies"] is None
    # the cosine sets every epoch's rate itself: an unset --lr-patience resolves to 0 instead of being refused
    assert (record["config"]["lr_schedule"], record["config"]["lr_patience"]) == ("cosine", 0)
    status, _, err = cli_here("train", "--data", data, "--out", tmp_path / "q.keras", "--augment", "fancy")
    assert status == 2 and "invalid choice: 'fancy'" in err


@pytest.mark.usefixtures("few_timed_frames")
def test_default_init_is_the_bundled_generalist_and_bundled_inits_are_refused_for_another_schema(tmp_path, cli_here):
    import cv2

    from fcnpose_tf.data.via import ViaFrame, write_via_project
    from fcnpose_tf.keypoints import KeypointSchema

    arm = KeypointSchema("arm4", ("base", "elbow", "wrist", "tip"), ((0, 1), (1, 2), (2, 3)))
    (tmp_path / "d" / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(5):
        cv2.imwrite(str(tmp_path / "d" / "images" / f"f{i}.png"), np.full((48, 64, 3), 60, np.uint8))
        frames.append(ViaFrame(f"f{i}.png", 64, 48, np.c_[rng.uniform(5, 58, 4), rng.uniform(5, 42, 4)]))
    write_via_project(tmp_path / "d" / "labels.json", frames, arm)
    status, _, err = cli_here("train", "--data", tmp_path / "d", "--out", tmp_path / "m.keras", "--epochs", "1",
                              "--input-size", "32")
    assert status == 2 and err.strip().splitlines()[-1].startswith("error: ")
    assert "fcnpose_ur5_generalist.keras: trained for base, shoulder" in err
    assert "pass --init none to train from scratch" in err and not (tmp_path / "m.keras").exists()
    status, _, err = cli_here("train", "--data", tmp_path / "d", "--out", tmp_path / "m.keras", "--epochs", "1",
                              "--input-size", "32", "--init", "workcell")
    assert status == 2 and "fcnpose_ur5.keras: trained for base, shoulder" in err
    status, stdout, err = cli_here("train", "--data", tmp_path / "d", "--out", tmp_path / "m.keras", "--epochs", "1",
                                   "--input-size", "32", "--init", "none", "--quiet")
    assert status == 0, err
    record = json.loads((tmp_path / "m_train.json").read_text())
    assert record["init"] is None and record["schema"]["keypoints"] == list(arm.keypoints)
