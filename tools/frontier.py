#!/usr/bin/env python
"""Accuracy against speed over compressed files: the frontier (docs/results.md, "The frontier").

Every .tflite given (any rate, widths, input size, format: compress's or sweep's files) is measured on the same
held-out frames with the package's runtime, in one run:
  - accuracy: PCK@0.5, PCK@0.05 (normalised by max(bbox w, h)) and EPE, every frame scored once, the default
    decoding (weighted centroid);
  - speed: end to end (preprocess + invoke + post-processing), the files and the unpruned Keras model (A, the
    paper's desktop path) taking turns frame by frame (`bench_speedup.interleaved_times`), medians, one thread by
    default; each file's FPS ratio to A.
A file is on the frontier when no other file is both faster (end-to-end median) and at least as accurate (PCK@0.05).
The table marks the frontier and the shipped file (default: the bundled 70 % int8), says which files meet the target
(default: >= 18x A at PCK@0.05 >= 0.84) and, with --plot, draws PCK@0.05 against end-to-end ms.

    python tools/frontier.py runs/c192/*.tflite runs/c160/*.tflite --threads 1 --plot docs/img/frontier.png
    python tools/frontier.py results/fold0/*/*.tflite --data DIR --markdown --json frontier.json

Accuracy comes from one set of frames (default: the 100 held-out synthetic frames the bundled files are measured
on), not from folds: give sweep files of one fold, or average folds yourself.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import sys
from pathlib import Path
from typing import Any, Sequence

TARGET_RATIO = 18.0
"""End-to-end FPS over the unpruned Keras model set as the shipped file's target (docs/results.md, "The frontier")."""
TARGET_PCK = 0.84
"""Held-out PCK@0.05 that ratio must keep."""


def _bench_speedup() -> Any:
    """tools/bench_speedup.py as a module (its interleaved timing), from beside this file."""
    path = Path(__file__).resolve().with_name("bench_speedup.py")
    spec = importlib.util.spec_from_file_location("bench_speedup", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For (ms, accuracy) points: True where no other point is faster and at least as accurate, or as fast and more
    accurate (lower ms is better, higher accuracy is better)."""
    front = []
    for i, (ms, acc) in enumerate(points):
        dominated = any((m < ms and a >= acc) or (m <= ms and a > acc)
                        for j, (m, a) in enumerate(points) if j != i)
        front.append(not dominated)
    return front


def file_labels(files: Sequence[str]) -> list[str]:
    """A name per file for the table and plot: the file name, or folder/name where two files share a name
    (compress writes the same names into every --out-dir)."""
    names = [Path(f).name for f in files]
    return [f"{Path(f).parent.name}/{n}" if names.count(n) > 1 else n for f, n in zip(files, names)]


def file_format(model: Any) -> str:
    """int8 (integer input and output), float16 (float16 weights) or float32, from the file's tensors."""
    import numpy as np

    if model.io.input.dtype != np.float32:
        return "int8"
    return "float16" if "float16" in model.stats().weight_dtypes else "float32"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("tflite", type=Path, nargs="*", help="compressed .tflite files")
    parser.add_argument("--shipped", type=Path, help="the file marked as shipped, added when not listed (default: "
                        "the bundled 70 %% int8 file)")
    parser.add_argument("--keras", type=Path, help="the unpruned Keras model, A (default: the bundled baseline)")
    parser.add_argument("--data", type=Path, help="the frames to measure on (default: held-out synthetic)")
    parser.add_argument("--frames", type=int, default=200, help="timed frames per model (default: 200)")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--target-ratio", type=float, default=TARGET_RATIO)
    parser.add_argument("--target-pck", type=float, default=TARGET_PCK, help="PCK@0.05 the target ratio must keep")
    parser.add_argument("--plot", type=Path, help="write PCK@0.05 against end-to-end ms as a PNG")
    parser.add_argument("--json", type=Path, help="write every figure as JSON")
    parser.add_argument("--force", action="store_true", help="overwrite --json and --plot if they exist")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    return parser


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Accuracy of every file, then the interleaved timing of A and every file; the JSON-ready result."""
    from fcnpose_tf.bundled import baseline_model, models_dir
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.data.synthcache import heldout_data
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.training.evaluate import KerasKeypointModel, evaluate_predictor
    from fcnpose_tf.training.tfsetup import set_tensorflow_threads

    set_tensorflow_threads(args.threads)
    shipped = (args.shipped or models_dir() / "fcnpose_ur5_p70_int8.tflite").resolve()
    paths = [p.resolve() for p in args.tflite]
    paths = list(dict.fromkeys(paths + ([shipped] if shipped not in paths else [])))
    keras_path = args.keras or baseline_model()
    dataset = load_dataset(args.data or heldout_data())
    indices = list(range(len(dataset)))
    keras_model = KerasKeypointModel(keras_path, keras_path, num_threads=args.threads)
    models = [KeypointModel(p, num_threads=args.threads) for p in paths]
    rows = []
    for path, model in zip([keras_path, *paths], [keras_model, *models]):
        metrics = evaluate_predictor(model, dataset, indices, dataset.schema, min_timed_frames=1, warmup=1).metrics
        print(f"  {path.name}: PCK@0.05 {metrics.pck[0.05]:.3f}", file=sys.stderr, flush=True)
        metrics = metrics.to_json()
        rows.append({"file": str(path), "metrics": {k: metrics[k] for k in ("pck@0.5_bbox", "pck@0.05_bbox", "epe_px")}})
    bench = _bench_speedup()
    frames = [dataset.load_image(i) for i in indices[:50]]
    times = bench.interleaved_times([keras_model, *models], frames, args.frames, args.warmup)
    keras_stats = bench.latency_stats(times[0])
    rows[0].update(format="Keras float32", input_size=keras_model.view.size_record, timing=keras_stats)
    for row, model, ts in zip(rows[1:], models, times[1:]):
        stats = bench.latency_stats(ts)
        row.update(format=file_format(model), input_size=model.view.size_record, macs=int(model.stats().macs),
                   size_bytes=model.stats().size_bytes, timing=stats,
                   ratio=keras_stats["total_ms_median"] / stats["total_ms_median"])
    points = [(r["timing"]["total_ms_median"], r["metrics"]["pck@0.05_bbox"]) for r in rows[1:]]
    for row, on_front in zip(rows[1:], pareto_front(points)):
        row["front"] = on_front
        row["shipped"] = row["file"] == str(shipped)
        row["meets_target"] = bool(row["ratio"] >= args.target_ratio
                                   and row["metrics"]["pck@0.05_bbox"] >= args.target_pck)
    return {"threads": args.threads, "frames_timed": args.frames, "data": str(dataset.via_path),
            "frames_scored": len(indices), "keras": rows[0], "files": rows[1:],
            "target": {"ratio": args.target_ratio, "pck@0.05": args.target_pck}}


def table(result: dict[str, Any], markdown: bool) -> str:
    from fcnpose_tf.tables import format_table

    a = result["keras"]
    rows = [[f"A {Path(a['file']).name}", a["format"], a["input_size"], None, a["metrics"]["pck@0.5_bbox"],
             a["metrics"]["pck@0.05_bbox"], a["metrics"]["epe_px"], a["timing"]["inference_ms_median"],
             a["timing"]["total_ms_median"], 1.0, ""]]
    labels = dict(zip((r["file"] for r in result["files"]), file_labels([r["file"] for r in result["files"]])))
    for r in sorted(result["files"], key=lambda r: r["timing"]["total_ms_median"]):
        marks = ", ".join(m for m, on in (("front", r["front"]), ("shipped", r["shipped"]),
                                          ("target", r["meets_target"])) if on)
        rows.append([labels[r["file"]], r["format"], r["input_size"], r["macs"] / 1e6, r["metrics"]["pck@0.5_bbox"],
                     r["metrics"]["pck@0.05_bbox"], r["metrics"]["epe_px"], r["timing"]["inference_ms_median"],
                     r["timing"]["total_ms_median"], r["ratio"], marks])
    return format_table(["file", "format", "input", "MMACs", "PCK@0.5", "PCK@0.05", "EPE px", "invoke ms",
                         "e2e ms", "x A", "marks"], rows, markdown=markdown,
                        digits=[None, None, None, 1, 3, 3, 2, 2, 2, 1, None])


def plot(result: dict[str, Any], path: Path) -> None:
    """PCK@0.05 against end-to-end ms: every file (marker by format), the frontier as a line, the shipped file
    ringed, the target's corner shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = result["files"]
    fig, ax = plt.subplots(figsize=(7.5, 5))
    markers = {"int8": "o", "float16": "s", "float32": "^"}
    for fmt, marker in markers.items():
        chosen = [r for r in files if r["format"] == fmt]
        if chosen:
            ax.scatter([r["timing"]["total_ms_median"] for r in chosen], [r["metrics"]["pck@0.05_bbox"] for r in chosen],
                       marker=marker, s=45, label=fmt, zorder=3)
    # One label per model: its files in several formats (NAME_int8, NAME_fp16) share it, at the fastest one.
    named = set()
    for r, label in sorted(zip(files, file_labels([r["file"] for r in files])),
                           key=lambda pair: pair[0]["timing"]["total_ms_median"]):
        name = re.sub(r"_(int8|fp16|fp16native)$", "", label.removesuffix(".tflite")).replace("fcnpose_ur5_", "")
        if name not in named:
            named.add(name)
            ax.annotate(name, (r["timing"]["total_ms_median"], r["metrics"]["pck@0.05_bbox"]),
                        textcoords="offset points", xytext=(5, -10), fontsize=7)
    front = sorted((r for r in files if r["front"]), key=lambda r: r["timing"]["total_ms_median"])
    ax.plot([r["timing"]["total_ms_median"] for r in front], [r["metrics"]["pck@0.05_bbox"] for r in front],
            "k--", lw=1, label="frontier", zorder=2)
    for r in files:
        if r["shipped"]:
            ax.scatter([r["timing"]["total_ms_median"]], [r["metrics"]["pck@0.05_bbox"]], s=220, facecolors="none",
                       edgecolors="red", lw=1.5, label="shipped", zorder=4)
    keras_ms = result["keras"]["timing"]["total_ms_median"]
    target = result["target"]
    limit = keras_ms / target["ratio"]
    ax.set_xlim(left=0)
    bottom, top = ax.get_ylim()
    bottom, top = min(bottom, target["pck@0.05"] - 0.01), max(top, target["pck@0.05"] + 0.01)
    ax.set_ylim(bottom, top)
    ax.fill_between([0, limit], target["pck@0.05"], top, color="green", alpha=0.08, lw=0,
                    label=f">= {target['ratio']:g}x at PCK@0.05 >= {target['pck@0.05']:g}")
    ax.set_xlabel(f"end-to-end ms per frame (median, {result['threads']} thread(s)); "
                  f"{target['ratio']:g}x the unpruned Keras model = {limit:.2f} ms")
    ax.set_ylabel(f"PCK@0.05 on {result['frames_scored']} held-out frames")
    ax.set_title("FCN-Pose files: accuracy against speed")
    ax.legend(loc="center right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    from fcnpose_tf.fileio import check_writable, write_json

    for path in args.tflite + ([args.shipped] if args.shipped else []):
        if not path.is_file() or path.suffix != ".tflite":
            print(f"error: {path}: not a .tflite file", file=sys.stderr)
            return 2
    for out in (args.plot, args.json):
        if out is not None and not out.parent.is_dir():
            print(f"error: {out.parent}: no such folder", file=sys.stderr)
            return 2
        if out is not None:
            check_writable(out, args.force)  # before the measurement, not after
    result = measure(args)
    print(f"{result['frames_scored']} frames of {result['data']} scored; {result['frames_timed']} frames timed per "
          f"model, interleaved, {result['threads']} thread(s); medians")
    print(table(result, args.markdown))
    target = result["target"]
    met = [label for r, label in zip(result["files"], file_labels([r["file"] for r in result["files"]]))
           if r["meets_target"]]
    print(f"target (>= {target['ratio']:g}x A at PCK@0.05 >= {target['pck@0.05']:g}): "
          + (", ".join(met) if met else "no file meets it"))
    if args.json:
        write_json(args.json, result, force=args.force)
    if args.plot:
        plot(result, args.plot)
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
