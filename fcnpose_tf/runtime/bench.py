"""Benchmark a .tflite FCN-Pose model: invoke-only and end-to-end latency and FPS per thread count.

For each thread count a fresh interpreter is warmed up, then every timed
iteration runs one full frame (preprocess + invoke + postprocess, timed per
stage) followed by one extra invoke on the same input (the invoke-only
figure). Interleaving the two keeps them under the same machine load, which
matters on a shared or thermally throttled CPU. Figures are medians, p95,
mean and std over the timed iterations; FPS follows timing.FPS_DEFINITION.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.preprocess import FrameView, read_image
from fcnpose_tf.progress import SILENT, Reporter
from fcnpose_tf.records import HostInfo, host_info
from fcnpose_tf.runtime.estimator import KeypointModel
from fcnpose_tf.runtime.interpreter import check_tflite_file, default_num_threads
from fcnpose_tf.runtime.timing import FPS_DEFINITION, LatencyLog, describe_ms, fps_from_ms
from fcnpose_tf.system import oversubscription_note
from fcnpose_tf.tables import format_table

MIN_FRAMES_FOR_STATS = 50
"""Mean and std over at least this many frames (docs/runtime.md, how FPS is defined)."""


def synthetic_frame(width: int = 640, height: int = 480, seed: int = 0) -> np.ndarray:
    """A deterministic BGR test frame (gradient, noise and a drawn arm-like chain) of the given size.

    Args:
        width, height: the frame's size in pixels.
        seed: seed of the noise.
    Returns:
        height x width x 3 uint8.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    base = 60 + 80 * (x / max(width - 1, 1)) + 40 * (y / max(height - 1, 1))
    img = np.stack([base, base * 0.9, base * 0.8], axis=-1) + rng.normal(0, 8, (height, width, 3))
    img = np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8))
    pts = np.array([[0.5, 0.9], [0.5, 0.75], [0.62, 0.5], [0.75, 0.32], [0.8, 0.28], [0.84, 0.3],
                    [0.86, 0.36], [0.88, 0.42]]) * [width, height]
    pts = pts.round().astype(np.int32)
    thick = max(2, round(min(width, height) / 30))
    cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, (200, 200, 210), thick, cv2.LINE_AA)
    for p in pts:
        cv2.circle(img, (int(p[0]), int(p[1])), thick, (40, 40, 200), -1, cv2.LINE_AA)
    return img


def default_thread_counts(cores: int | None = None) -> tuple[int, ...]:
    """1, 2, 4, ... up to the number of cores, and the core count itself (1, 2, 4 on a Raspberry Pi).

    Args:
        cores: the core count (default: the cores this process may use).
    Returns:
        The thread counts, increasing.
    """
    cores = cores or default_num_threads()
    counts = [n for n in (1, 2, 4, 8, 16, 32, 64) if n <= cores]
    if cores not in counts:
        counts.append(cores)
    return tuple(counts)


@dataclass
class ThreadResult:
    """Latencies (ms) and FPS at one thread count."""

    threads: int
    status: str
    invoke: dict[str, float] = field(default_factory=dict)
    preprocess: dict[str, float] = field(default_factory=dict)
    postprocess: dict[str, float] = field(default_factory=dict)
    end_to_end: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Whether this thread count ran (status "ok")."""
        return self.status == "ok"

    @property
    def fps_end_to_end(self) -> float:
        """1000 / the end-to-end mean ms (NaN when not measured)."""
        return fps_from_ms(self.end_to_end.get("mean", float("nan")))

    @property
    def fps_invoke(self) -> float:
        """1000 / the invoke-only mean ms (NaN when not measured)."""
        return fps_from_ms(self.invoke.get("mean", float("nan")))

    @property
    def pre_post_share_percent(self) -> float:
        """Preprocess + postprocess as a share of the end-to-end mean (docs/runtime.md's <= 15% target)."""
        total = self.end_to_end.get("mean", float("nan"))
        if not total or not np.isfinite(total):
            return float("nan")
        return 100.0 * (self.preprocess["mean"] + self.postprocess["mean"]) / total

    def to_dict(self) -> dict[str, Any]:
        """The row as the bench report's JSON holds it (stable keys, units in the names; NaN written as null).

        Returns:
            The row's keys in order.
        """
        def clean(d):
            return {k: (round(v, 4) if np.isfinite(v) else None) for k, v in d.items()}

        def num(v):
            return round(float(v), 3) if np.isfinite(v) else None

        return {"threads": self.threads, "status": self.status,
                "invoke_latency_ms": clean(self.invoke), "preprocess_latency_ms": clean(self.preprocess),
                "postprocess_latency_ms": clean(self.postprocess), "end_to_end_latency_ms": clean(self.end_to_end),
                "fps_end_to_end": num(self.fps_end_to_end), "fps_invoke": num(self.fps_invoke),
                "pre_post_share_percent": num(self.pre_post_share_percent)}


@dataclass
class BenchReport:
    """A benchmark of one model over several thread counts, printable as a table and serialisable as JSON."""

    model: str
    size_bytes: int
    params: int | None
    macs: int | None
    weight_dtypes: tuple[str, ...]
    io: str
    input_shape: tuple[int, ...]
    output_shape: tuple[int, ...]
    backend: str
    backend_version: str
    frames: int
    warmup: int
    frame: str
    threshold: float
    results: list[ThreadResult] = field(default_factory=list)
    host: HostInfo | None = None
    stopped_after: int | None = None
    """A stop signal (Ctrl-C) ended the run: the thread counts asked for; `results` holds the ones that finished.
    None: every count ran."""

    def header(self) -> str:
        """The lines above the table.

        Returns:
            Model (I/O, weight types), cost (parameters, MACs, size) and run (backend, frames, host), joined.
        """
        macs = f"{self.macs / 1e6:,.1f} M" if self.macs is not None else "unknown"
        params = f"{self.params:,}" if self.params is not None else "unknown"
        weights = ", ".join(self.weight_dtypes) or "unknown"
        return "\n".join([
            f"Model:   {self.model} ({self.io}; weights {weights})",
            f"Cost:    {params} parameters; {macs} MACs per frame (FLOPs = 2 x MACs); "
            f"{self.size_bytes / 1e6:.3f} MB ({self.size_bytes:,} bytes)",
            f"Run:     {self.backend} {self.backend_version}; {self.frames} timed frames after {self.warmup} "
            f"warm-up; frame: {self.frame}; host {self.host.machine if self.host else '?'}, "
            f"{self.host.cpu_count if self.host else '?'} cores",
        ])

    def table(self, markdown: bool = False) -> str:
        """The per-thread-count table (Ultralytics-style: status, latencies, FPS).

        Args:
            markdown: a Markdown table instead of aligned text.
        Returns:
            The table's text; a failed thread count's row holds its status only.
        """
        rows = []
        for r in self.results:
            if not r.ok:
                rows.append((r.threads, r.status) + (None,) * 8)
                continue
            rows.append((r.threads, r.status,
                         round(r.invoke["median"], 2), round(r.invoke["p95"], 2),
                         round(r.end_to_end["median"], 2), round(r.end_to_end["p95"], 2),
                         f"{r.end_to_end['mean']:.2f} ± {r.end_to_end['std']:.2f}",
                         round(r.pre_post_share_percent, 1),
                         round(r.fps_end_to_end, 1), round(r.fps_invoke, 1)))
        headers = ["Threads", "Status", "Invoke p50 (ms)", "Invoke p95 (ms)", "E2E p50 (ms)", "E2E p95 (ms)",
                   "E2E mean ± std (ms)", "Pre+post (%)", "FPS", "FPS invoke"]
        return format_table(headers, rows, markdown=markdown)

    def report(self, markdown: bool = False) -> str:
        """Header, table and the definitions needed to read them.

        Args:
            markdown: the table in Markdown.
        Returns:
            The lines, joined.
        """
        cores = self.host.cpu_count if self.host else None
        notes = [f"E2E = preprocess + invoke + postprocess of one frame; {FPS_DEFINITION}."]
        over = oversubscription_note([r.threads for r in self.results], cores) if cores else None
        if over:
            notes.append(over)
        if self.frames < MIN_FRAMES_FOR_STATS:
            notes.append(f"Fewer than {MIN_FRAMES_FOR_STATS} timed frames: indicative figures only.")
        if self.stopped_after is not None:
            notes.append(f"Stopped: {len(self.results)} of {self.stopped_after} thread counts finished.")
        return "\n".join([self.header(), "", self.table(markdown), ""] + notes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with stable keys and units in the key names.

        Returns:
            The report's object.
        """
        return {"model": self.model, "size_bytes": self.size_bytes, "params": self.params, "macs": self.macs,
                "weight_dtypes": list(self.weight_dtypes), "input_shape": list(self.input_shape),
                "output_shape": list(self.output_shape), "backend": self.backend,
                "backend_version": self.backend_version, "frames": self.frames, "warmup": self.warmup,
                "frame": self.frame, "threshold": self.threshold, "fps_definition": FPS_DEFINITION,
                "host": self.host.to_json() if self.host else {}, "results": [r.to_dict() for r in self.results],
                **({"stopped_after_of": [len(self.results), self.stopped_after]} if self.stopped_after else {})}


def comparison_table(reports: list[BenchReport], markdown: bool = False) -> str:
    """Several models' benchmarks side by side (`bench A.tflite B.tflite`): per thread count and model its MACs,
    end-to-end p50 and FPS, invoke-only FPS, and its end-to-end FPS as a multiple of the first model's at that
    thread count. The models ran one after the other, not interleaved: for a speed claim, repeat in both orders.

    Args:
        reports: one benchmark per model, the first the reference.
        markdown: a Markdown table instead of aligned text.
    Returns:
        The table.
    """
    first = {r.threads: r for r in reports[0].results if r.ok}
    rows = []
    for threads in sorted({r.threads for report in reports for r in report.results}):
        for report in reports:
            r = next((r for r in report.results if r.threads == threads), None)
            if r is None or not r.ok:
                rows.append((threads, Path(report.model).name, None, None, None, None,
                             r.status if r is not None else "not run"))
                continue
            base = first.get(threads)
            ratio = f"{r.fps_end_to_end / base.fps_end_to_end:.2f}x" if base else None
            rows.append((threads, Path(report.model).name,
                         round(report.macs / 1e6, 1) if report.macs is not None else None,
                         round(r.end_to_end["median"], 2), round(r.fps_end_to_end, 1), round(r.fps_invoke, 1),
                         ratio))
    return format_table(["Threads", "Model", "MMACs", "E2E p50 (ms)", "FPS", "FPS invoke",
                         f"FPS vs {Path(reports[0].model).name}"], rows, markdown=markdown)


def crop_frame_size(model_path: str | os.PathLike, default: tuple[int, int] = (640, 480)) -> tuple[int, int]:
    """(width, height) of the frames a .tflite's crop was set on (its view in the metadata), so the synthetic frame
    is of its camera's aspect; `default` for a whole-frame model or a file whose metadata cannot be read (loading it
    says why)."""
    from fcnpose_tf.runtime.tflite_metadata import VIEW_METADATA, read_metadata

    try:
        stored = read_metadata(model_path).get(VIEW_METADATA)
        view = FrameView.from_json(json.loads(stored)) if stored is not None else None
    except (OSError, ValueError, KeyError, TypeError, RecursionError, UserError):
        return default
    return tuple(view.frame_size) if view is not None and view.frame_size is not None else default


def load_frame(path: str | os.PathLike | None, size: tuple[int, int] = (640, 480)) -> tuple[np.ndarray, str]:
    """The benchmark frame: an image file, or the synthetic frame of `size`.

    Args:
        path: an image file (None: the synthetic frame).
        size: (width, height) of the synthetic frame.
    Returns:
        (BGR frame, its description).
    Raises:
        UserError: a missing or unreadable image.
    """
    if path is None:
        return synthetic_frame(*size), f"synthetic {size[0]}x{size[1]}"
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {'a folder, not an image' if path.is_dir() else 'image not found'}")
    image = read_image(path)
    if image is None:
        raise UserError(f"{path}: cannot be read as an image")
    return np.ascontiguousarray(image), f"{path} ({image.shape[1]}x{image.shape[0]})"


def bench_threads(model: KeypointModel, frame: np.ndarray, frames: int, warmup: int) -> ThreadResult:
    """Time one loaded model: `warmup` untimed frames, then `frames` interleaved full-frame + invoke-only runs.

    Args:
        model: the model, its interpreter at the thread count to time.
        frame: the BGR frame every run processes.
        frames: timed runs.
        warmup: untimed runs first.
    Returns:
        The latencies and FPS at the model's thread count.
    """
    for _ in range(warmup):
        model.predict(frame)
    log = LatencyLog()
    invoke_ms = np.empty(frames, np.float64)
    clock = time.perf_counter
    for i in range(frames):
        log.add(model.predict(frame).times)
        t0 = clock()
        model.invoke()
        invoke_ms[i] = (clock() - t0) * 1e3
    s = log.summary()
    return ThreadResult(model.num_threads, "ok", describe_ms(invoke_ms), s["preprocess"], s["postprocess"],
                        s["end_to_end"])


def benchmark(model_path: str | os.PathLike, threads: Sequence[int] | None = None, frames: int = 200,
              warmup: int = 10, frame: np.ndarray | None = None, frame_label: str | None = None,
              backend: str = "auto", decoding: Decoding | None = None, reporter: Reporter = SILENT) -> BenchReport:
    """Benchmark a .tflite at each thread count.

    Args:
        model_path: the .tflite file.
        threads: thread counts (default: default_thread_counts()).
        frames: timed iterations per thread count (>= 50 for meaningful mean and std).
        warmup: untimed iterations first (XNNPACK packs weights and warms caches on the first runs).
        frame: the BGR frame to process (default: synthetic_frame()).
        frame_label: how the frame is described in the report.
        backend, decoding: as for KeypointModel.
        reporter: where a short line goes before each thread count (default: nowhere).
    Returns:
        A BenchReport; a thread count whose interpreter fails is reported with its error as status. A stop signal
        (Ctrl-C) after at least one count finished ends it early with those counts (`BenchReport.stopped_after`).
    Raises:
        UserError: a missing/corrupt/non-FCN-Pose model, bad counts.
        KeyboardInterrupt: a stop signal before the first count finished.
    """
    if frames < 1 or warmup < 0:
        raise UserError(f"--frames must be >= 1 and --warmup >= 0, got {frames} and {warmup}")
    counts = tuple(threads) if threads else default_thread_counts()
    if frame is None:
        frame, frame_label = synthetic_frame(), "synthetic 640x480"
    path = check_tflite_file(model_path)
    decoding = decoding if decoding is not None else Decoding()
    first = KeypointModel(path, counts[0], decoding, backend=backend)  # UserError for a bad model, before timing
    stats = first.stats()
    report = BenchReport(str(model_path), stats.size_bytes, stats.params, stats.macs, stats.weight_dtypes,
                         first.io.describe(), first.io.input.shape[1:], first.io.output.shape[1:],
                         first.backend.name, first.backend.version, frames, warmup,
                         frame_label or f"{frame.shape[1]}x{frame.shape[0]}", decoding.threshold, host=host_info())
    for n in counts:
        reporter.say(f"{n} thread{'s' if n != 1 else ''}: {warmup} warm-up + {frames} timed frames")
        try:
            if first is not None:  # counts[0]: reuse the interpreter that was checked above
                model, first = first, None
            else:
                model = KeypointModel(path, n, decoding, backend=backend)
            report.results.append(bench_threads(model, frame, frames, warmup))
        except (RuntimeError, ValueError) as exc:  # an interpreter failure at this count; keep the others
            report.results.append(ThreadResult(n, f"failed: {' '.join(str(exc).split())[:60]}"))
        except KeyboardInterrupt:  # Ctrl-C: the counts that finished are the report (a long --frames run on a Pi)
            if not report.results:
                raise
            report.stopped_after = len(counts)
            break
        model = None  # free this interpreter before creating the next
    return report
