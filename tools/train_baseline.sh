#!/usr/bin/env bash
# Retrain the bundled baseline (saved_models/fcnpose_ur5.keras), its held-out figures and its 70% export.
# Data: the default synthetic workcell (scene seed 0). Takes about 1.5 hours on 2 CPU cores
# (the bundled run: 78 min of training, early stop at epoch 42, best 30, with other jobs sharing the cores). Run from the repository root in an environment with '.[train]'.
#   tools/train_baseline.sh [WORKDIR]        (WORKDIR holds the generated data; default: data/)
set -euo pipefail
work=${1:-data}
fcnpose-tf synth --out "$work/ur5_train" --n 1200 --seed 0 --force
fcnpose-tf synth --out "$work/ur5_retrain" --n 400 --seed 0 --force    # the first 400 of the same frames
fcnpose-tf synth --out "$work/ur5_heldout" --n 100 --seed 1 --force
fcnpose-tf train --data "$work/ur5_train" --out saved_models/fcnpose_ur5.keras \
  --epochs 40 --patience 12 --lr-patience 4 --positive-weight 20 --augment-copies 0 --quiet --force
fcnpose-tf evaluate saved_models/fcnpose_ur5.keras --data "$work/ur5_heldout" --threads 1 \
  --json saved_models/fcnpose_ur5_heldout.json --force
fcnpose-tf compress --rate 0.7 --model saved_models/fcnpose_ur5.keras --data "$work/ur5_retrain" \
  --test-data "$work/ur5_heldout" --retrain-epochs 40 --patience 8 --lr-patience 4 --out-dir saved_models --force
