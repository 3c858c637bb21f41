#!/usr/bin/env bash
# Retrain the bundled baseline (saved_models/fcnpose_ur5.keras), its held-out figures and its 70% export.
# Data: the default synthetic workcell (scene seed 0). Takes about 45 minutes on 2 CPU cores
# (training about 35 min: 40 epochs of 960 frames; compress about 8 min). Run from the repository
# root in an environment with '.[train]', then `python tools/write_model_card.py`.
#   tools/train_baseline.sh [WORKDIR]        (WORKDIR holds the generated data; default: data/)
set -euo pipefail
work=${1:-data}
fcnpose-tf synth --out "$work/ur5_train" --n 1200 --seed 0 --force
fcnpose-tf synth --out "$work/ur5_heldout" --n 100 --seed 1 --force
fcnpose-tf train --data "$work/ur5_train" --out saved_models/fcnpose_ur5.keras \
  --init none --input-size 224 --crop none --augment paper --epochs 40 --patience 12 --lr-patience 4 --positive-weight 20 --augment-copies 0 \
  --max-minutes 600 --quiet --force
fcnpose-tf evaluate saved_models/fcnpose_ur5.keras --data "$work/ur5_heldout" --threads 1 \
  --json saved_models/fcnpose_ur5_heldout.json --force
# the headline command on its defaults: the bundled baseline just written, retrained on the first 400
# of the same frames (cached), measured on the held-out frames (seed 1)
fcnpose-tf compress --rate 0.7 --out-dir saved_models --force
