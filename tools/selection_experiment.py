#!/usr/bin/env python3
"""Which frames are worth correcting? `predict --select --by` strategies measured on a proxy (maintainers only).

The protocol of docs/data.md ("Which strategy?"), one round of the correction loop per strategy and seed:

    seed s: 60 frames drawn from the labelled set ──► train (the round-1 model, v1)
            for each strategy: predict v1 --source POOL --select 60 --by STRATEGY
                               ──► "correct" the picked frames (their ground truth pasted in, standing in for
                                   a person in VIA) ──► data merge round 1 + corrected
                               ──► train --init v1 on the merged frames ──► the fixed test set

Two checks of the loop's measuring sticks run with it: after each round 2, how many of round 1's validation
frames validate round 2 too (all of them, and none of round 1's training frames, since `data merge` keeps the
inputs' roles), and once a seed, round 1's frames copied under another path and offered as round 2's
`--test-data` (refused: the overlap is checked by content).

Every step is a `fcnpose-tf` command (printed before it runs; `--dry-run` prints them all) except drawing the
round-1 frames and the correction, which stand in for the person. A step whose output exists is skipped and an
interrupted training is resumed from its checkpoint, so the experiment continues where it stopped (across
sessions: each training is 5-15 minutes); seeds can run in parallel processes (`--seeds 1` beside `--seeds 2`),
and a seed another process is working on is skipped. The table (strategy x
seed: test PCK@0.5, PCK@0.05, EPE after one round, and the mean over seeds) is printed and written to
WORK/results.md and WORK/results.json from whatever has finished.

The pool is a synthetic folder with ground truth, best a motion sequence (frames in their video order, so `jump`
has tracks to follow), of the same camera as the labelled and test sets:

    fcnpose-tf synth --out runs/sel/pool --motion 5 --n 300 --looks heldout --labels kinematic --scene-seed 1 --seed 300
    python tools/selection_experiment.py --work runs/sel --labelled runs/ho_fixed_train/ur5_synth.json \\
        --pool runs/sel/pool --test runs/ho_fixed_test/ur5_synth.json --seeds 0,1,2
    python tools/selection_experiment.py --work runs/sel ... --train-args "--input-size 224"   # cheaper rounds
"""

from __future__ import annotations

import argparse
import fcntl
import json
import random
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fcnpose_tf.data.dataset import resolve_data  # noqa: E402
from fcnpose_tf.data.via import read_via  # noqa: E402
from fcnpose_tf.errors import UserError  # noqa: E402
from fcnpose_tf.fileio import write_json, write_text  # noqa: E402

STRATEGIES = ("uniform", "uncertain", "jump", "disagree")
"""`predict --by`'s choices, the baseline first."""
FIGURES = (("pck@0.5_bbox", "PCK@0.5", 3), ("pck@0.05_bbox", "PCK@0.05", 3), ("epe_px", "EPE px", 2))
"""The test figures of the table: key in NAME_train.json's "test", column title, decimals."""


def images_folder(data: Path) -> tuple[Path, Path]:
    """(VIA file, the folder its images are in) of a DATA folder or file, as `train --data` finds them
    (`data.via.read_via`); UserError when its frames lie in several folders."""
    via_path, images = resolve_data(data, None)
    folders = {Path(frame.image_path).parent for frame in read_via(via_path, images).frames}
    if len(folders) != 1:
        raise UserError(f"{via_path}: its images lie in {len(folders)} folders; the experiment needs one")
    return via_path, folders.pop()


def draw_round1(labelled: Path, images_dir: Path, n: int, seed: int, out: Path) -> None:
    """A VIA project of `n` frames of `labelled` drawn with `seed`, its images found on their own folder."""
    project = json.loads(labelled.read_text())
    ids = list(project["_via_image_id_list"])
    if n > len(ids):
        raise UserError(f"{labelled}: {len(ids)} frames, fewer than --start-frames {n}")
    picked = sorted(random.Random(seed).sample(ids, n), key=ids.index)
    project["_via_img_metadata"] = {key: project["_via_img_metadata"][key] for key in picked}
    project["_via_image_id_list"] = picked
    project["_via_settings"]["core"]["default_filepath"] = str(images_dir.resolve()) + "/"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(project))


def correct(pre: Path, truth: Path, out: Path) -> int:
    """`pre` with each frame's regions replaced by the ground truth of the frame of the same name in `truth` (what
    a person correcting the pre-annotation in VIA would produce); the number of frames corrected."""
    by_name = {entry["filename"]: entry for entry in json.loads(truth.read_text())["_via_img_metadata"].values()}
    project = json.loads(pre.read_text())
    for entry in project["_via_img_metadata"].values():
        if entry["filename"] not in by_name:
            raise UserError(f"{pre}: {entry['filename']} has no ground truth in {truth}")
        entry["regions"] = by_name[entry["filename"]]["regions"]
    write_text(out, json.dumps(project), force=True)
    return len(project["_via_img_metadata"])


def kept_roles(round1: Path, merged: Path) -> dict:
    """How round 1's stored hold-out split fared in the merged project's (after round 2's training stored it): its
    validation frames still validation frames, none of its training frames validating round 2."""
    from fcnpose_tf.data.dataset import load_dataset

    first, second = load_dataset(round1, write_splits=False), load_dataset(merged, write_splits=False)
    train1, val1 = ({first.names[i] for i in part} for part in first.split())
    val2 = {second.names[i] for i in second.split()[1]}
    return {"round1_validation": len(val1), "kept_as_validation": len(val1 & val2),
            "round1_training_in_validation": len(train1 & val2), "round2_validation": len(val2)}


def copy_refused(round1: Path, merged: Path, folder: Path, fcnpose: list[str]) -> str:
    """Round 1's frames copied under another path and offered as round 2's `--test-data`: the error line `train`
    answers with (exit status 2 expected, nothing trained)."""
    import shutil

    via, images = images_folder(round1)
    copy = folder / "copy_of_round1"
    if copy.exists():
        shutil.rmtree(copy)
    shutil.copytree(images, copy / "images")
    project = json.loads(via.read_text())
    project["_via_settings"]["core"]["default_filepath"] = ""
    write_text(copy / "labels.json", json.dumps(project))
    command = fcnpose + ["train", "--data", str(merged), "--test-data", str(copy), "--out", str(folder / "refused.keras")]
    print("$ " + shlex.join(command), flush=True)
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 2 or (folder / "refused.keras").exists():
        raise UserError(f"a copy of round 1's frames as --test-data was not refused (exit {done.returncode})")
    return done.stderr.strip().splitlines()[-1]


def run(command: list[str], log: Path, dry_run: bool) -> None:
    print("$ " + shlex.join(command), flush=True)
    if dry_run:
        return
    with log.open("w") as stream:
        code = subprocess.call(command, stdout=stream, stderr=subprocess.STDOUT)
    if code != 0:
        raise UserError(f"exit {code}: {shlex.join(command)} (log: {log})")


def resumed(model: Path) -> list[str]:
    """["--resume"] when an interrupted training of `model` left its checkpoint (train's NAME.ckpt/), else []."""
    checkpoint = model.with_suffix(".ckpt")
    return ["--resume"] if (checkpoint / "state.json").is_file() and (checkpoint / "last.keras").is_file() else []


def test_figures(model: Path) -> dict | None:
    """The test-set figures `train --test-data` recorded beside `model` (the end of the run), or None."""
    record = model.with_name(model.stem + "_train.json")
    if not record.is_file():
        return None
    test = json.loads(record.read_text()).get("test") or {}
    return test.get("end")


def experiment(args: argparse.Namespace) -> dict:
    fcnpose = [sys.executable, "-m", "fcnpose_tf"]
    labelled, labelled_images = images_folder(args.labelled)
    pool_via, pool_images = images_folder(args.pool)
    train_args = shlex.split(args.train_args)
    results: dict = {}
    for seed in args.seeds:
        folder = args.work / f"seed{seed}"
        if not args.dry_run:
            folder.mkdir(parents=True, exist_ok=True)
            lock = (folder / ".lock").open("w")
            try:  # held until the process ends: two runs on one work folder share out the seeds
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                print(f"seed {seed}: another run of this tool is working on {folder}; skipped", flush=True)
                continue
        round1 = folder / "round1" / "labels.json"
        if not round1.exists() and not args.dry_run:
            draw_round1(labelled, labelled_images, args.start_frames, seed, round1)
        v1 = folder / "v1.keras"
        if not v1.exists():
            run(fcnpose + ["train", "--data", str(round1), "--test-data", str(args.test), "--out", str(v1),
                           "--seed", str(seed), *train_args, *resumed(v1)], folder / "v1.log", args.dry_run)
        results[seed] = {"start": test_figures(v1)}
        for strategy in args.strategies:
            step = folder / strategy
            pre, corrected, merged = step / "pre.json", step / "corrected.json", step / "merged" / "labels.json"
            model = folder / f"{strategy}.keras"
            if not model.exists():
                if not pre.exists():
                    if not args.dry_run:
                        step.mkdir(parents=True, exist_ok=True)
                    run(fcnpose + ["predict", str(v1), "--source", str(pool_images), "--via", str(pre),
                                   "--select", str(args.select), "--by", strategy],
                        step / "predict.log", args.dry_run)
                if not args.dry_run:
                    correct(pre, pool_via, corrected)
                if not merged.exists():
                    run(fcnpose + ["data", "merge", str(round1), str(corrected), "--out", str(merged)],
                        step / "merge.log", args.dry_run)
                run(fcnpose + ["train", "--data", str(merged), "--init", str(v1), "--test-data", str(args.test),
                               "--out", str(model), "--seed", str(seed), *train_args, *resumed(model)],
                    step / "train.log", args.dry_run)
            results[seed][strategy] = test_figures(model)
            if not args.dry_run:
                results[seed][f"{strategy} roles"] = roles = kept_roles(round1, merged)
                print(f"seed {seed}, {strategy}: {roles['kept_as_validation']} of round 1's {roles['round1_validation']} "
                      f"validation frames validate round 2 too ({roles['round2_validation']} in all); "
                      f"{roles['round1_training_in_validation']} of its training frames do", flush=True)
        if not args.dry_run and args.strategies:
            merged = folder / args.strategies[0] / "merged" / "labels.json"
            results[seed]["copy as --test-data"] = line = copy_refused(round1, merged, folder, fcnpose)
            print(f"seed {seed}: round 1's frames copied elsewhere as --test-data: {line}", flush=True)
    return results


def table(results: dict, strategies: list[str], start_frames: int) -> str:
    """Markdown: one row per strategy and seed (and the round-1 start), then the mean over the seeds done."""
    header = "| strategy | seed | " + " | ".join(title for _, title, _ in FIGURES) + " |"
    lines = [header, "|---|---|" + "---:|" * len(FIGURES)]

    def cells(figures: dict) -> str:
        return " | ".join(f"{figures[key]:.{digits}f}" for key, _, digits in FIGURES)

    for name in ["start", *strategies]:
        done = [(seed, row[name]) for seed, row in results.items() if row.get(name)]
        label = f"round 1 ({start_frames} frames, before selection)" if name == "start" else name
        for seed, figures in done:
            lines.append(f"| {label} | {seed} | {cells(figures)} |")
        if len(done) > 1:
            mean = {key: statistics.fmean(figures[key] for _, figures in done) for key, _, _ in FIGURES}
            lines.append(f"| **{label}** | mean of {len(done)} | {cells(mean)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--work", type=Path, required=True, help="folder for every round's files (reused: resumes)")
    parser.add_argument("--labelled", type=Path, required=True, help="labelled frames round 1 is drawn from (DATA)")
    parser.add_argument("--pool", type=Path, required=True,
                        help="unlabelled frames to select from: a synthetic folder whose VIA file is the ground truth")
    parser.add_argument("--test", type=Path, required=True, help="the fixed test set (train --test-data)")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    parser.add_argument("--strategies", default=",".join(STRATEGIES), help="comma-separated --by choices")
    parser.add_argument("--start-frames", type=int, default=60, help="labelled frames of round 1 (default 60)")
    parser.add_argument("--select", type=int, default=60, help="frames each strategy picks (default 60)")
    parser.add_argument("--train-args", default="", help="more options for both trainings, e.g. \"--input-size 224\"")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    try:
        args.seeds = [int(seed) for seed in args.seeds.split(",")]
    except ValueError:
        parser.error(f"--seeds: whole numbers separated by commas, got {args.seeds!r}")
    try:
        args.strategies = [name.strip() for name in args.strategies.split(",")]
        unknown = sorted(set(args.strategies) - set(STRATEGIES))
        if unknown:
            raise UserError(f"--strategies: unknown {', '.join(unknown)} (of {', '.join(STRATEGIES)})")
        results = experiment(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.dry_run:
        return 0
    text = table(results, args.strategies, args.start_frames)
    print(text)
    write_text(args.work / "results.md", text, force=True)
    write_json(args.work / "results.json", {str(seed): row for seed, row in results.items()}, force=True)
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
