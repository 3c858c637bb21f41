import signal

import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import atomic_path, stop_signals_as_interrupt, write_json, write_text


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


def test_files_written_as_one_replace_nothing_unless_every_one_is_written(tmp_path):
    import errno
    import os

    from fcnpose_tf.fileio import WriteError, atomic_paths

    old = {name: f"epoch 1 {name}" for name in ("best.npz", "last.keras", "state.json")}
    for name, text in old.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(WriteError, match=rf"^{tmp_path}: no space left on device$"):
        with atomic_paths([tmp_path / name for name in old], force=True) as temporaries:
            temporaries[0].write_text("epoch 2 best")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # the second file finds the disk full
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == old  # no temporary left, no target touched
    with atomic_paths([tmp_path / name for name in old], force=True) as temporaries:
        for tmp, name in zip(temporaries, old):
            tmp.write_text(f"epoch 2 {name}")
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == {name: f"epoch 2 {name}" for name in old}


def test_a_libraries_multi_line_os_error_is_reduced_to_its_reason():
    from fcnpose_tf.fileio import os_error_reason

    hdf5 = OSError("Can't close file (file write failed: time = Tue Nov 24 12:28:03 2026\n, filename = '/d/x.h5', "
                   "file descriptor = 3, errno = 28, error message = 'No space left on device', buf = 0x55ed)")
    assert os_error_reason(hdf5) == "no space left on device"
    assert os_error_reason(OSError(28, "No space left on device")) == "no space left on device"
    assert os_error_reason(OSError("first line\nsecond")) == "first line"


def test_parts_of_one_output_are_kept_and_named_only_as_the_whole(tmp_path):
    from fcnpose_tf.fileio import command_outputs, make_folder, parts_of, remove_tree

    with command_outputs() as outputs:
        with pytest.raises(RuntimeError):
            with parts_of(tmp_path / "set"):
                write_text(make_folder(tmp_path / "set" / "images") / "frame0.png", "a frame")
                raise RuntimeError("the disk filled before the set's index was written")
        assert outputs.completed == []
        outputs.remove_created_folders()
        assert list(tmp_path.iterdir()) == []
        with parts_of(tmp_path / "set"):
            write_text(make_folder(tmp_path / "set" / "images") / "frame0.png", "a frame")
            write_text(tmp_path / "set" / "index.json", "{}")
        assert outputs.completed == [tmp_path / "set"]
        outputs.remove_created_folders()  # a later failure keeps the whole set, its subfolders too
        assert (tmp_path / "set" / "images" / "frame0.png").is_file()
        remove_tree(tmp_path / "set")  # e.g. a finished run's checkpoint: gone, and no longer named
        assert outputs.completed == [] and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("inherited", [signal.default_int_handler, signal.SIG_IGN],
                         ids=["python-default", "ignored-in-the-background"])
def test_ctrl_c_and_a_kill_stop_the_block_whatever_sigint_was_inherited_as(inherited):
    """A command started with `cmd &` from a script inherits an ignored SIGINT; Ctrl-C must still stop its run."""
    previous = signal.signal(signal.SIGINT, inherited)
    term_before = signal.getsignal(signal.SIGTERM)
    try:
        for sig, message in ((signal.SIGINT, ""), (signal.SIGTERM, "terminated (SIGTERM)")):
            with pytest.raises(KeyboardInterrupt) as exc:
                with stop_signals_as_interrupt():
                    signal.raise_signal(sig)
            assert str(exc.value) == message
        assert signal.getsignal(signal.SIGINT) == inherited  # the inherited action is back after the block
        assert signal.getsignal(signal.SIGTERM) == term_before
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("exc, words", [
    (KeyError("num_frames"), "no 'num_frames' entry"),
    (TypeError("'int' object is not subscriptable"), "an entry holds the wrong kind of value"),
    (ValueError("invalid literal for int() with base 10: 'q'"), "an entry holds the wrong kind of value"),
    (ValueError("not enough values to unpack (expected 2, got 1)"), "an entry holds the wrong kind of value"),
    (ValueError("seed must be a whole number\nmore"), "seed must be a whole number"),
])
def test_entry_problem_says_what_was_wrong_in_words(exc, words):
    from fcnpose_tf.fileio import entry_problem

    assert entry_problem(exc) == words


def test_a_bad_splits_file_and_schema_are_described_in_words(tmp_path):
    from fcnpose_tf.data.splits import splits_from_dict
    from fcnpose_tf.keypoints import KeypointSchema

    with pytest.raises(UserError, match=r"not a valid splits file \(no 'frames_sha256' entry\)"):
        splits_from_dict({"num_frames": 2}, ["a", "b"], "x.splits.json")
    with pytest.raises(UserError, match=r"\(no 'edges' entry\)$"):
        KeypointSchema.from_dict({"name": "a", "keypoints": ["x"]})
