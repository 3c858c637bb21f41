#!/usr/bin/env python
"""Parameters and multiply-accumulates of a keras.applications network before and after graph pruning
(`fcnpose_tf.compression.graph_prune.prune_graph`), with the group table.

    python tools/depgraph_measure.py                       # MobileNetV2, alpha 1.0, 224 x 224, rate 0.5
    python tools/depgraph_measure.py --alpha 0.35 --size 96 --rate 0.7 --keras keras3 --groups
    python tools/depgraph_measure.py --round-to 8 --tflite int8 --threads 1 --rounds 5   # and the files' speed

The network is built with weights=None (its random initial weights; the counts do not depend on them), pruned
with the L1 importance, and the pruned model's parameter count is checked against the plan's. With --tflite, both
networks are exported to that format as `fcnpose-tf export` does for a model that is not a keypoint model (output
parity on random inputs in [-1, 1], keras.applications' range; int8 calibrated on such inputs), and their invoke
times measured in LiteRT in interleaved rounds (unpruned, pruned, unpruned, ...): the median of each round's
median, and the ratio.
"""

from __future__ import annotations

import argparse
import importlib
import time

from fcnpose_tf.errors import UserError

FLAVOURS = {"tf_keras": "tf_keras", "keras3": "keras"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--net", default="MobileNetV2", help="a keras.applications builder (default MobileNetV2)")
    parser.add_argument("--alpha", type=float, default=1.0, help="width multiplier (default 1.0)")
    parser.add_argument("--size", type=int, default=224, help="input side (default 224)")
    parser.add_argument("--rate", default="0.5", help="fraction of each group's channels removed (default 0.5)")
    parser.add_argument("--keras", choices=sorted(FLAVOURS), default="tf_keras", help="the Keras to build with")
    parser.add_argument("--round-to", type=int, default=1, help="kept channels rounded up to a multiple (default 1)")
    parser.add_argument("--groups", action="store_true", help="print every group, not only the totals")
    parser.add_argument("--tflite", choices=("float32", "float16", "int8"),
                        help="also export both networks to this format and time their invokes")
    parser.add_argument("--threads", type=int, default=1, help="LiteRT threads for the timing (default 1)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--invokes", type=int, default=10, help="invokes per model per round (default 10)")
    return parser


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.compression.graph_prune import plan_graph, rebuild

    keras = importlib.import_module(FLAVOURS[args.keras])
    builder = getattr(keras.applications, args.net, None)
    if builder is None:
        raise UserError(f"--net {args.net}: no such builder in {keras.__name__}.applications")
    model = builder(input_shape=(args.size, args.size, 3), alpha=args.alpha, weights=None)
    start = time.perf_counter()
    plan = plan_graph(model, args.rate, round_to=args.round_to)
    pruned = rebuild(plan)
    seconds = time.perf_counter() - start
    if pruned.count_params() != plan.params[1]:
        raise RuntimeError(f"pruned model has {pruned.count_params()} parameters, the plan says {plan.params[1]}")
    text = plan.describe()
    print(text if args.groups else "\n".join(text.splitlines()[-2:]))
    prunable = sum(not p.group.frozen for p in plan.groups)
    print(f"{args.net} alpha {args.alpha} {args.size}x{args.size} ({keras.__name__}), rate {args.rate}: "
          f"{len(plan.groups)} groups, {prunable} pruned; planned and rebuilt in {seconds:.1f} s")
    if args.tflite:
        time_files(model, pruned, args)
    return 0


def time_files(model, pruned, args: argparse.Namespace) -> None:
    """Export both networks to --tflite (verified by output parity) and print their interleaved invoke times."""
    import numpy as np

    from fcnpose_tf.compression.export import export_generic
    from fcnpose_tf.compression.verify import _interpreter

    files = {}
    for name, net in (("unpruned", model), ("pruned", pruned)):
        export = export_generic(net, args.tflite, input_range=(-1.0, 1.0), num_threads=args.threads)
        parity = export.parity
        files[name] = export.data
        print(f"{name} {args.tflite}: {export.size_bytes / 1e3:,.0f} KB, verified on {parity.frames} inputs "
              f"(max relative output difference {parity.relative_diff:.2g})")
    interpreters = {name: _interpreter(data, args.threads) for name, data in files.items()}
    x = np.random.default_rng(0).uniform(-1, 1, (1, args.size, args.size, 3)).astype(np.float32)
    for interpreter in interpreters.values():
        interpreter.set_tensor(interpreter.get_input_details()[0]["index"], x)
        interpreter.invoke()  # warm-up: XNNPACK packs the weights on the first invoke
    medians: dict[str, list[float]] = {name: [] for name in interpreters}
    for _ in range(args.rounds):
        for name, interpreter in interpreters.items():
            times = []
            for _ in range(args.invokes):
                start = time.perf_counter()
                interpreter.invoke()
                times.append((time.perf_counter() - start) * 1e3)
            medians[name].append(float(np.median(times)))
    for name, values in medians.items():
        print(f"{name}: invoke {np.median(values):.2f} ms (round medians {', '.join(f'{v:.2f}' for v in values)})")
    ratio = np.median(medians["unpruned"]) / np.median(medians["pruned"])
    print(f"pruned {args.tflite} file {ratio:.2f}x faster ({args.threads} LiteRT thread(s), {args.rounds} interleaved "
          f"rounds of {args.invokes} invokes)")


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))  # a UserError: `run_tool`'s one line and status 2


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
