#!/usr/bin/env python3
"""Would a per-frame crop around the arm reach what a static workspace crop cannot? (maintainers only)

A fixed camera's workspace can span most of the frame (the held-out fixed camera's: 0.84 x 1.0 of it), so a static
crop gives its arm few more pixels than the whole frame. Top-down pose estimators (RTMPose, MoveNet, MediaPipe) read
a crop around the subject instead: found by a first pass, or by the previous frame on video. This script measures
that lever with the package's own commands, on datasets of crops it writes:

    prepare --data D_train --out C_train --copies 3 --jitter 0.15    # crops around the labelled arm, jittered
    prepare --data D_test --out C_test_gt                             # the oracle: crops around the labelled arm
    prepare --data D_test --out C_test_pass1 --boxes-from FIRST.keras # a real first pass: FIRST's keypoints' box
    fcnpose-tf train --data C_train --input-size 192 --crop none --augment paper --out M.keras --test-data C_test_gt
    fcnpose-tf evaluate M.keras --data C_test_pass1 --split all

and what a model that reads a static crop does when the arm leaves it (frames shifted sideways so that part of the
arm lies outside the model's crop; the keypoints outside counted as lost, placed at the crop's border, or elsewhere,
and how many such frames `run`'s crop_edge flags):

    leave --model M_int8.tflite --data D_test --shift -150

and, on video (a motion sequence's frames in order), what each way of choosing the second pass's crop gives against
the first pass alone on the whole frame: each second model alone on the whole frame, over the first pass's box every
frame (two passes a frame), over the previous frame's keypoints (`run --track`'s `TrackingCrop`: one pass a frame, its
own view after a frame with fewer than --min-found keypoints), and over the labels' box (the oracle), with the
multiply-adds a frame each costs:

    track --first FIRST.keras --second M.keras --data D_motion [--data D_motion2 ...]

A crop is a square of side max(box width, box height) x (1 + 2 x margin) about the keypoint box's centre, moved
inside the frame; `--jitter J` moves its centre by up to J of its side and scales it by 1 +- J, copy by copy (a
first pass's error). Crops keep the frame's pixels (no resizing), so EPE stays in frame pixels; a keypoint the crop
cut off is unlabelled in it, and counted missing by `evaluate`, which is what a second pass could not see. With
`--boxes-from`, a frame whose first pass found fewer than two keypoints keeps the whole frame.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def square_crop(box_lo: np.ndarray, box_hi: np.ndarray, margin: float, frame_wh: tuple[int, int],
                shift: np.ndarray = np.zeros(2), scale: float = 1.0) -> tuple[int, int, int, int]:
    """(x, y, side_w, side_h) of the square crop about a keypoint box, inside the frame."""
    fw, fh = frame_wh
    side = max(box_hi - box_lo) * (1 + 2 * margin) * scale
    side = int(round(min(max(side, 16), fw, fh)))
    centre = (box_lo + box_hi) / 2 + shift * side
    x = int(np.clip(round(centre[0] - side / 2), 0, fw - side))
    y = int(np.clip(round(centre[1] - side / 2), 0, fh - side))
    return x, y, side, side


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True)
    prep = sub.add_parser("prepare", help="write a dataset of crops around the arm")
    prep.add_argument("--data", type=Path, required=True, help="a dataset folder (VIA project + images)")
    prep.add_argument("--out", type=Path, required=True, help="the crops' dataset folder (new)")
    prep.add_argument("--margin", type=float, default=0.25, help="added on each side, share of the box's side")
    prep.add_argument("--copies", type=int, default=1, help="crops per frame")
    prep.add_argument("--jitter", type=float, default=0.0, help="random shift (share of the side) and scale")
    prep.add_argument("--boxes-from", type=Path, help="a model whose keypoints on the whole frame give the box")
    prep.add_argument("--seed", type=int, default=0)
    leave = sub.add_parser("leave", help="shift frames so the arm leaves a crop model's crop; count what happens")
    leave.add_argument("--model", type=Path, required=True, help="a .tflite or .keras model that reads a crop")
    leave.add_argument("--data", type=Path, required=True, help="a dataset folder (VIA project + images)")
    leave.add_argument("--shift", type=int, default=-150, help="pixels to move every frame's content sideways")
    leave.add_argument("--share", type=float, default=None, help="the crop-edge band (default: run's)")
    track = sub.add_parser("track", help="on motion sequences: whole frame vs two passes vs a tracking crop")
    track.add_argument("--first", type=Path, required=True, help="a whole-frame .keras model (the first pass)")
    track.add_argument("--second", type=Path, action="append", required=True,
                       help="a model that reads a crop (repeatable): a .keras at its own input size or PATH@S "
                            "to run it at S x S, or a .tflite (LiteRT, as run --track runs it)")
    track.add_argument("--data", type=Path, action="append", required=True,
                       help="a motion sequence's dataset folder (repeatable; each sequence tracked on its own)")
    track.add_argument("--margin", type=float, default=0.25, help="added on each side, share of the box's side")
    track.add_argument("--min-found", type=int, default=4, help="fewer keypoints found: the next frame's box "
                                                                 "comes from the first pass again")
    args = parser.parse_args(argv)
    if args.action == "leave":
        return leave_crop(args)
    if args.action == "track":
        return track_crop(args)

    import cv2

    from fcnpose_tf.data.dataset import resolve_data
    from fcnpose_tf.data.via import ViaFrame, read_via, write_via_project
    from fcnpose_tf.preprocess import read_image

    via_path, images = resolve_data(args.data, None)
    annotations = read_via(via_path, images)
    predictor = None
    if args.boxes_from is not None:
        from fcnpose_tf.training.evaluate import open_model

        predictor = open_model(args.boxes_from)
    (args.out / "images").mkdir(parents=True, exist_ok=False)
    rng = np.random.default_rng(args.seed)
    frames, whole = [], 0
    for frame in annotations.frames:
        image = read_image(frame.image_path)
        if predictor is not None:
            found = predictor.predict(image).keypoints
            points = found[np.isfinite(found).all(axis=1)]
        else:
            points = frame.keypoints[np.isfinite(frame.keypoints).all(axis=1)]
        for copy in range(args.copies):
            if len(points) < 2:
                crop, whole = (0, 0, frame.width, frame.height), whole + 1
            else:
                shift = rng.uniform(-args.jitter, args.jitter, 2) if args.jitter else np.zeros(2)
                scale = 1 + rng.uniform(-args.jitter, args.jitter) if args.jitter else 1.0
                crop = square_crop(points.min(axis=0), points.max(axis=0), args.margin, (frame.width, frame.height),
                                   shift, scale)
            x, y, w, h = crop
            kps = frame.keypoints - (x, y)
            outside = ~((kps >= -0.5) & (kps <= (w - 0.5, h - 0.5))).all(axis=1)
            kps[outside] = np.nan
            name = f"{Path(frame.filename).stem}_c{copy}.png"
            cv2.imwrite(str(args.out / "images" / name), np.ascontiguousarray(image[y:y + h, x:x + w]))
            frames.append(ViaFrame(name, w, h, kps))
    write_via_project(args.out / "crops.json", frames, annotations.schema)
    sides = [f.width for f in frames]
    print(f"{args.out}: {len(frames)} crops of {len(annotations.frames)} frames; side median {np.median(sides):.0f} px "
          f"(p10 {np.percentile(sides, 10):.0f}, p90 {np.percentile(sides, 90):.0f}); "
          f"{sum(int(np.isnan(f.keypoints).any()) for f in frames)} crops cut a keypoint off; "
          f"{whole} whole frames (first pass found < 2 keypoints)")
    return 0


def leave_crop(args: argparse.Namespace) -> int:
    """Frames shifted by --shift px (the vacated strip black): keypoints that land outside the model's crop, and what
    the model reports for them."""
    from fcnpose_tf.data.dataset import resolve_data
    from fcnpose_tf.data.via import read_via
    from fcnpose_tf.preprocess import read_image
    from fcnpose_tf.training.evaluate import open_model

    model = open_model(args.model)
    if model.view.crop is None:
        print(f"{args.model}: reads the whole frame; nothing to leave")
        return 2
    via_path, images = resolve_data(args.data, None)
    counts = {"outside": 0, "lost": 0, "at the border": 0, "elsewhere": 0, "frames with one outside": 0,
              "of those flagged": 0, "frames flagged with none outside": 0, "frames": 0}
    for frame in read_via(via_path, images).frames:
        image = read_image(frame.image_path)
        shifted = np.zeros_like(image)
        dx = args.shift
        if dx < 0:
            shifted[:, :dx] = image[:, -dx:]
        else:
            shifted[:, dx:] = image[:, :image.shape[1] - dx]
        truth = frame.keypoints + (dx, 0)
        truth[(truth[:, 0] < -0.5) | (truth[:, 0] > image.shape[1] - 0.5)] = np.nan  # out of the frame: unlabelled
        prediction = model.predict(shifted)
        x, y, w, h = prediction.crop
        with np.errstate(invalid="ignore"):
            outside = ((truth < (x - 0.5, y - 0.5)) | (truth > (x + w - 0.5, y + h - 0.5))).any(axis=1)
        found = prediction.found
        edge = prediction.at_crop_edge() if args.share is None else prediction.at_crop_edge(args.share)
        counts["frames"] += 1
        counts["outside"] += int(outside.sum())
        counts["lost"] += int((outside & ~found).sum())
        counts["at the border"] += int((outside & edge).sum())
        counts["elsewhere"] += int((outside & found & ~edge).sum())
        if outside.any():
            counts["frames with one outside"] += 1
            counts["of those flagged"] += int(edge.any())
        elif edge.any():
            counts["frames flagged with none outside"] += 1
    print(f"{args.model} ({model.view.describe()}), frames of {via_path} shifted by {args.shift} px:")
    for name, value in counts.items():
        print(f"  {name}: {value}")
    return 0


def _predictor(spec: Path):
    """A predictor from PATH (.keras/.h5, or a .tflite run by LiteRT) or PATH@S (a Keras model rebuilt at S x S), and
    its multiply-adds a frame."""
    path, _, size = str(spec).partition("@")
    if path.endswith(".tflite"):
        from fcnpose_tf.runtime.estimator import KeypointModel

        if size:
            raise SystemExit(f"{spec}: a .tflite runs at its own input size (export --input-size makes another)")
        model = KeypointModel(path)
        return model, model.stats().macs
    from fcnpose_tf.compression.costs import model_facts
    from fcnpose_tf.training.evaluate import KerasKeypointModel
    from fcnpose_tf.training.model import at_input_size, load_model

    model = load_model(path)
    if size:
        model = at_input_size(model, int(size))
    return KerasKeypointModel(model, path), model_facts(model).macs


def track_crop(args: argparse.Namespace) -> int:
    """Per sequence and pooled: PCK@0.5/0.2/0.05 and EPE of the first pass alone and of each second model over each
    way of choosing its crop (`runtime.tracking.follow_box`, as `run --track` does), with the multiply-adds a frame."""
    from fcnpose_tf import metrics
    from fcnpose_tf.data.dataset import resolve_data
    from fcnpose_tf.data.via import read_via
    from fcnpose_tf.preprocess import read_image
    from fcnpose_tf.runtime.tracking import TrackingCrop, follow_box, predict_over

    first, first_macs = _predictor(args.first)
    seconds = [(str(spec), *_predictor(spec)) for spec in args.second]

    def over(predictor, image, keypoints):
        """The predictor over follow_box of `keypoints` (its own view when there is no box)."""
        box = follow_box(keypoints, image.shape, predictor.view.shape, args.margin, min_found=2)
        return predict_over(predictor, image, box).keypoints

    rows: dict[str, list] = {}
    macs: dict[str, float] = {}
    truth_all, whole_reads = [], {}
    for data in args.data:
        via_path, images = resolve_data(data, None)
        frames = read_via(via_path, images).frames
        pictures = [read_image(frame.image_path) for frame in frames]
        truth_all.extend(frame.keypoints for frame in frames)
        whole = [first.predict(image).keypoints for image in pictures]
        rows.setdefault("first pass alone (whole frame)", []).extend(whole)
        macs["first pass alone (whole frame)"] = first_macs
        for name, predictor, second_macs in seconds:
            tracker = TrackingCrop(predictor, margin=args.margin, min_found=args.min_found)
            for label, cost, values in (
                    (f"{name} alone (whole frame)", second_macs, [predictor.predict(im).keypoints for im in pictures]),
                    (f"two passes: {name} over the first pass's box", first_macs + second_macs,
                     [over(predictor, im, k) for im, k in zip(pictures, whole)]),
                    (f"tracking: {name} over the previous frame's box", second_macs,
                     [tracker.predict(im).keypoints for im in pictures]),
                    (f"oracle: {name} over the labels' box", second_macs,
                     [over(predictor, im, f.keypoints) for im, f in zip(pictures, frames)])):
                rows.setdefault(label, []).extend(values)
                macs[label] = cost
            whole_reads[name] = whole_reads.get(name, 0) + tracker.whole_view_frames
    truth = np.stack(truth_all)
    print(f"{len(truth)} frames of {len(args.data)} sequences; first pass {args.first} ({first_macs / 1e9:.2f} G a "
          f"frame); crops: follow_box, margin {args.margin:g}")
    print("| model and crop | PCK@0.5 | PCK@0.2 | PCK@0.05 | EPE px | missing | G MACs a frame |")
    print("|---|---|---|---|---|---|---|")
    for label, values in rows.items():
        pred = np.stack(values)
        note = ""
        if label.startswith("tracking"):
            name = label[len("tracking: "):label.index(" over ")]
            note = f" ({whole_reads[name]} frames over its own view)"
        print(f"| {label}{note} | {metrics.pck(pred, truth, 0.5):.3f} | {metrics.pck(pred, truth, 0.2):.3f} | "
              f"{metrics.pck(pred, truth, 0.05):.3f} | {metrics.epe(pred, truth):.2f} | "
              f"{metrics.missing_fraction(pred, truth):.3f} | {macs[label] / 1e9:.2f} |")
    return 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
