"""Pictures to look at: a grid of synthetic frames with keypoints, skeleton and names drawn."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.data.synth.datasets import IMAGE_DIR, SynthReport
from fcnpose_tf.draw import contact_sheet, draw_keypoints
from fcnpose_tf.errors import UserError


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
        tiles.append(draw_keypoints(tile, keypoints, labels=labels, occluded=occluded, point_scale=f))
    return contact_sheet(tiles, columns)


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
