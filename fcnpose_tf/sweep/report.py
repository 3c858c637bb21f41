"""Tables, plot and results.json of a sweep, rebuilt from its saved job records alone.

Reads OUT/jobs/*.json (the records of finished jobs of OUT/sweep.json's configuration) and writes

    OUT/summary.md                   every table with its caption, the plot, the definitions
    OUT/tables/NAME.md, NAME.csv     folds, pruning, requirements, quantization (the paper's
                                     "5-Folds Desktop", "Pruning Results", "Requirements",
                                     "Pruning and Quantization"); CSV has _mean/_std columns
    OUT/pck_vs_fps.png               PCK@0.5 vs FPS, Keras and float16 TFLite, one point per rate
    OUT/results.json                 configuration, runs, machine, library versions, every table
                                     as records, every job record

Means and standard deviations are over folds (population std, ddof=0, as numpy's default);
a "folds" column says how many folds a row averages, so an unfinished sweep is visible as such.
numpy and matplotlib only; no TensorFlow.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Sequence, TypedDict

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import atomic_path, os_error_reason, parse_json, write_json, write_text
from fcnpose_tf.records import MachineInfo, library_versions, machine_info
from fcnpose_tf.sweep.executors import ExecutorInfo
from fcnpose_tf.sweep.jobs import JOBS_DIR, RECORD_VERSION, Job, JobRecord, plan_jobs, read_record, tflite_sections
from fcnpose_tf.sweep.rates import describe_per_rate, rate_label

SWEEP_FILE = "sweep.json"
TABLE_NAMES = ("folds", "pruning", "requirements", "quantization")
PLOT_FILE = "pck_vs_fps.png"
PCK_KEYS = ("pck@0.5_bbox", "pck@0.2_bbox", "pck@0.05_bbox")


# ------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------

class StatJson(TypedDict):
    """A `Stat` as results.json holds it (rounded to 6 decimals)."""

    mean: float | None
    std: float | None
    n: int


TableRow = dict[str, "StatJson | float | int | str | None"]
"""A table row as results.json holds it: column key -> a mean ± std over folds, a number, a label or None."""


@dataclass(frozen=True)
class Stat:
    """Mean and population standard deviation over folds, and how many folds gave a value."""

    mean: float | None
    std: float | None
    n: int

    def to_dict(self) -> StatJson:
        return {"mean": _round(self.mean), "std": _round(self.std), "n": self.n}


def stat(values: Iterable[Any]) -> Stat:
    """Stat of the finite numbers among `values` (None and NaN are left out)."""
    nums = [float(v) for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)
            and math.isfinite(float(v))]
    if not nums:
        return Stat(None, None, 0)
    mean = sum(nums) / len(nums)
    std = math.sqrt(sum((v - mean) ** 2 for v in nums) / len(nums))
    return Stat(mean, std, len(nums))


@dataclass(frozen=True)
class Column:
    """A table column: header for people, key for CSV/JSON, number format, alignment."""

    header: str
    key: str
    fmt: str = ""
    align: str = "right"
    rate: bool = False
    """Cells are pruning rates: shown as "full" / "70%", written to CSV as 0.0 / 0.7."""


@dataclass
class Table:
    """A titled table whose cells are str, int, float, Stat or None; rendered as Markdown, text or CSV."""

    key: str
    title: str
    caption: str
    columns: list[Column]
    rows: list[list[Any]] = field(default_factory=list)

    def _cell(self, value: Any, column: Column) -> str:
        if value is None:
            return "-"
        if column.rate and isinstance(value, (int, float)):
            return rate_label(value)
        if isinstance(value, Stat):
            if value.mean is None:
                return "-"
            mean = _number(value.mean, column.fmt)
            return f"{mean} ± {_number(value.std, column.fmt.lstrip('+'))}" if value.n >= 2 else mean
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return _number(value, column.fmt)
        return str(value)

    def _grid(self) -> tuple[list[str], list[list[str]], list[int]]:
        headers = [c.header for c in self.columns]
        cells = [[self._cell(v, c) for v, c in zip(row, self.columns)] for row in self.rows]
        widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]
        return headers, cells, widths

    def _line(self, values: Sequence[str], widths: Sequence[int], markdown: bool) -> str:
        parts = [v.ljust(w) if c.align == "left" else v.rjust(w) for v, w, c in zip(values, widths, self.columns)]
        return ("| " + " | ".join(parts) + " |") if markdown else "  ".join(parts).rstrip()

    def markdown(self) -> str:
        """A GitHub-flavoured Markdown table (numbers right-aligned)."""
        headers, cells, widths = self._grid()
        sep = "|" + "|".join(("-" * (w + 2)) if c.align == "left" else ("-" * (w + 1) + ":")
                             for w, c in zip(widths, self.columns)) + "|"
        return "\n".join([self._line(headers, widths, True), sep] + [self._line(r, widths, True) for r in cells])

    def text(self) -> str:
        """Aligned plain text for the terminal."""
        headers, cells, widths = self._grid()
        rule = "  ".join("-" * w for w in widths)
        return "\n".join([self._line(headers, widths, False), rule] + [self._line(r, widths, False) for r in cells])

    def _stat_columns(self) -> list[bool]:
        return [any(isinstance(row[i], Stat) for row in self.rows) for i in range(len(self.columns))]

    def csv(self) -> str:
        """CSV with raw numbers; a mean ± std column becomes KEY_mean, KEY_std (std empty for one fold)."""
        stats = self._stat_columns()
        header: list[str] = []
        for column, is_stat in zip(self.columns, stats):
            header += [f"{column.key}_mean", f"{column.key}_std"] if is_stat else [column.key]
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(header)
        for row in self.rows:
            out: list[Any] = []
            for value, is_stat, column in zip(row, stats, self.columns):
                if is_stat:
                    if isinstance(value, Stat):
                        out += [_csv(value.mean, column.fmt), _csv(value.std, column.fmt) if value.n >= 2 else ""]
                    else:
                        out += [_csv(value, column.fmt), ""]
                else:
                    out.append(_csv(value, column.fmt))
            writer.writerow(out)
        return buffer.getvalue()

    def records(self) -> list[TableRow]:
        """Rows as JSON-ready dicts keyed by column key (a Stat as {mean, std, n})."""
        return [{c.key: (v.to_dict() if isinstance(v, Stat) else _round(v)) for v, c in zip(row, self.columns)}
                for row in self.rows]


def _number(value: float | None, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if fmt.endswith("d"):
        return format(int(round(value)), fmt)
    if fmt:
        return format(value, fmt)
    from fcnpose_tf.tables import format_cell

    return format_cell(value)


def _round(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 6) if math.isfinite(value) else None
    return value


def _csv(value: Any, fmt: str = "") -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        if not math.isfinite(value):
            return ""
        return int(round(value)) if fmt.endswith("d") and value == round(value) else repr(round(value, 6))
    return value


# ------------------------------------------------------------------------------------------
# Collecting job records
# ------------------------------------------------------------------------------------------

@dataclass
class SweepResults:
    """The finished jobs of one configuration: base records by fold, rate records by rate and fold."""

    config: dict[str, Any]
    """sweep.json's "config" (`SweepFile`)."""
    bases: dict[int, JobRecord] = field(default_factory=dict)
    rates: dict[float, dict[int, JobRecord]] = field(default_factory=dict)
    ignored: list[str] = field(default_factory=list)

    @property
    def records(self) -> list[JobRecord]:
        return [self.bases[k] for k in sorted(self.bases)] + [
            self.rates[r][k] for r in sorted(self.rates) for k in sorted(self.rates[r])]

    def missing(self) -> list[str]:
        """Names of the configured jobs without a record."""
        have = {rec["job"] for rec in self.records}
        return [job.name for job in plan_jobs(int(self.config["folds"]), tuple(self.config["rates"]))
                if job.name not in have]


class RunEntry(ExecutorInfo, total=False):
    """One run of a sweep, as sweep.json's "runs" holds it: a sweep run (`new_run_entry`, completed by the driver)
    or a retime (kind "retime")."""

    kind: str
    """"retime"; a sweep run has no kind."""
    started_utc: str
    seconds: float
    jobs_planned: list[str]
    jobs_done: list[str]
    jobs_failed: dict[str, str]
    """Job name -> error."""
    interrupted: bool
    threads: int
    """A retime's thread count."""
    machine: MachineInfo
    """The machine a retime measured on."""
    jobs_retimed: list[str]


class SweepFile(TypedDict):
    """OUT/sweep.json (`read_sweep`): the configuration and every run. The driver and `--retime` add runs to the
    JSON object as read, so a file written by another version keeps every key."""

    config: dict[str, Any]
    """`SweepConfig.to_dict` without "force", with the rates of every run and the data's "num_frames"."""
    runs: list[RunEntry]


def read_sweep(out: str | Path) -> SweepFile:
    """OUT/sweep.json: the sweep's configuration and its runs; UserError if there is none."""
    path = Path(out) / SWEEP_FILE
    try:
        data = parse_json(path.read_text("utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: not found; {out} holds no sweep (run `fcnpose-tf sweep --out {out}` first)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({os_error_reason(exc)})") from None
    except ValueError as exc:  # not UTF-8, not JSON, nested too deep
        raise UserError(f"{path}: not a sweep file ({str(exc).splitlines()[0]})") from None
    config = data.get("config") if isinstance(data, dict) else None
    if not isinstance(config, dict) or not isinstance(config.get("rates"), list):
        raise UserError(f"{path}: not a sweep file (it has no configuration with a list of rates)")
    return data


def collect(out: str | Path, config: dict[str, Any]) -> SweepResults:
    """Every job record in OUT/jobs made with `config`'s result-affecting settings.

    Records of another configuration (a sweep redone with --force and other settings) are
    listed in `ignored`, not mixed in.
    """
    from fcnpose_tf.sweep.jobs import KEY_DEFAULTS, KEY_FIELDS, record_matches

    key = {name: config.get(name, KEY_DEFAULTS.get(name)) for name in KEY_FIELDS}
    by_rate = config.get("retrain_epochs_by_rate", ())
    results = SweepResults(config)
    for path in sorted((Path(out) / JOBS_DIR).glob("*.json")):
        record = read_record(path)
        if record is None or not record_matches(record, key, by_rate):
            results.ignored.append(path.name)
            continue
        fold = int(record["fold"])
        if record["kind"] == "base":
            results.bases[fold] = record
        else:
            results.rates.setdefault(float(record["rate"]), {})[fold] = record
    return results


def _metric(record: JobRecord | None, section: str, key: str) -> Any:
    if record is None or section not in record or record[section] is None:
        return None
    return record[section].get("metrics", {}).get(key)


def _timing(record: JobRecord | None, section: str, key: str) -> Any:
    if record is None or not (record.get(section) or {}).get("timing"):
        return None
    value = record[section]["timing"].get(key)
    return value.get("mean") if isinstance(value, dict) else value


def _value(record: JobRecord | None, section: str, key: str) -> Any:
    if record is None or not record.get(section):
        return None
    return record[section].get(key)


def _over(records: Iterable[JobRecord], getter, section: str, key: str) -> Stat:
    return stat(getter(r, section, key) for r in records)


def _mb(value: float | None) -> float | None:
    return None if value is None else value / 1e6


def _millions(value: float | None) -> float | None:
    return None if value is None else value / 1e6


# ------------------------------------------------------------------------------------------
# The four tables
# ------------------------------------------------------------------------------------------

PCK_COLUMNS = [Column("PCK@0.5", "pck@0.5_bbox", ".3f"), Column("PCK@0.2", "pck@0.2_bbox", ".3f"),
               Column("PCK@0.05", "pck@0.05_bbox", ".3f"), Column("EPE px", "epe_px", ".2f")]


def folds_table(results: SweepResults) -> Table:
    """The paper's "5-Folds Desktop": the unpruned model of every fold, then mean and std."""
    columns = [Column("fold", "fold", align="left"), Column("val frames", "val_frames", ",d"), *PCK_COLUMNS,
               Column("inference ms", "inference_ms", ".2f"), Column("FPS", "fps", ".1f"),
               Column("FPS (inference only)", "fps_inference_only", ".1f"), Column("epochs", "epochs_run", ",d"),
               Column("train min", "train_minutes", ".1f")]
    table = Table("folds", 'Per fold: the unpruned model (Keras) — the paper\'s "5-Folds Desktop"',
                  "Each fold's base model on that fold's validation frames.", columns)
    numeric: list[list[Any]] = []
    for fold in sorted(results.bases):
        rec = results.bases[fold]
        seconds = (rec.get("training") or {}).get("seconds")
        values = [_metric(rec, "keras", k) for k in (*PCK_KEYS, "epe_px")] + [
            _timing(rec, "keras", "inference_ms"), _timing(rec, "keras", "fps"),
            _timing(rec, "keras", "fps_inference_only"), (rec.get("training") or {}).get("epochs_run"),
            None if seconds is None else seconds / 60]
        numeric.append(values)
        table.rows.append([str(fold), rec.get("eval_frames")] + values)
    if len(numeric) >= 2:
        stats = [stat(col) for col in zip(*numeric)]
        table.rows.append(["mean", None] + [s.mean for s in stats])
        table.rows.append(["std", None] + [s.std for s in stats])
    return table


def pruning_table(results: SweepResults) -> Table:
    """The paper's "Pruning Results" (Keras, after retraining), with PCK@0.2/0.05, EPE and PCK before retraining."""
    columns = [Column("rate", "rate", align="left", rate=True), Column("folds", "folds", "d"),
               Column("params", "params", ",d"),
               *PCK_COLUMNS, Column("PCK@0.5 before retraining", "pck@0.5_bbox_before_retraining", ".3f"),
               Column("inference ms", "inference_ms", ".2f"), Column("FPS", "fps", ".1f"),
               Column("speed-up", "speedup", ".2f")]
    table = Table("pruning", 'Pruning results, Keras — the paper\'s "Pruning Results"',
                  "Pruned, retrained models (tf_keras, direct call) on each fold's validation frames; the full row is "
                  "the unpruned base models. Speed-up: FPS relative to the full row.", columns)
    bases = list(results.bases.values())
    full_fps = _over(bases, _timing, "keras", "fps").mean
    if bases:
        table.rows.append(_keras_row(0.0, bases, None, full_fps))
    for rate in sorted(r for r in results.rates if r > 0):
        recs = list(results.rates[rate].values())
        table.rows.append(_keras_row(rate, recs, _over(
            recs, _metric, "pruned_before_retraining", "pck@0.5_bbox"), full_fps))
    return table


def _keras_row(rate: float, recs: list[JobRecord], before: Stat | None, full_fps: float | None) -> list[Any]:
    fps = _over(recs, _timing, "keras", "fps")
    return [rate, len(recs), _over(recs, _value, "keras", "params").mean,
            *[_over(recs, _metric, "keras", k) for k in (*PCK_KEYS, "epe_px")], before,
            _over(recs, _timing, "keras", "inference_ms"), fps,
            None if not full_fps or fps.mean is None else fps.mean / full_fps]


def requirements_table(results: SweepResults) -> Table:
    """The paper's "Requirements": FPS, FLOPs (with MACs), size and parameters per rate (Keras)."""
    columns = [Column("rate", "rate", align="left", rate=True), Column("FPS", "fps", ".1f"),
               Column("MMACs", "macs_millions", ".1f"),
               Column("MFLOPs", "flops_millions", ".1f"), Column("size MB (.h5)", "h5_size_mb", ".3f"),
               Column("size MB (.keras)", "keras_size_mb", ".3f"), Column("params", "params", ",d"),
               Column("params vs full", "params_fraction", ".1%")]
    table = Table("requirements", 'Requirements per rate, Keras — the paper\'s "Requirements"',
                  "MACs: multiply-accumulates of all convolutions for one frame; FLOPs = 2 x MACs (the paper's "
                  "\"Flops\" column is not this quantity: its values are close to the parameter count). Sizes: the "
                  "file as written, without optimizer state.", columns)
    bases = list(results.bases.values())
    full_params = _over(bases, _value, "keras", "params").mean
    groups = ([(0.0, bases)] if bases else []) + [
        (r, list(results.rates[r].values())) for r in sorted(results.rates) if r > 0]
    for label, recs in groups:
        params = _over(recs, _value, "keras", "params").mean
        table.rows.append([label, _over(recs, _timing, "keras", "fps").mean,
                           _millions(_over(recs, _value, "keras", "macs").mean),
                           _millions(_over(recs, _value, "keras", "flops").mean),
                           _mb(_over(recs, _value, "keras", "h5_size_bytes").mean),
                           _mb(_over(recs, _value, "keras", "keras_size_bytes").mean), params,
                           None if not full_params or params is None else params / full_params])
    return table


def quantization_table(results: SweepResults) -> Table:
    """The paper's "Pruning and Quantization": the TFLite models (LiteRT) per rate, one row per format
    (the paper's float16, then full-integer int8 when the jobs wrote it)."""
    columns = [Column("rate", "rate", align="left", rate=True), Column("format", "quantize", align="left"),
               Column("folds", "folds", "d"), *PCK_COLUMNS,
               Column("ΔPCK@0.5 vs Keras", "pck@0.5_bbox_delta_vs_keras", "+.3f"),
               Column("inference ms", "inference_ms", ".2f"), Column("FPS", "fps", ".1f"),
               Column("size MB (.tflite)", "tflite_size_mb", ".3f"), Column("params", "params", ",d")]
    table = Table("quantization", 'Pruning and quantization, TFLite — the paper\'s "Pruning and Quantization"',
                  "Each retrained model exported to TFLite, float16 (the paper's) and full-integer int8 (calibrated on "
                  "the fold's training frames), each verified against Keras before it is written, and run by the "
                  "LiteRT interpreter on the same frames; ΔPCK: TFLite minus Keras, per fold. The full row appears "
                  "when the sweep includes rate 0 (`--rates full,...`).", columns)
    for rate in sorted(results.rates):
        recs = list(results.rates[rate].values())
        sections = list(dict.fromkeys(s for r in recs for s in tflite_sections(r)))
        for section in sections:
            delta = stat(None if _metric(r, section, "pck@0.5_bbox") is None or _metric(r, "keras", "pck@0.5_bbox")
                         is None else _metric(r, section, "pck@0.5_bbox") - _metric(r, "keras", "pck@0.5_bbox")
                         for r in recs)
            formats = {(r.get(section) or {}).get("quantize") for r in recs} - {None}
            table.rows.append([rate, "/".join(sorted(formats)) or "float16",
                               sum(1 for r in recs if r.get(section)),
                               *[_over(recs, _metric, section, k) for k in (*PCK_KEYS, "epe_px")],
                               delta, _over(recs, _timing, section, "inference_ms"), _over(recs, _timing, section, "fps"),
                               _mb(_over(recs, _value, section, "tflite_size_bytes").mean),
                               _over(recs, _value, section, "params").mean])
    return table


def build_tables(results: SweepResults) -> dict[str, Table]:
    """The four tables, keyed by TABLE_NAMES."""
    return {"folds": folds_table(results), "pruning": pruning_table(results),
            "requirements": requirements_table(results), "quantization": quantization_table(results)}


# ------------------------------------------------------------------------------------------
# The plot
# ------------------------------------------------------------------------------------------

def _series(results: SweepResults, section: str) -> list[tuple[str, Stat, Stat]]:
    """(label, FPS, PCK@0.5) per rate for "keras" (full = the bases) or "tflite"."""
    points = []
    if section == "keras" and results.bases:
        bases = list(results.bases.values())
        points.append(("full", _over(bases, _timing, "keras", "fps"), _over(bases, _metric, "keras", "pck@0.5_bbox")))
    for rate in sorted(results.rates):
        if section == "keras" and rate == 0:
            continue
        recs = list(results.rates[rate].values())
        points.append((rate_label(rate), _over(recs, _timing, section, "fps"),
                       _over(recs, _metric, section, "pck@0.5_bbox")))
    return [p for p in points if p[1].mean is not None and p[2].mean is not None]


def plot_pck_vs_fps(results: SweepResults, path: str | Path, subtitle: str = "") -> Path:
    """PCK@0.5 against FPS for the Keras and float16 TFLite models, one labelled point per rate.

    Error bars are the std over folds of both quantities; the FPS axis turns logarithmic when
    the fastest point is more than 8x the slowest. Written atomically as a PNG.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig, ax = plt.subplots(figsize=(8, 5.2), dpi=120)
    styles = {"keras": ("Keras (tf_keras)", "tab:blue", "o"), "tflite": ("float16 TFLite (LiteRT)", "tab:orange", "s")}
    labels: list[tuple[str, float, float, str, int]] = []
    for section, (name, color, marker) in styles.items():
        points = _series(results, section)
        if not points:
            continue
        xs = [p[1].mean for p in points]
        ys = [p[2].mean for p in points]
        ax.errorbar(xs, ys, xerr=[p[1].std if p[1].n > 1 else 0 for p in points],
                    yerr=[p[2].std if p[2].n > 1 else 0 for p in points], color=color, marker=marker,
                    markersize=6, linewidth=1.2, elinewidth=0.8, capsize=2, label=name)
        labels += [(p[0], x, y, color, 1 if section == "keras" else -1) for p, x, y in zip(points, xs, ys)]
    fps = [x for _, x, _, _, _ in labels]
    log_x = bool(fps) and min(fps) > 0 and max(fps) / min(fps) > 8
    if log_x:  # Keras and TFLite, unpruned and 90%: an order of magnitude apart
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 3.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
    else:
        ax.set_xlim(left=0)
    ax.set_xlabel("FPS = 1 / (preprocess + inference + post-processing)" + (", log scale" if log_x else ""))
    ax.set_ylabel("PCK@0.5 (normalised by max(bbox w, h))")
    ax.set_ylim(-0.03, 1.05)
    ax.grid(alpha=0.3)
    ax.set_title("FCN-Pose: PCK@0.5 vs FPS per pruning rate (mean ± std over folds)", fontsize=11)
    if subtitle:
        fig.text(0.5, 0.01, subtitle, ha="center", va="bottom", fontsize=8, color="dimgray")
    fig.tight_layout(rect=(0, 0.04 if subtitle else 0, 1, 1))
    _place_labels(fig, ax, labels)
    if labels:
        ax.legend(loc="best", framealpha=0.9)
    else:
        ax.text(0.5, 0.5, "no finished jobs yet", transform=ax.transAxes, ha="center", color="dimgray")
    path = Path(path)
    with atomic_path(path, force=True) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return path


def _place_labels(fig: Any, ax: Any, labels: list[tuple[str, float, float, str, int]], fontsize: float = 8) -> None:
    """Annotate each point with its rate where the text overlaps no other label and no marker (greedy)."""
    fig.canvas.draw()  # fixes the limits, so data -> display coordinates are final
    scale = fig.dpi / 72.0  # display pixels per point
    centres = [ax.transData.transform((x, y)) for _, x, y, _, _ in labels]
    taken = [(cx - 4 * scale, cy - 4 * scale, cx + 4 * scale, cy + 4 * scale) for cx, cy in centres]

    frame = ax.get_window_extent()

    def free(box: tuple[float, float, float, float]) -> bool:
        inside = frame.x0 <= box[0] and box[2] <= frame.x1 and frame.y0 <= box[1] and box[3] <= frame.y1
        return inside and all(box[2] <= o[0] or box[0] >= o[2] or box[3] <= o[1] or box[1] >= o[3] for o in taken)

    renderer = fig.canvas.get_renderer()

    def size(text: str) -> tuple[float, float]:  # the label's real extent in points, with 1.5 pt to spare
        probe = ax.text(0, 0, text, fontsize=fontsize)
        box = probe.get_window_extent(renderer)
        probe.remove()
        return box.width / scale + 1.5, box.height / scale

    for (text, x, y, color, side), (cx, cy) in zip(labels, centres):
        w, h = size(text)
        options = [(5, 5), (5, -5 - h), (-5 - w, 5), (-5 - w, -5 - h), (5, 15), (5, -15 - h), (-5 - w, 15),
                   (-5 - w, -15 - h), (5, 25), (5, -25 - h)]
        if side < 0:  # TFLite labels prefer below their points, Keras above
            options = [(dx, -dy - h) for dx, dy in options]
        chosen = options[0]
        for dx, dy in options:
            box = (cx + dx * scale, cy + dy * scale, cx + (dx + w) * scale, cy + (dy + h) * scale)
            if free(box):
                chosen = (dx, dy)
                break
        dx, dy = chosen
        taken.append((cx + dx * scale, cy + dy * scale, cx + (dx + w) * scale, cy + (dy + h) * scale))
        ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize, color=color,
                    va="bottom", ha="left")


# ------------------------------------------------------------------------------------------
# Writing everything
# ------------------------------------------------------------------------------------------

DEFINITIONS = """\
- **PCK@α (bbox)**: a keypoint is correct when its distance to the ground truth, divided by max(w, h) of the
  ground-truth keypoints' bounding box, is below α; missing predictions count as wrong; mean over keypoints.
- **EPE**: mean Euclidean error in pixels of the original frame (found keypoints only).
- **Inference ms**: the model's forward pass for one frame (Keras: direct call; TFLite: `invoke`), after warm-up,
  mean over at least 50 frames; the ± is the std of the per-fold means.
- **FPS** = 1 / (preprocess + inference + post-processing), mean over folds (the inference-only rate is in the
  CSV/JSON of the folds table and in results.json).
- **Mean ± std** over folds; std is the population std (ddof = 0). A value without ± comes from one fold.
- **MACs**: multiply-accumulates of all convolutions for one frame; FLOPs = 2 × MACs.
"""


def _subtitle(results: SweepResults, machine: MachineInfo) -> str:
    cfg = results.config
    return (f"{len(results.bases)} of {cfg['folds']} folds, input {cfg['input_size']}x{cfg['input_size']}, "
            f"{cfg['threads']} thread(s), {machine.get('cpu_model', 'unknown CPU')}")


def _hosts(records: list[JobRecord]) -> list[dict[str, Any]]:
    seen: dict[tuple, dict[str, Any]] = {}
    for rec in records:
        m = rec.get("machine") or {}
        key = (m.get("hostname"), m.get("cpu_model"))
        entry = seen.setdefault(key, {"hostname": key[0], "cpu_model": key[1], "cpu_cores": m.get("cpu_cores"),
                                      "jobs": 0})
        entry["jobs"] += 1
    return list(seen.values())


class RetimeHost(TypedDict):
    """A machine `--retime` measured on, and how many jobs (`TimingSource`)."""

    hostname: str | None
    cpu_model: str | None
    cpu_cores: int | None
    threads: int | None
    jobs: int


class TimingSource(TypedDict):
    """Where a sweep's timings come from (results.json's "timing_source", `timing_source`)."""

    jobs: int
    retimed_jobs: int
    """Jobs whose timings `--retime` replaced."""
    retimed_utc: list[str]
    """When, one entry per retime."""
    retimed_on: list[RetimeHost]


def timing_source(records: list[JobRecord]) -> TimingSource:
    """Where the timings come from: the jobs themselves, or `--retime` (when, on which hosts, how many jobs)."""
    retimed = [r["retimed"] for r in records if isinstance(r.get("retimed"), dict)]
    hosts: dict[tuple, RetimeHost] = {}
    for entry in retimed:
        m = entry.get("machine") or {}
        host = hosts.setdefault((m.get("hostname"), m.get("cpu_model")), {
            "hostname": m.get("hostname"), "cpu_model": m.get("cpu_model"), "cpu_cores": m.get("cpu_cores"),
            "threads": m.get("threads"), "jobs": 0})
        host["jobs"] += 1
    return {"jobs": len(records), "retimed_jobs": len(retimed), "retimed_utc": sorted({e.get("utc") for e in retimed}),
            "retimed_on": list(hosts.values())}


def _timing_line(source: TimingSource) -> str:
    if not source["retimed_jobs"]:
        return ("- **Timing**: measured by each job right after it ran, on the machine and with the load it ran "
                "with; `fcnpose-tf sweep --out OUT --retime` re-measures every job on one idle machine")
    hosts = "; ".join(f"{h['hostname']} ({h['cpu_model']}, {h['cpu_cores']} cores)" for h in source["retimed_on"])
    when = ", ".join(source["retimed_utc"])
    which = ("every job" if source["retimed_jobs"] == source["jobs"] else
             f"{source['retimed_jobs']} of {source['jobs']} jobs (the others as measured by their jobs)")
    return (f"- **Timing**: re-measured with `--retime` for {which}, sequentially, on {hosts} at {when}; "
            "the keypoint metrics of every re-measurement were identical to the jobs'")


def _importance(cfg: dict[str, Any]) -> str:
    """The sweep's filter criterion in words (folders from before criteria were selectable used the L1 norm)."""
    name = cfg.get("importance") or "l1"
    words = {"l1": "L1 norm", "l2": "L2 norm", "activation": "mean activation", "taylor": "first-order Taylor"}
    frames = f" on {cfg.get('importance_frames')} training frames" if name in ("activation", "taylor") else ""
    return f"{words.get(name, name)}{frames}"


def _widths(cfg: dict[str, Any]) -> str:
    """How the sweep's rates set each layer's width, in words (folders from before --min-filters: the keep rule)."""
    rule = "n - floor(n·rate) filters per layer"
    floor = cfg.get("min_filters") or 0
    if floor <= 1:
        return f"keeping {rule}"
    return (f"with no layer under {floor} filters (lowered where that does not fit), the others narrower, within the "
            f"parameters of {rule}")


def _epochs(n: int) -> str:
    return f"{n} epoch" + ("" if n == 1 else "s")


def summary_markdown(results: SweepResults, tables: dict[str, Table], machine: MachineInfo,
                     versions: dict[str, Any], runs: list[RunEntry]) -> str:
    """OUT/summary.md: a header with the configuration, the plot, every table, the definitions."""
    cfg = results.config
    missing = results.missing()
    compute = sum(float(r.get("seconds") or 0) for r in results.records)
    sweep_runs = [r for r in runs if r.get("kind") != "retime"]
    wall = sum(float(r.get("seconds") or 0) for r in sweep_runs)
    lines = [
        "# FCN-Pose pruning sweep", "",
        f"- **Data**: `{cfg['data']}` ({cfg.get('num_frames', '?')} frames), {cfg['folds']}-fold cross-validation "
        f"(split seed {cfg['split_seed']}), {cfg['augment_copies']} augmented copies per training frame",
        f"- **Training**: input {cfg['input_size']}x{cfg['input_size']}, base models up to {_epochs(cfg['epochs'])} "
        f"(patience {cfg['patience']}), retraining up to "
        f"{describe_per_rate(cfg['retrain_epochs'], cfg.get('retrain_epochs_by_rate', ()))} (patience "
        f"{cfg['retrain_patience']}), batch {cfg['batch_size']}, Adam {cfg['learning_rate']:g}"
        + (f" halved after {_epochs(cfg['lr_patience'])} without a better validation loss (floor 1e-5)"
           if cfg.get("lr_patience") else "") + ", "
        + ("binary cross-entropy" if cfg["positive_weight"] == 1 else
           f"binary cross-entropy with keypoint pixels weighted {cfg['positive_weight']:g}")
        + (f", retraining distilled from the base model's maps (teacher weight {cfg['distill']:g})"
           if cfg.get("distill") else "") + f", seed {cfg['seed']}",
        f"- **Rates**: {', '.join(rate_label(r) for r in cfg['rates'])}; filter pruning {_widths(cfg)} ranked by "
        f"{_importance(cfg)} (output layer untouched), float16 TFLite",
        f"- **Machine**: {machine.get('cpu_model')}, {machine.get('cpu_cores')} cores; timing on {cfg['threads']} "
        f"thread(s) per job" + (f"; jobs ran on {len(_hosts(results.records))} hosts"
                                if len(_hosts(results.records)) > 1 else ""),
        f"- **Software**: fcnpose-tf {versions.get('fcnpose_tf')}, TensorFlow {versions.get('tensorflow')}, "
        f"tf_keras {versions.get('tf_keras')}, LiteRT {versions.get('ai_edge_litert')}, numpy {versions.get('numpy')}, "
        f"OpenCV {versions.get('opencv')}",
        f"- **Jobs**: {len(results.records)} finished"
        + (f", {len(missing)} missing ({', '.join(missing[:8])}{', ...' if len(missing) > 8 else ''}): rerun the "
           "sweep to finish them" if missing else " (complete)")
        + f"; {compute / 60:.1f} min of job time" + (f", {wall / 60:.1f} min wall-clock over {len(sweep_runs)} "
                                                     "run(s)" if wall else ""),
        _timing_line(timing_source(results.records)),
        "", f"![PCK@0.5 vs FPS]({PLOT_FILE})", ""]
    for name in TABLE_NAMES:
        table = tables[name]
        lines += [f"## {table.title}", "", table.caption, "", table.markdown() if table.rows else "_no finished jobs_",
                  ""]
    lines += ["## Definitions", "", DEFINITIONS]
    return "\n".join(lines)


@dataclass(frozen=True)
class SweepReport:
    """What `write_report` rebuilt: the job records it read, the tables and the files it wrote."""

    results: SweepResults
    tables: dict[str, Table]
    """By TABLE_NAMES."""
    files: list[Path]


def write_report(out: str | Path, *, machine: MachineInfo | None = None,
                 versions: dict[str, Any] | None = None) -> SweepReport:
    """Rebuild every table, the plot, summary.md and results.json of OUT from its job records.

    Args:
        out: the results folder.
        machine: the machine the report names (default: this one, `records.machine_info`).
        versions: the library versions it names (default: this process's, `records.library_versions`).
    Returns:
        The records read, the tables and the files written.
    Raises:
        UserError: OUT holds no sweep.json.
    """
    out = Path(out)
    sweep = read_sweep(out)
    results = collect(out, sweep["config"])
    tables = build_tables(results)
    machine = machine or machine_info(sweep["config"].get("threads"))
    versions = versions or library_versions()
    files: list[Path] = []
    for name, table in tables.items():
        files.append(write_text(out / "tables" / f"{name}.md",
                                f"### {table.title}\n\n{table.caption}\n\n{table.markdown()}\n", force=True))
        files.append(write_text(out / "tables" / f"{name}.csv", table.csv(), force=True))
    files.append(plot_pck_vs_fps(results, out / PLOT_FILE, _subtitle(results, machine)))
    runs = sweep.get("runs", [])
    files.append(write_text(out / "summary.md", summary_markdown(results, tables, machine, versions, runs),
                            force=True))
    document = {
        "record_version": RECORD_VERSION,
        "generated_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config": sweep["config"],
        "runs": runs,
        "machine": machine,
        "job_hosts": _hosts(results.records),
        "threads": sweep["config"].get("threads"),
        "versions": versions,
        "complete": not results.missing(),
        "missing_jobs": results.missing(),
        "ignored_job_files": results.ignored,
        "job_seconds_total": round(sum(float(r.get("seconds") or 0) for r in results.records), 1),
        "timing_source": timing_source(results.records),
        "tables": {name: {"title": t.title, "caption": t.caption, "rows": t.records()} for name, t in tables.items()},
        "jobs": results.records,
    }
    files.append(write_json(out / "results.json", document, force=True))
    return SweepReport(results, tables, files)


def new_run_entry(executor: ExecutorInfo, jobs_run: Sequence[Job]) -> RunEntry:
    """A fresh entry for sweep.json's "runs" (completed by the driver)."""
    return {"started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"), **executor,
            "jobs_planned": [j.name for j in jobs_run]}
