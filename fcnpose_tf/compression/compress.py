"""The paper's whole compression for one rate: prune, retrain, quantize, and measure every step.

    base model ──► filter surgery at rate r, filters ranked by an importance criterion (first-order
                   Taylor by default, the paper's L1 with --preset paper; or tfmot magnitude pruning)
                   ──► retrain (optionally distilled from the base model's maps) ──► TFLite export
                   (float16 and int8 by default), verified against Keras
    measured at each step on the same frames: PCK@0.5/0.2/0.05 (bbox), EPE, PCK-AUC,
    parameters, MACs, file sizes, inference time and FPS (Keras and TFLite, thread count stated).

`compress_model` is the library entry point (the `compress` and `sweep` commands call it); it runs the steps of
`fcnpose_tf.compression.steps` in order (measure_base, importance_step, prune_step, retrain_step, measure_retrained),
then those of `fcnpose_tf.compression.export_steps` (`export_formats`: export_step and measure_quantized per format),
each returning its part of the report. Beside it:
`fcnpose_tf.compression.options` (what a run is asked: `CompressOptions`, the files it writes),
`fcnpose_tf.compression.methods` (how: a `PruningMethod`, `FilterPruning` with an importance criterion from
`fcnpose_tf.compression.importance` or `MagnitudePruning`; both retrain through `train.fit`) and
`fcnpose_tf.compression.report` (what it measured: the `CompressReport` written as NAME_pXX_report.json, its table).
A format whose file fails its gate is a "refused" entry of the report (a `RefusedFormat`), not the end of the run;
post-training int8 refused falls back to quantization-aware training (`qat_step`, `fcnpose_tf.compression.qat`).
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Sequence

from fcnpose_tf import progress, settings
from fcnpose_tf.compression.methods import pruned_start, pruning_method, start_height
from fcnpose_tf.compression.options import CheckedOptions, OutputFiles, output_files
from fcnpose_tf.compression.report import CompressReport, _check_metadata
from fcnpose_tf.compression.export_steps import export_formats
from fcnpose_tf.compression.steps import (Run, SharedScoring, measure_base, measure_retrained, prune_step, retrain_step,
                                          shared_importance)
from fcnpose_tf.errors import UserError
from fcnpose_tf.progress import Reporter
from fcnpose_tf.fileio import write_json

# TensorFlow is imported inside the functions: `sweep.jobs` and the CLI import this module (or
# read its settings) without needing TensorFlow until a compression runs.


def compress_model(base_path: str | os.PathLike, train_dataset: Any, eval_dataset: Any, eval_indices: Sequence[int],
                   out_dir: str | os.PathLike, options: CheckedOptions, *, force: bool = False,
                   eval_description: str = "", reporter: Reporter | None = None,
                   metadata: dict[str, Any] | None = None, shared: SharedScoring | None = None,
                   outputs: OutputFiles | None = None) -> CompressReport:
    """Prune, retrain, export and measure one model at one rate; write the files; return the report.

    Args:
        base_path: the unpruned (or any) .keras/.h5 FCN-Pose.
        train_dataset: dataset to retrain on, score filters and calibrate int8 on (the fold `steps.retrain_fold`
            decides: `options.fold`, else the base model's own, else the hold-out split).
        eval_dataset, eval_indices: the frames every step is measured on.
        out_dir: where NAME_p70.keras, NAME_p70_fp16.tflite (one file per `options.quantize` format) and
            NAME_p70_report.json go.
        options: rate, method, strategy, quantize, calibration frames, retraining settings, threads, as
            `CompressOptions.checked(base_path)` returns them (resolved and validated once, by the caller, with an
            explicit start's file; the report's "options" holds the values used).
        force: replace existing output files; the caller refuses them before any work (`options.check_outputs`),
            else a run that finds one writes nothing at its end.
        reporter: where the step lines and progress go (`fcnpose_tf.progress`; default: the current one): data
            preparation's progress, then the retraining one line per epoch; nothing when silent.
        metadata: more facts for the report (e.g. the command's "preset"), top-level keys of its file.
        shared: the base model's measurement and filter scores shared by several rates of the same base model
            and frames (`compress --rates`): the first call fills it, the next ones read it instead of measuring
            and scoring again.
        outputs: the run's files as the caller's check named them (`options.check_outputs`); None: named here.
    Returns:
        The `CompressReport` (its `to_json()` written as NAME_pXX_report.json). Its `quantized` is the
        first TFLite file written (the paper's float16 by default; None if every format was refused),
        `other_quantized` the other files written, `refused` the formats whose file failed its gate
        (`RefusedFormat`: reason, the gate's facts, quantization-aware training's when it was tried). A
        refused format writes no file and does not end the run; `files` names the files written.
    Raises:
        UserError: an existing output without force, an unwritable folder, or a model whose
            maps or keypoint names do not match the dataset.
        ValueError: `metadata` names a section of the report, or options not checked (`CompressOptions.checked`).
    """
    from fcnpose_tf.training.model import architecture_of, at_input_height, in_keypoint_order, load_model, view_of
    from fcnpose_tf.compression.frames import check_enough_frames
    from fcnpose_tf.compression.plan import check_chain, plan_widths

    base_path = Path(base_path)
    _check_metadata(metadata)
    if not isinstance(options, CheckedOptions):
        raise ValueError("compress_model takes the options of CompressOptions.checked(base_path), every "
                         "per-run choice made")
    checked, options = options, options.options
    start = time.perf_counter()
    reporter = progress.resolve(reporter)
    say = reporter.say
    outputs = outputs if outputs is not None else output_files(base_path, out_dir, options)
    base = load_model(base_path)
    if base.output_shape[-1] != train_dataset.schema.num_maps:
        raise UserError(f"{base_path}: {base.output_shape[-1]} output maps, but the data's schema needs "
                        f"{train_dataset.schema.num_maps}")
    # what the files' maps stand for: the data they are retrained on (the same keypoints in another order: reordered)
    in_keypoint_order(base, train_dataset.schema, str(base_path),
                      "compress it with frames of its own keypoints (--data)")
    architecture = architecture_of(base)
    saved_view = view_of(base)
    if options.input_size:  # the height; an H x W input keeps its aspect
        if architecture == "fcn-pose":
            check_chain(base)  # rebuilt at another size only when the surgery understands it: refused first
        base = at_input_height(base, options.input_size)
    # the widths at the rate, computed once and read by every step; FCN-Pose that is not a plain chain of supported
    # layers is refused here, before any work
    plan = plan_widths(base, options.rate, options.min_filters if options.method == "l1" else 0,
                       branches=architecture != "fcn-pose")
    start_name, start_file = pruned_start(checked, base_path, plan, architecture, reporter)
    start_side = start_height(start_file, base, options)
    if start_side is not None:  # the pruned start's own pixel density; the plan's widths are the same at any side
        base = at_input_height(base, start_side)
        plan = plan_widths(base, options.rate, options.min_filters, branches=architecture != "fcn-pose")
        options = replace(options, input_size=start_side)  # recipe and report say so; the files keep their names
    method = pruning_method(options, plan, start_name, start_file)
    options = replace(options, start=method.start_name)
    run = Run(base_path, base, method, options, outputs, train_dataset, eval_dataset, eval_indices, force, reporter)
    check_enough_frames(options.quantize, len(eval_indices), len(run.training_frames), train_dataset.via_path)
    steps = 4 + 2 * len(options.quantize)
    resized = f", rebuilt from its {saved_view.height}x{saved_view.width}" if saved_view != run.input_size else ""
    resized += f": the height {start_name} was retrained at" if start_side is not None else ""
    say(f"[1/{steps}] base model {base_path} ({run.input_size.describe(whole='')}{resized})")
    if plan.floor < options.min_filters:
        say(f"  --min-filters {options.min_filters} does not fit the parameter budget of rate {options.rate:g}: "
            f"no layer under {plan.floor} filters")
    shared = shared if shared is not None else SharedScoring()
    if run.input_size not in shared.base_steps:
        shared.base_steps[run.input_size] = measure_base(run)
    else:
        say("  measured already (an earlier rate's figures)")
    base_step = shared.base_steps[run.input_size]
    say(f"[2/{steps}] pruning: {run.method.words}")
    importance = None
    if run.method.ranks_filters:
        importance = shared_importance(run, shared)
    pruned, pruned_sections, pruned_step = prune_step(run, importance)
    spent = (time.perf_counter() - start) / 60
    ranking = (pruned_sections.pruning or {}).get("ranking_seconds", 0.0) / 60
    budget = options.retraining_minutes(spent, ranking, options.polish_minutes if run.polishes else 0.0)
    if budget != options.max_minutes and options.retrain_epochs:
        over = " (the least it gets: this run takes longer than its total)" \
            if budget == settings.MIN_RETRAIN_MINUTES else ""
        ranked = f" ({ranking:.1f} of them ranking filters)" if ranking >= 0.05 else ""
        say(f"  retraining budget {budget:.1f} min{over}: what --total-minutes {options.total_minutes:g} leaves after "
            f"{spent:.1f} min before retraining{ranked}, twice the rest kept for the steps after"
            f"{f' and {options.polish_minutes:g} for the polish' if run.polishes else ''} (--max-minutes "
            f"{'none' if options.max_minutes is None else f'{options.max_minutes:g}'})")
        options = run.options = replace(options, max_minutes=budget)
    say(f"[3/{steps}] retraining: up to {options.retrain_epochs} epochs")
    retrained, retrained_sections = retrain_step(run, pruned)
    say(f"[4/{steps}] measuring the retrained Keras model")
    retrained_step = measure_retrained(run, retrained)
    files, refused = export_formats(run, retrained, retrained_step, steps)
    refused_files = {outputs.tflite[entry.quantize] for entry in refused}
    report = CompressReport(
        base_model=str(base_path), method=options.method, recipe=method.recipe, options=asdict(options),
        evaluation_frames=eval_description or f"{len(eval_indices)} frames of {eval_dataset.via_path}",
        pck_normalisation="max(w, h) of the ground-truth keypoints' bounding box", threads=options.threads,
        metadata=dict(metadata or {}), base=base_step, **vars(pruned_sections), pruned_before_retraining=pruned_step,
        **vars(retrained_sections), retrained=retrained_step,
        # the first file written (the paper's float16 by default), None when every format was refused
        quantized=files[0] if files else None, other_quantized=files[1:], refused=refused,
        files={key: str(path) for key, path in outputs.paths.items() if path not in refused_files},
        seconds=round(time.perf_counter() - start, 1))
    write_json(outputs.paths["report"], report.to_json(), force=force)
    return report
