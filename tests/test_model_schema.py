"""A model carries the names of its keypoints: train stores the data's schema in the model file, export in the
.tflite metadata, so that predict, run and the correction loop (predict -> correct -> data merge) speak the user's
names, not kp0..kpN or UR5's; files written before take their training record's. An exported file also carries which
frames its model was trained on, so that evaluate away from the record still measures on validation frames."""

import json
import zipfile

import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema, named_schema, schema_for_maps
from tests.test_train_evaluate import make_via_folder

MINE = KeypointSchema("arm4", ("j0", "j1", "j2", "tip"), ((0, 1), (1, 2), (2, 3)))
TRAIN_FROM = ("--epochs", "1", "--input-size", "64", "--augment", "paper", "--augment-copies", "0", "--batch-size",
              "4", "--quiet", "--threads", "1")
TRAIN = (*TRAIN_FROM, "--init", "none")


def _own_schema_folder(folder, schema=MINE, n=6, size=64):
    return make_via_folder(folder, n=n, size=(size, size), seed=3, schema=schema, suffix=".png")


def test_named_schema_reads_the_stored_entry_then_the_record(tmp_path):
    model = tmp_path / "m.keras"
    assert named_schema(5, None, model) is None  # neither: the caller's default (kp0..kp3)
    assert schema_for_maps(5).keypoints == ("kp0", "kp1", "kp2", "kp3")
    with pytest.raises(UserError, match=r"^a model of 1 output map\(s\) is no FCN-Pose keypoint model"):
        schema_for_maps(1)  # "schema 'generic': keypoint names must be non-empty and unique" before
    assert named_schema(5, json.dumps(MINE.to_dict()), model) == MINE
    (tmp_path / "m_train.json").write_text(json.dumps({"schema": MINE.to_dict()}))
    assert named_schema(5, None, model) == MINE
    assert named_schema(5, None, tmp_path / "m_fp16.tflite") == MINE  # an export of it finds the record too
    (tmp_path / "m_p70_train.json").write_text(json.dumps({"pruned_from": "m.keras"}))  # compress's, before today
    for derived in ("m_p70.keras", "m_p70_fp16.tflite", "m_p70_int8.tflite"):
        assert named_schema(5, None, tmp_path / derived) == MINE, derived  # the base's record names them
    assert named_schema(9, None, model) is None  # a record of another map count says nothing
    assert named_schema(9, json.dumps(UR5.to_dict()), model) == UR5  # the stored entry wins
    with pytest.raises(UserError, match="stored keypoint schema 'arm4' has 4 keypoints, but the model has 9 output"):
        named_schema(9, json.dumps(MINE.to_dict()), model)
    with pytest.raises(UserError, match="stored keypoint schema is not JSON"):
        named_schema(5, "{", model)
    with pytest.raises(UserError, match="invalid keypoint schema"):
        named_schema(5, json.dumps({"name": "x"}), model)



@pytest.mark.parametrize("edit", [
    {"keypoints": [1, 2, 3, 4]},  # not names: read as '1'..'4' before
    {"keypoints": "abcd"},  # a string: read as the names a, b, c, d before
    {"edges": [[0, 1.9]]},  # read as (0, 1) before
    {"edges": [[True, False]]},
    {"edges": ["01", "12"]},  # a string's characters: read as (0, 1), (1, 2) before
    {"name": {"x": 1}},
    {"keypoints": ["j0", "j1\nerror: forged", "j2", "tip"]},  # its names reach messages, tables and files
    {"keypoints": ["j0", "j1\x00", "j2", "tip"]},
    {"keypoints": ["", "j1", "j2", "tip"]},
    {"keypoints": ["j0", "j1\ud800", "j2", "tip"]},  # no UTF-8: `run --save-video` died in OpenCV (SIGSEGV)
])
def test_a_stored_schema_is_read_as_its_json_holds_it_or_refused_on_one_line_naming_the_file(tmp_path, edit):
    stored = json.dumps({**MINE.to_dict(), **edit})
    with pytest.raises(UserError, match=r"^\S*m\.keras: invalid keypoint schema") as refused:
        named_schema(5, stored, tmp_path / "m.keras")
    assert str(refused.value).isprintable()

def test_the_schema_survives_saving_resizing_and_surgery(tmp_path):
    from fcnpose_tf.compression.magnitude import magnitude_prune
    from fcnpose_tf.compression.graph_prune import prune_graph
    from fcnpose_tf.compression.prune import prune_model
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.training.model import (SCHEMA_ENTRY, at_input_size, build_fcn_pose, given_schema, given_view,
                                           load_model, save_for_inference, schema_of, with_facts_of, with_schema,
                                           with_view)

    model = build_fcn_pose(input_size=64, num_maps=MINE.num_maps)
    assert given_schema(model) is None and schema_of(model).keypoints == ("kp0", "kp1", "kp2", "kp3")
    with pytest.raises(UserError, match="5 output maps cannot stand for schema 'ur5'"):
        with_schema(model, UR5)
    with_schema(model, MINE)
    assert schema_of(at_input_size(model, 96)) == MINE
    for suffix in (".keras", ".h5"):
        path = tmp_path / f"m{suffix}"
        save_for_inference(model, path)
        assert schema_of(load_model(path)) == MINE
    with zipfile.ZipFile(tmp_path / "m.keras") as archive:
        assert json.loads(archive.read(SCHEMA_ENTRY)) == MINE.to_dict()
    view = FrameView(64, 64, crop=(8, 8, 48, 48), frame_size=(64, 64))
    with_view(model, view)
    for pruned in (prune_model(model, 0.5), prune_graph(model, 0.5), magnitude_prune(model, 0.5),
                   with_facts_of(build_fcn_pose(input_size=64, num_maps=MINE.num_maps), model)):
        assert schema_of(pruned) == MINE and given_view(pruned) == view  # the library's surgery lost both before
    plain = build_fcn_pose(input_size=64, num_maps=MINE.num_maps)
    save_for_inference(plain, tmp_path / "plain.keras")  # no schema given: none stored, no record: the default
    assert given_schema(load_model(tmp_path / "plain.keras")) is None


@pytest.mark.slow
def test_own_keypoints_go_from_train_through_export_predict_and_run_to_merge(tmp_path, cli_here):
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.records import DEPLOYED_RECORD_KEYS, file_sha256, training_record
    from fcnpose_tf.runtime.tflite_metadata import RECORD_METADATA, SCHEMA_METADATA, read_metadata
    from fcnpose_tf.training.model import load_model, schema_of

    data = _own_schema_folder(tmp_path / "mine")
    model = tmp_path / "models" / "arm.keras"
    status, out, err = cli_here("train", "--data", data, "--out", model, *TRAIN)
    assert status == 0, out + err
    assert schema_of(load_model(model)) == MINE
    status, out, err = cli_here("export", model, "--data", data, "--quantize", "float16", "--threads", "1", "--quiet")
    assert status == 0, out + err
    tflite = tmp_path / "models" / "arm_fp16.tflite"
    assert json.loads(read_metadata(tflite)[SCHEMA_METADATA]) == MINE.to_dict()
    alone = tmp_path / "pi" / "arm_fp16.tflite"  # on the Pi the file travels without its training record
    alone.parent.mkdir()
    alone.write_bytes(tflite.read_bytes())
    assert KeypointModel(alone, num_threads=1).schema == MINE
    own = training_record(alone)  # which frames it was trained on travels with it too, without paths
    assert own is not None and own.data_sha256 == file_sha256(data / "labels.json") and own.split == "hold-out 80/20"
    assert set(json.loads(read_metadata(alone)[RECORD_METADATA])) <= set(DEPLOYED_RECORD_KEYS)
    status, out, err = cli_here("evaluate", alone, "--data", data, "--threads", "1", "--quiet", "--worst", "0")
    assert status == 0, out + err
    assert "validation frames of the hold-out 80/20 split (" in out, out
    status, out, err = cli_here("run", alone, "--source", data / "images", "--out", tmp_path / "run.jsonl",
                                "--threads", "1", "--quiet")
    assert status == 0, out + err
    first = json.loads((tmp_path / "run.jsonl").read_text().splitlines()[0])
    assert [k["name"] for k in first["keypoints"]] == list(MINE.keypoints)
    for source in (model, alone):  # the Keras model and the Pi's file: predict, correct, merge
        project = tmp_path / f"pre_{source.suffix[1:]}" / "pre.json"
        status, out, err = cli_here("predict", source, "--source", data / "images", "--via", project, "--threads",
                                    "1", "--quiet")
        assert status == 0, out + err
        assert json.loads(project.read_text())["fcnpose_schema"] == MINE.to_dict()
        merged = tmp_path / f"merged_{source.suffix[1:]}" / "m.json"
        status, out, err = cli_here("data", "merge", data / "labels.json", project, "--out", merged, "--prefer", "last")
        assert status == 0, out + err


TREE = KeypointSchema("gripper", ("base", "wrist", "finger L", "finger R"), ((0, 1), (1, 2), (1, 3)))


def _reordered(folder, schema, order, name="labels.json"):
    """The same frames and points, the dropdown (and the stored schema) listing the keypoints in `order`."""
    from fcnpose_tf.data.via import read_via, write_via_project

    frames = read_via(folder / "labels.json").frames
    other = KeypointSchema(schema.name, tuple(schema.keypoints[i] for i in order),
                           tuple((order.index(a), order.index(b)) for a, b in schema.edges))
    moved = [type(f)(f.filename, f.width, f.height, f.keypoints[list(order)]) for f in frames]
    write_via_project(folder / name, moved, other)
    return other


def test_a_model_is_read_by_its_keypoint_names_and_refused_for_other_ones(tmp_path, cli_here):
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
    from fcnpose_tf.training.model import build_fcn_pose, save_for_inference, with_schema
    from tests.weights import randomize

    data = _own_schema_folder(tmp_path / "d", TREE)
    model = tmp_path / "m.keras"
    save_for_inference(with_schema(randomize(build_fcn_pose(input_size=64, num_maps=5), seed=1), TREE), model)
    swapped = tmp_path / "swapped"
    swapped.mkdir()
    (swapped / "images").symlink_to(data / "images")
    _reordered(data, TREE, (0, 1, 3, 2), name="swapped.json")
    (data / "swapped.json").rename(swapped / "labels.json")
    predictor = KerasKeypointModel(model, num_threads=1)
    original, other = load_dataset(data, write_splits=False), load_dataset(swapped, write_splits=False)
    assert other.schema.keypoints == ("base", "wrist", "finger R", "finger L")
    a = evaluate_predictor(predictor, original, range(len(original)), original.schema, min_timed_frames=0, warmup=0)
    b = evaluate_predictor(predictor, other, range(len(other)), other.schema, min_timed_frames=0, warmup=0)
    assert np.array_equal(a.predictions[:, [0, 1, 3, 2]], b.predictions, equal_nan=True)  # finger R read as finger R
    mine = _own_schema_folder(tmp_path / "mine", MINE)
    status, _, err = cli_here("evaluate", model, "--data", mine, "--threads", "1")
    assert status == 2 and "m.keras: trained for base, wrist, finger L, finger R, but the data's schema" in err
    assert "the data lacks base, wrist, finger L, finger R; m.keras lacks j0, j1, j2, tip" in err
    lone = tmp_path / "lone"  # no training record beside it: the names stored in the file decide
    lone.mkdir()
    (lone / "m.keras").write_bytes(model.read_bytes())
    status, _, err = cli_here("train", "--data", mine, "--init", lone / "m.keras", "--out", tmp_path / "t.keras",
                              *TRAIN_FROM)
    assert status == 2 and "m.keras: trained for base, wrist, finger L, finger R" in err
    # the same keypoints in another order: the start's maps are put in the data's order, not refused
    from fcnpose_tf.training.model import in_keypoint_order, load_model, schema_of

    start, reordered = load_model(lone / "m.keras"), load_model(lone / "m.keras")
    in_keypoint_order(reordered, other.schema, "m.keras", "")
    frame = np.random.default_rng(0).random((1, 64, 64, 3), np.float32)
    np.testing.assert_array_equal(start(frame).numpy()[..., [0, 1, 3, 2, 4]], reordered(frame).numpy())
    status, out, err = cli_here("train", "--data", swapped, "--init", lone / "m.keras", "--out", tmp_path / "t.keras",
                                *TRAIN_FROM)
    assert status == 0, out + err
    assert schema_of(load_model(tmp_path / "t.keras")) == other.schema
    plain = tmp_path / "old" / "p.keras"  # no schema stored, no record: read in the data's order, and said so
    plain.parent.mkdir()
    save_for_inference(randomize(build_fcn_pose(input_size=64, num_maps=5), seed=1), plain)
    status, out, err = cli_here("evaluate", plain, "--data", mine, "--threads", "1", "--worst", "0")
    assert status == 0 and "note: p.keras names no keypoints" in out and "read as the data's j0, j1, j2, tip" in out
    status, _, err = cli_here("compress", "--rate", "0.7", "--model", lone / "m.keras", "--data", mine, "--out-dir",
                              tmp_path / "c", "--quantize", "float16", "--threads", "1")
    assert status == 2 and "compress it with frames of its own keypoints" in err and not (tmp_path / "c").exists()


def test_the_schema_survives_a_save_in_via_and_projects_of_the_same_keypoints_merge(tmp_path, cli_here):
    from fcnpose_tf.data.via import SCHEMA_KEY, read_via

    data = _own_schema_folder(tmp_path / "d", TREE, n=4)
    project = json.loads((data / "labels.json").read_text())
    via_keys = ("_via_settings", "_via_img_metadata", "_via_attributes", "_via_data_format_version",
                "_via_image_id_list")  # what VIA 2's Project > Save writes (via.js, project_save_confirmed)
    saved = tmp_path / "saved"
    saved.mkdir()
    (saved / "images").symlink_to(data / "images")
    (saved / "labels.json").write_text(json.dumps({k: project[k] for k in via_keys}))
    assert SCHEMA_KEY not in json.loads((saved / "labels.json").read_text())
    assert read_via(saved / "labels.json").schema == TREE  # name, order and skeleton, from the description
    described = project["_via_attributes"]["region"]["keypoint"]["description"]
    noted = {k: project[k] for k in via_keys}
    noted["_via_attributes"]["region"]["keypoint"]["description"] = described + " (checked by Ann)"  # words added
    (saved / "noted.json").write_text(json.dumps(noted))
    assert read_via(saved / "noted.json").schema == TREE
    status, out, err = cli_here("data", "merge", data / "labels.json", saved / "labels.json", "--out",
                                tmp_path / "m" / "m.json")
    assert status == 0, out + err
    reordered = tmp_path / "reordered"  # another project listing the same keypoints in another order
    reordered.mkdir()
    (reordered / "images").symlink_to(data / "images")
    _reordered(data, TREE, (3, 2, 1, 0), name="other.json")
    (data / "other.json").rename(reordered / "labels.json")
    status, out, err = cli_here("data", "merge", data / "labels.json", reordered / "labels.json", "--out",
                                tmp_path / "m2" / "m.json")
    assert status == 0, out + err  # identical annotations, read by name
    assert read_via(tmp_path / "m2" / "m.json").schema == TREE
    status, _, err = cli_here("data", "merge", data / "labels.json", _own_schema_folder(tmp_path / "mine", MINE) /
                              "labels.json", "--out", tmp_path / "m3" / "m.json")
    assert status == 2 and "only projects of the same keypoints can be merged" in err and "lacks" in err


@pytest.mark.slow
def test_a_copied_file_is_scored_on_the_validation_frames_of_its_own_split_seed(tmp_path, cli_here):
    """A model trained on `--split-seed 3` splits, exported, copied away from its record, evaluated on a copy of the
    data without its splits file: its validation frames are seed 3's (the file's record), not seed 0's. With the
    splits file, commands that give no --split-seed take the stored seed instead of refusing it."""
    import shutil

    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.data.splits import make_splits

    data = make_via_folder(tmp_path / "d", n=10, size=(64, 64))
    model = tmp_path / "m.keras"
    status, out, err = cli_here("train", "--data", data, "--split-seed", "3", "--out", model, *TRAIN)
    assert status == 0, out + err
    status, out, err = cli_here("export", model, "--quantize", "float16", "--threads", "1", "--quiet")
    assert status == 0, out + err  # its data and the stored seed-3 splits, with no --split-seed
    status, out, err = cli_here("evaluate", model, "--data", data, "--threads", "1", "--quiet", "--worst", "0")
    assert status == 0, out + err
    copy = tmp_path / "copy"
    shutil.copytree(data, copy, ignore=shutil.ignore_patterns("*.splits.json"))
    (tmp_path / "pi").mkdir()
    alone = tmp_path / "pi" / "m_fp16.tflite"
    shutil.copy(tmp_path / "m_fp16.tflite", alone)
    status, out, err = cli_here("evaluate", alone, "--data", copy, "--threads", "1", "--quiet", "--worst", "0",
                                "--json", tmp_path / "e.json")
    assert status == 0, out + err
    frames = [s.filename for s in load_dataset(copy, write_splits=False, split_seed=None).samples]
    seed3, seed0 = (sorted(frames[i] for i in make_splits(10, 5, 0.2, seed).holdout[1]) for seed in (3, 0))
    assert seed3 != seed0
    report = json.loads((tmp_path / "e.json").read_text())
    assert sorted(row["frame"] for row in report["per_frame"]) == seed3
    assert report["keypoints"] == list(UR5.keypoints)  # what per_frame's errors_px are, in order


def test_a_merge_names_every_point_one_way_and_keeps_the_schema_through_a_save_in_via(tmp_path, cli_here):
    """`data merge --keypoint-attr joint` of the user's project (points under `joint`) and predict's (under
    `keypoint`): every point of the merged project under `joint` (a reader of `joint` took the others in schema
    order, mislabelling frames missing a keypoint), and the schema, skeleton too, in the attribute's description."""
    from fcnpose_tf.data.via import SCHEMA_KEY, read_via, write_via_project

    data = _own_schema_folder(tmp_path / "d", TREE, n=4)
    frames = read_via(data / "labels.json").frames
    write_via_project(data / "labels.json", frames[:2], TREE, attribute="joint", force=True)
    predicted = tmp_path / "pre"
    predicted.mkdir()
    (predicted / "images").symlink_to(data / "images")
    later = [type(f)(f.filename, f.width, f.height, f.keypoints.copy()) for f in frames[2:]]
    later[0].keypoints[2] = np.nan  # a keypoint not found: its frame's points must not shift by one
    write_via_project(predicted / "pre.json", later, TREE)
    merged = tmp_path / "m" / "m.json"
    status, out, err = cli_here("data", "merge", data / "labels.json", predicted / "pre.json", "--keypoint-attr",
                                "joint", "--out", merged)
    assert status == 0, out + err
    project = json.loads(merged.read_text())
    names = {name for meta in project["_via_img_metadata"].values() for r in meta["regions"]
             for name in r["region_attributes"]}
    assert names == {"joint"} and set(project["_via_attributes"]["region"]) == {"joint"}
    saved = tmp_path / "m" / "saved.json"  # VIA's own save: its keys only
    saved.write_text(json.dumps({k: v for k, v in project.items() if k != SCHEMA_KEY}))
    read = read_via(saved, attribute="joint", min_visible=1)
    assert read.schema == TREE
    by_name = {f.filename: f.keypoints for f in read.frames}
    np.testing.assert_array_equal(by_name[later[0].filename], later[0].keypoints)
