"""Pre-annotation: a model's keypoints written as a VIA project with their frames, to be corrected in VIA.

`ViaPredictions` collects (frame, prediction) pairs from `fcnpose-tf predict` or `run --via` and
writes one VIA 2.x project through `data.via.write_via_project`, the writer the synthetic sets
use, so `read_via`, `data inspect` and `train --data` read it unchanged. A keypoint that was not
found, or whose confidence (the pixel count of its cluster in the output map) is below
`min_confidence`, gets no point region (it is counted); correcting means moving, adding or
deleting points in VIA. Frames from image files are referenced where they are (the folder
becomes the project's default path); frames from a video or a camera are saved as PNGs in
`images/` beside the VIA file, named after the source and the frame number. With a pictures folder
(`predict --draw DIR`) every frame written is also drawn there with the points it gets, and a contact sheet of up to
SHEET_TILES of them (evenly spread) closes it.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import cv2
import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.data.via import ViaFrame, write_via_project
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.runtime.estimator import Prediction
from fcnpose_tf.runtime.sources import Frame, FrameSource

FRAMES_FOLDER = "images"
"""Where frames without an image file of their own are saved, beside the VIA file (read_via looks there)."""
SHEET_TILES = 12
"""Frames on the pictures folder's contact_sheet.png (all of them when there are fewer)."""
SHEET_TILE_WIDTH = 320


def check_via_output(via_path: str | os.PathLike, force: bool = False, min_confidence: float = 0.0,
                     every: int = 1) -> Path:
    """The VIA output checked before any work: a .json path that may be written, usable options."""
    via_path = Path(via_path)
    if via_path.suffix.lower() != ".json":
        raise UserError(f"{via_path}: a VIA project is a .json file")
    if not min_confidence >= 0:
        raise UserError(f"--min-confidence must be at least 0, got {min_confidence}")
    if every < 1:
        raise UserError(f"--via-every must be at least 1, got {every}")
    return fileio.check_writable(via_path, force)


class ViaPredictions:
    """Predictions of one source, collected for a VIA project (see the module docstring).

    Args:
        via_path: the .json project to write; checked here (exists without `force`, folder writable).
        schema: the model's keypoint names.
        source: the opened source; image sources are referenced, the others' frames saved as PNGs.
        force: replace an existing project and existing frame PNGs of the same names.
        min_confidence: keypoints with a lower confidence get no point (counted).
        every: keep one frame in this many of those offered to `add` (the first, then every Nth).
        pictures: a folder where every frame written is drawn with its points (NNNN_NAME.png) and, at `close`,
            contact_sheet.png; None draws nothing.
    Raises:
        UserError: a path that is not .json, an existing output without `force`, an image source
            whose images are not all in one folder, a pictures folder that holds files without `force`.
    """

    def __init__(self, via_path: str | os.PathLike, schema: KeypointSchema, source: FrameSource,
                 force: bool = False, min_confidence: float = 0.0, every: int = 1,
                 pictures: str | os.PathLike | None = None):
        self.via_path = check_via_output(via_path, force, min_confidence, every)
        self.pictures = None if pictures is None else fileio.check_output_folder(pictures, force)
        self.drawn: list[Path] = []
        self._tiles: list[np.ndarray] = []  # thumbnails of every `_stride`-th frame drawn, for the contact sheet
        self._stride = 1
        self.every = every
        self.offered = 0
        self.schema = schema
        self.force = force
        self.min_confidence = float(min_confidence)
        self.reference_files = source.kind == "images"
        self.image_dir: Path | None = None
        self.frames: list[ViaFrame] = []
        self.saved: list[Path] = []
        self.points = 0
        self.not_found = 0
        self.below_confidence = 0
        self.frames_dir = self.via_path.parent / FRAMES_FOLDER
        stem = Path(source.name).stem if source.kind == "video" else source.name
        self.prefix = re.sub(r"[^A-Za-z0-9]+", "-", stem).strip("-") or "frame"
        if source.live:  # a camera numbers frames from 0 in every run: the start time keeps runs apart
            self.prefix += time.strftime("_%Y%m%dT%H%M%SZ", time.gmtime())
        if not self.reference_files and not force and self.frames_dir.is_dir():
            clash = sorted(self.frames_dir.glob(f"{self.prefix}_*.png"))
            if clash:
                raise UserError(f"{clash[0]}: already exists (frames of an earlier run); pass --force to "
                                "replace them, or write the VIA file to another folder")

    def add(self, frame: Frame, prediction: Prediction) -> None:
        """Add one frame: its found keypoints (confident enough) as points; save the frame if it has no file.

        `run_stream` calls it with Ctrl-C and SIGTERM held back, so a saved frame is always in the project.
        """
        self.offered += 1
        if (self.offered - 1) % self.every:
            return
        if self.reference_files:
            image_path = Path(frame.name)
            folder = image_path.parent
            if self.image_dir is None:
                self.image_dir = folder
            elif folder.resolve() != self.image_dir.resolve():
                raise UserError(f"{image_path}: not in {self.image_dir}; a VIA project's images share one folder")
        else:
            image_path = self.frames_dir / f"{self.prefix}_{frame.index:06d}.png"
            ok, png = cv2.imencode(".png", frame.image)
            if not ok:
                raise UserError(f"{image_path}: OpenCV cannot encode the frame as PNG")
            with fileio.parts_of(None):  # parts of the project: kept and named with it, never alone
                fileio.write_bytes(image_path, png.tobytes(), force=self.force)
            self.saved.append(image_path)
        keypoints = np.array(prediction.keypoints, np.float64, copy=True)
        found = prediction.found
        confident = np.asarray(prediction.confidence, np.float64) >= self.min_confidence
        self.not_found += int((~found).sum())
        self.below_confidence += int((found & ~confident).sum())
        keypoints[~(found & confident)] = np.nan
        self.points += int((found & confident).sum())
        height, width = frame.image.shape[:2]
        self.frames.append(ViaFrame(image_path.name, width, height, keypoints, size=image_path.stat().st_size))
        if self.pictures is not None:
            self._draw(frame.image, image_path.name, keypoints)

    def _draw(self, image: np.ndarray, name: str, keypoints: np.ndarray) -> None:
        """The frame with the points it gets in the project, into the pictures folder; a thumbnail kept for the
        contact sheet (every `_stride`-th frame, the stride doubled whenever twice SHEET_TILES are kept)."""
        from fcnpose_tf.draw import draw_keypoints, enlarged, png_bytes, with_caption

        count = int(np.isfinite(keypoints).all(axis=1).sum())
        picture = with_caption(draw_keypoints(*enlarged(image, keypoints), self.schema),
                               f"{name}: {count} of {self.schema.num_keypoints} keypoints")
        path = self.pictures / f"{len(self.frames):04d}_{Path(name).stem}.png"
        with fileio.parts_of(None):  # kept with the project, removed with it when the run fails
            fileio.write_bytes(path, png_bytes(picture, path), force=self.force)
        self.drawn.append(path)
        if (len(self.frames) - 1) % self._stride == 0:
            scale = SHEET_TILE_WIDTH / picture.shape[1]
            self._tiles.append(cv2.resize(picture, (SHEET_TILE_WIDTH, max(1, round(picture.shape[0] * scale))),
                                          interpolation=cv2.INTER_AREA))
            if len(self._tiles) >= 2 * SHEET_TILES:
                self._tiles, self._stride = self._tiles[::2], self._stride * 2

    def close(self) -> Path | None:
        """Write the VIA project (atomically); None when no frame was added."""
        if not self.frames:
            return None
        written = write_via_project(self.via_path, self.frames, self.schema, force=self.force,
                                    image_dir=self.image_dir if self.reference_files else None)
        if self.saved:
            fileio.record_completed(self.frames_dir)
        if self.pictures is not None:
            self._write_sheet()
            fileio.record_completed(self.pictures)
        return written

    def _write_sheet(self) -> None:
        from fcnpose_tf.draw import contact_sheet, png_bytes

        tiles = self._tiles
        if len(tiles) > SHEET_TILES:  # evenly spread over those kept
            tiles = [tiles[i] for i in np.linspace(0, len(tiles) - 1, SHEET_TILES).round().astype(int)]
        path = self.pictures / "contact_sheet.png"
        fileio.write_bytes(path, png_bytes(contact_sheet(tiles, columns=min(3, len(tiles))), path), force=self.force)
        self.drawn.append(path)

    def discard(self) -> None:
        """Remove the frames saved and pictures drawn so far (a run that failed writes no project)."""
        for path in self.saved + self.drawn:
            path.unlink(missing_ok=True)
        self.saved.clear()
        self.drawn.clear()

    def describe(self) -> str:
        """One line: frames, points, what was left out, and where the frames are."""
        left = [f"{self.not_found} not found"]
        if self.min_confidence > 0:
            left.append(f"{self.below_confidence} below confidence {self.min_confidence:g}")
        where = (f"images in {self.image_dir}" if self.reference_files
                 else f"{len(self.saved)} frames saved in {self.frames_dir}")
        drawn = (f"; drawn in {self.pictures} ({len(self.drawn) - 1} PNG and contact_sheet.png)"
                 if self.pictures is not None and self.drawn else "")
        return (f"{len(self.frames)} frames, {self.points} keypoints as points "
                f"(left out: {', '.join(left)}); {where}{drawn}")


__all__ = ["ViaPredictions", "check_via_output", "FRAMES_FOLDER"]
