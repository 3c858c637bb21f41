"""What a compression report says to a reader: its table (one row per step and file; several rates in one), the note
`compress` prints when the compressed files lost more accuracy than the paper's, the best rate of several, and the
last lines of a command whose formats a gate may refuse (`finish_formats`: the files written, the exit status).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from fcnpose_tf.compression.report import CompressReport, RefusedFormat, Step, TFLiteStep
from fcnpose_tf.errors import UserError


PCK_DROP_BUDGET = 0.02
"""PCK@0.5 a compressed file may lose against the unpruned model on the measured frames: the paper's files stay
within it at the rates it ships, and so do the bundled 70 % files and three fixed-camera users' (docs/compression.md,
"On your own model"). Beyond it `accuracy_note` says so."""
FINE_PCK_DROP_BUDGET = 0.03
"""PCK@0.05 (fine localisation) a compressed file may lose against the unpruned model on the measured frames: about
what the bundled 70 % files and fixed-camera users' lose, less than keypoints on views that vary lose with PCK@0.5
held (docs/compression.md, "On your own model"). Beyond it `accuracy_note` says so, after PCK@0.5."""
VARIED_VIEWS_RATE = 0.5
"""The rate that came closest to PCK_DROP_BUDGET on the views-that-vary models measured, where 0.7 fell short
(docs/compression.md, "Views that vary: a lower rate")."""


MORE_FRAMES_ADVICE = ("more frames of your own camera, labelled by your model and given the minutes, keep more of "
                      "it (--more-frames VIDEO_OR_FOLDER: docs/compression.md, \"More frames of your look\")")
"""What `accuracy_note` names first: frames of the user's own camera labelled by the unpruned model and added to the
retraining's training frames (`compress --more-frames`), the lever that measured best where the 70 % network lost
most (docs/compression.md, "More frames of your look")."""


BUNDLED_TASK_FINE_SPREAD = 0.075
"""The largest PCK@0.05 loss the bundled task's 70 % files showed over the seeds and thread counts measured (0.073,
keeping the lowest validation loss: docs/results.md, 2026-12-04; keeping the best validation keypoints, the default
since the thirty-first session, at most 0.014): a larger one has another cause than the run's luck."""
BUNDLED_TASK_ADVICE = ("on the bundled task fine localisation varies from run to run with the seed, the thread "
                       "count and the kept epoch (70 % files at PCK@0.05 0.86-0.89 on the defaults, 0.80-0.89 with "
                       "--keep-best loss, against the unpruned 0.877: docs/compression.md, "
                       "\"Retraining in fcnpose-tf compress\"); the bundled 70 % files in saved_models/ are a run at "
                       "0.886, and --seed S makes another")
"""What `accuracy_note` says on the README's command (the bundled baseline on its own synthetic frames), where there are
no frames of a camera to add: the spread of the runs measured over seeds and thread counts (docs/results.md,
2026-12-04), and the bundled files' own figure (saved_models/fcnpose_ur5_p70_report.json, held equal by a test)."""


def _more_frames_advice(report: CompressReport) -> str:
    """MORE_FRAMES_ADVICE, or for a run that added frames already, how many and what more would take: more of them,
    and, when a model labelled them, every label corrected (docs/compression.md, "More frames of your look": true
    labels for all the frames kept the fine-localisation budget, true labels for a part of them did not)."""
    added = report.added_frames
    if not added:
        return MORE_FRAMES_ADVICE
    corrected = (", or every one of their labels corrected (--more-frames-via OUT.json, then --more-frames OUT.json)"
                 if added["labelled_by"] else "")
    return (f"this run retrained on {added['frames']} more frames of {added['source']}: more of them "
            f"(--more-frames-count){corrected} may keep more of it (docs/compression.md, \"More frames of your look\")")


def _drops(report: CompressReport) -> tuple[float, float] | None:
    """What the compressed files lost against the unpruned model on the measured frames: PCK@0.5 and PCK@0.05, each
    of the file best at it; None when no file was written."""
    if not report.tflite_files:
        return None
    return tuple(report.base.metrics.pck[t] - max(step.metrics.pck[t] for step in report.tflite_files)
                 for t in (0.5, 0.05))


def _within(drops: tuple[float, float] | None) -> bool:
    """Whether a rate's files kept both budgets (PCK_DROP_BUDGET, FINE_PCK_DROP_BUDGET)."""
    return drops is not None and drops[0] <= PCK_DROP_BUDGET and drops[1] <= FINE_PCK_DROP_BUDGET


def accuracy_note(report: CompressReport, bundled_task: bool = False) -> str | None:
    """One line when the compressed files lost more than PCK_DROP_BUDGET of the unpruned model's PCK@0.5, or more
    than FINE_PCK_DROP_BUDGET of its PCK@0.05, on the measured frames: how much, and what to try.

    Args:
        report: a compression run's report.
        bundled_task: the run compressed the bundled baseline on its synthetic frames: a loss within its spread
            (PCK@0.5 kept, PCK@0.05 within BUNDLED_TASK_FINE_SPREAD) gets BUNDLED_TASK_ADVICE, a larger one a lower
            rate, never a camera's frames.
    Returns:
        The line; None within both budgets, and when no file was written.
    """
    drops = _drops(report)
    if drops is None or _within(drops):
        return None
    rate = report.options["rate"]
    lower = (f"a lower --rate keeps more of it: on views that vary --rate {VARIED_VIEWS_RATE:g} came closest "
             f"(docs/compression.md, \"Views that vary: a lower rate\"); --rates {VARIED_VIEWS_RATE:g},{rate:g} "
             "compares them in one run" if rate > VARIED_VIEWS_RATE else "a lower --rate keeps more of it")
    coarse, fine = drops
    if not bundled_task:
        advice = f"{_more_frames_advice(report)}; else {lower}"
    else:  # a loss within the bundled task's run-to-run spread; beyond it, a lower rate
        advice = BUNDLED_TASK_ADVICE if coarse <= PCK_DROP_BUDGET and fine <= BUNDLED_TASK_FINE_SPREAD else lower
    retraining = report.retraining
    if retraining is not None and retraining.stopped_by_time_budget:
        advice = (f"the retraining stopped at its time budget after {retraining.epochs_run} of "
                  f"{report.options['retrain_epochs']} epochs (a slow or busy machine): more minutes may recover it "
                  f"(--max-minutes none --total-minutes none runs every epoch; docs/compression.md, \"Time budget\"), else {advice}")
    also = f"; PCK@0.05 {fine:.3f} below, more than {FINE_PCK_DROP_BUDGET:g}" if fine > FINE_PCK_DROP_BUDGET else ""
    if coarse <= PCK_DROP_BUDGET:
        return (f"note: {_loss(report, 0.05)}, more than the {FINE_PCK_DROP_BUDGET:g} budget for fine localisation "
                f"(PCK@0.5 within {PCK_DROP_BUDGET:g}: keypoints on the right part of the arm, less finely placed); "
                f"{advice}")
    return f"note: {_loss(report, 0.5)}, more than the {PCK_DROP_BUDGET:g} the paper's files lose{also}; {advice}"


def _loss(report: CompressReport, threshold: float) -> str:
    """"PCK@t of the file best at it (its format) is so much below the unpruned model's on these frames"."""
    best = max(report.tflite_files, key=lambda step: step.metrics.pck[threshold])
    base = report.base.metrics.pck[threshold]
    return (f"PCK@{threshold:g} {best.metrics.pck[threshold]:.3f} ({best.quantize}) is "
            f"{base - best.metrics.pck[threshold]:.3f} below the unpruned model's {base:.3f} on these frames")


def _row(label: str, step: Step, size: int | None) -> list:
    """A table row: the step's parameters, MACs, file size (`size` bytes), accuracy and timing."""
    m, t = step.metrics, step.timing
    return [label, step.params, step.macs / 1e6, size / 1e3 if size else None,
            m.pck.get(0.5), m.pck.get(0.2), m.pck.get(0.05), m.epe_px,
            t.inference_ms.mean if t else None, t.fps if t else None]


def _file_rows(report: CompressReport, prefix: str = "") -> list[list]:
    """One row per --quantize format, in the order asked: its file's, or REFUSED."""
    # (reports written before one file per format hold options.quantize as one name and no step["quantize"])
    quantize = report.options["quantize"]
    order = list(quantize) if isinstance(quantize, (list, tuple)) else []
    entries: list[tuple[Any, TFLiteStep | RefusedFormat]] = [(step.quantize or quantize, step)
                                                             for step in report.tflite_files]
    entries += [(entry.quantize, entry) for entry in report.refused]
    entries.sort(key=lambda entry: order.index(entry[0]) if entry[0] in order else len(order))
    rows = []
    for name, entry in entries:
        if isinstance(entry, RefusedFormat):
            rows.append([f"{prefix}{name} TFLite: REFUSED (gate)"] + [None] * 9)
        else:
            qat = " QAT" if entry.quantization == "quantization-aware training" else ""
            rows.append(_row(f"{prefix}{name}{qat} TFLite (.tflite)", entry, entry.tflite_size_bytes))
    return rows


_COLUMNS = ["model", "params", "MMACs", "size KB", "PCK@0.5", "PCK@0.2", "PCK@0.05", "EPE px", "infer ms", "FPS e2e"]
_DIGITS = [None, None, 1, 1, 3, 3, 3, 2, 2, 1]


def report_table(report: CompressReport | dict[str, Any], markdown: bool = False) -> str:
    """The compression report as a table: the unpruned model beside each step of the compressed one.

    Sizes in KB (1000 bytes): a TFLite row's file; a Keras row's model saved as .h5 (the paper's measure, whatever
    file holds it: the label says so);
    "infer ms" is the forward pass alone, FPS the whole frame (preprocess, inference, keypoints).

    Args:
        report: `compress_model`'s, or a NAME_pXX_report.json as parsed (read by `CompressReport.from_json`).
        markdown: a Markdown table instead of aligned text.
    Returns:
        The table.
    """
    from fcnpose_tf.tables import format_table

    if not isinstance(report, CompressReport):
        report = CompressReport.from_json(report)
    rows = [_row("unpruned (Keras; size as .h5)", report.base, report.base.h5_size_bytes),
            _row("pruned, before retraining", report.pruned_before_retraining, None),
            _row("pruned + retrained (Keras; size as .h5)", report.retrained, report.retrained.h5_size_bytes),
            *_file_rows(report)]
    return format_table(_COLUMNS, rows, markdown=markdown, digits=_DIGITS)


def rates_table(reports: Sequence[CompressReport], markdown: bool = False) -> str:
    """Several rates of one model in one table (`compress --rates`): the unpruned model once (the first report's
    measurement), then per rate its retrained Keras model and its files, each row named by its rate; a rate that ran
    at another input height (a pruned start's: `methods.start_height`) has its own unpruned row, measured there.

    Args:
        reports: one report per rate, of the same model.
        markdown: a Markdown table instead of aligned text.
    Returns:
        The table.
    """
    from fcnpose_tf.tables import format_table

    rows = [_row("unpruned (Keras; size as .h5)", reports[0].base, reports[0].base.h5_size_bytes)]
    for report in reports:
        prefix = f"rate {report.options['rate']:g}: "
        height = report.options.get("input_size")
        if height != reports[0].options.get("input_size"):
            rows.append(_row(f"{prefix}unpruned at height {height} (Keras)", report.base, report.base.h5_size_bytes))
        rows += [_row(f"{prefix}retrained (Keras; size as .h5)", report.retrained, report.retrained.h5_size_bytes),
                 *_file_rows(report, prefix)]
    return format_table(_COLUMNS, rows, markdown=markdown, digits=_DIGITS)


def best_rate_note(reports: Sequence[CompressReport]) -> str:
    """One line naming the highest rate whose files stayed within PCK_DROP_BUDGET of the unpruned model's PCK@0.5
    (`compress --rates`), with how much each higher rate lost; and, when that rate lost more than FINE_PCK_DROP_BUDGET
    of PCK@0.05, by how much and the highest rate within both budgets; or that no rate kept PCK@0.5.

    Args:
        reports: one report per rate, of the same model.
    Returns:
        The line.
    """
    base = {report.options["rate"]: report.base.metrics.pck[0.5] for report in reports}  # each rate's own
    measured = sorted(((report.options["rate"], _drops(report)) for report in reports), key=lambda pair: pair[0])
    kept = [(rate, d) for rate, d in measured if d is not None and d[0] <= PCK_DROP_BUDGET]
    beyond = ", ".join(f"{rate:g} loses {d[0]:.3f}" if d is not None else f"{rate:g} wrote no file"
                       for rate, d in measured if d is None or d[0] > PCK_DROP_BUDGET)
    if not kept:
        return (f"note: no rate kept PCK@0.5 within {PCK_DROP_BUDGET:g} of the unpruned model's "
                f"{base[reports[0].options['rate']]:.3f} on these "
                f"frames ({beyond}); try lower rates")
    rate, (coarse, fine) = kept[-1]
    line = (f"Best rate within the {PCK_DROP_BUDGET:g} PCK@0.5 budget: {rate:g} (its best file {coarse:+.3f} below "
            f"the unpruned model's {base[rate]:.3f})" + (f"; {beyond}" if beyond else ""))
    if fine <= FINE_PCK_DROP_BUDGET:
        return line
    both = [r for r, d in measured if _within(d)]
    lower = f"{both[-1]:g} keeps both" if both else "no rate measured keeps both"
    return (f"{line}; at {rate:g} PCK@0.05 loses {fine:.3f}, more than {FINE_PCK_DROP_BUDGET:g} (fine localisation): "
            f"{lower}")


def finish_formats(written: Sequence[Path], refused: Sequence[str], any_tflite: bool, named: bool,
                   gate: str = "keypoint gate") -> int:
    """The end of a command whose formats the keypoint gate may refuse (`export`, `compress`): name every
    file written, then its exit status.

    Args:
        written: the files written.
        refused: the formats refused.
        any_tflite: whether any .tflite file was written.
        named: whether the user named the formats with --quantize (a refusal is then an error).
        gate: what refused them, in words.
    Returns:
        0, with a note naming the refused formats.
    Raises:
        UserError: (exit 2) no .tflite file was written, or a format the user named was refused.
    """
    for path in written:
        print(f"wrote {path}")
    names = ", ".join(refused)
    kept = f"kept {', '.join(map(str, written))}" if written else "nothing written"
    if not any_tflite:
        raise UserError(f"no TFLite file written: {names} refused by the {gate} (the table above gives the "
                        f"reasons); {kept}")
    if named and refused:
        raise UserError(f"{names} (named with --quantize) refused by the {gate} (the table above gives the "
                        f"reason); {kept}")
    if refused:
        print(f"note: {names} refused by the {gate} (see above); the other formats were written")
    return 0
