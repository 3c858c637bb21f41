"""`fcnpose-tf data merge`: rounds of labelling joined by file name, images found wherever the inputs keep them."""

import json

import cv2
import numpy as np
import pytest

from fcnpose_tf.cli import main
from fcnpose_tf.data.dataset import load_dataset
from fcnpose_tf.data.via import ViaFrame, read_via, write_via_project
from fcnpose_tf.keypoints import UR5, KeypointSchema
from test_via import write_dataset


def _round(folder, names, seed, image_dir=None, schema=UR5, via_name="labels.json", size=(64, 48)):
    """A VIA project at folder/via_name naming `names`, its images in `image_dir` (default folder/images)."""
    rng = np.random.default_rng(seed)
    image_dir = image_dir or folder / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    w, h = size
    frames = []
    for name in names:
        if not (image_dir / name).exists():
            cv2.imwrite(str(image_dir / name), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        kps = np.c_[rng.uniform(6, w - 7, schema.num_keypoints), rng.uniform(6, h - 7, schema.num_keypoints)]
        frames.append(ViaFrame(name, w, h, kps.round(3)))
    write_via_project(folder / via_name, frames, schema, image_dir=image_dir)
    return folder / via_name, {f.filename: f.keypoints for f in frames}


def _merge(*args, capsys=None):
    status = main(["data", "merge", *map(str, args)])
    return status, (capsys.readouterr() if capsys else None)


def test_rounds_in_different_folders_merge_and_load_as_training_does(tmp_path, capsys):
    a, kps_a = _round(tmp_path / "round1", [f"a_{i}.png" for i in range(6)], seed=0)
    # round 2: a pre-labelled project whose images live in another folder (its VIA default path)
    b, kps_b = _round(tmp_path / "round2", [f"b_{i}.png" for i in range(4)], seed=1,
                      image_dir=tmp_path / "video_frames", via_name="pre.json")
    out = tmp_path / "merged" / "labels.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 0, captured.err
    assert f"Merged: {out}: 10 frames, schema ur5" in captured.out
    ds = load_dataset(out)
    assert ds.names == sorted(kps_a) + sorted(kps_b)
    for sample in ds.samples:
        np.testing.assert_allclose(sample.keypoints, {**kps_a, **kps_b}[sample.filename], atol=1e-3)
        assert sample.image_path.resolve().parent in ((tmp_path / "round1" / "images").resolve(),
                                                      (tmp_path / "video_frames").resolve())
    assert ds.load_image(7).shape == (48, 64, 3)
    settings = json.loads(out.read_text())["_via_settings"]["core"]
    assert settings["default_filepath"] == "../round1/images/" and settings["filepath"] == {"../video_frames/": 1}
    assert main(["data", "inspect", str(out)]) == 0
    assert "10 usable, 0 dropped" in capsys.readouterr().out
    # the output is not overwritten without --force
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 2 and "already exists; pass --force" in captured.err


def test_a_frame_annotated_twice_is_an_error_naming_it_unless_prefer_last(tmp_path, capsys):
    images = tmp_path / "frames"
    a, kps_a = _round(tmp_path / "r1", ["f0.png", "f1.png", "f2.png"], seed=0, image_dir=images)
    b, kps_b = _round(tmp_path / "r2", ["f1.png", "f3.png"], seed=5, image_dir=images)  # f1 corrected again
    out = tmp_path / "m.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 2 and not out.exists()
    assert captured.err.startswith("error: frame 'f1.png': annotated in") and "--prefer last" in captured.err
    assert len(captured.err.strip().splitlines()) == 1

    status, captured = _merge(a, b, "--out", out, "--prefer", "last", capsys=capsys)
    assert status == 0 and "1 replaced by a later input's annotation (--prefer last): f1.png" in captured.out
    merged = {f.filename: f.keypoints for f in read_via(out).frames}
    assert list(merged) == ["f0.png", "f1.png", "f2.png", "f3.png"]
    np.testing.assert_allclose(merged["f1.png"], kps_b["f1.png"], atol=1e-3)
    np.testing.assert_allclose(merged["f0.png"], kps_a["f0.png"], atol=1e-3)


def test_identical_annotations_are_kept_once_and_all_regions_carried_over(tmp_path, capsys):
    a, _ = _round(tmp_path / "r1", ["f0.png", "f1.png"], seed=0)
    data = json.loads(a.read_text())
    entry = next(iter(data["_via_img_metadata"].values()))
    entry["regions"].append({"shape_attributes": {"name": "rect", "x": 1, "y": 2, "width": 5, "height": 6},
                             "region_attributes": {}})
    entry["file_attributes"] = {"note": "occluded by a person"}
    a.write_text(json.dumps(data))
    copy = tmp_path / "r1" / "copy.json"
    copy.write_text(a.read_text())
    out = tmp_path / "r1" / "merged.json"
    status, captured = _merge(a, copy, "--out", out, capsys=capsys)
    assert status == 0 and "2 annotated identically in two inputs, kept once" in captured.out
    merged = json.loads(out.read_text())["_via_img_metadata"]
    assert len(merged) == 2
    first = next(iter(merged.values()))
    assert first["regions"][-1]["shape_attributes"]["name"] == "rect"
    assert first["file_attributes"] == {"note": "occluded by a person"}


def test_two_images_with_one_name_are_two_frames_and_a_name_that_would_find_another_image(tmp_path, capsys):
    a, kps_a = _round(tmp_path / "r1", ["f0.png", "f1.png"], seed=0)
    b, kps_b = _round(tmp_path / "r2", ["f1.png"], seed=1)  # another image called f1.png (another session's)
    out = tmp_path / "m.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 0, captured.err
    ds = load_dataset(out)
    assert len(ds.names) == 3
    for folder, kps in (("r1", kps_a), ("r2", kps_b)):  # each f1.png with its own image and keypoints
        image = (tmp_path / folder / "images/f1.png").resolve()
        i = next(i for i, sample in enumerate(ds.samples) if sample.image_path.resolve() == image)
        np.testing.assert_allclose(ds.samples[i].keypoints, kps["f1.png"], atol=1e-3)
        assert np.array_equal(ds.load_image(i), cv2.imread(str(tmp_path / folder / "images/f1.png")))

    # r2's x.png is annotated; r1's folder holds an unannotated x.png too: the merged entry keeps its path
    c, kps_c = _round(tmp_path / "r3", ["x.png"], seed=2)
    cv2.imwrite(str(tmp_path / "r1" / "images" / "x.png"), np.zeros((48, 64, 3), np.uint8))
    out = tmp_path / "m2.json"
    status, captured = _merge(a, c, "--out", out, capsys=capsys)
    assert status == 0 and "1 frame(s) stored with their path" in captured.out
    ds = load_dataset(out)
    x = ds.names.index("r3/images/x.png")
    assert ds.load_image(x).any() and ds.samples[x].image_path.resolve() == (tmp_path / "r3/images/x.png").resolve()


def test_keypoint_schemas_must_match(tmp_path, capsys):
    a, _ = _round(tmp_path / "r1", ["f0.png"], seed=0)
    other = KeypointSchema.chain("arm3", ("base", "elbow", "tip"))
    b, _ = _round(tmp_path / "r2", ["g0.png"], seed=1, schema=other)
    status, captured = _merge(a, b, "--out", tmp_path / "m.json", capsys=capsys)
    assert status == 2 and f"{b}: keypoint schema 'arm3' (base, elbow, tip) differs from" in captured.err
    assert not (tmp_path / "m.json").exists()


def test_a_missing_image_is_an_error_naming_the_frame_or_left_out_with_skip_bad(tmp_path, capsys):
    a, _ = _round(tmp_path / "r1", ["f0.png", "f1.png"], seed=0)
    b, _ = _round(tmp_path / "r2", ["g0.png", "g1.png"], seed=1)
    (tmp_path / "r2" / "images" / "g1.png").unlink()
    out = tmp_path / "m.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 2 and "frame 'g1.png': image file not found" in captured.err and not out.exists()
    status, captured = _merge(a, b, "--out", out, "--skip-bad", capsys=capsys)
    assert status == 0 and "1 bad frame(s) left out (--skip-bad)" in captured.out and "g1.png" in captured.out
    assert [f.filename for f in read_via(out).frames] == ["f0.png", "f1.png", "g0.png"]


def test_merge_needs_two_inputs_and_a_json_output(tmp_path, capsys):
    a, _ = _round(tmp_path / "r1", ["f0.png"], seed=0)
    status, captured = _merge(a, "--out", tmp_path / "m.json", capsys=capsys)
    assert status == 2 and "at least two VIA projects" in captured.err
    status, captured = _merge(a, a, "--out", tmp_path / "m.json", capsys=capsys)
    assert status == 2 and "given twice" in captured.err
    status, captured = _merge(a, a, "--out", tmp_path / "m.txt", capsys=capsys)
    assert status == 2 and "a VIA project is a .json file" in captured.err


def test_merged_rounds_train(tmp_path):
    """The merged project feeds training as any dataset does (load_dataset -> fold_data arrays)."""
    from fcnpose_tf.data.dataset import fold_data

    a, _ = write_dataset(tmp_path / "r1", n=6)
    b, _ = _round(tmp_path / "r2", [f"g{i}.png" for i in range(4)], seed=3)
    out = tmp_path / "merged" / "all.json"
    assert main(["data", "merge", str(a), str(b), "--out", str(out)]) == 0
    ds = load_dataset(out)
    train, val = fold_data(ds, None, 32, 0, progress=False)
    assert len(train) + len(val) == 10 and train.arrays()[0].shape[1:] == (32, 32, 3)


def test_frames_whose_name_and_size_run_together_alike_are_both_kept(tmp_path, capsys):
    # VIA keys a frame by its name and byte size run together: `x.png` of 1SSS bytes and `x.png1` of SSS bytes
    # both give `x.png1SSS`. Both frames are kept, under two keys.
    rng = np.random.default_rng(3)
    second = tmp_path / "round2" / "images" / "x.png1"
    second.parent.mkdir(parents=True)
    ok, png = cv2.imencode(".png", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    second.write_bytes(png.tobytes())
    first = tmp_path / "round1" / "images" / "x.png"
    first.parent.mkdir(parents=True)
    ok, png = cv2.imencode(".png", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    first.write_bytes(png.tobytes().ljust(int("1" + str(second.stat().st_size)), b"\0"))  # PNG readers stop at IEND
    a, kps_a = _round(tmp_path / "round1", ["x.png"], seed=0)
    b, kps_b = _round(tmp_path / "round2", ["x.png1"], seed=1)
    assert next(iter(json.loads(a.read_text())["_via_img_metadata"])) == \
        next(iter(json.loads(b.read_text())["_via_img_metadata"]))
    out = tmp_path / "merged.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 0, captured.err
    assert "2 frames" in captured.out
    ds = load_dataset(out)
    assert sorted(s.image_path.name for s in ds.samples) == ["x.png", "x.png1"]
    for sample in ds.samples:
        np.testing.assert_allclose(sample.keypoints, {**kps_a, **kps_b}[sample.image_path.name], atol=1e-3)


def test_a_prediction_project_keeps_frames_whose_keys_run_together_alike(tmp_path):
    frames = [ViaFrame("x.png", 64, 48, np.full((8, 2), 5.0), size=1300),
              ViaFrame("x.png1", 64, 48, np.full((8, 2), 9.0), size=300)]
    write_via_project(tmp_path / "p.json", frames)
    metadata = json.loads((tmp_path / "p.json").read_text())["_via_img_metadata"]
    assert list(metadata) == ["x.png1300", "x.png1300#2"]
    assert [m["filename"] for m in metadata.values()] == ["x.png", "x.png1"]
    with pytest.raises(Exception, match="appears twice"):
        write_via_project(tmp_path / "q.json", frames[:1] * 2)


def test_attributes_nested_hundreds_of_levels_are_refused_in_one_line(tmp_path, capsys):
    a, _ = _round(tmp_path / "round1", ["a.png"], seed=0)
    b, _ = _round(tmp_path / "round2", ["b.png"], seed=1)
    project = json.loads(a.read_text())
    next(iter(project["_via_img_metadata"].values()))["file_attributes"]["note"] = json.loads("[" * 500 + "]" * 500)
    a.write_text(json.dumps(project))
    status, captured = _merge(a, b, "--out", tmp_path / "m.json", capsys=capsys)
    assert status == 2
    assert captured.err.strip().splitlines() == [f"error: {a}: not a VIA project (JSON nested more than 64 levels deep)"]
    assert not (tmp_path / "m.json").exists()


def test_round_two_never_validates_on_round_ones_training_frames(tmp_path, capsys):
    """Round 1's stored hold-out split travels with its frames: the merged project's validation frames are round 1's
    validation frames plus new ones, so the start-as-candidate check is not biased toward the round-1 model."""
    from fcnpose_tf.data.via import SPLIT_ATTRIBUTE

    a, _ = _round(tmp_path / "round1", [f"a_{i:02d}.png" for i in range(20)], seed=0)
    first = load_dataset(a)  # stores round 1's splits, as train did
    round1_train = {first.names[i] for i in first.split()[0]}
    round1_val = {first.names[i] for i in first.split()[1]}
    b, _ = _round(tmp_path / "round2", [f"b_{i:02d}.png" for i in range(20)], seed=1)
    out = tmp_path / "merged" / "labels.json"
    status, captured = _merge(a, b, "--out", out, capsys=capsys)
    assert status == 0, captured.err
    assert "20 keep the training or validation role the inputs' splits gave them" in captured.out
    assert json.loads(out.read_text())["_via_attributes"]["file"][SPLIT_ATTRIBUTE]["type"] == "dropdown"
    merged = load_dataset(out)
    train, val = ({merged.names[i] for i in part} for part in merged.split())
    assert round1_val <= val and not (round1_train & val)
    assert len(val) == 8 and len(val - round1_val) == 8 - len(round1_val)  # 20 % of 40, new frames fill it
    # a third round merged with the merged project keeps every role again
    c, _ = _round(tmp_path / "round3", [f"c_{i:02d}.png" for i in range(10)], seed=2)
    out3 = tmp_path / "merged3" / "labels.json"
    status, captured = _merge(out, c, "--out", out3, capsys=capsys)
    assert status == 0, captured.err
    third = load_dataset(out3)
    val3 = {third.names[i] for i in third.split()[1]}
    assert val <= val3 and not (train & val3)
