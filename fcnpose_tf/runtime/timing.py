"""Latency bookkeeping shared by `run` and `bench`: per-stage logs, summaries, the FPS definition.

FPS (docs/runtime.md, timing) = 1000 / mean end-to-end milliseconds,
where end-to-end = preprocess + invoke + postprocess of one frame; the
invoke-only rate (1000 / mean invoke ms) is reported next to it. Capture,
drawing and writing are not part of either; `run` reports the wall-clock loop
rate separately.
"""

from __future__ import annotations

from array import array
from typing import Iterable, Sequence

import numpy as np

from fcnpose_tf.runtime.estimator import StageTimes
from fcnpose_tf.tables import format_table

STAGES: tuple[str, ...] = ("preprocess", "invoke", "postprocess", "end_to_end")

FPS_DEFINITION = "FPS = 1000 / mean(preprocess + invoke + postprocess ms); invoke-only FPS = 1000 / mean(invoke ms)"


def describe_ms(values: Sequence[float] | np.ndarray) -> dict[str, float]:
    """mean, std, median, p95, min, max of millisecond samples.

    The one summary of per-frame times (`run`, `bench`, `evaluate`, `compress`, the sweep).
    std is the sample standard deviation (ddof=1; 0 for a single sample), as docs/runtime.md
    defines it.

    Args:
        values: per-frame times in milliseconds.
    Returns:
        {"mean", "std", "median", "p95", "min", "max"}; NaN each for no samples.
    """
    arr = np.asarray(values, np.float64)
    if arr.size == 0:
        return {k: float("nan") for k in ("mean", "std", "median", "p95", "min", "max")}
    return {"mean": float(arr.mean()), "std": float(arr.std(ddof=1)) if arr.size > 1 else 0.0,
            "median": float(np.median(arr)), "p95": float(np.percentile(arr, 95)),
            "min": float(arr.min()), "max": float(arr.max())}


def fps_from_ms(ms: float) -> float:
    """Frames per second for a per-frame time in milliseconds.

    Args:
        ms: the time per frame.
    Returns:
        1000 / ms; NaN if not positive.
    """
    return 1e3 / ms if ms and ms > 0 else float("nan")


class LatencyLog:
    """Per-frame stage times, kept compactly (8 bytes per stage per frame).

    Args:
        times: frames' stage times to start with.
    """

    def __init__(self, times: Iterable[StageTimes] = ()):
        self._stages = {s: array("d") for s in STAGES[:3]}
        for t in times:
            self.add(t)

    def add(self, times: StageTimes) -> None:
        """Append one frame's stage times.

        Args:
            times: the frame's preprocess, invoke and postprocess times.
        """
        self._stages["preprocess"].append(times.preprocess_ms)
        self._stages["invoke"].append(times.invoke_ms)
        self._stages["postprocess"].append(times.postprocess_ms)

    def __len__(self) -> int:
        return len(self._stages["invoke"])

    def values(self, stage: str) -> np.ndarray:
        """Milliseconds of one stage per frame.

        Args:
            stage: preprocess, invoke, postprocess, or end_to_end (the sum of the three).
        Returns:
            One float64 per frame, in order (a copy).
        Raises:
            KeyError: another stage name.
        """
        if stage == "end_to_end":
            return sum(np.frombuffer(a, np.float64) for a in self._stages.values()) \
                if len(self) else np.empty(0)
        return np.frombuffer(self._stages[stage], np.float64).copy()

    def summary(self) -> dict[str, dict[str, float]]:
        """Every stage's statistics.

        Returns:
            Stage (STAGES, end_to_end last) -> `describe_ms` of its milliseconds.
        """
        return {s: describe_ms(self.values(s)) for s in STAGES}

    def fps(self) -> dict[str, float]:
        """The frame rates by the definition above (1000 / mean ms).

        Returns:
            {"end_to_end": ..., "invoke": ...}; NaN without frames.
        """
        s = self.summary()
        return {"end_to_end": fps_from_ms(s["end_to_end"]["mean"]), "invoke": fps_from_ms(s["invoke"]["mean"])}

    def table(self) -> str:
        """The per-stage latency table (mean, std, p50, p95 in ms) with the share of each stage in the end-to-end
        time.

        Returns:
            The table's text.
        """
        s = self.summary()
        total = s["end_to_end"]["mean"]
        rows = []
        for stage in STAGES:
            d = s[stage]
            share = 100.0 * d["mean"] / total if total > 0 else None
            rows.append((stage.replace("_", "-"), d["mean"], d["std"], d["median"], d["p95"], share))
        return format_table(["Stage", "Mean (ms)", "Std (ms)", "p50 (ms)", "p95 (ms)", "Share (%)"],
                            [tuple(_r(v) for v in row) for row in rows])


def _r(value):
    return round(value, 2) if isinstance(value, float) else value
