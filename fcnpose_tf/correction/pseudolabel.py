"""More frames of the user's camera for retraining, labelled by the user's own model (pseudo-labels).

`label_frames` runs a model over up to `count` frames of a video or an image folder, evenly spread over it, and
writes them as a VIA project (`prelabel.ViaPredictions`: a video's frames saved as PNGs, images referenced where they
are), skipping images that are frames of the user's labelled or measured sets. `project_frames` reads such a project
back, corrected by hand or not, with its labels as they are. `compress --more-frames` adds either to the retraining's
training split only (`data.dataset.with_training_frames`): a 70 % network
retrained on 720 such frames beside the user's 192 kept the unpruned model's PCK@0.5 within 0.02 on a look it was
never pretrained on, where the user's frames alone lost 0.05 (docs/compression.md, "More frames of your look").
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterable

import numpy as np

from fcnpose_tf.correction.merge import image_fingerprint
from fcnpose_tf.data.dataset import AddedFrames, Dataset, load_dataset
from fcnpose_tf.data.via import read_via
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema
from fcnpose_tf.progress import Reporter, resolve
from fcnpose_tf.runtime.estimator import KeypointPredictor
from fcnpose_tf.runtime.sources import FrameSource, open_source

VIA_NAME = "more_frames.json"
"""The labelled frames' VIA project in a temporary folder (`compress --more-frames` without --more-frames-via)."""


@dataclass(frozen=True)
class LabelledFrames:
    """What `label_frames` wrote: the VIA project and how its frames were chosen and labelled."""

    via_path: Path
    source: str
    """The source as the user named it."""
    total: int | None
    """The source's frame count (None: a video that does not say)."""
    read: int
    """Frames read, evenly spread over the source (`count` at most)."""
    known: int
    """Of those, images of the user's labelled or measured frames: left out."""
    frames: int
    """Frames written to the project."""
    keypoints: int
    """Keypoints written as points."""
    not_found: int
    """Keypoints the model did not find (no point)."""
    labelled_by: str
    seconds: float
    most_points: int
    """The most keypoints the model found in one frame."""

    def load(self, schema: KeypointSchema, min_visible: int) -> Dataset:
        """The frames as a dataset of `schema`, those with fewer than `min_visible` keypoints left out (counted by
        `added`, not warned about: the warning would repeat the count, naming a file the user may not know).

        Raises:
            UserError: no frame has `min_visible` keypoints.
        """
        if self.most_points < min_visible:
            raise UserError(f"--more-frames {self.source}: in none of the {self.frames} frames labelled did "
                            f"{self.labelled_by} find {min_visible} keypoints; frames it cannot label add nothing "
                            f"(look with `fcnpose-tf predict {self.labelled_by} --source {self.source} --via "
                            "check.json --draw pictures/`)")
        via_log = logging.getLogger(read_via.__module__)
        level = via_log.level
        via_log.setLevel(logging.ERROR)  # its warning of the frames dropped would name the temporary file
        try:
            return load_dataset(self.via_path, schema=schema, min_visible=min_visible, write_splits=False)
        finally:
            via_log.setLevel(level)

    def added(self, kept: int, min_visible: int) -> AddedFrames:
        """How the retraining's record names these frames once `kept` of them are added (`with_training_frames`: the
        others had fewer than `min_visible` keypoints)."""
        left = [f"{self.known} frames of --data or --test-data"] if self.known else []
        left += [f"{self.frames - kept} with fewer than {min_visible} keypoints"] if kept < self.frames else []
        left_out = f"; left out: {', '.join(left)}" if left else ""
        spread = f"{self.read} of its {self.total}, evenly spread" if self.total else f"its first {self.read}"
        return AddedFrames(self.source, self.labelled_by, kept,
                           f"{kept} frames of {self.source} ({spread}{left_out}) labelled by "
                           f"{self.labelled_by}: {self.keypoints:,} keypoints, {self.not_found:,} not found, in "
                           f"{self.seconds / 60:.1f} min")


FILES_ONLY = ("a camera; --more-frames reads a video file or an image folder: save a camera's frames first "
              "(`fcnpose-tf run MODEL.tflite --source CAMERA --via cam/cam.json --via-every 10`) and pass their "
              "folder, cam/images")
"""Why a camera is refused: a run needs a fixed set of frames, read once."""


def open_frames(source_spec: str | os.PathLike) -> FrameSource:
    """The video or image folder frames are labelled from (`runtime.sources.open_source`, cameras refused).

    Args:
        source_spec: a video file or an image folder (or one image).
    Returns:
        The opened source (the caller closes it).
    Raises:
        UserError: a camera, a missing or unreadable file, a folder without images.
    """
    return open_source(source_spec, refuse_cameras=FILES_ONLY, flag="--more-frames")


def spread_indices(total: int | None, count: int) -> frozenset[int] | None:
    """The frames to read so that `count` of them spread evenly over a source of `total` (all when it has no more):
    the first and the last among them; None when the length is unknown (the first `count` frames are read).

    Args:
        total: the source's frame count, None when it does not say.
        count: how many frames are wanted (at least 1).
    Returns:
        The frame indices, or None.
    """
    if not total:
        return None
    return frozenset(int(i) for i in np.linspace(0, total - 1, min(count, total)).round())


def source_length(source: FrameSource) -> int | None:
    """How many frames a source holds: an image folder's images, a video's frame count (None when it does not say)."""
    if source.kind == "images":
        return len(source.paths)
    return getattr(source, "frame_count", None)


def _known_images(paths: Iterable[str | os.PathLike]) -> set[str]:
    """The given images' pixel fingerprints (`merge.image_fingerprint`), to tell a source image that is one of them,
    under any name or encoding of the same pixels, at one decoding each."""
    return {digest for digest in map(image_fingerprint, map(Path, paths)) if digest is not None}


def _is_known(path: Path, known: set[str]) -> bool:
    return bool(known) and image_fingerprint(path) in known


def label_frames(predictor: KeypointPredictor, source_spec: str | os.PathLike, via_path: str | os.PathLike,
                 count: int, *, force: bool = False, known_images: Iterable[str | os.PathLike] = (),
                 labelled_by: str = "the model", reporter: Reporter | None = None) -> LabelledFrames:
    """Label up to `count` frames of a video or image folder with a model, as the VIA project `via_path`.

    Args:
        predictor: the model (its keypoints become the frames' labels; those it does not find are left out).
        source_spec: a video file or an image folder (a camera is refused: a run needs a fixed set of frames).
        via_path: the .json project to write (a video's frames go to images/ beside it); a project that is
            complete is kept and named by the command's exit path however it ends, the frames of one that is not
            are removed.
        count: at most this many frames, evenly spread over the source (`spread_indices`; the first `count` frames
            when a video does not say its length).
        force: replace an existing project and frame PNGs of the same names.
        known_images: image files of the user's labelled and measured sets: a source image that is one of them
            (the same file, or the same bytes) is left out, so no measured frame is trained on.
        labelled_by: the model's name, for the record.
        reporter: where the progress goes (default: the current one).
    Returns:
        What was written (`LabelledFrames`).
    Raises:
        UserError: a camera or a missing, unreadable or empty source; `count` below 1; an existing project without
            `force`; no frame left to write.
    """
    from fcnpose_tf.correction.prelabel import ViaPredictions

    if count < 1:
        raise UserError(f"--more-frames-count must be at least 1, got {count}")
    reporter = resolve(reporter)
    started = time.perf_counter()
    source = open_frames(source_spec)
    collected = None
    try:
        total = source_length(source)
        wanted = spread_indices(total, count)
        known = _known_images(known_images) if source.kind == "images" else {}
        collected = ViaPredictions(via_path, predictor.schema, source, force=force)
        read = left_out = 0
        expected = len(wanted) if wanted is not None else count
        with reporter.counter(expected, f"labelling frames of {source_spec} with {labelled_by}") as counter:
            for frame in source:
                if wanted is not None and frame.index not in wanted:
                    continue
                read += 1
                counter.update()
                if source.kind == "images" and _is_known(Path(frame.name), known):
                    left_out += 1
                else:
                    collected.add(frame, predictor.predict(frame.image))
                if read >= expected:
                    break
        written = collected.close()
    except BaseException:
        if collected is not None:
            collected.discard()
        raise
    finally:
        source.close()
    if written is None:
        why = f"all {read} frames read are frames of --data or --test-data" if read else "no frame could be read"
        raise UserError(f"{source_spec}: no frame to add ({why})")
    return LabelledFrames(written, os.fspath(source_spec), total, read, left_out, len(collected.frames),
                          collected.points, collected.not_found, labelled_by, round(time.perf_counter() - started, 1),
                          max(int(np.isfinite(frame.keypoints).all(axis=1).sum()) for frame in collected.frames))


def is_project(source_spec: str | os.PathLike) -> bool:
    """Whether a --more-frames source is a VIA project (its frames added with their labels) rather than frames."""
    return Path(source_spec).suffix.lower() == ".json"


def check_source(source_spec: str | os.PathLike) -> None:
    """Refuse, before anything heavy, a --more-frames source that cannot be read: a missing project, a camera, a
    missing or unreadable video, a folder without images (`open_frames`).

    Raises:
        UserError: as above, naming --more-frames.
    """
    if is_project(source_spec):
        if not Path(source_spec).is_file():
            raise UserError(f"--more-frames {source_spec}: VIA project not found")
    else:
        open_frames(source_spec).close()


def project_frames(project: str | os.PathLike, schema: KeypointSchema, min_visible: int, count: int, *,
                   known_images: Iterable[str | os.PathLike] = ()) -> tuple[Dataset, AddedFrames]:
    """The frames of a VIA project with their labels as they are (one `label_frames` wrote and a person corrected,
    or any project of the same keypoints): up to `count` of them, evenly spread, those that are frames of the
    user's sets left out.

    Args:
        project: the VIA .json file (its images beside it, in images/, or where it says).
        schema: the keypoints the model to compress predicts.
        min_visible: frames with fewer labelled keypoints are left out (warned about: the file is the user's).
        count: at most this many frames (`spread_indices` over those left).
        known_images: image files of the user's labelled and measured sets, left out (`label_frames`).
    Returns:
        (the frames as a dataset whose own splits are not to be read, how the records name them).
    Raises:
        UserError: not a readable VIA project of `schema`'s keypoints, or no frame left.
    """
    started = time.perf_counter()
    loaded = load_dataset(project, schema=schema, min_visible=min_visible, write_splits=False)
    known = _known_images(known_images)
    unknown = [sample for sample in loaded.samples if not _is_known(Path(sample.image_path), known)]
    if not unknown:
        raise UserError(f"--more-frames {project}: no frame to add (all {len(loaded)} of its frames are frames of "
                        "--data or --test-data)")
    samples = [unknown[i] for i in sorted(spread_indices(len(unknown), count))]
    left = [f"{len(loaded) - len(unknown)} frames of --data or --test-data"] if len(unknown) < len(loaded) else []
    left += [f"{n} {reason}" for reason, n in loaded.dropped.items() if n]
    spread = f"{len(samples)} of its {len(unknown)}, evenly spread; " if len(samples) < len(unknown) else ""
    points = sum(int(np.isfinite(sample.keypoints).all(axis=1).sum()) for sample in samples)
    description = (f"{len(samples)} frames of {project} ({spread}its labels as they are, {points:,} keypoints"
                   f"{'; left out: ' + ', '.join(left) if left else ''}; read in "
                   f"{(time.perf_counter() - started) / 60:.1f} min)")
    added = AddedFrames(os.fspath(project), None, len(samples), description)
    return replace(loaded, samples=samples), added


__all__ = ["LabelledFrames", "VIA_NAME", "spread_indices", "label_frames", "open_frames", "source_length",
           "is_project", "check_source", "project_frames"]
