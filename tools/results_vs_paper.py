#!/usr/bin/env python
"""The tables of docs/results.md: a finished sweep's figures beside the paper's, as Markdown.

Reads OUT/results.json (written by `fcnpose-tf sweep`, timings re-measured by `--retime` if it was
run) and prints four tables: the paper's "Pruning Results" (with PCK@0.2/0.05, PCK before
retraining and the retraining epochs), the per-fold unpruned models ("5-Folds Desktop"),
"Requirements" and "Pruning and Quantization". The paper's figures are transcribed from
../shared/paper/fcn-pose.tex (its Tables of the Desktop and the Raspberry Pi 3 setups).

    python tools/results_vs_paper.py results/ > tables.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# rate percent -> the paper's figures (None where the paper has no entry)
PAPER_DESKTOP = {  # PCK@0.5 mean, std; inference ms mean, std; FPS; speed-up
    0: (0.997, 0.001, 85, 1, 11.7, 1.00), 10: (0.998, 0.004, 89, 2, 11.1, 0.95),
    20: (0.995, 0.027, 70, 1, 14.1, 1.21), 30: (0.991, 0.036, 72, 1, 13.7, 1.17),
    40: (0.991, 0.004, 62, 0, 16.1, 1.37), 50: (0.985, 0.007, 35, 1, 27.8, 2.38),
    60: (0.980, 0.012, 34, 0, 29.3, 2.50), 70: (0.980, 0.009, 23, 1, 41.9, 3.58),
    80: (0.912, 0.051, 22, 1, 44.9, 3.84), 90: (0.284, 0.092, 16, 2, 61.9, 5.28),
}
PAPER_REQUIREMENTS = {  # params, "Flops", .h5 size MB
    0: (131705, 262674, 1.702), 10: (110237, 109909, 1.343), 20: (88375, 88084, 1.092),
    30: (68014, 67762, 0.858), 40: (51264, 51049, 0.668), 50: (35185, 35011, 0.482),
    60: (24209, 24067, 0.358), 70: (14668, 14563, 0.248), 80: (7206, 7138, 0.162), 90: (2480, 2449, 0.108),
}
PAPER_PI3 = {  # PCK@0.5 mean, std; FPS; .tflite size MB
    10: (0.998, 0.004, 2.86, 0.437), 20: (0.978, 0.027, 3.10, 0.351), 30: (0.975, 0.036, 3.81, 0.272),
    40: (0.990, 0.004, 4.30, 0.206), 50: (0.982, 0.007, 6.68, 0.143), 60: (0.974, 0.012, 7.76, 0.101),
    70: (0.969, 0.009, 10.04, 0.063), 80: (0.911, 0.051, 15.87, 0.034), 90: (0.087, 0.092, 27.78, 0.016),
}


def _pm(values, digits: int) -> str:
    """mean ± std over folds (population std, as the sweep's tables)."""
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if v.size == 0:
        return "-"
    return f"{v.mean():.{digits}f} ± {v.std():.{digits}f}"


def _stat(cell: dict | None, digits: int, signed: bool = False) -> str:
    if not cell:
        return "-"
    fmt = f"{{:+.{digits}f}}" if signed else f"{{:.{digits}f}}"
    return f"{fmt.format(cell['mean'])} ± {cell['std']:.{digits}f}"


def _label(pct: int) -> str:
    return "full" if pct == 0 else f"{pct}%"


def _table(headers: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
                     + ["| " + " | ".join(row) + " |" for row in rows])


def tables(results: dict) -> str:
    jobs: dict[tuple[int, int], dict] = {}
    for job in results["jobs"]:
        pct = 0 if job["kind"] == "base" else round(float(job["rate"]) * 100)
        key = (pct, int(job["fold"]))
        if job["kind"] == "base":
            jobs[(-1, key[1])] = job
        else:
            jobs[key] = job
    pruning = {round(float(r["rate"]) * 100): r for r in results["tables"]["pruning"]["rows"]}
    quant = {round(float(r["rate"]) * 100): r for r in results["tables"]["quantization"]["rows"]}
    reqs = {round(float(r["rate"]) * 100): r for r in results["tables"]["requirements"]["rows"]}
    folds = sorted({k[1] for k in jobs})

    def per_fold(pct: int, section: str, field: str) -> list:
        # the full row of the Keras tables is the base models; of the TFLite table the rate-0 export
        out = []
        for f in folds:
            job = jobs.get((-1, f)) if (pct == 0 and section == "keras") else jobs.get((pct, f))
            out.append(((job or {}).get(section) or {}).get("timing", {}).get(field))
        return out

    full_inv = np.mean([x for x in per_fold(0, "keras", "fps_inference_only") if x is not None])
    cfg = results["config"]
    budgets = {round(float(r) * 100): int(e) for r, e in cfg.get("retrain_epochs_by_rate", [])}

    rows = []
    for pct in sorted(pruning):
        r = pruning[pct]
        p = PAPER_DESKTOP.get(pct)
        inv = per_fold(pct, "keras", "fps_inference_only")
        ran = [(jobs.get((pct, f)) or {}).get("retraining", {}) for f in folds] if pct else []
        epochs = ("-" if not pct else
                  f"{', '.join(str(x.get('epochs_run', '?')) for x in ran)} "
                  f"({budgets.get(pct, cfg['retrain_epochs'])})")
        rows.append([_label(pct), f"{p[0]:.3f} ± {p[1]:.3f}" if p else "-", _stat(r["pck@0.5_bbox"], 3),
                     _stat(r["pck@0.2_bbox"], 3), _stat(r["pck@0.05_bbox"], 3),
                     _stat(r.get("pck@0.5_bbox_before_retraining"), 3) if pct else "-",
                     f"{p[2]} ± {p[3]}" if p else "-", _stat(r["inference_ms"], 1), f"{p[4]}" if p else "-",
                     _pm(inv, 1), _stat(r["fps"], 1), f"{p[5]:.2f}" if p else "-",
                     f"{np.mean([x for x in inv if x is not None]) / full_inv:.2f}", epochs])
    out = ["### Pruning results (Keras)", "", _table(
        ["rate", "PCK@0.5 paper", "PCK@0.5 ours", "PCK@0.2 ours", "PCK@0.05 ours", "ours before retraining",
         "inference ms paper", "inference ms ours", "FPS paper (1 / inference)", "FPS ours (1 / inference)",
         "FPS ours (end to end)", "speed-up paper", "speed-up ours", "retraining epochs run per fold (budget)"],
        rows)]

    rows = []
    for r in results["tables"]["folds"]["rows"]:
        if r["fold"] in ("mean", "std"):
            continue
        base = jobs.get((-1, int(r["fold"]))) or {}
        rows.append([r["fold"], str(r["val_frames"]), f"{r['pck@0.5_bbox']:.3f}", f"{r['pck@0.2_bbox']:.3f}",
                     f"{r['pck@0.05_bbox']:.3f}", f"{r['epe_px']:.1f}", f"{r['inference_ms']:.1f}",
                     f"{r['fps_inference_only']:.1f}", f"{r['fps']:.1f}", str(r["epochs_run"]),
                     str((base.get("training") or {}).get("best_epoch", "-")), f"{r['train_minutes']:.1f}"])
    out += ["", "### Per fold, the unpruned model", "", _table(
        ["fold", "val frames", "PCK@0.5", "PCK@0.2", "PCK@0.05", "EPE px", "inference ms", "FPS (1 / inference)",
         "FPS (end to end)", "epochs", "best epoch", "train min"], rows)]

    rows = []
    for pct in sorted(reqs):
        r, p = reqs[pct], PAPER_REQUIREMENTS.get(pct)
        rows.append([_label(pct), f"{p[0]:,}" if p else "-", f"{int(r['params']):,}", f"{p[1]:,}" if p else "-",
                     f"{r['macs_millions']:,.0f}", f"{p[2]:.3f}" if p else "-", f"{r['h5_size_mb']:.3f}",
                     f"{r['keras_size_mb']:.3f}", _pm(per_fold(pct, "keras", "fps_inference_only"), 1)])
    out += ["", "### Requirements", "", _table(
        ["rate", "params paper", "params ours", 'paper "Flops"', "MMACs ours (FLOPs = 2 × MACs)",
         "size MB paper (.h5)", "size MB ours (.h5)", "size MB ours (.keras)", "FPS ours (1 / inference)"], rows)]

    rows = []
    for pct in sorted(quant):
        r, p = quant[pct], PAPER_PI3.get(pct)
        rows.append([_label(pct), f"{p[0]:.3f} ± {p[1]:.3f}" if p else "-", _stat(r["pck@0.5_bbox"], 3),
                     _stat(r["pck@0.5_bbox_delta_vs_keras"], 3, signed=True), f"{p[2]:.2f}" if p else "-",
                     _stat(r["fps"], 1), _pm(per_fold(pct, "tflite", "fps_inference_only"), 1),
                     _stat(r["inference_ms"], 2), f"{p[3]:.3f}" if p else "-", f"{r['tflite_size_mb']:.3f}"])
    out += ["", "### Pruning and quantization (float16 TFLite)", "", _table(
        ["rate", "PCK@0.5 paper (Pi 3)", "PCK@0.5 ours", "ΔPCK@0.5 vs Keras ours", "FPS paper (Pi 3)",
         "FPS ours (this VM, 1 thread, end to end)", "FPS ours (1 / invoke)", "inference ms ours",
         "size MB paper", "size MB ours (.tflite)"], rows)]
    return "\n".join(out) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="the sweep's results folder (holding results.json)")
    args = parser.parse_args()
    path = args.out / "results.json"
    if not path.is_file():
        print(f"error: {path}: not found; run `fcnpose-tf sweep --out {args.out}` first", file=sys.stderr)
        return 2
    sys.stdout.write(tables(json.loads(path.read_text())))
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
