"""Reproduce the paper's experiment: every pruning rate on every fold, Keras, float16 and int8 TFLite, as tables and a
plot.

Per fold K it trains the unpruned model on the fold's training frames (or reuses
OUT/models/base_foldK.keras); per (fold, rate) it prunes (L1 filters), retrains, exports
verified float16 and int8 TFLite files and measures them on the fold's validation frames. It writes the
paper's tables ("5-Folds Desktop", "Pruning Results", "Requirements", "Pruning and
Quantization") as Markdown and CSV, OUT/summary.md, OUT/pck_vs_fps.png and OUT/results.json.
Each finished job is saved at once (OUT/jobs/): Ctrl-C loses at most the running job(s), and
rerunning the same command skips what is finished. Without --data it uses the synthetic UR5 set
the bundled baseline was trained on (generated once into a cache).
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "sweep"
RESUMABLE_OUTPUTS = ("out",)
"""Kept as it is when the sweep stops: its finished jobs, which a rerun skips."""
USES_TENSORFLOW = True
EXAMPLES = """\
  fcnpose-tf sweep --rates 0.1:0.9:0.1 --folds 5 --out results/          # the paper's nine rates, 5-fold CV
  fcnpose-tf sweep --preset paper --out results_paper/                    # the paper's epoch budgets (500, 100)
  fcnpose-tf sweep --rates full,0.5,0.7 --epochs 30 --retrain-epochs 10  # plus the unpruned TFLite row
  fcnpose-tf sweep --rates 0.5,0.7 --folds 2 --epochs 2 --retrain-epochs 1 --input-size 64   # a smoke test
  fcnpose-tf sweep --retrain-epochs 10,0.6:0.9:0.1=40                     # 40 retraining epochs from 60% up
  fcnpose-tf sweep --importance taylor --distill 0.5 --out results_taylor/ # another criterion, distilled retraining
  fcnpose-tf sweep --workers 2 --out results/                             # 2 local processes, 1 thread each
  fcnpose-tf sweep --executor ray --num-cpus 8 --threads 2                # a local Ray instance, 4 tasks at once
  fcnpose-tf sweep --executor ray --address auto --data /shared/ur5 --out /shared/results   # a Ray cluster
  fcnpose-tf sweep --out results/ --report-only                           # rebuild tables and plot only
  fcnpose-tf sweep --out results/ --retime                                # re-measure timings on this idle machine
"""


def PRIVATE_TEMP(args: argparse.Namespace) -> bool:  # noqa: N802 - the CLI reads it like the other commands' flag
    """A private temporary folder for the local executor (its workers inherit it); Ray tasks manage their own."""
    return args.executor == "local"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf import settings
    from fcnpose_tf.data.args import add_data_arguments
    from fcnpose_tf.sweep.rates import DEFAULT_RATES_SPEC

    parser.add_argument("--rates", default=DEFAULT_RATES_SPEC, metavar="SPEC",
                        help="pruning rates: START:STOP:STEP, a comma list, or both; 'full' (= 0) adds the "
                             "unpruned model's TFLite export")
    settings.FOLDS.add_to(parser)
    add_data_arguments(parser, positional=False, required=False, folds_option=False)
    parser.add_argument("--out", type=Path, default=Path("results"), metavar="DIR",
                        help="results folder (jobs/, models/, tables/, summary.md, pck_vs_fps.png, results.json)")
    train = parser.add_argument_group("training")
    settings.add_preset_argument(train)
    for setting in (settings.SWEEP_EPOCHS, settings.PATIENCE, settings.SWEEP_MAX_MINUTES):
        setting.add_to(train)
    settings.RETRAIN_EPOCHS_BY_RATE.add_to(train)
    for setting in (settings.RETRAIN_PATIENCE, settings.INPUT_SIZE, settings.BATCH_SIZE, settings.LEARNING_RATE,
                    settings.LR_PATIENCE, settings.LR_SCHEDULE, settings.POSITIVE_WEIGHT, settings.AUGMENT_COPIES,
                    settings.SEED, settings.IMPORTANCE, settings.IMPORTANCE_FRAMES, settings.DISTILL,
                    settings.MIN_FILTERS, settings.SWEEP_FREEZE):
        setting.add_to(train)
    run = parser.add_argument_group("execution")
    run.add_argument("--executor", choices=("local", "ray"), default="local",
                     help="local: this machine (sequential, or --workers processes); ray: one Ray task per job")
    run.add_argument("--workers", type=int, default=1,
                     help="local executor: jobs run at once, each in its own process")
    run.add_argument("--address", metavar="ADDR",
                     help="ray executor: the cluster to join (e.g. auto, or ray://head:10001); default: start "
                          "a local Ray instance")
    run.add_argument("--num-cpus", type=int, metavar="N",
                     help="ray executor: CPUs of the local Ray instance (default: all cores)")
    settings.SWEEP_THREADS.add_to(run)
    settings.SWEEP_CENTROID.add_to(parser)
    settings.FORCE.variant(help="redo every job (retraining the base models), also when OUT holds other settings"
                           ).add_to(parser)
    parser.add_argument("--report-only", action="store_true",
                        help="only rebuild the tables, plot and results.json from OUT's saved jobs")
    parser.add_argument("--retime", action="store_true",
                        help="re-measure inference time and FPS (Keras and TFLite) of every finished job from its "
                             "saved model files, sequentially on this machine with the sweep's --threads, without "
                             "retraining; the metrics must come out identical; then rebuild the report")


def resolve_threads(args: argparse.Namespace) -> int:
    """Threads per job: --threads, else all cores (sequential), cores / workers, or 1 per Ray task."""
    from fcnpose_tf.settings import THREADS
    from fcnpose_tf.system import available_cores

    if args.threads is not None:
        return THREADS.validate(args.threads)
    if args.executor == "ray":
        return 1
    return max(1, available_cores() // max(1, args.workers))


def make_executor(args: argparse.Namespace, threads: int):
    """The executor the options ask for (with the option combinations that make no sense refused)."""
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.sweep.executors import LocalExecutor, RayExecutor

    if args.executor == "local":
        if args.address or args.num_cpus is not None:
            raise UserError("--address and --num-cpus are for --executor ray")
        return LocalExecutor(workers=args.workers, threads=threads)
    if args.workers != 1:
        raise UserError("--workers is for the local executor; with ray, --threads sets the CPUs per task and "
                        "Ray runs as many tasks as the CPUs allow (--num-cpus for a local instance)")
    return RayExecutor(address=args.address, num_cpus=args.num_cpus, threads=threads)


def config_from_args(args: argparse.Namespace):
    """The SweepConfig of the parsed options (every setting by name; the rates and per-rate budgets read)."""
    from fcnpose_tf import settings
    from fcnpose_tf.progress import Reporter
    from fcnpose_tf.sweep import SweepConfig, parse_rates
    from fcnpose_tf.sweep.rates import parse_per_rate_epochs

    retrain_epochs, retrain_epochs_by_rate = parse_per_rate_epochs(args.retrain_epochs)
    parallel = args.workers > 1 or args.executor == "ray"
    return settings.from_args(args, SweepConfig, out=str(args.out), data=str(args.data),
                              images=str(args.images) if args.images else None, rates=parse_rates(args.rates),
                              retrain_epochs=retrain_epochs, retrain_epochs_by_rate=retrain_epochs_by_rate,
                              threads=resolve_threads(args), reporter=Reporter(quiet=args.quiet or parallel))


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.data import synthcache
    from fcnpose_tf.sweep import run_sweep, write_report

    if args.report_only and args.retime:
        from fcnpose_tf.errors import UserError

        raise UserError("--report-only and --retime exclude each other (--retime rebuilds the report too)")
    if args.report_only:
        result = write_report(args.out)
        _print_tables(result, args.out)
        return 0
    if args.retime:
        return _retime(args)
    executor = make_executor(args, resolve_threads(args))
    if args.data is None:
        args.data = synthcache.default_training_data()
    config = config_from_args(args)
    if args.resplit:  # store new splits first; the sweep then refuses OUT's old jobs unless --force
        from fcnpose_tf.data.args import load_from_args

        load_from_args(args)
    outcome = run_sweep(config, executor)
    _print_tables(outcome.report, args.out)
    print(f"\n{len(outcome.done)} job(s) run, {len(outcome.skipped)} skipped as finished, "
          f"{len(outcome.failed)} failed" + (f", {len(outcome.not_run)} not run" if outcome.not_run else "")
          + f"; {outcome.seconds / 60:.1f} min")
    for name, error in outcome.failed.items():
        print(f"  failed: {name}: {error}")
    return 1 if outcome.failed else 0


def _retime(args: argparse.Namespace) -> int:
    from fcnpose_tf.sweep.retime import retime_sweep
    from fcnpose_tf.tables import format_table

    outcome = retime_sweep(args.out, threads=args.threads, data=str(args.data) if args.data else None)
    _print_tables(outcome.report, args.out)
    rows = [[c["job"], c["section"], c["fps_before"], c["fps_after"],
             None if not c["fps_before"] or not c["fps_after"] else f"{c['fps_after'] / c['fps_before']:.2f}"]
            for c in outcome.changes]
    print("\nFPS as the jobs measured it and as re-measured now (metrics identical)")
    print(format_table(["job", "model", "FPS before", "FPS now", "ratio"], rows))
    print(f"\n{len(outcome.jobs)} job(s) re-timed in {outcome.seconds / 60:.1f} min")
    return 0


def _print_tables(report, out: Path) -> None:
    """The tables of a rebuilt report (`sweep.report.SweepReport`), then where they were written."""
    tables = report.tables
    results = report.results
    cfg = results.config
    print(f"\nPCK normalised by max(bbox w, h); mean ± std over folds; timing on {cfg['threads']} thread(s)")
    for name in ("folds", "pruning", "requirements", "quantization"):
        table = tables[name]
        if table.rows:
            print(f"\n{table.title}\n{table.text()}")
    missing = results.missing()
    if missing:
        print(f"\n{len(missing)} job(s) not finished yet: {', '.join(missing[:10])}{', ...' if len(missing) > 10 else ''}")
    out = Path(out)  # the folder given, not the one recorded in sweep.json (a copied or moved folder)
    print(f"\nwrote {out / 'summary.md'}, {out / 'tables'}/*.md|csv, {out / 'pck_vs_fps.png'}, {out / 'results.json'}")
