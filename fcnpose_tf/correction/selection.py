"""Frames worth correcting: score every processed frame of a video or image folder, pick N spread over it.

`predict --select N --by STRATEGY` runs the model over the source, keeps each frame's prediction
(`FrameScores.add`, the `run_stream` hook), then picks the N frames a person should correct first,
never two within `min_gap` frames of each other (default: one second of video, one frame of an image
folder). Strategies (docs/data.md, "Correcting and merging rounds"):

- `uniform`: evenly spread over the processed frames, the baseline (and the default: DeepLabCut found
  uncertainty sampling no better than uniform; ours is unmeasured until the selection experiment runs).
- `uncertain`: per keypoint 1 when missing, else how far its confidence (the pixel count of its winning
  map cluster) falls short of that keypoint's median confidence over the source, as a share of it;
  summed over keypoints.
- `jump`: the largest distance (frame pixels) of a keypoint from the midpoint of its positions in the
  previous and the next processed frame (at either end: from the line through the two on one side, scaled
  so noise scores alike): one frame off its track scores high, smooth fast motion does not.
- `disagree`: test-time augmentation: the frame flipped left-right (the labels of left/right pairs swapped back,
  `keypoints.KeypointSchema.mirror`; the UR5 chain has none) and zoomed out (centred on a canvas PAD_FRACTION
  larger, as the training's padding),
  each predicted and mapped back; per keypoint the largest distance to the plain prediction (the frame's
  diagonal when found in one and not the other), averaged over keypoints.

Ties go to the earlier frame; every choice is deterministic. numpy and OpenCV only (the Pi core).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.preprocess import Box
from fcnpose_tf.runtime.tracking import predict_over

STRATEGIES = ("uniform", "uncertain", "jump", "disagree")
DEFAULT_STRATEGY = "uniform"
PAD_FRACTION = 0.25
"""The zoomed-out view of `disagree`: the frame centred on a canvas 25 % larger on each axis (black border)."""


@dataclass
class FrameRecord:
    """One processed frame: its index in the source, keypoints (K x 2, NaN missing) and confidences, and for
    `disagree` the augmented views' keypoints mapped back to the frame."""

    index: int
    keypoints: np.ndarray
    confidence: np.ndarray
    shape: tuple[int, ...]
    views: list[np.ndarray] = field(default_factory=list)


def flip_back(keypoints: np.ndarray, width: int, mirror: Sequence[int] | None = None) -> np.ndarray:
    """Keypoints predicted on a left-right flipped frame, in the frame's pixels (pixel i's centre at i); with
    `mirror` (`KeypointSchema.mirror`) each left/right pair's labels swapped back."""
    out = np.array(keypoints, np.float64, copy=True)
    out[:, 0] = (width - 1) - out[:, 0]
    return out if mirror is None else out[list(mirror)]


def zoom_out(frame: np.ndarray, fraction: float = PAD_FRACTION) -> tuple[np.ndarray, tuple[int, int]]:
    """The frame centred on a black canvas `fraction` larger per axis, and the frame's (x, y) offset on it."""
    h, w = frame.shape[:2]
    pad_x, pad_y = int(round(w * fraction / 2)), int(round(h * fraction / 2))
    canvas = cv2.copyMakeBorder(frame, pad_y, pad_y, pad_x, pad_x, cv2.BORDER_CONSTANT, value=0)
    return canvas, (pad_x, pad_y)


def augmented_views(predict: Callable[[np.ndarray], np.ndarray], frame: np.ndarray,
                    mirror: Sequence[int] | None = None, box: Box | None = None) -> list[np.ndarray]:
    """`disagree`'s views of the part of a frame a model reads (`box`, x, y, width, height: its crop; None: the whole
    frame), flipped and zoomed out, each predicted by `predict` (BGR image -> K x 2, the image read whole) and mapped
    back to the frame (`mirror`: the schema's left/right pairs, `KeypointSchema.mirror`). A crop is flipped and zoomed
    out in place: the flipped frame's workspace is elsewhere, where the crop would not read it."""
    x, y, width, height = box if box is not None else (0, 0, frame.shape[1], frame.shape[0])
    part = frame[y:y + height, x:x + width]
    flipped = flip_back(predict(np.ascontiguousarray(part[:, ::-1])), width, mirror)
    canvas, (dx, dy) = zoom_out(part)
    zoomed = np.array(predict(canvas), np.float64, copy=True) - (dx, dy)
    return [flipped + (x, y), zoomed + (x, y)]


class FrameScores:
    """Predictions of the processed frames, kept to pick from (`run_stream`'s `on_frame` hook).

    Args:
        strategy: one of STRATEGIES; `disagree` predicts every frame's augmented views with `predictor`.
        predictor: the model (a `KeypointPredictor`), needed for `disagree` only.
    """

    def __init__(self, strategy: str, predictor: Any = None):
        if strategy not in STRATEGIES:
            raise UserError(f"--by must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
        if strategy == "disagree" and predictor is None:
            raise ValueError("disagree needs the predictor for its augmented views")
        self.strategy = strategy
        self.predictor = predictor
        self.records: list[FrameRecord] = []

    def add(self, frame: Any, prediction: Any) -> None:
        """Keep one frame's prediction (and for `disagree` its augmented views' keypoints)."""
        views = []
        if self.strategy == "disagree":
            schema = getattr(self.predictor, "schema", None)
            view = getattr(self.predictor, "view", None)
            box = view.box(frame.image.shape) if view is not None and view.crop is not None else None
            views = augmented_views(lambda image: predict_over(self.predictor, image, None if box is None else
                                                               (0, 0, image.shape[1], image.shape[0])).keypoints,
                                    frame.image, schema.mirror if schema is not None else None, box)
        self.records.append(FrameRecord(int(frame.index), np.array(prediction.keypoints, np.float64, copy=True),
                                        np.array(prediction.confidence, np.float64, copy=True),
                                        tuple(frame.image.shape), views))

    def scores(self) -> np.ndarray:
        """One score per processed frame (higher: more worth correcting; uniform: all zero)."""
        return frame_scores(self.strategy, self.records)

    def pick(self, n: int, min_gap: int) -> list[FrameRecord]:
        """The N records to write, in source order (fewer when no more fit `min_gap` apart)."""
        indices = [r.index for r in self.records]
        if self.strategy == "uniform":
            chosen = pick_uniform(indices, n, min_gap)
        else:
            chosen = pick_spread(self.scores(), indices, n, min_gap)
        return [self.records[i] for i in chosen]


def frame_scores(strategy: str, records: Sequence[FrameRecord]) -> np.ndarray:
    """Each record's score under `strategy` (see the module docstring)."""
    if not records:
        return np.zeros(0)
    kps = np.stack([r.keypoints for r in records])
    if strategy == "uniform":
        return np.zeros(len(records))
    if strategy == "uncertain":
        return uncertainty_scores(kps, np.stack([r.confidence for r in records]))
    if strategy == "jump":
        return jump_scores(kps)
    if strategy == "disagree":
        return np.array([disagreement(r.keypoints, r.views, float(np.hypot(*r.shape[:2]))) for r in records])
    raise UserError(f"--by must be one of {', '.join(STRATEGIES)}, got {strategy!r}")


def uncertainty_scores(keypoints: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """Per frame: sum over keypoints of 1 when missing, else max(0, 1 - confidence / that keypoint's median)."""
    found = np.isfinite(keypoints).all(axis=2)
    conf = np.where(found, confidence, np.nan)
    with np.errstate(all="ignore"):
        median = np.nanmedian(conf, axis=0) if found.any() else np.full(keypoints.shape[1], np.nan)
        shortfall = np.clip(1.0 - conf / median, 0.0, 1.0)
    shortfall = np.where(np.isfinite(shortfall), shortfall, 0.0)
    return np.where(found, shortfall, 1.0).sum(axis=1)


def jump_scores(keypoints: np.ndarray) -> np.ndarray:
    """Per frame: the largest distance of a keypoint from where its neighbours put it: the midpoint of its
    previous and next positions, else (at either end, or a neighbour missing it) the line through the two
    positions on one side (distance halved), else the one neighbour's position (times 0.87); 0 when no
    neighbour has it. The factors give per-frame noise the same score wherever it is measured."""
    n = len(keypoints)

    def shifted(by: int) -> np.ndarray:  # keypoints of frame t + by at row t (NaN outside)
        out = np.full_like(keypoints, np.nan)
        if abs(by) < n:
            if by > 0:
                out[:n - by] = keypoints[by:]
            else:
                out[-by:] = keypoints[:n + by]
        return out

    # each reference's distance scaled so that independent per-frame noise of std s scores alike with any of them:
    # p - (a + b) / 2 has variance 1.5 s^2, p - (2a - b) 6 s^2, p - a 2 s^2
    distance = np.full(keypoints.shape[:2], np.nan)
    for candidate, scale in (((shifted(-1) + shifted(1)) / 2, 1.0), (2 * shifted(-1) - shifted(-2), 0.5),
                             (2 * shifted(1) - shifted(2), 0.5), (shifted(-1), 0.75 ** 0.5),
                             (shifted(1), 0.75 ** 0.5)):
        distance = np.where(np.isfinite(distance), distance, scale * np.linalg.norm(keypoints - candidate, axis=2))
    distance = np.where(np.isfinite(distance), distance, 0.0)
    return distance.max(axis=1) if n else np.zeros(0)


def disagreement(keypoints: np.ndarray, views: Sequence[np.ndarray], diagonal: float) -> float:
    """Mean over keypoints of the largest distance between the plain prediction and an augmented view's (the
    frame's diagonal when one finds the keypoint and the other does not; 0 when none finds it)."""
    if not views:
        return 0.0
    found = np.isfinite(keypoints).all(axis=1)
    worst = np.zeros(len(keypoints))
    for view in views:
        seen = np.isfinite(view).all(axis=1)
        distance = np.where(found & seen, np.linalg.norm(np.nan_to_num(keypoints - view), axis=1), 0.0)
        distance = np.where(found != seen, diagonal, distance)
        worst = np.maximum(worst, distance)
    return float(worst.mean())


def pick_spread(scores: np.ndarray, indices: Sequence[int], n: int, min_gap: int) -> list[int]:
    """Positions (into `scores`) of the N highest scores whose source `indices` are at least `min_gap` apart,
    greedily from the highest (ties: the earlier frame), returned in source order."""
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), indices[i]))
    taken: list[int] = []
    for i in order:
        if len(taken) == n:
            break
        if all(abs(indices[i] - indices[j]) >= min_gap for j in taken):
            taken.append(i)
    return sorted(taken, key=lambda i: indices[i])


def pick_uniform(indices: Sequence[int], n: int, min_gap: int) -> list[int]:
    """Positions of N frames evenly spread over the processed ones (first and last included), at least
    `min_gap` source frames apart (fewer when the source is too short for N at that gap)."""
    if not indices or n < 1:
        return []
    span = indices[-1] - indices[0]
    fit = span // max(min_gap, 1) + 1
    count = min(n, len(indices), fit)
    while count > 0:
        targets = np.linspace(indices[0], indices[-1], count) if count > 1 else np.array([indices[0]])
        chosen: list[int] = []
        for target in targets:
            nearest = min(range(len(indices)), key=lambda i: (abs(indices[i] - target), i))
            if nearest not in chosen and all(abs(indices[nearest] - indices[j]) >= min_gap for j in chosen):
                chosen.append(nearest)
        if len(chosen) == count:
            return sorted(chosen)
        count -= 1
    return []


def default_min_gap(fps: float | None, kind: str) -> int:
    """One second of a video at its frame rate (30 when unknown), one frame of an image folder."""
    if kind == "video":
        return max(1, int(round(fps or 30.0)))
    return 1


__all__ = ["DEFAULT_STRATEGY", "FrameRecord", "FrameScores", "PAD_FRACTION", "STRATEGIES", "augmented_views",
           "default_min_gap", "disagreement", "flip_back", "frame_scores", "jump_scores", "pick_spread",
           "pick_uniform", "uncertainty_scores", "zoom_out"]
