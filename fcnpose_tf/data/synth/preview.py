"""Pictures to look at: a grid of synthetic frames with keypoints, skeleton and names drawn."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.data.synth.datasets import IMAGE_DIR, SynthReport
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5


_KEYPOINT_COLORS_BGR = ((60, 60, 230), (40, 160, 250), (40, 220, 230), (60, 200, 60), (220, 200, 40),
                        (230, 110, 40), (200, 60, 200), (250, 250, 250))


def draw_keypoints(image_bgr: np.ndarray, keypoints: np.ndarray, schema=UR5, labels: bool = True,
                   occluded: np.ndarray | None = None) -> np.ndarray:
    """A copy of a BGR frame with the skeleton, keypoint dots and (optionally) their names drawn on it.

    Names are placed greedily where they overlap neither each other nor the dots, with a thin leader
    line when pushed away; occluded keypoints (if given) are drawn as rings.
    """
    out = np.ascontiguousarray(image_bgr.copy())
    h, w = out.shape[:2]
    scale = max(0.6, h / 480)
    kp = np.asarray(keypoints, np.float64)
    shift = 4
    fx = lambda p: (int(round(p[0] * 16)), int(round(p[1] * 16)))  # noqa: E731
    for a, b in schema.edges:
        if np.isfinite(kp[[a, b]]).all():
            cv2.line(out, fx(kp[a]), fx(kp[b]), (255, 255, 255), max(1, int(3 * scale)), cv2.LINE_AA, shift)
            cv2.line(out, fx(kp[a]), fx(kp[b]), (40, 40, 40), max(1, int(1 * scale)), cv2.LINE_AA, shift)
    r = max(2, int(4 * scale))
    visible = [k for k in range(schema.num_keypoints) if np.isfinite(kp[k]).all()]
    for k in visible:
        color = _KEYPOINT_COLORS_BGR[k % len(_KEYPOINT_COLORS_BGR)]
        hollow = occluded is not None and bool(occluded[k])
        cv2.circle(out, fx(kp[k]), r * 16, color, max(1, int(2 * scale)) if hollow else -1, cv2.LINE_AA, shift)
        cv2.circle(out, fx(kp[k]), (r + 1) * 16, (0, 0, 0), 1, cv2.LINE_AA, shift)
    if not labels:
        return out
    fs = max(0.4, 0.45 * scale)
    taken = [(kp[k, 0] - r, kp[k, 1] - r, kp[k, 0] + r, kp[k, 1] + r) for k in visible]
    for k in visible:
        name = schema.keypoints[k]
        color = _KEYPOINT_COLORS_BGR[k % len(_KEYPOINT_COLORS_BGR)]
        (tw, th), base = cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)
        x, y = kp[k]
        best = None
        for dist in (r + 3, 3 * r + 8, 6 * r + 14, 10 * r + 22):
            for dx, dy in ((1, 0), (-1, 0), (0, -1), (0, 1), (1, -1), (-1, -1), (1, 1), (-1, 1)):
                x0 = x + dx * dist - (tw if dx < 0 else 0 if dx > 0 else tw / 2)
                y0 = y + dy * dist + (th / 2 if dy == 0 else 0 if dy > 0 else -th) - th / 2
                box = (x0 - 1, y0 - 1, x0 + tw + 1, y0 + th + base)
                if box[0] < 0 or box[1] < 0 or box[2] >= w or box[3] >= h:
                    continue
                if all(box[2] < t[0] or box[0] > t[2] or box[3] < t[1] or box[1] > t[3] for t in taken):
                    best = (box, dist)
                    break
            if best:
                break
        if best is None:
            continue  # no free spot: leave this name out rather than cover another
        box, dist = best
        taken.append(box)
        org = (int(box[0] + 1), int(box[1] + 1 + th))
        if dist > r + 3:
            anchor = (min(max(x, box[0]), box[2]), min(max(y, box[1]), box[3]))
            cv2.line(out, fx(kp[k]), fx(anchor), color, 1, cv2.LINE_AA, shift)
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, fs, color, 1, cv2.LINE_AA)
    return out


def preview_grid(frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]], columns: int = 3,
                 tile_width: int = 480, labels: bool = True) -> np.ndarray:
    """One BGR image tiling (image, keypoints, occluded-or-None) frames with skeleton, dots and names drawn."""
    if not frames:
        raise UserError("no frames to preview")
    tiles = []
    for image, keypoints, occluded in frames:
        f = tile_width / image.shape[1]
        tile = cv2.resize(image, (tile_width, int(round(image.shape[0] * f))),
                          interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
        tiles.append(draw_keypoints(tile, (np.asarray(keypoints) + 0.5) * f - 0.5, labels=labels, occluded=occluded))
    th = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, th - t.shape[0], 0, 0, cv2.BORDER_CONSTANT, value=(0, 0, 0)) for t in tiles]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.hstack([cv2.copyMakeBorder(t, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
                       for t in tiles[i:i + columns]]) for i in range(0, len(tiles), columns)]
    return np.ascontiguousarray(np.vstack(rows))


def write_preview(report: SynthReport, path: str | os.PathLike, count: int = 6, force: bool = False) -> Path:
    """Write a PNG grid of the report's first `count` frames (read back from disk) with keypoints drawn."""
    from fcnpose_tf import fileio

    image_dir = report.via_path.parent / IMAGE_DIR
    frames = []
    for record in report.frames[:count]:
        image = cv2.imread(str(image_dir / record.filename), cv2.IMREAD_COLOR)
        if image is None:
            raise UserError(f"{image_dir / record.filename}: cannot read the frame back")
        frames.append((image, record.keypoints, record.occluded))
    grid = preview_grid(frames, columns=3 if len(frames) > 4 else 2, tile_width=400)
    _, buf = cv2.imencode(".png", grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return fileio.write_bytes(path, buf.tobytes(), force=force)
