#!/usr/bin/env python
"""Parameters and multiply-accumulates of a keras.applications network before and after graph pruning
(`fcnpose_tf.compression.graph_prune.prune_graph`), with the group table.

    python tools/depgraph_measure.py                       # MobileNetV2, alpha 1.0, 224 x 224, rate 0.5
    python tools/depgraph_measure.py --alpha 0.35 --size 96 --rate 0.7 --keras keras3 --groups

The network is built with weights=None (its random initial weights; the counts do not depend on them), pruned
with the L1 importance, and the pruned model's parameter count is checked against the plan's.
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
    parser.add_argument("--groups", action="store_true", help="print every group, not only the totals")
    return parser


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.compression.graph_prune import plan_graph, rebuild

    keras = importlib.import_module(FLAVOURS[args.keras])
    builder = getattr(keras.applications, args.net, None)
    if builder is None:
        raise UserError(f"--net {args.net}: no such builder in {keras.__name__}.applications")
    model = builder(input_shape=(args.size, args.size, 3), alpha=args.alpha, weights=None)
    start = time.perf_counter()
    plan = plan_graph(model, args.rate)
    pruned = rebuild(plan)
    seconds = time.perf_counter() - start
    if pruned.count_params() != plan.params[1]:
        raise RuntimeError(f"pruned model has {pruned.count_params()} parameters, the plan says {plan.params[1]}")
    text = plan.describe()
    print(text if args.groups else "\n".join(text.splitlines()[-2:]))
    prunable = sum(not p.group.frozen for p in plan.groups)
    print(f"{args.net} alpha {args.alpha} {args.size}x{args.size} ({keras.__name__}), rate {args.rate}: "
          f"{len(plan.groups)} groups, {prunable} pruned; planned and rebuilt in {seconds:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))  # a UserError: `run_tool`'s one line and status 2


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
