"""tools/selection_experiment.py: the round-1 draw, the stand-in correction, the table, and its command plan.

No training runs here: the experiment's figures are what the tool is for (docs/data.md, "Which strategy?").
"""

import json

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.via import ViaFrame, read_via, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from tools_loader import tool


@pytest.fixture(scope="module")
def sel():
    yield from tool("selection_experiment")


def _project(folder, n, offset=0.0):
    """A VIA project of n 64x48 frames in folder/images, keypoints shifted by `offset` px."""
    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(n):
        cv2.imwrite(str(folder / "images" / f"f{i:03d}.png"), np.full((48, 64, 3), i, np.uint8))
        points = np.array([[4.0 + k * 6 + i % 3, 10.0 + k * 3] for k in range(8)]) + offset
        frames.append(ViaFrame(f"f{i:03d}.png", 64, 48, points))
    write_via_project(folder / "labels.json", frames, UR5)
    return folder / "labels.json"


def test_round1_is_a_seeded_subset_that_finds_its_images(sel, tmp_path):
    labelled = _project(tmp_path / "lab", 10)
    via, images = sel.images_folder(tmp_path / "lab")
    assert via == labelled and images == tmp_path / "lab" / "images"
    for seed in (0, 1):
        sel.draw_round1(via, images, 4, seed, tmp_path / f"r{seed}" / "labels.json")
    names = [[f.filename for f in read_via(tmp_path / f"r{seed}" / "labels.json").frames] for seed in (0, 1)]
    assert all(len(n) == 4 and n == sorted(n) for n in names) and names[0] != names[1]  # in the set's order
    sel.draw_round1(via, images, 4, 0, tmp_path / "again" / "labels.json")
    assert [f.filename for f in read_via(tmp_path / "again" / "labels.json").frames] == names[0]
    # the subset lies elsewhere, yet loads its images from the labelled set's folder
    from fcnpose_tf.data.dataset import load_dataset

    assert len(load_dataset(tmp_path / "r0" / "labels.json")) == 4
    with pytest.raises(UserError, match="fewer than --start-frames 11"):
        sel.draw_round1(via, images, 11, 0, tmp_path / "big" / "labels.json")


def test_correction_pastes_the_ground_truth_over_the_picked_frames_only(sel, tmp_path):
    truth = _project(tmp_path / "pool", 6)
    guessed = _project(tmp_path / "pre", 6, offset=3.0)
    project = json.loads(guessed.read_text())
    keep = project["_via_image_id_list"][1:4:2]  # two picked frames
    project["_via_img_metadata"] = {k: project["_via_img_metadata"][k] for k in keep}
    project["_via_image_id_list"] = keep
    guessed.write_text(json.dumps(project))
    out = tmp_path / "corrected.json"
    assert sel.correct(guessed, truth, out) == 2
    corrected = {f.filename: f.keypoints for f in read_via(out, tmp_path / "pool" / "images").frames}
    truth_points = {f.filename: f.keypoints for f in read_via(truth).frames}
    assert sorted(corrected) == ["f001.png", "f003.png"]
    for name, points in corrected.items():
        np.testing.assert_allclose(points, truth_points[name])
    other = _project(tmp_path / "other", 1)
    with pytest.raises(UserError, match="has no ground truth"):
        sel.correct(guessed, other, tmp_path / "bad.json")


def test_table_has_a_row_per_seed_and_the_mean(sel):
    def figures(pck5, pck05, epe):
        return {"pck@0.5_bbox": pck5, "pck@0.05_bbox": pck05, "epe_px": epe}

    results = {0: {"start": figures(0.9, 0.5, 12.0), "uniform": figures(0.95, 0.6, 10.0), "jump": None},
               1: {"start": figures(0.92, 0.52, 11.0), "uniform": figures(0.97, 0.64, 9.0)}}
    text = sel.table(results, ["uniform", "jump"], 60)
    assert "| uniform | 0 | 0.950 | 0.600 | 10.00 |" in text
    assert "| **uniform** | mean of 2 | 0.960 | 0.620 | 9.50 |" in text
    assert "| **round 1 (60 frames, before selection)** | mean of 2 | 0.910 | 0.510 | 11.50 |" in text
    assert "jump" not in text  # nothing finished: no row


def test_dry_run_prints_every_command_and_writes_nothing(sel, tmp_path, capsys):
    _project(tmp_path / "lab", 5)
    _project(tmp_path / "pool", 5)
    work = tmp_path / "work"
    assert sel.main(["--work", str(work), "--labelled", str(tmp_path / "lab"), "--pool", str(tmp_path / "pool"),
                     "--test", str(tmp_path / "lab"), "--seeds", "3", "--strategies", "uniform,jump",
                     "--train-args", "--input-size 224", "--dry-run"]) == 0
    commands = [line for line in capsys.readouterr().out.splitlines() if line.startswith("$ ")]
    assert len(commands) == 1 + 2 * 3  # round 1, then predict / merge / train per strategy
    assert commands[0].endswith("--seed 3 --input-size 224") and " train --data " in commands[0]
    assert "--select 60 --by jump" in commands[4] and "--init" in commands[-1]
    assert not work.exists()


def test_bad_arguments_exit_2(sel, tmp_path, capsys):
    common = ["--work", str(tmp_path / "w"), "--labelled", str(tmp_path), "--pool", str(tmp_path), "--test", "t"]
    assert sel.main(common + ["--strategies", "uniform,best"]) == 2
    assert "unknown best" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        sel.main(common + ["--seeds", "a"])
    assert stop.value.code == 2
    assert sel.main(common) == 2  # no VIA project in the folder
    assert "no VIA project file" in capsys.readouterr().err


def test_a_seed_another_run_holds_is_skipped(sel, tmp_path, capsys):
    import fcntl

    _project(tmp_path / "lab", 5)
    _project(tmp_path / "pool", 5)
    folder = tmp_path / "work" / "seed4"
    folder.mkdir(parents=True)
    with (folder / ".lock").open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert sel.main(["--work", str(tmp_path / "work"), "--labelled", str(tmp_path / "lab"), "--pool",
                         str(tmp_path / "pool"), "--test", str(tmp_path / "lab"), "--seeds", "4"]) == 0
    assert "seed 4: another run of this tool is working on" in capsys.readouterr().out
    assert not (folder / "round1").exists()
