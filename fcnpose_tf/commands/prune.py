"""Prune the filters of any Keras CNN (a .keras/.h5 of tf_keras or Keras 3): surgery only, no retraining.

The model's channels are traced through its graph into groups that go together (residual Adds couple their
inputs' filters; docs/compression.md, "Any CNN: the dependency graph"); every prunable group of n channels keeps
the n - floor(n x rate) most important, and the model is rebuilt narrower with the kept weights. Before
retraining it computes what the original computes with those channels deleted: retrain it in your own loop.
The input's channels, the outputs' and any layer named in --keep stay whole. The model is loaded with the Keras
that saved it (the file's keras_version) and the pruned model saved with the same one, atomically. Printed: the
groups (producers, channels, kept), parameters and multiply-accumulates before and after.

Exit status: 0 when the file was written; 2 for bad input (no such file, not a model, a layer the surgery does
not handle, a rate outside [0, 1), an unknown --keep layer), with nothing written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "prune"
USES_TENSORFLOW = True
OUTPUTS = ("out", "json")
FILE_OUTPUTS = ("out", "json")
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
IMPORTANCES = ("l1", "l2")
AGGREGATES = ("sum", "mean", "max")
EXAMPLES = """\
  fcnpose-tf prune my_cnn.keras --rate 0.5 --out my_cnn_p50.keras             # then retrain it in your own loop
  fcnpose-tf prune workcell --rate 0.7 --out workcell_p70.keras --json plan.json
  python -c "import keras; keras.applications.MobileNetV2(weights=None).save('mnv2.keras')"
  fcnpose-tf prune mnv2.keras --rate 0.5 --out mnv2_p50.keras --round-to 8    # 35 % of the parameters
  fcnpose-tf prune mnv2.keras --rate 0.5 --out mnv2_p50.keras --keep block_16_project --min-filters 16
"""


def _keep_list(text: str) -> tuple[str, ...]:
    names = tuple(part.strip() for part in str(text).split(",") if part.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"{text!r}: expected one or more layer names separated by commas")
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.bundled import KERAS_SUFFIXES, model_argument, names_help

    parser.add_argument("model", type=model_argument(KERAS_SUFFIXES), metavar="MODEL",
                        help=f"a .keras/.h5 model of tf_keras or Keras 3, or a bundled one by name "
                             f"({names_help(KERAS_SUFFIXES)})")
    parser.add_argument("--rate", type=float, required=True, metavar="R",
                        help="fraction of each prunable group's channels to remove, in [0, 1): a group of n keeps "
                             "n - floor(n x R)")
    parser.add_argument("--out", type=Path, required=True, metavar="OUT.keras",
                        help="the pruned model (.keras or .h5), saved with the Keras the model was saved with")
    parser.add_argument("--importance", choices=IMPORTANCES, default="l1",
                        help="a filter's score: the L1 or L2 norm of its kernel (bias excluded)")
    parser.add_argument("--aggregate", choices=AGGREGATES, default="sum",
                        help="a coupled channel's score from its producing layers' filter scores")
    parser.add_argument("--min-filters", type=int, default=0, metavar="N",
                        help="no group narrower than min(n, N) channels (0: the keep rule alone)")
    parser.add_argument("--round-to", type=int, default=1, metavar="M",
                        help="kept channels rounded up to a multiple of M per group (capped at n; e.g. 8 for "
                             "SIMD-friendly widths)")
    parser.add_argument("--keep", type=_keep_list, default=(), metavar="LAYER[,LAYER...]",
                        help="layers whose output channels are all kept")
    parser.add_argument("--json", type=Path, metavar="OUT.json",
                        help="also write the plan: groups (producers, channels, kept), per layer its widths, "
                             "parameters and MACs before and after")
    from fcnpose_tf import settings

    settings.FORCE.variant(help="replace existing --out (and --json) files").add_to(parser)


def plan_json(plan, model_path: Path, out: Path, settings: dict) -> dict:
    """The plan as JSON: groups, each layer's input and output widths before and after, params and MACs."""
    groups = [{"index": p.group.index, "producers": list(p.group.producers), "channels": p.group.width,
               "kept": int(len(p.kept)), "status": p.group.frozen or "pruned"} for p in plan.groups]
    layers = {}
    for op in plan.graph.ops:
        entry = plan.layers[op.layer.name]
        layers[op.layer.name] = {"type": type(op.layer).__name__,
                                 "in_channels": [int(shape[-1]) for shape in op.in_shapes],
                                 "in_channels_kept": [int(len(k)) for k in entry.kept_in],
                                 "out_channels": int(op.out_shape[-1]), "out_channels_kept": int(len(entry.kept_out)),
                                 "params": list(entry.params), "macs": list(entry.macs)}
    return {"model": str(model_path), "out": str(out), "keras": plan.graph.keras.__name__, **settings,
            "params": {"before": plan.params[0], "after": plan.params[1]},
            "macs": {"before": plan.macs[0], "after": plan.macs[1]}, "groups": groups, "layers": layers}


def run(args: argparse.Namespace) -> int:
    import time

    from fcnpose_tf.compression.graph_prune import plan_graph, rebuild
    from fcnpose_tf.compression.keras_file import load_any, save_to
    from fcnpose_tf.compression.keep_rule import exact_rate
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import atomic_paths, check_writable, json_text

    exact_rate(args.rate)  # a rate outside [0, 1): refused before the model is read
    for name, value, minimum in (("--min-filters", args.min_filters, 0), ("--round-to", args.round_to, 1)):
        if value < minimum:
            raise UserError(f"{name} must be at least {minimum}, got {value}")
    if args.out.suffix not in (".keras", ".h5"):
        raise UserError(f"{args.out}: the pruned model's file should end in .keras or .h5")
    for path in [args.out, *([args.json] if args.json else [])]:
        check_writable(path, args.force)
    start = time.perf_counter()
    model = load_any(args.model)
    settings = {"rate": args.rate, "importance": args.importance, "aggregate": args.aggregate,
                "min_filters": args.min_filters, "round_to": args.round_to, "keep": list(args.keep)}
    plan = plan_graph(model, args.rate, importance=args.importance, aggregate=args.aggregate,
                      min_filters=args.min_filters, round_to=args.round_to, keep=args.keep)
    pruned = rebuild(plan)
    seconds = time.perf_counter() - start
    print(plan.describe())  # the groups, then parameters and MACs before -> after (share left)
    print(f"{plan.graph.keras.__name__} model {model.name}: {sum(not p.group.frozen for p in plan.groups)} of "
          f"{len(plan.groups)} groups pruned at rate {args.rate:g}; loaded, planned and rebuilt in {seconds:.1f} s "
          "(surgery only: retrain it)")
    outputs = [args.out, *([args.json] if args.json else [])]
    with atomic_paths(outputs, args.force) as temporaries:  # every file appears together, or none
        save_to(pruned, temporaries[0])
        if args.json:
            temporaries[1].write_text(json_text(plan_json(plan, args.model, args.out, settings)), encoding="utf-8")
    for path in [args.out, *([args.json] if args.json else [])]:
        print(f"wrote {path}")
    return 0
