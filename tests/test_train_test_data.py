"""train --test-data (a fixed test set measured at the start and the end of every training) and a training
stopped before its first epoch ends (nothing to resume, nothing left behind)."""

import json

import numpy as np
import pytest

from fcnpose_tf.errors import UserError
from tests.test_train_evaluate import make_via_folder


@pytest.mark.slow
@pytest.mark.parametrize("trained_start", [True, False])
def test_stopped_before_the_first_epoch_leaves_no_checkpoint_and_does_not_suggest_resume(
        tmp_path, monkeypatch, trained_start):
    from fcnpose_tf import train
    from fcnpose_tf.data.dataset import fold_data, load_dataset
    from fcnpose_tf.model import build_fcn_pose

    ds = load_dataset(make_via_folder(tmp_path / "d", n=6))
    tr, va = fold_data(ds, None, 32, 0)
    out = tmp_path / "m.keras"
    config = train.FitConfig(epochs=2, patience=5, batch_size=4)

    def stop_in_first_epoch(self, epoch, logs=None):  # Ctrl-C or SIGTERM (the handler raises the same) mid-epoch
        raise KeyboardInterrupt

    monkeypatch.setattr(train._CheckpointAndStop, "on_epoch_end", stop_in_first_epoch)
    with pytest.raises(UserError) as info:
        train.fit(build_fcn_pose(input_size=32), tr.sequence(4), va.arrays(), out, config, verbose=0,
                  start_is_candidate=trained_start)
    assert "before the first epoch ended" in str(info.value) and "--resume" not in str(info.value)
    assert not (tmp_path / "m.ckpt").exists() and not out.exists()
    with pytest.raises(UserError, match="no checkpoint to resume from"):
        train.check_checkpoint(out, resume=True, force=False)
    train.check_checkpoint(out, resume=False, force=False)  # a plain rerun is not refused
