#!/usr/bin/env python3
"""Continue pretraining the bundled generalist on fresh domain-randomised frames (maintainers only).

The generalist's data command: renders `--n` frames of each *pretraining* look family named by
`--looks` (`varied` by default; `varied:3000,classic:1200` mixes families, each with its own frame
count and seed; a held-out family such as `heldout` is refused, so the looks that measure unseen arms
never reach pretraining), merges them into one project (`data merge`), then continues training the
bundled generalist on them with the recipe of saved_models/PROVENANCE.md (online augmentation, conv1-2 fixed, a
half-cosine rate over the time budget; `--architecture`, `--input-size` and `--freeze` change the network, its input and
the layers kept fixed). Takes `--minutes` plus a few minutes of rendering on 2 cores. Run from the repository root
in an environment with '.[train]'; copy the result over saved_models/fcnpose_ur5_generalist.keras
(with its _train.json, _loss.csv and _loss.png) only if it measures better on the proxies of
docs/training.md, and record the run in saved_models/PROVENANCE.md.

    python tools/pretrain_generalist.py --work runs/gen --n 4000 --seed 9000 --minutes 60
    python tools/pretrain_generalist.py --work runs/gen --looks varied:3000,classic:1200 --seed 11000 \
        --init saved_models/candidates/fcnpose_ur5_generalist_mixed.keras --learning-rate 5e-4 --minutes 95
    python tools/pretrain_generalist.py --work runs/gskip --n 1800 --seed 50000 --minutes 72 --learning-rate 1e-3 \
        --architecture fcn-pose-skip --input-size 224x288 --freeze 1 --threads 1
    python tools/pretrain_generalist.py --work runs/gen --dry-run      # print the commands only
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fcnpose_tf.data.synth.looks import PRETRAINING_LOOKS, check_pretraining_looks  # noqa: E402
from fcnpose_tf.errors import UserError  # noqa: E402


SEED_STEP = 2000
"""The i-th family of `--looks` renders with seed `--seed + i * SEED_STEP` (frames of one seed never repeat another's)."""


def looks_plan(spec: str, n: int) -> list[tuple[str, int]]:
    """`varied:3000,classic:1200` -> [("varied", 3000), ("classic", 1200)]; a family without a count gets `n`."""
    plan = []
    for part in spec.split(","):
        family, _, count = part.strip().partition(":")
        try:
            frames = int(count) if count else n
        except ValueError:
            raise UserError(f"--looks {spec!r}: {count!r} is not a frame count (FAMILY[:N],...)") from None
        check_pretraining_looks(family)
        if frames < 1 or family in dict(plan):
            raise UserError(f"--looks {spec!r}: each family once, with at least one frame")
        plan.append((family, frames))
    return plan


def commands(args: argparse.Namespace) -> list[list[str]]:
    exe = [sys.executable, "-m", "fcnpose_tf"]
    plan = looks_plan(args.looks, args.n)
    folders = [args.work / (f"frames_{family}" if len(plan) > 1 else "frames") for family, _ in plan]
    out = args.work / "generalist.keras"
    steps = [exe + ["synth", "--out", str(folder), "--scene", "random", "--looks", family, "--n", str(frames),
                    "--seed", str(args.seed + i * SEED_STEP), "--workers", str(args.threads), "--quiet"]
             for i, ((family, frames), folder) in enumerate(zip(plan, folders))]
    data = folders[0]
    if len(plan) > 1:
        data = args.work / "frames.json"
        steps.append(exe + ["data", "merge", *map(str, folders), "--out", str(data)])
    steps.append(exe + ["train", "--data", str(data), "--out", str(out), "--init", args.init, "--augment", "online",
                        "--freeze", str(args.freeze), "--architecture", args.architecture,
                        "--input-size", args.input_size, "--lr-schedule", "cosine", "--learning-rate", str(args.learning_rate),
                        "--max-minutes", str(args.minutes), "--patience", "60", "--threads", str(args.threads)])
    return steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="folder for the frames and the model (new)")
    parser.add_argument("--looks", default="varied",
                        help=f"look families to pretrain on, FAMILY[:N],... (of {', '.join(PRETRAINING_LOOKS)}; "
                             "default varied)")
    parser.add_argument("--n", type=int, default=4000, help="frames per family without a count (default 4000)")
    parser.add_argument("--seed", type=int, default=9000, help="frame seed; use one no earlier run used")
    parser.add_argument("--minutes", type=float, default=60.0, help="training budget in minutes (default 60)")
    parser.add_argument("--learning-rate", type=float, default=7e-4, help="start of the half cosine (default 7e-4)")
    parser.add_argument("--init", default="generalist", help="model to continue from (default: the bundled one)")
    parser.add_argument("--architecture", default="fcn-pose", choices=("fcn-pose", "fcn-pose-skip"),
                        help="the network pretrained (default fcn-pose, the bundled generalist's; fcn-pose-skip adds "
                             "the skip at zero to an fcn-pose --init)")
    parser.add_argument("--input-size", default="224", help="S or HxW (default 224; the convolutions do not depend on it)")
    parser.add_argument("--freeze", type=int, default=2, help="convolutions kept fixed, conv1..convN (default 2)")
    parser.add_argument("--threads", type=int, default=2, help="cores for rendering and training (default 2)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    try:
        steps = commands(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for command in steps:
        print(shlex.join(command), flush=True)
        if not args.dry_run:
            subprocess.run(command, check=True)
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
