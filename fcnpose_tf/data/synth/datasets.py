"""Dataset folders: frames rendered by a pool of workers into images/*.png plus one VIA project file.

The same seed gives byte-identical files for any number of workers.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from fcnpose_tf.data.synth.frame import render_sample
from fcnpose_tf.data.synth.looks import DEFAULT_LABELS, DEFAULT_LOOKS, check_labels, look_family
from fcnpose_tf.data.synth.scene import DEFAULT_SCENE, DEFAULT_TIGHT_FRAMING, SCENES
from fcnpose_tf import progress as reporting
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5
from fcnpose_tf.system import available_cores


VIA_FILENAME = "ur5_synth.json"
"""Name of the VIA project file `generate` writes in the output folder."""
IMAGE_DIR = "images"
IMAGE_NAME = "synth_{index:05d}.png"
STAGING_PREFIX = ".synth-new."
"""A new set is rendered into OUT/.synth-new.PID/ and replaces the earlier one only once it is complete."""
PNG_COMPRESSION = 1  # fast; level 3 saves only ~4 % on noisy frames


@dataclass
class FrameRecord:
    """What a worker reports about one written frame."""

    index: int
    filename: str
    size: int
    keypoints: np.ndarray
    occluded: np.ndarray
    person: str
    mount: str
    tool: str
    arm: str = "ur5"


@dataclass
class SynthReport:
    """Result of `generate_dataset`: where the VIA file is, one record per frame, and the wall time."""

    via_path: Path
    frames: list[FrameRecord]
    seconds: float
    workers: int
    width: int
    height: int
    looks: str = DEFAULT_LOOKS
    labels: str = DEFAULT_LABELS
    motion_fps: float | None = None

    def summary_rows(self) -> list[tuple[str, object]]:
        """(quantity, value) rows for the CLI's closing table."""
        n = len(self.frames)
        kp = np.stack([f.keypoints for f in self.frames])
        visible = np.isfinite(kp).all(-1)
        occluded = np.stack([f.occluded for f in self.frames])
        span = []
        for k in kp:
            k = k[np.isfinite(k).all(1)]
            if len(k):
                span.append((k[:, 1].max() - k[:, 1].min()) / self.height)
        count = lambda attr, value: sum(getattr(f, attr) == value for f in self.frames)  # noqa: E731
        return [
            ("frames", n),
            ("frame size (px)", f"{self.width}x{self.height}"),
            ("look family / keypoint labels", f"{self.looks} / {self.labels}"),
            ("motion sequence", "no" if self.motion_fps is None else
             f"{self.motion_fps:g} FPS, {n / self.motion_fps:.1f} s, {MOTION_VIDEO}"),
            ("arms", ", ".join(f"{a} {sum(f.arm == a for f in self.frames)}"
                               for a in sorted({f.arm for f in self.frames}))),
            ("end effectors", ", ".join(f"{t} {count('tool', t)}" for t in sorted({f.tool for f in self.frames}))),
            ("keypoints annotated (in frame)", f"{int(visible.sum())} of {visible.size}"),
            ("frames with all 8 keypoints", int(visible.all(1).sum())),
            ("frames with the person hiding part of the arm", int(occluded.any(1).sum())),
            ("keypoints hidden by the person (still annotated)", int(occluded.sum())),
            ("frames with a person in the scene", n - count("person", "none")),
            ("mounts floor / pedestal / table", f"{count('mount', 'floor')} / {count('mount', 'pedestal')} / "
                                                f"{count('mount', 'table')}"),
            ("keypoint box height / frame height, median", round(float(np.median(span)), 3) if span else None),
            ("wall time (s)", round(self.seconds, 1)),
            ("frames per second", round(n / max(self.seconds, 1e-9), 1)),
            ("workers", self.workers),
        ]


def _init_worker() -> None:
    import signal

    cv2.setNumThreads(1)  # one process per core; OpenCV's own threads would only compete
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the main process ends the pool


def _render_and_write(task: tuple) -> FrameRecord:
    """Worker: render frame `index`, write it as PNG atomically, return its record."""
    from fcnpose_tf import fileio

    seed, index, width, height, image_dir, tight_framing, scene, scene_seed, looks, labels, joints = task
    sample = render_sample(seed, index, width, height, tight_framing, scene, scene_seed, looks, labels,
                           joints=None if joints is None else np.array(joints), person=joints is None)
    ok, buf = cv2.imencode(".png", sample.image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 BGR image
        raise RuntimeError("PNG encoding failed")
    name = IMAGE_NAME.format(index=index)
    data = buf.tobytes()
    fileio.write_bytes(Path(image_dir) / name, data, force=True)
    return FrameRecord(index, name, len(data), sample.keypoints, sample.occluded, sample.person, sample.mount,
                       sample.tool, sample.arm)


def default_workers() -> int:
    """Cores this process may run on."""
    return available_cores()


def _prepare_output(out_dir: Path, force: bool) -> Path:
    from fcnpose_tf import fileio

    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise UserError(f"{out_dir}: folder is not empty; pass --force to write into it (replacing earlier "
                        "synthetic frames)")
    fileio.make_folder(out_dir / IMAGE_DIR)
    for folder in (out_dir, out_dir / IMAGE_DIR):
        if not os.access(folder, os.W_OK | os.X_OK):
            raise UserError(f"{folder}: output folder is not writable")
    return out_dir / IMAGE_DIR


def _staging_folder(out_dir: Path) -> Path:
    """OUT/.synth-new.PID/, made for this process; those a killed (SIGKILL) earlier run left are removed first."""
    import shutil

    from fcnpose_tf import fileio

    for stale in out_dir.glob(STAGING_PREFIX + "*"):
        pid = stale.name[len(STAGING_PREFIX):]
        if pid.isdigit() and (int(pid) == os.getpid() or not fileio._process_alive(int(pid))):
            shutil.rmtree(stale, ignore_errors=True)
    return fileio.make_folder(out_dir / f"{STAGING_PREFIX}{os.getpid()}")


MAX_FRAMES = 1_000_000
"""`--n` at most: a million frames of 640 x 480 fill about 300 GB; more is a typing slip, refused before any work."""
MAX_SIDE = 8192
"""`--width`/`--height` at most (8K): the scene is drawn at the frame's size, 190 MB a frame at 8192 x 8192."""
MAX_MOTION_FPS = 1000.0
"""`--motion` at most: a frame rate a camera has (infinity or 1e300 would make the steps between frames zero)."""


def generate_dataset(out_dir: str | os.PathLike, n: int = 500, seed: int = 0, width: int = 640, height: int = 480,
                     workers: int | None = None, force: bool = False, progress: bool = True,
                     tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE,
                     scene_seed: int = 0, looks: str = DEFAULT_LOOKS, labels: str = DEFAULT_LABELS,
                     motion_fps: float | None = None) -> SynthReport:
    """Render n frames into out_dir/images/*.png and write out_dir/ur5_synth.json (VIA 2.x project).

    Frames are rendered by a pool of `workers` processes (default: one per core);
    the files are the same for any number of workers. `scene` and `scene_seed` choose one fixed
    workcell or a new random cell per frame (see DEFAULT_SCENE); `looks` the look family and `labels`
    the keypoint convention (`looks.FAMILIES`, `looks.LABEL_CONVENTIONS`). A non-empty out_dir is refused
    unless force, which also removes what belonged to the set being replaced: synth_*.png
    frames beyond n and the stored folds (ur5_synth.splits.json). The new set is rendered beside the
    old one (OUT/.synth-new.PID/) and replaces it only once complete: a full disk or a stop signal
    leaves the earlier set as it was. With `motion_fps` (workcell only) the frames are a sequence: the
    arm moving smoothly through its task at that frame rate (`motion.motion_joints`), nobody beside it,
    also written as OUT/motion.mp4.

    Raises:
        UserError: n outside 1..MAX_FRAMES, a frame side below 32 or above MAX_SIDE, workers < 1, an unknown
            scene, look family or label convention, tight_framing outside [0, 1], or an output folder that is not empty (without force), not a folder, or not writable.
            Every option is checked before anything in out_dir is touched.
    """
    from fcnpose_tf import fileio
    from fcnpose_tf.data.splits import splits_path
    from fcnpose_tf.data.via import ViaFrame, write_via_project

    if int(n) != n or not 1 <= n <= MAX_FRAMES:
        raise UserError(f"--n must be between 1 and {MAX_FRAMES:,}, got {n}")
    if width < 32 or height < 32:
        raise UserError(f"frame size {width}x{height} is too small; expected at least 32x32")
    if max(width, height) > MAX_SIDE:
        raise UserError(f"frame size {width}x{height} is too large; expected sides of at most {MAX_SIDE} pixels")
    if scene not in SCENES:
        raise UserError(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}")
    look_family(looks)
    check_labels(labels)
    if motion_fps is not None and (not 0 < motion_fps <= MAX_MOTION_FPS or scene != "workcell"):
        raise UserError(f"--motion needs a frame rate above 0 and at most {MAX_MOTION_FPS} and --scene workcell, "
                        f"got {motion_fps} FPS with --scene {scene}")
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    if not 0.0 <= tight_framing <= 1.0:
        raise UserError(f"--tight-framing must be between 0 and 1, got {tight_framing}")
    out_dir = Path(out_dir)  # every option checked
    image_dir = _prepare_output(out_dir, force)
    staging = _staging_folder(out_dir)

    start = time.perf_counter()
    joints = [None] * n
    if motion_fps is not None:
        from fcnpose_tf.data.synth.motion import motion_joints

        joints = motion_joints(seed, n, motion_fps, scene_seed, width, height, looks).tolist()
    tasks = [(int(seed), i, int(width), int(height), str(staging), float(tight_framing), scene, int(scene_seed),
              looks, labels, joints[i]) for i in range(n)]
    workers = min(workers, n)
    records: list[FrameRecord] = []
    # the frames are parts of the set: a failure before its VIA file is written keeps none of them as an
    # output of its own, whether a worker process or this one wrote it
    reporter = reporting.current() if progress else reporting.Reporter(silent=True)
    try:
        with fileio.parts_of(out_dir), reporter.counter(n, "synth") as bar:
            if workers == 1:
                for task in tasks:
                    records.append(_render_and_write(task))
                    bar.update()
            else:
                import multiprocessing

                ctx = multiprocessing.get_context("spawn")  # safe even when the caller has threads (TF, OpenCV)
                with ctx.Pool(workers, initializer=_init_worker) as pool:
                    for record in pool.imap_unordered(_render_and_write, tasks, chunksize=4):
                        records.append(record)
                        bar.update()
            records.sort(key=lambda r: r.index)
            frames = [ViaFrame(r.filename, width, height, r.keypoints, size=r.size) for r in records]
            if motion_fps is not None:
                _write_video(staging / MOTION_VIDEO, [staging / r.filename for r in records], motion_fps, width, height)
            with fileio.signals_deferred():  # the earlier set is replaced whole, or not at all
                # a full disk fails here
                write_via_project(staging / VIA_FILENAME, frames, UR5, attribute="keypoint", force=True)
                keep = {r.filename for r in records}
                for stale in image_dir.glob("synth_*.png"):  # what belonged to the set being replaced
                    if stale.name not in keep:
                        stale.unlink()
                splits_path(out_dir / VIA_FILENAME).unlink(missing_ok=True)  # folds of the set being replaced
                for record in records:
                    os.replace(staging / record.filename, image_dir / record.filename)
                if motion_fps is not None:
                    os.replace(staging / MOTION_VIDEO, out_dir / MOTION_VIDEO)
                via_path = out_dir / VIA_FILENAME
                os.replace(staging / VIA_FILENAME, via_path)
                staging.rmdir()
    except fileio.WriteError as exc:  # `OUT/.synth-new.PID/synth_00007.png: no space left on device`
        raise fileio.WriteError(_named_as_output(str(exc), staging, out_dir)) from None
    return SynthReport(Path(via_path), records, time.perf_counter() - start, workers, int(width), int(height), looks,
                       labels, motion_fps)


def _named_as_output(message: str, staging: Path, out_dir: Path) -> str:
    """A write error's `PATH: reason` about a file in the staging folder, told of the output folder the user named
    (`OUT: no space left on device`); any other message as it is."""
    if not message.startswith(str(staging)):
        return message
    _, _, reason = message[len(str(staging)):].partition(": ")  # the staged files' own names hold no ": "
    return f"{out_dir}: {reason}"


MOTION_VIDEO = "motion.mp4"
"""The video `generate_dataset` writes beside the frames of a motion sequence."""


def _write_video(path: Path, images: list[Path], fps: float, width: int, height: int) -> None:
    """The frames as an MPEG-4 video (OpenCV's mp4v) at `fps`."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (int(width), int(height)))
    if not writer.isOpened():  # pragma: no cover - opencv-python-headless ships the mp4v encoder
        raise UserError(f"{path}: OpenCV cannot write an mp4v video here")
    try:
        for image in images:
            writer.write(cv2.imdecode(np.fromfile(image, np.uint8), cv2.IMREAD_COLOR))
    finally:
        writer.release()


def generate(out_dir: str | os.PathLike, n: int = 500, seed: int = 0, width: int = 640, height: int = 480,
             workers: int | None = None, force: bool = False, progress: bool = True,
             tight_framing: float = DEFAULT_TIGHT_FRAMING, scene: str = DEFAULT_SCENE, scene_seed: int = 0,
             looks: str = DEFAULT_LOOKS, labels: str = DEFAULT_LABELS, motion_fps: float | None = None) -> Path:
    """Render a synthetic UR5 dataset into out_dir (see `generate_dataset`); returns the VIA file's path.

    Example:
        >>> via = generate("data/synth", n=500, seed=0)   # data/synth/images/*.png + ur5_synth.json
    """
    return generate_dataset(out_dir, n, seed, width, height, workers, force, progress, tight_framing, scene,
                            scene_seed, looks, labels, motion_fps).via_path
