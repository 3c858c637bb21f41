"""VIA 2.x import/export: round trips, real-world exports, drops, and clear errors for broken files."""

import json
import logging

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.via import ViaFrame, read_via, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema


def write_dataset(folder, n=10, size=(64, 48), seed=0, images_subdir="images", via_name="ann.json",
                  missing=None, schema=UR5, margin=6):
    """A small dataset: n random-noise PNG frames and a VIA project with random in-frame keypoints.

    `missing` maps frame index -> keypoint indices to leave unannotated. Returns (via path, frames).
    """
    folder.mkdir(parents=True, exist_ok=True)
    image_dir = folder / images_subdir if images_subdir else folder
    image_dir.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    w, h = size
    frames = []
    for i in range(n):
        cv2.imwrite(str(image_dir / f"frame_{i:03d}.png"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        kps = np.c_[rng.uniform(margin, w - 1 - margin, schema.num_keypoints),
                    rng.uniform(margin, h - 1 - margin, schema.num_keypoints)]
        for k in (missing or {}).get(i, ()):
            kps[k] = np.nan
        frames.append(ViaFrame(f"frame_{i:03d}.png", w, h, kps))
    via = folder / via_name
    write_via_project(via, frames, schema)
    return via, frames


def region(x, y, label=None, attribute="keypoint"):
    return {"shape_attributes": {"name": "point", "cx": x, "cy": y},
            "region_attributes": {} if label is None else {attribute: label}}


def export(tmp_path, entries, name="export.json"):
    """A VIA region-data export: {filename+size: {filename, size, regions, file_attributes}}."""
    data = {}
    for filename, regions in entries:
        size = (tmp_path / filename).stat().st_size if (tmp_path / filename).exists() else -1
        data[f"{filename}{size}"] = {"filename": filename, "size": size, "regions": regions, "file_attributes": {}}
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


def image(tmp_path, name, w=64, h=48):
    cv2.imwrite(str(tmp_path / name), np.zeros((h, w, 3), np.uint8))


def test_round_trip_keeps_keypoints_sizes_and_schema(tmp_path):
    via, frames = write_dataset(tmp_path, n=4, missing={1: [3]})
    data = json.loads(via.read_text())
    assert set(data) >= {"_via_settings", "_via_img_metadata", "_via_attributes", "fcnpose_schema"}
    assert list(data["_via_attributes"]["region"]["keypoint"]["options"]) == list(UR5.keypoints)
    size0 = (tmp_path / "images" / "frame_000.png").stat().st_size
    assert f"frame_000.png{size0}" in data["_via_img_metadata"]  # VIA's key: filename + byte size
    assert len(data["_via_img_metadata"][f"frame_001.png{(tmp_path / 'images/frame_001.png').stat().st_size}"]
               ["regions"]) == 7  # the missing keypoint writes no region

    ann = read_via(via)
    assert ann.schema == UR5 and ann.num_dropped == 0
    assert [f.filename for f in ann.frames] == [f.filename for f in frames]
    for got, want in zip(ann.frames, frames):
        assert (got.width, got.height) == (64, 48)
        assert got.image_path == tmp_path / "images" / want.filename
        np.testing.assert_allclose(got.keypoints, want.keypoints, atol=5e-4)  # stored to 1/1000 px
    assert np.isnan(ann.frames[1].keypoints[3]).all()


def test_round_trip_with_another_robot_schema(tmp_path):
    schema = KeypointSchema("tri", ("a", "b", "c"), ((0, 1), (0, 2)))
    via, frames = write_dataset(tmp_path, n=2, schema=schema)
    ann = read_via(via)
    assert ann.schema == schema
    np.testing.assert_allclose(ann.frames[0].keypoints, frames[0].keypoints, atol=5e-4)


def test_writer_refuses_to_overwrite(tmp_path):
    via, frames = write_dataset(tmp_path, n=1)
    with pytest.raises(UserError, match="already exists"):
        write_via_project(via, frames)
    write_via_project(via, frames, force=True)


def test_real_world_region_export_any_frame_size(tmp_path):
    """Integer clicks, labels in any order, extra rectangles, several frame sizes, JPEG and PNG, unlabelled frames."""
    cv2.imwrite(str(tmp_path / "cam_0001.jpg"), np.zeros((720, 1280, 3), np.uint8))
    image(tmp_path, "phone.png", 300, 500)
    names = list(UR5.keypoints)
    frame_a = [region(100 + 10 * k, 600 - 50 * k, names[k]) for k in (7, 2, 0, 1, 3, 4, 5, 6)]
    frame_a.insert(3, {"shape_attributes": {"name": "rect", "x": 5, "y": 5, "width": 40, "height": 40},
                       "region_attributes": {"keypoint": ""}})
    frame_b = [region(10 + 30 * k, 20 + 55 * k) for k in range(6)]  # unlabelled: taken in schema order
    path = export(tmp_path, [("cam_0001.jpg", frame_a), ("phone.png", frame_b)])

    ann = read_via(path)
    a, b = ann.frames
    assert (a.width, a.height, b.width, b.height) == (1280, 720, 300, 500)
    np.testing.assert_array_equal(a.keypoints, [[100 + 10 * k, 600 - 50 * k] for k in range(8)])
    np.testing.assert_array_equal(b.keypoints[:6], [[10 + 30 * k, 20 + 55 * k] for k in range(6)])
    assert np.isnan(b.keypoints[6:]).all()
    assert ann.ignored_regions == 1


def test_via1_style_regions_checkbox_labels_and_custom_attribute(tmp_path):
    image(tmp_path, "a.png")
    regions = {str(i): {"shape_attributes": {"name": "point", "cx": 5 + i, "cy": 7},
                        "region_attributes": {"joint": {name: True, "other": False}}}
               for i, name in enumerate(UR5.keypoints)}
    path = export(tmp_path, [("a.png", regions)])
    ann = read_via(path, attribute="joint")
    np.testing.assert_array_equal(ann.frames[0].keypoints[:, 0], np.arange(5, 13))


def test_schema_from_dropdown_options(tmp_path):
    image(tmp_path, "a.png")
    meta = {"a.png-1": {"filename": "a.png", "size": -1, "file_attributes": {},
                        "regions": [region(1, 2, "hip"), region(3, 4, "knee"), region(5, 6, "ankle")]}}
    project = {"_via_img_metadata": meta, "_via_attributes": {"region": {"keypoint": {
        "type": "dropdown", "options": {"hip": "", "knee": "", "ankle": ""}}}}}
    (tmp_path / "p.json").write_text(json.dumps(project))
    ann = read_via(tmp_path / "p.json")
    assert ann.schema.keypoints == ("hip", "knee", "ankle") and ann.schema.edges == ((0, 1), (1, 2))
    assert ann.min_visible == 2



def test_a_schema_the_file_declares_badly_is_refused_on_one_line_naming_the_file(tmp_path):
    via, _ = write_dataset(tmp_path, n=2, schema=KeypointSchema.chain("arm", ("a", "b", "c")))
    project = json.loads(via.read_text())
    project["_via_attributes"]["region"]["keypoint"]["options"] = {"a": "", "b\nerror: forged": "", "c": ""}
    del project["fcnpose_schema"]  # the dropdown decides (it fell back to UR5's names before)
    (tmp_path / "dropdown.json").write_text(json.dumps(project))
    with pytest.raises(UserError, match=r"^\S*dropdown\.json: schema 'keypoint': name 'b\\nerror: forged' is empty or "
                                        "holds a control character") as refused:
        read_via(tmp_path / "dropdown.json")
    assert "\n" not in str(refused.value)
    project = json.loads(via.read_text())
    project["fcnpose_schema"]["keypoints"] = ["a", "a", "c"]
    (tmp_path / "stored.json").write_text(json.dumps(project))
    with pytest.raises(UserError, match=r"^\S*stored\.json: invalid keypoint schema .*must be non-empty and unique"):
        read_via(tmp_path / "stored.json")


def test_a_described_schema_the_dropdown_overrules_is_said_not_silently_dropped(tmp_path, caplog):
    tree = KeypointSchema("gripper", ("base", "wrist", "finger L", "finger R"), ((0, 1), (1, 2), (1, 3)))
    via, _ = write_dataset(tmp_path, n=2, schema=tree)
    project = json.loads(via.read_text())
    del project["fcnpose_schema"]  # as VIA's Project > Save leaves it: the description holds the schema
    attribute = project["_via_attributes"]["region"]["keypoint"]
    described = attribute["description"]
    for name, description, why in [
            ("cut.json", described[:-30], "cannot be read (Unterminated string"),  # edited by hand
            ("renamed.json", described.replace('"base"', '"root"'), "names other keypoints (root, wrist")]:
        attribute["description"] = description
        (tmp_path / name).write_text(json.dumps(project))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="fcnpose_tf"):
            schema = read_via(tmp_path / name).schema
        assert schema == KeypointSchema.chain("keypoint", tree.keypoints)  # the dropdown's chain, as before: now said
        said = " ".join(caplog.messages)
        assert f"{name}: the fcnpose-tf schema in the 'keypoint' attribute's description {why}" in said
        assert "joined in a chain (base, wrist, finger L, finger R)" in said
    attribute["description"] = described
    (tmp_path / "saved.json").write_text(json.dumps(project))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="fcnpose_tf"):
        assert read_via(tmp_path / "saved.json").schema == tree
    assert not any("description" in message for message in caplog.messages)

def test_occluded_frames_are_dropped_and_counted_with_a_warning(tmp_path, caplog):
    via, _ = write_dataset(tmp_path, n=5, missing={1: range(5), 3: range(8)})  # 3 visible; none
    with caplog.at_level(logging.WARNING):
        ann = read_via(via)
    assert len(ann.frames) == 3
    assert ann.dropped == {"fewer than 4 visible keypoints": 1, "no keypoints annotated": 1}
    assert "dropped 1 frame(s) with fewer than 4 visible keypoints" in caplog.text
    assert len(read_via(via, min_visible=2).frames) == 4
    assert len(read_via(via, min_visible=8).frames) == 3
    with pytest.raises(UserError, match="min_visible"):
        read_via(via, min_visible=9)


def test_click_on_the_last_pixel_edge_is_clipped_not_refused(tmp_path):
    image(tmp_path, "a.png", 64, 48)
    path = export(tmp_path, [("a.png", [region(64, 48, "base"), region(-1, 0, "shoulder"), region(3, 3, "elbow"),
                                         region(4, 4, "wrist1")])])
    kps = read_via(path).frames[0].keypoints
    np.testing.assert_array_equal(kps[:2], [[63.5, 47.5], [-0.5, 0]])


BROKEN = {
    "truncated JSON": "truncated",
    "missing image": ("gone.png", [region(5, 5, "base")], "gone.png.*image file not found"),
    "unknown label": ("a.png", [region(5, 5, "bsae")], r"'a.png' regions\[0\]: unknown keypoint label 'bsae'"),
    "string coordinate": ("a.png", [region("12", 5, "base")], r"'a.png' regions\[0\]: point cx must be a finite "
                                                              r"number, got '12'"),
    "null coordinate": ("a.png", [region(3, 3, "elbow"), region(5, None, "base")],
                        r"regions\[1\]: point cy must be a finite number, got None"),
    "outside the image": ("a.png", [region(5, 5, "base"), region(80, 5, "tool")],
                          r"regions\[1\]: point \(80, 5\) is outside the 64x48 image"),
    "duplicate keypoint": ("a.png", [region(5, 5, "base"), region(6, 6, "base")],
                           r"regions\[1\]: duplicate keypoint 'base' \(also regions\[0\]\)"),
    "mixed labelled and unlabelled": ("a.png", [region(5, 5, "base"), region(6, 6)],
                                      r"regions\[1\]: point has no 'keypoint' label"),
    "regions not a list": ("a.png", "oops", "'regions' must be a list"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_files_give_one_clear_error_naming_file_and_region(tmp_path, case):
    image(tmp_path, "a.png")
    spec = BROKEN[case]
    if spec == "truncated":
        via, _ = write_dataset(tmp_path, n=2)
        via.write_text(via.read_text()[:300])
        with pytest.raises(UserError, match=r"ann.json: invalid JSON at line \d+ column \d+.*truncated"):
            read_via(via)
        return
    filename, regions, message = spec
    path = export(tmp_path, [(filename, regions)])
    with pytest.raises(UserError, match=message) as info:
        read_via(path)
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)
    # with skip_bad the frame is skipped and counted instead
    ann = read_via(path, skip_bad=True)
    assert ann.frames == [] and ann.dropped == {"bad annotation or image (skipped)": 1}
    assert len(ann.problems) == 1


def test_another_robots_names_typed_as_text_point_to_a_dropdown(tmp_path):
    """A VIA text attribute holding another robot's names declares no schema: UR5's is expected, and the error says
    how to declare one (a typo in UR5's names keeps the plain message)."""
    image(tmp_path, "a.png")
    path = export(tmp_path, [("a.png", [region(5, 5, "Base"), region(9, 9, "Gripper")])])
    with pytest.raises(UserError, match="the file declares no keypoints, so UR5's are expected: for your own robot's, "
                                        "make 'keypoint' a dropdown region attribute"):
        read_via(path)


def test_skip_bad_keeps_good_frames_and_errors_count_the_rest(tmp_path):
    for name in ("a.png", "b.png", "c.png"):
        image(tmp_path, name)
    good = [region(5 + k, 5, name) for k, name in enumerate(UR5.keypoints)]
    path = export(tmp_path, [("a.png", good), ("b.png", [region(5, 5, "nope")]), ("c.png", good),
                             ("missing.png", good)])
    message = r"regions\[0\]: unknown keypoint label 'nope'; .* \(and 1 more problem\(s\)\).*--skip-bad"
    with pytest.raises(UserError, match=message):
        read_via(path)
    ann = read_via(path, skip_bad=True)
    assert [f.filename for f in ann.frames] == ["a.png", "c.png"]
    assert ann.dropped["bad annotation or image (skipped)"] == 2


def test_duplicate_frame_names(tmp_path):
    image(tmp_path, "a.png")
    regions = [region(5 + k, 5, name) for k, name in enumerate(UR5.keypoints)]
    data = {"a.png1": {"filename": "a.png", "size": 1, "regions": regions, "file_attributes": {}},
            "a.png2": {"filename": "a.png", "size": 2, "regions": regions, "file_attributes": {}}}
    (tmp_path / "d.json").write_text(json.dumps(data))
    with pytest.raises(UserError, match=r"frame 'a.png': duplicate frame \(entries 'a.png1' and 'a.png2'\)"):
        read_via(tmp_path / "d.json")


@pytest.mark.parametrize("content, message", [
    ("", "empty file"),
    ("[1, 2]", "expected a JSON object"),
    ('{"a.png1": {"name": 3}}', "entry 'a.png1': not a VIA frame"),
    ('{"project": {}, "file": {}, "metadata": {}, "attribute": {}}', "VIA 3 project"),
    ('{"_via_img_metadata": [1]}', "_via_img_metadata: expected an object"),
    (b"\xff\xfe\x00binary", "not a UTF-8 text file"),
])
def test_not_a_via_file(tmp_path, content, message):
    path = tmp_path / "x.json"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(UserError, match=message):
        read_via(path)


def test_missing_file_and_images_folder(tmp_path):
    with pytest.raises(UserError, match="nope.json: VIA file not found"):
        read_via(tmp_path / "nope.json")
    via, _ = write_dataset(tmp_path, n=1)
    with pytest.raises(UserError, match="imgs: images folder not found"):
        read_via(via, tmp_path / "imgs")


def test_images_dir_argument_and_default_filepath(tmp_path):
    via, _ = write_dataset(tmp_path / "a", n=2, images_subdir="frames")
    with pytest.raises(UserError, match="image file not found"):
        read_via(via)
    assert len(read_via(via, tmp_path / "a" / "frames").frames) == 2
    data = json.loads(via.read_text())
    data["_via_settings"]["core"]["default_filepath"] = "frames/"
    via.write_text(json.dumps(data))
    assert len(read_via(via).frames) == 2


def test_viaframe_shape_is_checked_by_the_writer(tmp_path):
    with pytest.raises(UserError, match="expected 8 x 2 keypoints"):
        write_via_project(tmp_path / "p.json", [ViaFrame("a.png", 10, 10, np.zeros((3, 2)))])


def test_a_project_none_of_whose_images_is_found_points_to_images_not_skip_bad(tmp_path):
    """Every image missing means the images are elsewhere: the error names --images, not --skip-bad (which would
    then leave no frame)."""
    from test_train_evaluate import make_via_folder

    data = make_via_folder(tmp_path / "d", n=3)
    (data / "images").rename(tmp_path / "photos")
    with pytest.raises(UserError, match=r"none of its images is there; pass --images DIR"):
        read_via(data / "labels.json")
    assert len(read_via(data / "labels.json", tmp_path / "photos").frames) == 3
    (tmp_path / "photos" / sorted(p.name for p in (tmp_path / "photos").iterdir())[0]).unlink()
    with pytest.raises(UserError, match=r"fix the file or pass --skip-bad"):  # one missing: the frame is the problem
        read_via(data / "labels.json", tmp_path / "photos")
