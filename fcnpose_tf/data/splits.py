"""Hold-out (80/20) and K-fold (K=5) splits, deterministic for a seed and stored beside the dataset.

One random permutation of the frames (by seed) gives both: K-fold cuts it into
K nearly equal validation folds, and the hold-out validation set is its first
round(n * val_fraction) frames, so with val_fraction = 1/K the hold-out split is
fold 0 (the paper: 508 frames -> 406 train / 102 val). The splits are stored as
`<VIA file stem>.splits.json` next to the VIA file, by frame file name, the
first time a dataset is loaded, and reused afterwards so training, pruning and
evaluation all see the same folds.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError
from fcnpose_tf.settings import FOLDS, SPLIT_SEED

SPLITS_VERSION = 1


@dataclass(frozen=True)
class Splits:
    """Sorted index arrays into a dataset's frame list: a hold-out split and K folds."""

    seed: int
    k: int
    val_fraction: float
    holdout: tuple[np.ndarray, np.ndarray]
    folds: tuple[tuple[np.ndarray, np.ndarray], ...]
    """K (train, val) pairs; empty when the dataset has fewer than K frames."""

    def get(self, fold: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(train, val) indices of fold `fold` (0-based), or the hold-out split when None."""
        if fold is None:
            return self.holdout
        if not self.folds:
            raise UserError(f"the dataset has too few frames for {self.k} folds")
        if not 0 <= fold < self.k:
            raise UserError(f"fold must be between 0 and {self.k - 1}, got {fold}")
        return self.folds[fold]

    def with_training(self, indices: np.ndarray) -> Splits:
        """These splits with `indices` (frames after the split ones) in the training side of the hold-out split and
        of every fold, and in no validation side.

        Args:
            indices: the added frames' indices, none of them already split.
        Returns:
            The new splits (sorted index arrays, as every split's).
        """
        indices = np.asarray(indices, dtype=np.int64)

        def grown(train: np.ndarray, val: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return np.sort(np.concatenate([train, indices])), val

        return replace(self, holdout=grown(*self.holdout), folds=tuple(grown(*fold) for fold in self.folds))

    def before(self, count: int) -> Splits:
        """These splits with only the frames before index `count` (the split frames, without those `with_training`
        added after them).

        Args:
            count: how many frames the splits were made for.
        Returns:
            The splits of those frames.
        """
        def kept(train: np.ndarray, val: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return train[train < count], val[val < count]

        return replace(self, holdout=kept(*self.holdout), folds=tuple(kept(*fold) for fold in self.folds))


def _permutation(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).permutation(n)


def holdout_split(n: int, val_fraction: float = 0.2, seed: int = 0, roles: Sequence[str | None] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(train, val) sorted indices: round(n * val_fraction) frames for validation (at least 1 when n >= 2).

    `roles` (per frame "train", "val" or None) keeps the frames an earlier round gave a role in it (`data merge`
    carries them as the VIA file attribute `via.SPLIT_ATTRIBUTE`), so round 2's validation frames are never round
    1's training frames; the frames without one fill the validation set up to its size, by the seed. Without
    roles the split is the seeded permutation's, as before."""
    if not 0 < val_fraction < 1:
        raise UserError(f"validation fraction must be between 0 and 1, got {val_fraction}")
    n_val = int(round(n * val_fraction))
    if n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    perm = _permutation(n, seed)
    if roles is None or not any(roles):
        return np.sort(perm[n_val:]), np.sort(perm[:n_val])
    fixed_val = [i for i in perm if roles[i] == "val"]
    free = [i for i in perm if roles[i] not in ("train", "val")]
    val = fixed_val + free[:max(n_val - len(fixed_val), 0)]
    if n >= 2 and len(val) == 0 and free:
        val = free[:1]
    val_set = set(val)
    return np.array(sorted(i for i in range(n) if i not in val_set), np.int64), np.array(sorted(val), np.int64)


def check_fold_count(k: int, n: int, source: str = "the dataset") -> int:
    """Return K if n frames can make K folds (K >= 2, one validation frame per fold at least), else UserError.

    The one check of a K that was asked for (`--folds`, a fold index, a sweep): `load_or_create_splits`
    runs it before stored splits are read or new ones written, so `data inspect`, `train`, `evaluate`,
    `compress` and `sweep` refuse the same K with the same message, and no empty K-fold split is stored.
    """
    FOLDS.validate(k)
    if n < k:
        fix = f"pass {FOLDS.flag} {n} or fewer" if n >= 2 else "K-fold cross-validation needs at least 2"
        raise UserError(f"{source}: too few frames for {k} folds ({n} usable frame{'s' if n != 1 else ''}, and each "
                        f"fold needs a validation frame); {fix}")
    return k


def kfold_split(n: int, k: int = 5, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """K (train, val) pairs of sorted indices; the validation folds partition range(n), sizes differ by <= 1."""
    check_fold_count(k, n)
    perm = _permutation(n, seed)
    parts = np.array_split(perm, k)
    all_idx = np.arange(n)
    return [(np.setdiff1d(all_idx, part), np.sort(part)) for part in parts]


def make_splits(n: int, k: int = 5, val_fraction: float = 0.2, seed: int = 0,
                roles: Sequence[str | None] | None = None) -> Splits:
    """Hold-out and K-fold splits of n frames from one seeded permutation (the hold-out keeps `roles`, see
    `holdout_split`).

    With fewer than K frames there are no folds (Splits.get(fold) says so); with
    one frame the hold-out validation set is empty.
    """
    if k < 2:
        raise UserError(f"number of folds must be at least 2, got {k}")
    folds = kfold_split(n, k, seed) if n >= k else []
    return Splits(seed, k, val_fraction, holdout_split(n, val_fraction, seed, roles), tuple(folds))


def splits_path(via_path: str | os.PathLike) -> Path:
    """Where a dataset's splits are stored: `<VIA stem>.splits.json` beside the VIA file."""
    via_path = Path(via_path)
    return via_path.with_name(f"{via_path.stem}.splits.json")


def _fingerprint(names: Sequence[str]) -> str:
    return hashlib.sha256("\n".join(names).encode("utf-8", "surrogatepass")).hexdigest()


def splits_to_dict(splits: Splits, names: Sequence[str]) -> dict:
    """JSON-ready splits; folds list frame file names, so they do not depend on frame order."""
    def named(idx):
        return [names[i] for i in idx]

    return {
        "version": SPLITS_VERSION,
        "seed": splits.seed,
        "num_frames": len(names),
        "frames_sha256": _fingerprint(sorted(names)),
        "holdout": {"val_fraction": splits.val_fraction, "train": named(splits.holdout[0]),
                    "val": named(splits.holdout[1])},
        "kfold": {"k": splits.k, "folds": [{"train": named(t), "val": named(v)} for t, v in splits.folds]},
    }


def stored_seed(via_path: str | os.PathLike) -> int | None:
    """The seed of the splits stored beside a VIA file, None when there are none or they cannot be read (loading
    them says why): what a command given no --split-seed uses (`load_or_create_splits`)."""
    try:
        seed = fileio.parse_json(splits_path(via_path).read_text("utf-8")).get("seed")
    except (OSError, ValueError, AttributeError):
        return None
    return seed if isinstance(seed, int) and not isinstance(seed, bool) else None


def splits_from_dict(data: dict, names: Sequence[str], source: str = "splits") -> Splits:
    """Splits from `splits_to_dict` output, as indices into `names`; UserError if the frame lists differ."""
    try:
        stored_n = int(data["num_frames"])
        index = {name: i for i, name in enumerate(names)}
        if stored_n != len(names) or data["frames_sha256"] != _fingerprint(sorted(names)):
            all_stored = set(data["holdout"]["train"]) | set(data["holdout"]["val"])
            missing = sorted(set(names) - all_stored)[:3]
            extra = sorted(all_stored - set(names))[:3]
            detail = "; ".join(x for x in (f"new: {', '.join(missing)}" if missing else "",
                                           f"gone: {', '.join(extra)}" if extra else "") if x)
            raise UserError(f"{source}: made for a different frame list ({stored_n} frames, now {len(names)}"
                            f"{'; ' + detail if detail else ''}); delete it (or pass --resplit) to split again, "
                            "or load the dataset with the same options as before (e.g. --min-visible)")

        def idx(seq):
            return np.sort(np.array([index[name] for name in seq], dtype=np.int64))

        holdout = (idx(data["holdout"]["train"]), idx(data["holdout"]["val"]))
        folds = tuple((idx(f["train"]), idx(f["val"])) for f in data["kfold"]["folds"])
        return Splits(int(data["seed"]), int(data["kfold"]["k"]), float(data["holdout"]["val_fraction"]),
                      holdout, folds)
    except UserError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise UserError(f"{source}: not a valid splits file ({fileio.entry_problem(exc)}); delete it to split "
                        "again") from None


def stored_roles(via_path: str | os.PathLike) -> dict[str, str]:
    """{frame name: "train" or "val"}: the hold-out split stored beside a VIA file (what `data inspect` and `train`
    wrote for it), for `data merge` to carry; empty when there is none or it cannot be read."""
    try:
        holdout = fileio.parse_json(splits_path(via_path).read_text("utf-8"))["holdout"]
        return {**{str(name): "train" for name in holdout["train"]}, **{str(name): "val" for name in holdout["val"]}}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def load_or_create_splits(via_path: str | os.PathLike, names: Sequence[str], k: int | None = None,
                          val_fraction: float = 0.2, seed: int | None = 0, write: bool = True,
                          resplit: bool = False, roles: Sequence[str | None] | None = None
                          ) -> tuple[Splits, Path, str]:
    """The dataset's stored splits, or new ones saved beside the VIA file (when `write`).

    `k`: the K folds asked for, refused (`check_fold_count`) when there are fewer frames; None:
    no K asked for: the stored splits' K, whatever it is, or for new splits the default K (5), whose folds a dataset
    too small for them simply lacks (the hold-out split still serves). `seed`: None, no seed asked for: the stored
    splits' seed, or 0 for new ones. Returns (splits, path of the splits file,
    status) with status "loaded", "created", or "not saved" (folder not writable or write=False). Stored
    splits made with another seed, K or fraction, or for another frame list, are
    an error unless `resplit` replaces them.
    """
    asked, asked_seed = k, SPLIT_SEED.validate(seed)
    seed = 0 if seed is None else seed
    if k is None:
        k = FOLDS.default
    else:
        check_fold_count(k, len(names), str(via_path))
    path = splits_path(via_path)
    if path.exists() and not resplit:
        try:
            data = fileio.parse_json(path.read_text("utf-8"))
        except (OSError, ValueError) as exc:
            reason = fileio.os_error_reason(exc) if isinstance(exc, OSError) else fileio.entry_problem(exc)
            raise UserError(f"{path}: cannot read splits file ({reason}); delete it to split again") from None
        splits = splits_from_dict(data, names, str(path))
        k = splits.k if asked is None else k  # a command that asks for no K (the hold-out split) takes the stored one
        seed = splits.seed if asked_seed is None else seed  # and no seed: the stored one
        if (splits.seed, splits.k) != (seed, k) or abs(splits.val_fraction - val_fraction) > 1e-9:
            raise UserError(f"{path}: stored splits use seed {splits.seed}, {splits.k} folds, validation fraction "
                            f"{splits.val_fraction:g}, but seed {seed}, {k} folds, {val_fraction:g} were asked for; "
                            f"use the stored settings (--split-seed {splits.seed} --folds {splits.k}, or leave both "
                            "out), or pass --resplit to replace them")
        return splits, path, "loaded"
    splits = make_splits(len(names), k, val_fraction, seed, roles)
    if not write:
        return splits, path, "not saved"
    try:
        fileio.write_json(path, splits_to_dict(splits, names), force=resplit)
    except UserError:
        if os.access(path.parent, os.W_OK):
            raise
        return splits, path, "not saved"
    return splits, path, "created"
