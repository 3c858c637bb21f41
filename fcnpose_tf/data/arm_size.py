"""Where the arm is in a dataset's frames and how large: `train --input-size auto` chooses the model's view by it
(the crop of the frame the network sees and its H x W input).

Fine localisation is judged against the arm's size (PCK@0.05: within 5 % of the keypoint box), and the network
cannot place a keypoint much finer than a few of its input pixels: where the arm spans few input pixels, fine
localisation falls, whatever the training. Input pixels cost every epoch and every Pi frame, so they go where the
arm is: for one fixed camera, `workspace_box` is the box that holds every training keypoint plus
WORKSPACE_MARGIN of it on each side (the arm never leaves its workspace); the input takes that region's own
aspect (`aspect_inputs`) instead of squeezing it into a square. `choose_view` then takes the smallest such input
at which the median frame's arm spans MIN_ARM_INPUT_PX input pixels, and never more than AUTO_MAX_INPUT_PIXELS
(docs/training.md, "Input size"). Where the views vary there is no workspace, and the whole frame keeps the square
side measured best there (WHOLE_FRAME_MIN_SIDE to AUTO_MAX_SIDE).

Measured (docs/training.md, "Someone else's arm"): on a wide-angle fixed camera whose arm spans 0.39 of the
frame, PCK@0.05 0.673 at 224 (an 87-px arm), 0.733 at 320 (125 px) and 0.773 at 384 (149 px); on a
fixed cell whose arm spans 0.53, 0.879 at 224 (118 px) and 0.929 at 320.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from fcnpose_tf import progress, settings
from fcnpose_tf.metrics import FCN_POSE_P70_WIDTHS, fcn_pose_macs
from fcnpose_tf.preprocess import Box, FrameView, same_aspect
from fcnpose_tf.progress import Reporter
from fcnpose_tf.settings import INPUT_SIZE_MULTIPLE

MIN_ARM_INPUT_PX = 140
"""The arm's keypoint box should span at least this many input pixels: PCK@0.05's radius is then 7 of them."""
AUTO_MAX_INPUT_PIXELS = 224 * 288
"""The most input pixels `auto` spends on a fixed camera's workspace: 224 x 288, 1.29x the multiply-adds of the
paper's 224 x 224 (1.9 G a frame unpruned) — on a 2-core machine shared with another job an epoch at 384 x 384 took 150-240 s, and the
30-minute budget trained 6-8 epochs."""
AUTO_MIN_SIDE = 128
"""The shortest input side `auto` considers for a workspace crop."""
WHOLE_FRAME_MIN_SIDE = 224
"""The smallest square side `auto` takes over the whole frame (views that vary): with no workspace to crop to, fewer
pixels only cost accuracy, so views that vary keep the square rule (measured on held-out random views: docs/results.md,
2026-11-28)."""
AUTO_MAX_SIDE = 384
"""The longest input side `auto` considers."""
WORKSPACE_MARGIN = 0.05
"""Added on each side of the training keypoints' box, as a share of its size: on the held-out fixed camera and the
new cell no test keypoint fell outside the box with 0.02 (0.6 % of the new cell's did with none)."""


def _points(keypoints) -> np.ndarray:
    points = np.asarray(keypoints, np.float64).reshape(-1, 2)
    return points[np.isfinite(points).all(axis=1)]


def frame_size_of(frames: Sequence[tuple[np.ndarray, int, int]]) -> tuple[int, int]:
    """(width, height) of the largest of the frames (640 x 480 for none): the size a crop chosen on them is stated in."""
    return max({(int(w), int(h)) for _, w, h in frames} or {(640, 480)})


def workspace_box(frames: Sequence[tuple[np.ndarray, int, int]], margin: float = WORKSPACE_MARGIN) -> Box | None:
    """The box (x, y, width, height in pixels of the largest frame, `frame_size_of`) holding every keypoint of `frames`,
    grown by `margin` of its size on each side and kept inside the frame; frames of another size but the same aspect
    (`preprocess.same_aspect`: the camera at another resolution) count with their keypoints scaled to it. None when the
    frames differ in aspect or hold fewer than two keypoints."""
    fw, fh = frame_size_of(frames)
    if not all(same_aspect((int(w), int(h)), (fw, fh)) for _, w, h in frames):
        return None
    points = [(_points(k) + 0.5) * (fw / int(w), fh / int(h)) - 0.5 for k, w, h in frames]  # through pixel edges
    points = np.concatenate(points) if points else np.empty((0, 2))
    if len(points) < 2:
        return None
    lo, hi = points.min(axis=0), points.max(axis=0)
    grow = margin * (hi - lo)
    x0, y0 = (int(np.floor(v)) for v in np.maximum(lo - grow, 0))
    x1, y1 = (int(np.ceil(v)) + 1 for v in np.minimum(hi + grow, (fw - 1, fh - 1)))
    return x0, y0, max(1, x1 - x0), max(1, y1 - y0)


def fit_aspect(box: Box, aspect: float, frame_wh: tuple[int, int]) -> Box:
    """`box` grown along one axis (about its centre, shifted to stay inside the frame) to width / height = `aspect`,
    so the input's pixels are square in the frame; an axis the frame is too small for stops at the frame."""
    x, y, w, h = box
    fw, fh = frame_wh
    if w / h < aspect:
        w2, h2 = min(fw, int(round(h * aspect))), h
    else:
        w2, h2 = w, min(fh, int(round(w / aspect)))
    x2 = int(np.clip(round(x + w / 2 - w2 / 2), 0, fw - w2))
    y2 = int(np.clip(round(y + h / 2 - h2 / 2), 0, fh - h2))
    return x2, y2, w2, h2


def block_friendly(box: Box, input_shape: tuple[int, int], frame_wh: tuple[int, int]) -> Box:
    """`box` with each side grown to a multiple of its reduction factor (side // input side), inside the frame, so
    preprocessing's box filter takes OpenCV's whole-block path: a 547 x 479 crop to 256 x 224 took 2.9 ms a frame,
    548 x 480 0.67 ms (`preprocess.block_factor`)."""
    x, y, w, h = box
    out = []
    for start, side, size, frame in ((x, w, input_shape[1], frame_wh[0]), (y, h, input_shape[0], frame_wh[1])):
        factor = side // size
        if factor >= 2:
            grown = -(-side // factor) * factor
            if grown > frame:
                grown = side
            start = int(min(max(0, start - (grown - side) // 2), frame - grown))
            side = grown
        out.append((start, side))
    (x, w), (y, h) = out
    return x, y, w, h


def aspect_inputs(aspect: float) -> list[tuple[int, int]]:
    """(height, width) inputs, multiples of 32, whose aspect is closest to `aspect` for each height, fewest pixels
    first; a region wider (taller) than AUTO_MAX_SIDE : AUTO_MIN_SIDE gets the inputs of that extreme aspect (its
    pixels then squeezed along its long side, as the whole frame in a square input would squeeze them more)."""
    m = INPUT_SIZE_MULTIPLE
    extreme = AUTO_MAX_SIDE / AUTO_MIN_SIDE
    aspect = min(max(aspect, 1 / extreme), extreme)
    shapes = set()
    for height in range(AUTO_MIN_SIDE, AUTO_MAX_SIDE + 1, m):
        width = int(round(height * aspect / m)) * m
        if AUTO_MIN_SIDE <= width <= AUTO_MAX_SIDE:
            shapes.add((height, width))
    return sorted(shapes, key=lambda s: (s[0] * s[1], s))


def arm_input_px(frames: Sequence[tuple[np.ndarray, int, int]], view: FrameView) -> float:
    """Median over frames of the arm's keypoint box in input pixels under `view`: max(width, height) after the
    crop's resize to the input."""
    spans = []
    for keypoints, width, height in frames:
        points = _points(keypoints)
        if len(points) < 2:
            continue
        _, _, bw, bh = view.box((height, width))
        extent = points.max(axis=0) - points.min(axis=0)
        spans.append(max(extent[0] * view.width / bw, extent[1] * view.height / bh))
    return float(np.median(spans)) if spans else 0.0


def choose_view(frames: Sequence[tuple[np.ndarray, int, int]], fixed_camera: bool,
                start: FrameView | None = None) -> FrameView:
    """The view `train --input-size auto` takes for these frames (keypoints, frame width, frame height).

    For one fixed camera whose frames share one size: the workspace (`workspace_box`, fitted to the input's aspect)
    at the fewest pixels, at its aspect, at which the median arm spans MIN_ARM_INPUT_PX input pixels, capped at
    AUTO_MAX_INPUT_PIXELS (the most pixels within the cap when no input reaches it). Otherwise (views that vary)
    the whole frame at the smallest square side from WHOLE_FRAME_MIN_SIDE to AUTO_MAX_SIDE that gives the arm
    MIN_ARM_INPUT_PX pixels (AUTO_MAX_SIDE when none does): there 288 x 288 measured ahead of 224 x 288 (see
    WHOLE_FRAME_MIN_SIDE). `start` (the starting model's own view) is kept instead when its crop holds
    every keypoint of the frames, the frames are of the aspect of those its crop was set on (not stretched:
    `FrameView.aspect_note`), the arm spans MIN_ARM_INPUT_PX there and it is of the kind the rule would take
    (a crop for a workspace, the whole frame otherwise): the correction loop's next round stays at the view it
    learnt.
    """
    frame_wh = frame_size_of(frames)
    box = workspace_box(frames) if fixed_camera else None
    if (start is not None and (start.crop is None) == (box is None) and _holds(start, frames)
            and not any(start.aspect_note((h, w)) for _, w, h in frames)
            and arm_input_px(frames, start) >= MIN_ARM_INPUT_PX):
        return start  # a start of the same kind (a crop for a workspace, the whole frame otherwise) that still fits
    if box is None:
        for side in range(WHOLE_FRAME_MIN_SIDE, AUTO_MAX_SIDE + 1, INPUT_SIZE_MULTIPLE):
            if arm_input_px(frames, FrameView(side, side)) >= MIN_ARM_INPUT_PX:
                return FrameView(side, side)
        return FrameView(AUTO_MAX_SIDE, AUTO_MAX_SIDE)
    best = None
    for height, width in aspect_inputs(box[2] / box[3]):
        if height * width > AUTO_MAX_INPUT_PIXELS:
            break
        best = FrameView(height, width, block_friendly(fit_aspect(box, width / height, frame_wh), (height, width),
                                                       frame_wh), frame_wh)
        if arm_input_px(frames, best) >= MIN_ARM_INPUT_PX:
            break
    return best if best is not None else FrameView(224, 224)


def _holds(view: FrameView, frames: Sequence[tuple[np.ndarray, int, int]]) -> bool:
    """True when every keypoint of the frames lies inside the view's crop (always, for the whole frame)."""
    for keypoints, width, height in frames:
        x, y, w, h = view.box((height, width))
        points = _points(keypoints)
        if len(points) and ((points < (x - 0.5, y - 0.5)).any() or (points > (x + w - 0.5, y + h - 0.5)).any()):
            return False
    return True


@dataclass(frozen=True)
class ViewChoice:
    """The view a run trains at and what it was based on (`resolve_view`; NAME_train.json's "view_auto")."""

    arm_input_px: float
    """The arm's keypoint box in input pixels in the median frame (`arm_input_px`), rounded to 0.1."""
    min_arm_input_px: int
    """What the choice aims for (MIN_ARM_INPUT_PX)."""
    crop: str
    """`train --crop` as given: auto, workspace or none."""
    fixed_camera: bool
    chose: FrameView
    macs: int
    """Multiply-adds of a frame at the view, unpruned (`metrics.fcn_pose_macs`)."""
    start_view: FrameView | None = None
    """The starting model's view, when there was one to keep."""

    def to_json(self) -> dict[str, Any]:
        """{"arm_input_px", "min_arm_input_px", "crop", "fixed_camera", "chose", "macs"[, "start_view"]}."""
        out = {"arm_input_px": self.arm_input_px, "min_arm_input_px": self.min_arm_input_px, "crop": self.crop,
               "fixed_camera": self.fixed_camera, "chose": self.chose.to_json(), "macs": self.macs}
        if self.start_view is not None:
            out["start_view"] = self.start_view.to_json()
        return out


def resolve_view(frames: Sequence[Any], input_size: Any, crop: str, fixed_camera: bool,
                 reporter: Reporter | None = None, start: FrameView | None = None) -> ViewChoice:
    """The view a run trains at (`preprocess.FrameView`) for `train --input-size` and `--crop`, and what it was based
    on, said through `reporter`.

    Args:
        frames: `data.via` frames (keypoints, frame sizes).
        input_size: "auto" chooses crop and input together (`choose_view`, the workspace crop where `crop` is "auto"
            and the camera is fixed); S or (H, W) is the user's input, over the whole frame unless `crop` is
            "workspace".
        crop: `train --crop`: auto, workspace or none.
        fixed_camera: whether the frames are one fixed camera (`data.views`).
        reporter: where the choice is said (default: the current one).
        start: the starting model's view, kept by "auto" where it still fits.
    Returns:
        The view (`chose`) and what it was based on, for NAME_train.json.
    """
    boxes = [(f.keypoints, f.width, f.height) for f in frames]
    chosen = input_size == settings.AUTO_INPUT_SIZE
    use_crop = crop == "workspace" or (crop == "auto" and chosen and fixed_camera)
    if chosen:
        view = choose_view(boxes, use_crop, start=start)
        if crop == "none" and view.crop is not None:  # a start's own crop, refused
            view = choose_view(boxes, False)
    else:
        view = FrameView.of(input_size)
        box = workspace_box(boxes) if use_crop else None
        if box is not None:
            frame_wh = frame_size_of(boxes)
            view = FrameView(view.height, view.width, block_friendly(fit_aspect(box, view.width / view.height, frame_wh),
                                                                     view.shape, frame_wh), frame_wh)
    arm_px = arm_input_px(boxes, view)
    macs = fcn_pose_macs(view.shape)
    kept = "; the starting model's own view, kept" if start is not None and view == start else ""
    where = ("its workspace" + (": one fixed camera" if fixed_camera else "") if view.crop is not None else
             "the whole frame" + (": views vary" if chosen and crop == "auto" and not fixed_camera else
                                  ": frames of several aspects" if use_crop else ""))
    progress.resolve(reporter).say(
        f"View: {view.describe()} ({where}{kept}); the arm's keypoint box spans {arm_px:.0f} input pixels in the "
        f"median frame ({MIN_ARM_INPUT_PX} wanted); {macs / 1e9:.2f} G multiply-adds a frame unpruned, "
        f"{fcn_pose_macs(view.shape, FCN_POSE_P70_WIDTHS) / 1e6:.0f} M at 70 %")
    return ViewChoice(arm_input_px=round(arm_px, 1), min_arm_input_px=MIN_ARM_INPUT_PX, crop=crop,
                      fixed_camera=bool(fixed_camera), chose=view, macs=macs, start_view=start)
