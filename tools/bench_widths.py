#!/usr/bin/env python
"""Invoke time of FCN-Pose's convolutions and of whole FCN-Pose models against their channel widths
(measured: docs/results.md, "Widths the kernels like?").

XNNPACK's int8 and float kernels work on channels in tiles, so a convolution's time need not follow its
multiply-accumulates (MACs) when the widths change. This tool prints the figures to judge that by; it
draws no conclusion itself. Three modes:

--layer NAME[=C_OUT]   single-convolution models, swept over output channels
    python tools/bench_widths.py --layer conv3 --c-out 6:18
    python tools/bench_widths.py --layer conv1=22:38 --layer conv2=8:24 --threads 1,2 --json layers.json

    Each model is one of FCN-Pose's convolutions as it sits in the network (`build_fcn_pose`): a 3x3 'same'
    stride-1 Conv2D with ReLU (conv10: sigmoid) at that layer's resolution for --size, reading C_IN channels
    (default: the previous layer's width in --widths, today's 70 % widths if not given; 3 for conv1). conv7..conv10
    come right after a nearest UpSampling2D (factors 2, 2, 2, 4; FCN-Pose has no transposed convolutions),
    which the model includes, as the exported network runs it: with --fold auto (default) the int8 model is
    folded (`fcnpose_tf.compression.inference_graph.fold_upsampling`: one convolution at the low resolution
    with f*f*C_OUT filters, then DEPTH_TO_SPACE; the "kernel c_out" column) and the float16 model is not,
    as `fcnpose_tf.compression.export` does (settings.TFLITE_FORMATS' fold_upsampling); --fold on / off forces either.
    Pooling is not included. The int8 model has an int8 input and output (as inside the network, no
    QUANTIZE/DEQUANTIZE op at its ends), calibrated on random activations in [0, 1); the float16 model is
    what export's float16 mode writes (float16 weights, float32 input and output). C_OUT is a range A:B
    (inclusive) or A:B:STEP, or a comma list; --c-out is the default for layers given without one (default:
    the layer's width in --widths +- 8).
    Prints one table per format and thread count: c_out, MACs, median and p95 microseconds per invoke and
    microseconds per million MACs.

--widths W [--widths W ...]   whole FCN-Pose models
    python tools/bench_widths.py --widths 30,15,12,12,8,8,12,12,15 --widths 32,16,8,8,8,8,8,16,16

    Each list is conv1..conv9's filters (conv10 keeps 9 maps); models with random weights (seeded) are exported
    with the package's own `fcnpose_tf.compression.export.export_tflite` (int8: calibrated on random frames,
    timing does not depend on the weights; float16; each with the format's default folding unless --fold),
    its verification run with map and keypoint gates off (random weights make maps without keypoints; the
    file must still load and give finite maps). Prints each list's parameters and MACs, then per format and
    thread count the invoke medians and p95 and each list's time as a ratio to the first list's.

--budget-round N[,N...] --widths W   plain arithmetic, no TensorFlow
    python tools/bench_widths.py --budget-round 8 --widths 30,15,12,12,8,8,12,12,15

    The width lists with every width rounded to a multiple of N (never below N): the nearest multiple (a
    width halfway between two multiples gives both lists) and every other floor/ceil combination whose
    parameter count is within --tolerance percent of the original's, with parameters and MACs next to the
    original's, to pick lists of the same parameter budget for --widths.

Timing: every interpreter is created with its thread count (LiteRT through `fcnpose_tf.runtime.interpreter`,
XNNPACK as the interpreter's default delegate), its input set once to random values, warmed up, then
`invoke()` alone is timed, round by round, all models of one thread count in one round, in a freshly
shuffled order every round, so load from other processes hits them alike (thread counts are timed one
after the other, in blocks: a 2-thread interpreter's worker spinning after its invoke would otherwise
share the cores with the next 1-thread one). --clock cpu times the calling thread's CPU time instead of
wall time (one thread only), the figure to quote from a loaded machine.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.metrics import conv_macs
from fcnpose_tf.settings import check_input_size
from fcnpose_tf.tables import format_table

P70_WIDTHS: tuple[int, ...] = (15, 15, 15, 15, 8, 8, 15, 15, 15)
"""conv1..conv9 of the shipped 70 %-pruned model (saved_models/fcnpose_ur5_p70.keras; the test checks it)."""
NUM_MAPS = 9
"""conv10's filters: 8 keypoints + the skeleton map (kept by every width list here)."""
NUM_CONVS = 10
KERNEL = 3
# FCN-Pose's layout (fcnpose_tf.training.model.build_fcn_pose; the test checks these against it), written out here
# so --budget-round needs no TensorFlow: conv1..conv5 each followed by a 2x2 max pool, conv6, then
# UpSampling2D(f) + conv for f in 2, 2, 2, 4 (conv7..conv10).
NUM_POOLS = 5
UPSAMPLE_FACTORS = (2, 2, 2, 4)
FORMATS = ("int8", "float16")
CALIBRATION_FRAMES = 8
INT8_SAMPLE_FRAMES = 16  # export_tflite's minimum for int8 (settings.TFLITE_FORMATS' min_frames)


# ---------------------------------------------------------------------------- FCN-Pose arithmetic

@dataclass(frozen=True)
class ConvSite:
    """Where one of FCN-Pose's convolutions runs for a given input size."""

    name: str
    side: int          # output height = width (also its input's, after any upsampling)
    upsample: int      # factor of the nearest UpSampling2D right before it; 1: none
    activation: str

    @property
    def input_side(self) -> int:
        """Side of the tensor the layer model takes (before its upsampling)."""
        return self.side // self.upsample


def conv_sites(size: int) -> list[ConvSite]:
    """conv1..conv10 of FCN-Pose at input size `size` (a multiple of 32)."""
    sites, side = [], size
    for i in range(1, NUM_POOLS + 1):
        sites.append(ConvSite(f"conv{i}", side, 1, "relu"))
        side //= 2
    sites.append(ConvSite(f"conv{NUM_POOLS + 1}", side, 1, "relu"))
    for j, factor in enumerate(UPSAMPLE_FACTORS):
        side *= factor
        last = j == len(UPSAMPLE_FACTORS) - 1
        sites.append(ConvSite(f"conv{NUM_POOLS + 2 + j}", side, factor, "sigmoid" if last else "relu"))
    return sites


def conv_channels(widths: Sequence[int], num_maps: int = NUM_MAPS) -> list[tuple[int, int]]:
    """(c_in, c_out) of conv1..conv10 for conv1..conv9 widths `widths`."""
    outs = [*widths, num_maps]
    return list(zip([3, *widths], outs))


def fcn_params(widths: Sequence[int], num_maps: int = NUM_MAPS) -> int:
    """Parameters of FCN-Pose with these widths: 3x3 kernels plus biases (= Keras count_params)."""
    return sum(KERNEL * KERNEL * c_in * c_out + c_out for c_in, c_out in conv_channels(widths, num_maps))


def fcn_macs(widths: Sequence[int], size: int, num_maps: int = NUM_MAPS) -> int:
    """Multiply-accumulates of all ten convolutions for one size x size frame."""
    return sum(conv_macs(site.side, site.side, KERNEL, KERNEL, c_in, c_out)
               for site, (c_in, c_out) in zip(conv_sites(size), conv_channels(widths, num_maps)))


def parse_widths(text: str) -> tuple[int, ...]:
    """'30,15,...' -> 9 positive ints (conv1..conv9), else UserError naming the list."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        widths = tuple(int(p) for p in parts)
    except ValueError:
        raise UserError(f"--widths {text!r}: expected {NUM_CONVS - 1} comma-separated positive integers "
                        f"(filters of conv1..conv9), e.g. {','.join(map(str, P70_WIDTHS))}") from None
    if len(widths) != NUM_CONVS - 1:
        raise UserError(f"--widths {text!r}: expected {NUM_CONVS - 1} widths (conv1..conv9; conv10 keeps "
                        f"{NUM_MAPS} maps), got {len(widths)}")
    if min(widths) < 1:
        raise UserError(f"--widths {text!r}: every width must be at least 1")
    return widths


def parse_int_list(text: str, what: str) -> tuple[int, ...]:
    """'1,2' -> (1, 2): positive ints, at least one, duplicates dropped."""
    try:
        values = tuple(dict.fromkeys(int(p) for p in str(text).split(",")))
    except ValueError:
        raise UserError(f"{what} {text!r}: expected comma-separated positive integers") from None
    if not values or min(values) < 1:
        raise UserError(f"{what} {text!r}: expected positive integers")
    return values


def parse_c_out(text: str) -> tuple[int, ...]:
    """'6:18' (inclusive), '6:18:2' or '8,12,16' -> sorted positive channel counts."""
    text = str(text).strip()
    if ":" in text:
        try:
            parts = [int(p) for p in text.split(":")]
        except ValueError:
            parts = []
        if len(parts) not in (2, 3) or parts[0] < 1 or parts[1] < parts[0] or (len(parts) == 3 and parts[2] < 1):
            raise UserError(f"c_out {text!r}: expected A:B or A:B:STEP with 1 <= A <= B and STEP >= 1")
        return tuple(range(parts[0], parts[1] + 1, parts[2] if len(parts) == 3 else 1))
    return tuple(sorted(parse_int_list(text, "c_out")))


def nearest_multiples(width: int, n: int) -> tuple[int, ...]:
    """The multiple(s) of n nearest to width, at least n; two when width lies halfway between them."""
    low, high = max(n, width // n * n), max(n, -(-width // n) * n)
    if low == high:
        return (low,)
    d_low, d_high = width - low, high - width
    return (low,) if d_low < d_high else (high,) if d_high < d_low else (low, high)


def floor_ceil_multiples(width: int, n: int) -> tuple[int, ...]:
    """The multiples of n just below and above width (at least n); one when width is a multiple."""
    return tuple(sorted({max(n, width // n * n), max(n, -(-width // n) * n)}))


def rounded_lists(widths: Sequence[int], n: int) -> tuple[list[tuple[int, ...]], list[tuple[int, ...]]]:
    """(nearest lists, every floor/ceil list) of `widths` rounded to multiples of n; conv10 is not in `widths`."""
    nearest = [tuple(c) for c in itertools.product(*(nearest_multiples(w, n) for w in widths))]
    every = [tuple(c) for c in itertools.product(*(floor_ceil_multiples(w, n) for w in widths))]
    return nearest, every


def budget_rows(widths: Sequence[int], n: int, size: int, tolerance: float, top: int) -> list[dict[str, Any]]:
    """The original, its nearest rounded lists, and up to `top` other floor/ceil lists within ±tolerance %
    of its parameters (closest first)."""
    base_p, base_m = fcn_params(widths), fcn_macs(widths, size)

    def row(kind: str, ws: Sequence[int]) -> dict[str, Any]:
        p, m = fcn_params(ws), fcn_macs(ws, size)
        return {"round_to": n, "kind": kind, "widths": list(ws), "params": p,
                "params_change_percent": 100.0 * (p - base_p) / base_p, "macs": m,
                "macs_change_percent": 100.0 * (m - base_m) / base_m}

    nearest, every = rounded_lists(widths, n)
    rows = [row("original", widths)]
    rows += sorted((row("nearest", ws) for ws in nearest), key=lambda r: abs(r["params_change_percent"]))
    others = [row("floor/ceil", ws) for ws in every if ws not in set(nearest) and tuple(ws) != tuple(widths)]
    others = [r for r in others if abs(r["params_change_percent"]) <= tolerance]
    rows += sorted(others, key=lambda r: (abs(r["params_change_percent"]), r["widths"]))[:top]
    return rows


def run_budget(args: argparse.Namespace, width_lists: list[tuple[int, ...]]) -> dict[str, Any]:
    multiples = parse_int_list(args.budget_round, "--budget-round")
    report = {"mode": "budget-round", "size": args.size, "tolerance_percent": args.tolerance, "lists": []}
    for widths in width_lists:
        print(f"\nwidths {','.join(map(str, widths))}: {fcn_params(widths):,} parameters, "
              f"{fcn_macs(widths, args.size) / 1e6:.2f} M MACs at {args.size}x{args.size} (conv10: {NUM_MAPS} maps)")
        for n in multiples:
            rows = budget_rows(widths, n, args.size, args.tolerance, args.top)
            report["lists"].append({"widths": list(widths), "round_to": n, "rows": rows})
            print(f"\nrounded to multiples of {n} (nearest, then other floor/ceil lists within "
                  f"±{args.tolerance:g} % of the parameters, closest first, at most {args.top}):")
            print(format_table(["kind", "widths", "params", "Δparams %", "MMACs", "ΔMACs %"],
                               [[r["kind"], ",".join(map(str, r["widths"])), r["params"],
                                 round(r["params_change_percent"], 1), round(r["macs"] / 1e6, 2),
                                 round(r["macs_change_percent"], 1)] for r in rows],
                               markdown=args.markdown, digits=[None, None, None, 1, 2, 1]))
    return report


# ---------------------------------------------------------------------------- models and files

def layer_model(site: ConvSite, c_in: int, c_out: int, fold: bool):
    """One FCN-Pose convolution (with its upsampling, folded or not) as a tf_keras model."""
    import tf_keras as keras

    inputs = keras.Input((site.input_side, site.input_side, c_in), name="activations")
    x = inputs
    if site.upsample > 1:
        x = keras.layers.UpSampling2D(site.upsample, name="up")(x)
    x = keras.layers.Conv2D(c_out, KERNEL, padding="same", activation=site.activation, name=site.name)(x)
    model = keras.Model(inputs, x, name=f"{site.name}_{c_out}")
    if fold and site.upsample > 1:
        from fcnpose_tf.compression.inference_graph import fold_upsampling

        model = fold_upsampling(model)
    return model


def layer_tflite(model, fmt: str, rng: np.random.Generator) -> bytes:
    """A layer model as TFLite, converted as `fcnpose_tf.compression.export` converts (static shape, built-in
    ops, the model as trackable object, float16 weights or full-integer int8), except that int8 keeps int8 at
    both ends, as the tensors inside the network are (export's files take uint8 pixels)."""
    import tensorflow as tf

    from fcnpose_tf.nativelog import native_stderr_captured

    shape = (1, *model.input_shape[1:])
    forward = tf.function(lambda x: model(x, training=False), input_signature=[tf.TensorSpec(shape, tf.float32)])
    converter = tf.lite.TFLiteConverter.from_concrete_functions([forward.get_concrete_function()], model)
    converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS]
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    if fmt == "float16":
        converter.target_spec.supported_types = [tf.float16]
    else:
        calibration = [rng.random(shape, dtype=np.float32) for _ in range(CALIBRATION_FRAMES)]
        converter.representative_dataset = lambda: ([frame] for frame in calibration)
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
        converter.inference_input_type = tf.int8
        converter.inference_output_type = tf.int8
    try:
        with native_stderr_captured():
            return bytes(converter.convert())
    except Exception as exc:
        raise UserError(f"TFLite conversion of {model.name} ({fmt}) failed: {type(exc).__name__}: "
                        f"{(str(exc).strip().splitlines() or ['no detail'])[0]}") from exc


def whole_model_tflite(widths: Sequence[int], size: int, fmt: str, fold: bool | None, seed: int):
    """FCN-Pose with these widths and random weights, exported by the package: (export, params, macs)."""
    import tf_keras as keras

    from fcnpose_tf.compression.export import export_tflite
    from fcnpose_tf.training.model import build_fcn_pose, describe

    keras.utils.set_random_seed(seed)
    model = build_fcn_pose(widths, input_size=size, num_maps=NUM_MAPS)
    rng = np.random.default_rng(seed)
    frames = rng.random((INT8_SAMPLE_FRAMES if fmt == "int8" else 2, size, size, 3), dtype=np.float32)
    calibration = rng.random((CALIBRATION_FRAMES, size, size, 3), dtype=np.float32) if fmt == "int8" else None
    export = export_tflite(model, fmt, sample_frames=frames, calibration_frames=calibration, check_keypoints=False,
                           map_atol=float("inf"), num_threads=1, fold_upsampling=fold)
    return export, int(model.count_params()), int(sum(row.macs for row in describe(model)))


# ---------------------------------------------------------------------------- timing

def make_invoke(data: bytes, threads: int, rng: np.random.Generator) -> Callable[[], None]:
    """An allocated interpreter for `data` with `threads` threads, its input set to random values; its invoke."""
    from fcnpose_tf.nativelog import native_stderr_captured
    from fcnpose_tf.runtime.interpreter import find_backend

    with native_stderr_captured():
        interpreter = find_backend().interpreter_class(model_content=data, num_threads=threads)
        interpreter.allocate_tensors()
    detail = interpreter.get_input_details()[0]
    dtype = np.dtype(detail["dtype"])
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        values = rng.integers(info.min, info.max, detail["shape"], dtype=dtype, endpoint=True)
    else:
        values = rng.random(detail["shape"]).astype(dtype)
    interpreter.set_tensor(detail["index"], values)
    return interpreter.invoke


def time_block(invokes: list[Callable[[], None]], rounds: int, warmup: int, clock: Callable[[], int],
               rng: np.random.Generator, label: str) -> list[np.ndarray]:
    """Per invoke: `rounds` times in ns, all timed once per round in a shuffled order."""
    warm = [[] for _ in invokes]
    for _ in range(warmup):
        for i, invoke in enumerate(invokes):
            t0 = time.perf_counter_ns()
            invoke()
            warm[i].append(time.perf_counter_ns() - t0)
    per_round = sum(float(np.median(w)) for w in warm) / 1e9 if warmup else float("nan")
    print(f"timing {label}: {len(invokes)} models x {rounds} rounds"
          + (f", about {per_round * rounds:.1f} s" if warmup else ""), file=sys.stderr, flush=True)
    times = [np.empty(rounds, dtype=np.int64) for _ in invokes]
    order = list(range(len(invokes)))
    for r in range(rounds):
        rng.shuffle(order)
        for i in order:
            invoke = invokes[i]
            t0 = clock()
            invoke()
            times[i][r] = clock() - t0
    return times


def stats_us(ns: np.ndarray) -> dict[str, float]:
    us = np.asarray(ns, dtype=np.float64) / 1e3
    return {"median_us": float(np.median(us)), "p95_us": float(np.percentile(us, 95)),
            "p25_us": float(np.percentile(us, 25)), "p75_us": float(np.percentile(us, 75)),
            "min_us": float(us.min()), "mean_us": float(us.mean())}


@dataclass
class Variant:
    """One TFLite file to time and what it is."""

    info: dict[str, Any]
    fmt: str
    data: bytes
    macs: int
    results: dict[int, dict[str, float]] = field(default_factory=dict)  # threads -> stats


def time_variants(variants: list[Variant], args: argparse.Namespace, threads: Sequence[int]) -> None:
    clock = time.thread_time_ns if args.clock == "cpu" else time.perf_counter_ns
    rng = np.random.default_rng(args.seed)
    for t in threads:
        invokes = [make_invoke(v.data, t, rng) for v in variants]
        times = time_block(invokes, args.rounds, args.warmup, clock, rng, f"{t} thread(s)")
        for v, ns in zip(variants, times):
            v.results[t] = stats_us(ns)
        del invokes


def fold_choice(fold: str) -> bool | None:
    return {"auto": None, "on": True, "off": False}[fold]


def default_fold(fmt: str) -> bool:
    from fcnpose_tf.settings import TFLITE_FORMATS

    return bool(TFLITE_FORMATS[fmt].fold_upsampling)


# ---------------------------------------------------------------------------- modes

def parse_layers(specs: Sequence[str], default_c_out: str | None, widths: Sequence[int],
                 size: int) -> list[tuple[ConvSite, int, tuple[int, ...]]]:
    """--layer NAME[=C_OUT] -> (site, its width in `widths`, c_out values)."""
    sites = {site.name: site for site in conv_sites(size)}
    out = []
    for spec in specs:
        name, _, c_out = str(spec).partition("=")
        name = name.strip()
        if name not in sites:
            raise UserError(f"--layer {spec!r}: expected one of conv1..conv{NUM_CONVS}, optionally =C_OUT "
                            "(e.g. conv3=6:18)")
        index = int(name[4:]) - 1
        width = ([*widths, NUM_MAPS])[index]
        if c_out:
            values = parse_c_out(c_out)
        elif default_c_out:
            values = parse_c_out(default_c_out)
        else:
            values = tuple(range(max(1, width - 8), width + 9))
        out.append((sites[name], width, values))
    return out


def run_layers(args: argparse.Namespace, widths: tuple[int, ...], layers: list[tuple[ConvSite, int, tuple[int, ...]]],
               threads: Sequence[int], formats: Sequence[str]) -> dict[str, Any]:
    import tf_keras as keras

    keras.utils.set_random_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    channels = conv_channels(widths)
    variants: list[Variant] = []
    start = time.perf_counter()
    for site, width, values in layers:
        c_in = args.c_in or channels[int(site.name[4:]) - 1][0]
        for fmt in formats:
            fold = default_fold(fmt) if args.fold == "auto" else args.fold == "on"
            folded = fold and site.upsample > 1
            for c_out in values:
                data = layer_tflite(layer_model(site, c_in, c_out, folded), fmt, rng)
                macs = conv_macs(site.side, site.side, KERNEL, KERNEL, c_in, c_out)
                info = {"layer": site.name, "input": f"{site.input_side}x{site.input_side}x{c_in}",
                        "output": f"{site.side}x{site.side}x{c_out}", "c_in": c_in, "c_out": c_out,
                        "width_in_list": width, "upsample": site.upsample, "folded": folded,
                        "kernel_c_out": c_out * site.upsample ** 2 if folded else c_out,
                        "kernel_side": site.input_side if folded else site.side, "size_bytes": len(data)}
                variants.append(Variant(info, fmt, data, macs))
        print(f"exported {site.name}: {len(values)} widths x {len(formats)} formats "
              f"({time.perf_counter() - start:.0f} s so far)", file=sys.stderr, flush=True)
    time_variants(variants, args, threads)
    results = []
    for fmt in formats:
        for t in threads:
            rows = []
            for v in (v for v in variants if v.fmt == fmt):
                s = v.results[t]
                per = s["median_us"] / (v.macs / 1e6)
                results.append({**v.info, "format": fmt, "threads": t, "macs": v.macs, **s, "us_per_mmac": per})
                rows.append([v.info["layer"], v.info["input"], v.info["c_out"], v.info["kernel_c_out"],
                             round(v.macs / 1e6, 3), round(s["median_us"], 1), round(s["p95_us"], 1), round(per, 2)])
            print(f"\n{fmt}, {t} thread(s): invoke µs, {args.rounds} rounds")
            print(format_table(["layer", "input", "c_out", "kernel c_out", "MMACs", "median µs", "p95 µs",
                                "µs/MMAC"], rows, markdown=args.markdown, digits=[None] * 4 + [3, 1, 1, 2]))
    return {"mode": "layer", "context_widths": list(widths), "results": results}


def run_widths(args: argparse.Namespace, width_lists: list[tuple[int, ...]], threads: Sequence[int],
               formats: Sequence[str]) -> dict[str, Any]:
    fold = fold_choice(args.fold)
    variants: list[Variant] = []
    summary = []
    start = time.perf_counter()
    for k, widths in enumerate(width_lists):
        for fmt in formats:
            export, params, macs = whole_model_tflite(widths, args.size, fmt, fold, args.seed + k)
            if params != fcn_params(widths) or macs != fcn_macs(widths, args.size):  # the arithmetic of --budget-round
                raise RuntimeError(f"parameter/MAC arithmetic disagrees with build_fcn_pose for {widths}")
            info = {"variant": k + 1, "widths": list(widths), "params": params, "size_bytes": export.size_bytes,
                    "folded": bool(export.graph_rewrites), "max_abs_diff_vs_keras": export.parity.max_abs_diff}
            variants.append(Variant(info, fmt, export.data, macs))
            print(f"exported #{k + 1} {','.join(map(str, widths))} {fmt}: {export.size_bytes:,} bytes"
                  f"{', folded' if export.graph_rewrites else ''} ({time.perf_counter() - start:.0f} s so far)",
                  file=sys.stderr, flush=True)
        base_p, base_m = fcn_params(width_lists[0]), fcn_macs(width_lists[0], args.size)
        summary.append([k + 1, ",".join(map(str, widths)), fcn_params(widths),
                        round(100.0 * (fcn_params(widths) - base_p) / base_p, 1),
                        round(fcn_macs(widths, args.size) / 1e6, 2),
                        round(100.0 * (fcn_macs(widths, args.size) - base_m) / base_m, 1)])
    time_variants(variants, args, threads)
    print(f"\nwidth lists (conv1..conv9; conv10 {NUM_MAPS} maps), {args.size}x{args.size}:")
    print(format_table(["#", "widths", "params", "Δparams %", "MMACs", "ΔMACs %"], summary, markdown=args.markdown,
                       digits=[None, None, None, 1, 2, 1]))
    results = []
    for fmt in formats:
        for t in threads:
            ours = [v for v in variants if v.fmt == fmt]
            first = ours[0].results[t]["median_us"]
            rows = []
            for v in ours:
                s = v.results[t]
                ratio = s["median_us"] / first
                per = s["median_us"] / (v.macs / 1e6)
                results.append({**v.info, "format": fmt, "threads": t, "macs": v.macs, **s, "us_per_mmac": per,
                                "time_ratio_to_first": ratio})
                rows.append([v.info["variant"], ",".join(map(str, v.info["widths"])), v.info["size_bytes"],
                             round(s["median_us"], 1), round(s["p95_us"], 1), round(per, 2), round(ratio, 3)])
            print(f"\n{fmt}{' (folded)' if ours[0].info['folded'] else ''}, {t} thread(s): invoke µs, "
                  f"{args.rounds} rounds")
            print(format_table(["#", "widths", "bytes", "median µs", "p95 µs", "µs/MMAC", "time / #1"], rows,
                               markdown=args.markdown, digits=[None, None, None, 1, 1, 2, 3]))
    return {"mode": "widths", "results": results}


# ---------------------------------------------------------------------------- command line

def environment(args: argparse.Namespace) -> dict[str, Any]:
    from fcnpose_tf.runtime.interpreter import find_backend
    from fcnpose_tf.system import available_cores

    return {"backend": find_backend().label, "machine": platform.machine(), "processor": platform.processor(),
            "cores": available_cores(), "load_average_start": list(os.getloadavg()), "size": args.size,
            "rounds": args.rounds, "warmup": args.warmup, "clock": args.clock, "seed": args.seed, "fold": args.fold}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--layer", action="append", default=[], metavar="NAME[=C_OUT]",
                    help="single-convolution sweep of this FCN-Pose layer (conv1..conv10); repeat for more")
    ap.add_argument("--c-out", help="output channels for --layer: A:B (inclusive), A:B:STEP or a comma list "
                                    "(default: the layer's width +- 8)")
    ap.add_argument("--c-in", type=int, help="input channels for --layer (default: from --widths)")
    ap.add_argument("--widths", action="append", default=[], metavar="W1,...,W9",
                    help="conv1..conv9 widths: whole models to time (repeat), the context of --layer "
                         f"(default {','.join(map(str, P70_WIDTHS))}), or the list for --budget-round")
    ap.add_argument("--budget-round", metavar="N[,N...]", help="print --widths rounded to multiples of N "
                                                               "with their parameter counts (no timing)")
    ap.add_argument("--tolerance", type=float, default=5.0, help="--budget-round: ± percent of the parameters "
                                                                 "for the floor/ceil lists (default 5)")
    ap.add_argument("--top", type=int, default=10, help="--budget-round: at most this many floor/ceil lists")
    ap.add_argument("--formats", default=",".join(FORMATS), help="int8,float16 (default both)")
    ap.add_argument("--threads", default="1", help="interpreter thread counts, e.g. 1,2 (default 1)")
    ap.add_argument("--rounds", type=int, default=200, help="timed rounds (default 200)")
    ap.add_argument("--warmup", type=int, default=10, help="untimed invokes per model first (default 10)")
    ap.add_argument("--size", type=int, default=224, help="FCN-Pose input side, a multiple of 32 (default 224)")
    ap.add_argument("--fold", choices=("auto", "on", "off"), default="auto",
                    help="fold upsampling into the next convolution: auto = the export's default per format "
                         "(int8 folded, float16 not), on, off")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="wall: perf_counter; cpu: the calling thread's CPU time (one thread only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--markdown", action="store_true", help="print Markdown tables")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("--force", action="store_true", help="overwrite --json if it exists")
    return ap


def run(args: argparse.Namespace) -> int:
    check_input_size(args.size)
    width_lists = [parse_widths(w) for w in args.widths]
    if args.budget_round is not None:
        if args.layer:
            raise UserError("--budget-round is arithmetic on --widths lists; it does not take --layer")
        if not width_lists:
            raise UserError("--budget-round needs a --widths list to round")
        if args.tolerance < 0 or args.top < 0:
            raise UserError("--tolerance and --top must not be negative")
        report = run_budget(args, width_lists)
    else:
        if not args.layer and not width_lists:
            raise UserError("give --layer NAME (single convolutions), --widths LIST (whole models) "
                            "or --budget-round N --widths LIST")
        if args.layer and len(width_lists) > 1:
            raise UserError("--layer takes at most one --widths list (the widths around the layer)")
        threads = parse_int_list(args.threads, "--threads")
        formats = tuple(dict.fromkeys(f.strip() for f in args.formats.split(",")))
        if not formats or any(f not in FORMATS for f in formats):
            raise UserError(f"--formats {args.formats!r}: expected a comma list of {', '.join(FORMATS)}")
        if args.rounds < 1 or args.warmup < 0:
            raise UserError("--rounds must be at least 1 and --warmup not negative")
        if args.c_in is not None and args.c_in < 1:
            raise UserError(f"--c-in must be a positive integer, got {args.c_in}")
        if args.clock == "cpu" and max(threads) > 1:
            raise UserError("--clock cpu measures the calling thread only: use it with --threads 1")
        if args.json and not args.force and Path(args.json).exists():
            raise UserError(f"{args.json}: exists; add --force to overwrite it")
        context = width_lists[0] if width_lists else P70_WIDTHS
        layers = parse_layers(args.layer, args.c_out, context, args.size) if args.layer else []
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
        env = environment(args)
        started = time.perf_counter()
        if args.layer:
            report = run_layers(args, context, layers, threads, formats)
        else:
            report = run_widths(args, width_lists, threads, formats)
        env.update(threads=list(threads), formats=list(formats), load_average_end=list(os.getloadavg()),
                   seconds=round(time.perf_counter() - started, 1))
        report = {**report, "environment": env}
        print(f"\n{env['backend']}, {env['machine']}, {env['cores']} cores, {args.clock} clock, "
              f"{args.rounds} rounds after {args.warmup} warm-up invokes, fold {args.fold}; load average "
              f"{env['load_average_start'][0]:.2f} at start, {env['load_average_end'][0]:.2f} at end; "
              f"{env['seconds']:.0f} s")
    if args.json:
        from fcnpose_tf.fileio import write_json

        write_json(args.json, report, force=args.force)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
