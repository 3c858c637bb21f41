"""Failures a user can cause end in one `error:` line, exit 2, and leave nothing half-written."""

import pytest

from fcnpose_tf.cli import build_parser, main


@pytest.mark.parametrize("command", [
    ["train", "--data", "d", "--out", "m.keras"],
    ["compress", "--rate", "0.5"],
    ["sweep"],
    ["evaluate", "--data", "d"],
    ["run", "m.tflite", "--source", "0"],
    ["bench", "m.tflite"],
])
@pytest.mark.parametrize("threads", ["0", "-1", "two"])
def test_every_threads_option_refuses_counts_below_one_while_parsing(command, threads, capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([*command, "--threads", threads])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: argument --threads:") and threads in err and "Traceback" not in err


def test_threads_parse_to_whole_counts():
    args = build_parser().parse_args(["train", "--data", "d", "--out", "m.keras", "--threads", "3"])
    assert args.threads == 3
    assert build_parser().parse_args(["bench", "m.tflite", "--threads", "1,2,2"]).threads == (1, 2)


@pytest.mark.parametrize("side_file", ["ow_train.json", "ow_loss.csv", "ow_loss.png"])
def test_train_refuses_an_existing_side_file_before_any_work(tmp_path, capsys, side_file):
    (tmp_path / side_file).write_text("mine")
    status = main(["train", "--data", str(tmp_path / "no_data"), "--out", str(tmp_path / "ow.keras")])
    assert status == 2
    assert f"{tmp_path / side_file}: already exists; pass --force" in capsys.readouterr().err
    assert (tmp_path / side_file).read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == [side_file]


@pytest.mark.parametrize("side_file", ["m_p50_train.json", "m_p50_loss.csv", "m_p50_loss.png"])
def test_compress_refuses_an_existing_side_file_before_any_work(tmp_path, capsys, side_file):
    (tmp_path / "m.keras").write_bytes(b"a model would be read only after the outputs are checked")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / side_file).write_text("mine")
    status = main(["compress", "--model", str(tmp_path / "m.keras"), "--rate", "0.5", "--data",
                   str(tmp_path / "no_data"), "--out-dir", str(out_dir)])
    assert status == 2
    assert f"{out_dir / side_file}: already exists; pass --force" in capsys.readouterr().err
    assert [p.name for p in out_dir.iterdir()] == [side_file]


def test_compress_without_retraining_writes_no_training_side_files():
    from fcnpose_tf.compress import CompressOptions, output_paths

    names = [p.name for p in output_paths("m.keras", "out", CompressOptions(rate=0.5, retrain_epochs=0))]
    assert names == ["m_p50.keras", "m_p50_fp16.tflite", "m_p50_report.json"]
