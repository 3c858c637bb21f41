import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import atomic_path, write_json, write_text


def test_existing_file_needs_force(tmp_path):
    target = tmp_path / "out.txt"
    write_text(target, "first")
    with pytest.raises(UserError, match="already exists; pass --force"):
        write_text(target, "second")
    assert target.read_text() == "first"
    write_text(target, "second", force=True)
    assert target.read_text() == "second"


def test_failed_write_leaves_nothing(tmp_path):
    target = tmp_path / "sub" / "model.keras"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert tmp.suffix == ".keras" and tmp.parent == target.parent
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert list(target.parent.iterdir()) == []


def test_json_rejects_nan_and_converts_numpy(tmp_path):
    import numpy as np

    write_json(tmp_path / "a.json", {"latency_ms": np.float32(1.5), "v": np.arange(2)})
    assert (tmp_path / "a.json").read_text().count("1.5") == 1
    with pytest.raises(ValueError):
        write_json(tmp_path / "b.json", {"x": float("nan")})
    assert not (tmp_path / "b.json").exists()


def test_unwritable_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(UserError, match="cannot create output folder"):
        write_text(blocker / "out.txt", "y")


def test_a_folder_a_failed_block_created_is_removed_only_when_left_empty(tmp_path):
    from fcnpose_tf.fileio import removed_if_left_empty

    made = tmp_path / "made"
    with pytest.raises(KeyboardInterrupt):
        with removed_if_left_empty(made):
            made.mkdir()
            raise KeyboardInterrupt
    assert not made.exists()
    with pytest.raises(RuntimeError):  # something was written: kept
        with removed_if_left_empty(made):
            made.mkdir()
            (made / "checkpoint").write_text("x")
            raise RuntimeError("late failure")
    assert (made / "checkpoint").is_file()
    mine = tmp_path / "mine"
    mine.mkdir()
    with pytest.raises(RuntimeError):  # existed before: never removed, even empty
        with removed_if_left_empty(mine):
            raise RuntimeError("x")
    assert mine.is_dir()
