"""What a model measured, typed: keypoint accuracy (`KeypointMetrics`), timing (`Timing`), both (`Measurement`), and
an evaluation's whole result (`Evaluation`). Standard library only (runtime/ and the Pi side may use it).

Each type's `to_json()` writes exactly the keys (and key order) of the files written before the types existed
("metrics", "timing" of NAME_train.json, NAME_pXX_report.json, a sweep job's record, `evaluate --json`), and
`from_json()` reads those files back; metric definitions in docs/training.md (evaluation) and `fcnpose_tf.metrics`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict

if TYPE_CHECKING:
    import numpy as np

__all__ = ["DEFAULT_MAX_PX", "pck_key", "auc_key", "KeypointScores", "KeypointMetrics", "StageTiming", "Timing",
           "MeasurementJson", "Measurement", "Evaluation", "TrackScores", "SequenceReport"]

DEFAULT_MAX_PX: float = 20.0
"""Upper pixel threshold of PCK-AUC (DREAM)."""


def pck_key(alpha: float) -> str:
    """Report key of PCK@alpha with bbox normalisation, e.g. ``pck@0.5_bbox``."""
    return f"pck@{float(alpha):g}_bbox"


def auc_key(max_px: float = DEFAULT_MAX_PX) -> str:
    """Report key of the pixel PCK-AUC, e.g. ``pck_auc_0-20px``."""
    return f"pck_auc_0-{float(max_px):g}px"


_PCK_KEY = re.compile(r"^pck@(.+)_bbox$")
_AUC_KEY = re.compile(r"^pck_auc_0-(.+)px$")


def _pck_values(entry: dict[str, Any]) -> dict[float, float | None]:
    """alpha -> PCK@alpha of a JSON entry's ``pck@ALPHA_bbox`` keys, in the entry's order."""
    return {float(m.group(1)): value for key, value in entry.items() if (m := _PCK_KEY.match(key))}


def _auc_value(entry: dict[str, Any]) -> tuple[float, float | None]:
    """(max_px, PCK-AUC) of a JSON entry's ``pck_auc_0-MAXpx`` key ((DEFAULT_MAX_PX, None) without one)."""
    for key, value in entry.items():
        m = _AUC_KEY.match(key)
        if m:
            return float(m.group(1)), value
    return DEFAULT_MAX_PX, None


def _accuracy_json(pck: dict[float, float | None], max_px: float, pck_auc: float | None) -> dict[str, Any]:
    """The keys every accuracy entry starts with: PCK@alpha per alpha, then the pixel AUC."""
    return {**{pck_key(alpha): value for alpha, value in pck.items()}, auc_key(max_px): pck_auc}


@dataclass(frozen=True)
class KeypointScores:
    """One keypoint's accuracy (a value of `KeypointMetrics.per_keypoint`); None where undefined."""

    pck: dict[float, float | None]
    """alpha -> PCK@alpha (bbox normalisation), in the order reported."""
    max_px: float
    """Upper pixel threshold of `pck_auc`."""
    pck_auc: float | None
    """PCK-AUC 0-max_px px."""
    epe_px: float | None
    """Mean pixel error of the predicted keypoints."""
    missing_fraction: float | None
    """Missing predictions / visible ground-truth keypoints."""
    num_gt_visible: int | None
    """Frames where the keypoint's ground truth is visible."""

    def to_json(self) -> dict[str, Any]:
        """The entry as a report's "per_keypoint" holds it."""
        return {**_accuracy_json(self.pck, self.max_px, self.pck_auc), "epe_px": self.epe_px,
                "missing_fraction": self.missing_fraction, "num_gt_visible": self.num_gt_visible}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> KeypointScores:
        """The scores of a parsed "per_keypoint" entry (a key it lacks reads as None)."""
        max_px, auc = _auc_value(entry)
        return cls(pck=_pck_values(entry), max_px=max_px, pck_auc=auc, epe_px=entry.get("epe_px"),
                   missing_fraction=entry.get("missing_fraction"), num_gt_visible=entry.get("num_gt_visible"))


@dataclass(frozen=True)
class KeypointMetrics:
    """Every keypoint metric of N frames (`metrics.keypoint_report`): the overall values and each keypoint's.

    PCK (bbox) is the mean over keypoints of each keypoint's; PCK-AUC, EPE and missing_fraction are pooled over every
    keypoint (docs/training.md, evaluation). Undefined values are None, never NaN (strict JSON). Counts a file lacks
    read as None."""

    pck: dict[float, float | None]
    """alpha -> PCK@alpha (bbox), mean over keypoints, in the order reported (0.5, 0.2, 0.05 by default)."""
    max_px: float
    """Upper pixel threshold of `pck_auc` (20 px: DREAM's)."""
    pck_auc: float | None
    """PCK-AUC 0-max_px px, pooled."""
    epe_px: float | None
    """Mean pixel error of the predicted keypoints (read next to `missing_fraction`)."""
    epe_median_px: float | None
    """Median pixel error of the predicted keypoints."""
    missing_fraction: float | None
    """Missing predictions / visible ground-truth keypoints."""
    num_frames: int | None = None
    num_keypoints: int | None = None
    num_gt_visible: int | None = None
    num_missing: int | None = None
    num_frames_excluded_bbox: int | None = None
    """Frames with visible ground truth but a zero-size box, left out of the bbox PCK."""
    per_keypoint: dict[str, KeypointScores] = field(default_factory=dict)
    """Keypoint name -> its scores, in map order."""

    def to_json(self) -> dict[str, Any]:
        """The metrics as every report's "metrics" holds them (stable keys naming their normalisation)."""
        return {**_accuracy_json(self.pck, self.max_px, self.pck_auc), "epe_px": self.epe_px,
                "epe_median_px": self.epe_median_px, "missing_fraction": self.missing_fraction,
                "num_frames": self.num_frames, "num_keypoints": self.num_keypoints,
                "num_gt_visible": self.num_gt_visible, "num_missing": self.num_missing,
                "num_frames_excluded_bbox": self.num_frames_excluded_bbox,
                "per_keypoint": {name: scores.to_json() for name, scores in self.per_keypoint.items()}}

    @classmethod
    def from_json(cls, report: dict[str, Any]) -> KeypointMetrics:
        """The metrics of a parsed "metrics" object (a key it lacks reads as None, "per_keypoint" as {}).

        Raises:
            TypeError: not a JSON object.
        """
        if not isinstance(report, dict):
            raise TypeError(f"keypoint metrics are a JSON object, not {type(report).__name__}")
        max_px, auc = _auc_value(report)
        per = report.get("per_keypoint") or {}
        return cls(pck=_pck_values(report), max_px=max_px, pck_auc=auc, epe_px=report.get("epe_px"),
                   epe_median_px=report.get("epe_median_px"), missing_fraction=report.get("missing_fraction"),
                   num_frames=report.get("num_frames"), num_keypoints=report.get("num_keypoints"),
                   num_gt_visible=report.get("num_gt_visible"), num_missing=report.get("num_missing"),
                   num_frames_excluded_bbox=report.get("num_frames_excluded_bbox"),
                   per_keypoint={name: KeypointScores.from_json(entry) for name, entry in per.items()})


@dataclass(frozen=True)
class StageTiming:
    """Milliseconds of one stage per frame: mean, sample std (ddof=1) and median, rounded to 4 decimals."""

    mean: float
    std: float
    median: float

    def to_json(self) -> dict[str, float]:
        """{"mean", "std", "median"}."""
        return {"mean": self.mean, "std": self.std, "median": self.median}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> StageTiming:
        """The stage of a parsed "*_ms" object."""
        return cls(mean=entry["mean"], std=entry["std"], median=entry["median"])


@dataclass(frozen=True)
class Timing:
    """How fast a model read frames (docs/training.md, metric definitions): after warm-up, per stage, and FPS =
    1 / (preprocess + inference + post-processing) with the invoke-only rate beside it, the thread count stated."""

    threads: int | None
    """CPU threads of the forward pass (None: the backend's default)."""
    backend: str
    """What ran the forward pass ("tf_keras (direct call)", "ai_edge_litert 2.3.0", ...)."""
    frames_timed: int
    preprocess_ms: StageTiming
    inference_ms: StageTiming
    postprocess_ms: StageTiming
    total_ms: StageTiming
    """The whole frame: preprocess + inference + post-processing."""
    fps: float
    """1000 / total_ms.mean, rounded to 2 decimals."""
    fps_inference_only: float
    """1000 / inference_ms.mean, rounded to 2 decimals."""

    _STAGES = ("preprocess_ms", "inference_ms", "postprocess_ms", "total_ms")

    def to_json(self) -> dict[str, Any]:
        """The timing as every report's "timing" holds it."""
        return {"threads": self.threads, "backend": self.backend, "frames_timed": self.frames_timed,
                **{name: getattr(self, name).to_json() for name in self._STAGES},
                "fps": self.fps, "fps_inference_only": self.fps_inference_only}

    @classmethod
    def from_json(cls, timing: dict[str, Any]) -> Timing:
        """The timing of a parsed "timing" object.

        Raises:
            TypeError: not a JSON object.
            KeyError: a key every timing holds is missing.
        """
        if not isinstance(timing, dict):
            raise TypeError(f"a timing is a JSON object, not {type(timing).__name__}")
        return cls(threads=timing["threads"], backend=timing["backend"], frames_timed=timing["frames_timed"],
                   **{name: StageTiming.from_json(timing[name]) for name in cls._STAGES},
                   fps=timing["fps"], fps_inference_only=timing["fps_inference_only"])


class MeasurementJson(TypedDict):
    """A `Measurement` as files hold it (`Measurement.to_json`)."""

    metrics: dict[str, Any]
    """`KeypointMetrics.to_json`."""
    timing: NotRequired[dict[str, Any]]
    """`Timing.to_json`, when timed."""


@dataclass(frozen=True)
class Measurement:
    """A model measured on frames: its keypoint metrics, and its timing when it was timed."""

    metrics: KeypointMetrics
    timing: Timing | None = None

    def to_json(self) -> MeasurementJson:
        """{"metrics"[, "timing"]}: "timing" only when timed."""
        return {"metrics": self.metrics.to_json(), **({"timing": self.timing.to_json()} if self.timing else {})}

    @classmethod
    def from_json(cls, entry: MeasurementJson | dict[str, Any]) -> Measurement:
        """The measurement of a parsed object holding "metrics" and (when timed) "timing"."""
        timing = entry.get("timing")
        return cls(KeypointMetrics.from_json(entry["metrics"]), Timing.from_json(timing) if timing else None)


@dataclass(frozen=True, eq=False)
class Evaluation:
    """What `training.evaluate.evaluate_predictor` measured: metrics and timing, with the keypoints compared."""

    metrics: KeypointMetrics
    timing: Timing
    predictions: np.ndarray = field(repr=False)
    """N x K x 2 predicted keypoints in frame pixels, NaN where missing, in the order of the frames scored."""
    ground_truth: np.ndarray = field(repr=False)
    """N x K x 2 ground-truth keypoints of the same frames."""

    def measurement(self, timed: bool = True) -> Measurement:
        """Metrics and (when `timed`) timing, without the keypoints."""
        return Measurement(self.metrics, self.timing if timed else None)


@dataclass(frozen=True)
class TrackScores:
    """How steady a video's keypoint tracks are (`training.evaluate.sequence_report`), beside their accuracy;
    None where undefined."""

    jitter_px: float | None
    """RMS frame-to-frame change of the error vector, px (`metrics.jitter_px`)."""
    lag_frames: float | None
    """Frames by which the predicted tracks trail the ground truth (`metrics.lag_frames`)."""
    epe_px: float | None
    pck_fine: float | None
    """PCK@0.05 (bbox)."""
    missing_fraction: float | None

    def to_json(self) -> dict[str, Any]:
        """{"jitter_px", "lag_frames", "epe_px", "pck@0.05_bbox", "missing_fraction"}."""
        return {"jitter_px": self.jitter_px, "lag_frames": self.lag_frames, "epe_px": self.epe_px,
                pck_key(0.05): self.pck_fine, "missing_fraction": self.missing_fraction}

    @classmethod
    def from_json(cls, entry: dict[str, Any]) -> TrackScores:
        """The scores of a parsed "raw" or "smoothed" entry."""
        return cls(jitter_px=entry.get("jitter_px"), lag_frames=entry.get("lag_frames"), epe_px=entry.get("epe_px"),
                   pck_fine=entry.get(pck_key(0.05)), missing_fraction=entry.get("missing_fraction"))


@dataclass(frozen=True)
class SequenceReport:
    """Jitter and lag of a video's tracks (`evaluate --sequence`): the raw tracks', and with a smoothing filter the
    smoothed tracks' beside the filter's parameters (the "sequence" of `evaluate --json`)."""

    fps: float
    """The video's frame rate."""
    definitions: str
    """How jitter and lag are defined (`metrics.SEQUENCE_DEFINITIONS`), printed next to the figures."""
    raw: TrackScores
    smoothing: dict[str, Any] | None = None
    """The filter as written: {"filter": "one-euro", "min_cutoff_hz", "beta", "d_cutoff_hz", "max_coast_frames"}."""
    smoothed: TrackScores | None = None

    def to_json(self) -> dict[str, Any]:
        """{"fps", "definitions", "raw"[, "smoothing", "smoothed"]}."""
        out: dict[str, Any] = {"fps": self.fps, "definitions": self.definitions, "raw": self.raw.to_json()}
        if self.smoothing is not None:
            out["smoothing"] = self.smoothing
        if self.smoothed is not None:
            out["smoothed"] = self.smoothed.to_json()
        return out

    @classmethod
    def from_json(cls, report: dict[str, Any]) -> SequenceReport:
        """The report of a parsed "sequence" object."""
        smoothed = report.get("smoothed")
        return cls(fps=report["fps"], definitions=report["definitions"], raw=TrackScores.from_json(report["raw"]),
                   smoothing=report.get("smoothing"),
                   smoothed=TrackScores.from_json(smoothed) if smoothed is not None else None)
