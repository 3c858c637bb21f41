"""`fcnpose-tf data inspect`: the report, the preview PNG, and one-line errors with exit status 2."""

import json

import cv2
import pytest

from fcnpose_tf.cli import main
from test_via import write_dataset


def test_inspect_reports_counts_folds_and_writes_a_preview(cli, tmp_path):
    write_dataset(tmp_path / "demo", n=10, missing={4: [2], 7: range(6)})
    proc = cli("data", "inspect", "demo", "--out", "preview.png", "--input-size", "64", "--samples", "3")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "Frames:  9 usable, 1 dropped" in out
    assert "fewer than 4 visible keypoints" in out and "dropped 1 frame(s)" in proc.stderr
    assert "ur5, 8 keypoints" in out and "9 target maps" in out
    assert "Frame sizes: 64x48 (9)" in out
    lines = out.splitlines()
    per_frame = lines[lines.index("Keypoints per frame") + 3:lines.index("Keypoints per frame") + 5]
    assert [line.split() for line in per_frame] == [["8", "8"], ["7", "1"]]
    hold_out = next(line for line in lines if line.startswith("hold-out")).split()
    # 9 frames: 7 train, 2 val; these frames vary, so train augments online: 7 samples, new transforms every epoch
    assert "augmentation online" in out and hold_out == ["hold-out", "7", "2", "7"]
    assert "Train samples (online augmentation: new transforms every epoch)" in out
    assert sum(1 for line in lines if line.startswith("fold ")) == 5
    assert "created" in out and (tmp_path / "demo" / "ann.splits.json").exists()
    preview = cv2.imread(str(tmp_path / "preview.png"))
    assert preview is not None and preview.shape[1] == 3 * 256 and preview.shape[0] > 3 * 256

    again = cli("data", "inspect", "demo", "--out", "preview.png")
    assert again.returncode == 2 and "preview.png: already exists; pass --force" in again.stderr
    given = cli("data", "inspect", "demo", "--out", "preview.png", "--force", "--input-size", "64",
                "--samples", "1", "--augment-copies", "2")
    assert given.returncode == 0
    hold_out = next(line for line in given.stdout.splitlines() if line.startswith("hold-out")).split()
    assert hold_out == ["hold-out", "7", "2", "21"]  # --augment-copies 2: 7 train + 2 copies each


def test_inspect_without_preview_and_with_options(tmp_path, capsys):
    write_dataset(tmp_path / "d", n=6, missing={0: range(5)}, via_name="labels.json", images_subdir="frames")
    status = main(["data", "inspect", str(tmp_path / "d" / "labels.json"), "--images", str(tmp_path / "d" / "frames"),
                   "--min-visible", "2", "--folds", "3", "--augment-copies", "0"])
    out = capsys.readouterr().out
    assert status == 0
    assert "6 usable, 0 dropped" in out and "at least 2 of 8" in out
    assert sum(1 for line in out.splitlines() if line.startswith("fold ")) == 3
    assert [p.parent.name for p in tmp_path.rglob("*.png")] == ["frames"] * 6  # no preview without --out


def _break(folder, how):
    via = folder / "ann.json"
    if how == "truncated JSON":
        via.write_text(via.read_text()[:200])
        return "invalid JSON at line"
    data = json.loads(via.read_text())
    meta = data["_via_img_metadata"]
    first = next(iter(meta.values()))
    if how == "missing image":
        (folder / "images" / first["filename"]).unlink()
        return "frame 'frame_000.png': image file not found"
    if how == "unknown label":
        first["regions"][1]["region_attributes"]["keypoint"] = "elbow2"
        message = r"frame 'frame_000.png' regions[1]: unknown keypoint label 'elbow2'"
    elif how == "wrong type":
        first["regions"][2]["shape_attributes"]["cx"] = "12px"
        message = r"frame 'frame_000.png' regions[2]: point cx must be a finite number, got '12px'"
    via.write_text(json.dumps(data))
    return message


@pytest.mark.parametrize("how", ["truncated JSON", "missing image", "unknown label", "wrong type"])
def test_broken_dataset_is_one_line_exit_2_and_skip_bad_continues(cli_here, tmp_path, monkeypatch, how):
    """In this process (`cli_here`: the CLI's parser, exit path and messages); the report and preview test above runs
    the command as a new process."""
    write_dataset(tmp_path / "demo", n=6)
    message = _break(tmp_path / "demo", how)
    monkeypatch.chdir(tmp_path)
    status, stdout, stderr = cli_here("data", "inspect", "demo")
    assert status == 2, stdout + stderr
    assert stderr.startswith("error: ") and message in stderr
    assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
    if how != "truncated JSON":
        status, stdout, stderr = cli_here("data", "inspect", "demo", "--skip-bad")
        assert status == 0, stderr
        assert "5 usable, 1 dropped" in stdout and "bad annotation or image (skipped)" in stdout


@pytest.mark.parametrize("args, message", [
    (["data"], "the following arguments are required: ACTION"),
    (["data", "inspect"], "the following arguments are required: DATA"),
    (["data", "inspect", "nowhere"], "nowhere: not found"),
    (["data", "inspect", ".", "--out", "p.gif"], "preview must be a .png"),
    (["data", "inspect", ".", "--samples", "0"], "--samples must be at least 1"),
])
def test_argument_errors(tmp_path, monkeypatch, capsys, args, message):
    write_dataset(tmp_path, n=5)
    monkeypatch.chdir(tmp_path)
    try:
        status = main(args)
    except SystemExit as exc:  # argparse errors exit directly
        status = exc.code
    assert status == 2
    assert message in capsys.readouterr().err


def test_keypoint_attribute_option_reaches_the_reader(tmp_path, capsys):
    via, _ = write_dataset(tmp_path, n=5)
    data = json.loads(via.read_text().replace('"keypoint"', '"joint"'))
    next(iter(data["_via_img_metadata"].values()))["regions"][0]["region_attributes"]["joint"] = "zzz"
    via.write_text(json.dumps(data))
    assert main(["data", "inspect", str(tmp_path), "--keypoint-attr", "joint"]) == 2
    assert "unknown keypoint label 'zzz'" in capsys.readouterr().err
    assert main(["data", "inspect", str(tmp_path), "--keypoint-attr", "joint", "--skip-bad"]) == 0
    assert "4 usable, 1 dropped" in capsys.readouterr().out


def test_frame_names_that_are_not_utf8_load_and_split(cli_here, tmp_path):
    # `predict --via` on a folder holding `fram\xe9_000.png` (Latin-1) writes such a name into its VIA file
    via, _ = write_dataset(tmp_path / "set", n=6)
    odd = "fram\udce9_000.png"  # the name as Python holds the byte \xe9 (surrogateescape)
    (tmp_path / "set" / "images" / "frame_000.png").rename(tmp_path / "set" / "images" / odd)
    project = json.loads(via.read_text())
    metadata = project["_via_img_metadata"]
    key = next(k for k in metadata if metadata[k]["filename"] == "frame_000.png")
    metadata[key]["filename"] = odd
    via.write_text(json.dumps(project))
    status, out, err = cli_here("data", "inspect", via)
    assert status == 0, err
    assert "6 usable, 0 dropped" in out
