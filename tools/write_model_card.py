#!/usr/bin/env python
"""Write saved_models/README.md (the model card) from the bundled models' own JSON records.

Reads fcnpose_ur5_train.json (written by `train`), fcnpose_ur5_heldout.json (by `evaluate --json`),
fcnpose_ur5_p70_report.json (by `compress`), fcnpose_ur5_p70_int8_export.json (by `export --json`) and
fcnpose_ur5_p70_{fp16,int8}_heldout.json (by `evaluate --json`), so every figure in the card comes
from a file that a command wrote. Run after tools/train_baseline.sh:

    python tools/write_model_card.py [--models saved_models] [--out saved_models/README.md --force]

The card bundled today began as this tool's draft and is kept by hand since (notes on decoding, timing and
reproducibility that no record holds), so the tool never replaces an existing card without --force: compare
its draft (--out another file) with the card instead.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fcnpose_tf.compression.summary import report_table


def _load(path: Path) -> dict:
    if not path.is_file():
        sys.exit(f"error: {path}: not found (run tools/train_baseline.sh first)")
    return json.loads(path.read_text())


def _f(value, digits=3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=Path, default=Path("saved_models"))
    parser.add_argument("--out", type=Path, metavar="MD", help="where the card goes (default: MODELS/README.md)")
    parser.add_argument("--force", action="store_true", help="replace an existing card (it is kept by hand)")
    parser.add_argument("--provenance", type=Path, metavar="MD",
                        help="a Markdown paragraph on how the bundled weights were actually made, if not by "
                             "tools/train_baseline.sh alone (kept in saved_models/PROVENANCE.md)")
    args = parser.parse_args()
    d = args.models
    out = args.out or d / "README.md"
    if out.exists() and not args.force:
        sys.exit(f"error: {out}: already exists (the bundled card is kept by hand); pass --force to replace it, "
                 "or --out another file to compare")
    train = _load(d / "fcnpose_ur5_train.json")
    held = _load(d / "fcnpose_ur5_heldout.json")
    comp = _load(d / "fcnpose_ur5_p70_report.json")
    int8_export = _load(d / "fcnpose_ur5_p70_int8_export.json")["files"][0]
    held_70 = {q: _load(d / f"fcnpose_ur5_p70_{q}_heldout.json") for q in ("fp16", "int8")}
    gate = int8_export["parity"]
    rows_70 = "\n".join(
        f"| `{Path(r['model']).name}` | {r['size_bytes']:,} | {_f(r['metrics']['pck@0.5_bbox'], 4)} | "
        f"{_f(r['metrics']['pck@0.2_bbox'], 4)} | {_f(r['metrics']['pck@0.05_bbox'], 4)} | "
        f"{_f(r['metrics']['epe_px'], 2)} | {_f(r['metrics']['missing_fraction'], 4)} |" for r in held_70.values())
    m, t = held["metrics"], held["timing"]
    cfg = train["config"]
    val = train.get("validation", {}).get("metrics", {})

    per_kp = "\n".join(
        f"| {name} | {_f(v['pck@0.5_bbox'])} | {_f(v['pck@0.2_bbox'])} | {_f(v['pck@0.05_bbox'])} | "
        f"{_f(v['epe_px'], 1)} | {_f(v['missing_fraction'])} |" for name, v in m["per_keypoint"].items())
    provenance_path = args.provenance or (d / "PROVENANCE.md")
    provenance = provenance_path.read_text().strip() if provenance_path.is_file() else ""
    init_line = (f"\n- Initialised from `{train['init']}`, not from random weights (see Provenance)."
                 if train.get("init") else "")
    card = f"""# Bundled models: FCN-Pose for a UR5, trained on synthetic frames

Drafted by `tools/write_model_card.py` from the JSON records beside the models; kept by hand since, each figure
from the record or the command it names.

| file | what |
|---|---|
| `fcnpose_ur5.keras` | the baseline: unpruned FCN-Pose (131,705 parameters), 224 x 224, 9 maps, no optimizer state |
| `fcnpose_ur5_loss.png/.csv`, `fcnpose_ur5_train.json` | its loss curves and training record |
| `fcnpose_ur5_heldout.json` | its figures on held-out synthetic frames |
| `fcnpose_ur5_p70.keras` | pruned to 70 % and retrained by `fcnpose-tf compress --rate 0.7` on its defaults ({comp['recipe']}; {comp['retrained']['params']:,} parameters) |
| `fcnpose_ur5_p70_fp16.tflite` | the same, float16 TFLite (the paper's format), verified against Keras |
| `fcnpose_ur5_p70_fp16native.tflite` (+ `_export.json`) | the float16 file with reduced-precision metadata: computed in float16 on a Pi 5's Cortex-A76 (docs/raspberry-pi.md) |
| `fcnpose_ur5_p70_report.json` | `compress` report: every step measured |
| `fcnpose_ur5_p70_int8.tflite` | the same 70 % model, full-integer int8 (uint8 pixel input, int8 maps), verified on keypoints; the file to run on a Pi 3, 4 and 5 (docs/raspberry-pi.md) |
| `fcnpose_ur5_p70_int8_export.json`, `fcnpose_ur5_p70_{{fp16,int8}}_heldout.json` | how the int8 file was made and verified; both 70 % files on the held-out frames |
| `fcnpose_ur5_generalist.keras` (+ `_train.json`, `_loss.csv/.png`) | the generalist: the baseline fine-tuned on 16,000 domain-randomised frames (13 epochs at 160 x 160, 29 at 224, the last 25 annealed); `train`'s starting point for your frames (PROVENANCE.md) |
| `fcnpose_ur5_generalist_p70.keras` (+ `_train.json`, `_loss.csv/.png`) | the generalist pruned at 0.7 (the widths of `compress --rate 0.7`: no layer under 15 filters) and retrained on domain-randomised frames (37 minutes on 1,920 at 224, two hours on 3,200 more, then 81 minutes on 2,400 at 256 x 256, the side it runs at); `compress`'s pruned start for the generalist itself (`--start auto`, the default) and with `--start generalist-p70`, the model rebuilt at 256 (docs/compression.md, PROVENANCE.md) |

`evaluate`, `predict` and `compress` use `fcnpose_ur5.keras` when no model is given (`train` starts from the
generalist); `run`/`bench` take the .tflite.

## Training

- Data: `fcnpose-tf synth --out DIR --n {train['num_frames']} --seed 0` (640 x 480, the default workcell: scene seed 0, one
  fixed camera, the arm in a new pose in every frame), {train['split']} split:
  {train['train_samples']} training samples ({train['augment_copies']} augmented copies per frame), {train['val_frames']} validation frames.
- Adam (learning rate {cfg['learning_rate']}), batch {cfg['batch_size']}, binary cross-entropy with keypoint-disc pixels
  weighted x{cfg.get('positive_weight', 1)} (`--positive-weight`, see docs/training.md), early stopping patience {cfg['patience']},
  learning rate halved after {cfg.get('lr_patience', 0)} epochs without a better validation loss (0 = never).
- Epochs run: {train['epochs_run']} (best: {train['best_epoch']}, validation loss {train['best_val_loss']:.5f}),
  {'stopped early' if train['stopped_early'] else f"epoch limit {cfg['epochs']}"}; training time {train['train_seconds'] / 60:.0f} min on 2 CPU cores.{init_line}
- Retrain: `tools/train_baseline.sh` (one command; about 45 minutes on 2 cores).

## Held-out figures

{held['frames']} (`fcnpose-tf synth --out DIR --n 100 --seed 1`: the same workcell, poses from a seed never used for training).
PCK normalised by max(w, h) of the ground-truth keypoints' bounding box; EPE in 640 x 480 frame pixels.

| keypoint | PCK@0.5 | PCK@0.2 | PCK@0.05 | EPE px | missing |
|---|---|---|---|---|---|
{per_kp}
| **all** | **{_f(m['pck@0.5_bbox'])}** | **{_f(m['pck@0.2_bbox'])}** | **{_f(m['pck@0.05_bbox'])}** | **{_f(m['epe_px'], 1)}** | {_f(m['missing_fraction'])} |

PCK-AUC 0–20 px: {_f(m['pck_auc_0-20px'])}. Validation split of the training set: PCK@0.5 {_f(val.get('pck@0.5_bbox'))},
PCK@0.05 {_f(val.get('pck@0.05_bbox'))}. Keras inference {t['inference_ms']['mean']:.1f} ± {t['inference_ms']['std']:.1f} ms per frame,
{t['fps']:.1f} FPS end to end ({t['threads']} thread, {t['frames_timed']} frames after warm-up).

## Compression at 70 %

Measured on {comp['evaluation_frames']}; timing with {comp['threads'] or 'all'} thread(s).

{report_table(comp, markdown=True)}

## Full-integer int8 (`fcnpose_ur5_p70_int8.tflite`)

`fcnpose-tf export saved_models/fcnpose_ur5_p70.keras --quantize int8`: int8 weights and activations
calibrated on {int8_export['calibration_frames']} frames of the default training data (seeded choice from its training
split, never a measured frame), upsampling folded ({len(int8_export['graph_rewrites'])} rewrites: faster in int8), built-in int8 ops only.
Verification gate (keypoints in map pixels, on {gate['frames']} real frames of the validation split): {gate['keypoints_within_px']} of
{gate['keypoints_compared']} keypoints within {gate['keypoint_px']:g} px of the Keras model's (at least {gate['min_keypoint_share']:.0%} required), {gate['keypoints_lost_or_gained']} lost
or gained, largest distance {gate['max_keypoint_px']:.2f} px, largest map difference {gate['max_abs_diff']:.3f}.
Both 70 % files, `fcnpose-tf evaluate FILE --data <synth --n 100 --seed 1>` ({held_70['int8']['frames']}):

| file | bytes | PCK@0.5 | PCK@0.2 | PCK@0.05 | EPE px | missing |
|---|---|---|---|---|---|---|
{rows_70}

Speed: docs/runtime.md ("Full-integer int8"), measured with `tools/bench_speedup.py`.
""" + (f"\n## Provenance\n\n{provenance}\n" if provenance else "")
    out.write_text(card)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
