"""Frame preprocessing shared by training and the Pi runtime (numpy + OpenCV only).

What a model sees of a frame is its `FrameView`: a box of the frame (the whole frame, as in the paper,
or a workspace crop chosen from the training annotations) resized to the model's H x W input (no
letterbox). A frame (H x W x 3, uint8, BGR as OpenCV reads it) is cropped to the box, resized to the
input, converted to RGB and scaled to [0, 1] float32. Keypoints move with the same offset and factors,
so a keypoint found in map pixels maps back to frame pixels exactly. Wherever a view is taken, an int
S means the whole frame at S x S.

Downscaling is done in two steps: a box filter by the largest whole factor per
axis that divides the side and keeps the frame at least the input size (OpenCV's
INTER_AREA fast path for whole blocks, exact integer arithmetic on uint8;
`block_factor` has the rule), then bilinear to the input size with
INTER_LINEAR_EXACT. On a 640x480 frame to 224x224 this takes
about 0.23 ms against 0.85 ms for INTER_AREA straight to 224 (one core), and
still averages the pixels it drops (no aliasing of sensor noise). Both steps map
the frame's pixel edges onto the output's, so the keypoint scaling below stays
exact.

The bilinear step is OpenCV's bit-exact variant, not INTER_LINEAR: the plain
uint8 kernels round their fixed-point sums differently on x86 and arm64 (a few
pixels one grey level apart), which moved a keypoint by 0.6 px between x86 and
an emulated arm64 Raspberry Pi userland (tools/pi_emulated_check.sh).
INTER_LINEAR_EXACT gives the same bytes on both and stays on the 1/255 grid, so
training arrays stored as uint8 hold exactly the runtime's input. It costs about
0.06 ms more per 640x480 frame than INTER_LINEAR here (0.23 vs 0.17 ms); a
float32 bilinear would be about as fast as INTER_LINEAR and agree across
platforms to ~1e-5, but its output is off the 1/255 grid.
"""

from __future__ import annotations

import contextlib
import json
import os
import zlib
from dataclasses import dataclass
from typing import Any, Union

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import read_regular_file
from fcnpose_tf.nativelog import native_stderr_captured

Box = tuple[int, int, int, int]
"""(x, y, width, height) of a box in frame pixels: columns x..x+width-1, rows y..y+height-1."""


ASPECT_TOLERANCE = 0.01
"""Frames whose width/height differs from a crop's frames' by more than this share get `FrameView.aspect_note`
(1280x720 against 640x480: 0.33; a rounding of the same mode, 1278x720 against 1280x720: 0.002)."""


def same_aspect(size: tuple[int, int], other: tuple[int, int]) -> bool:
    """Whether frames of (width, height) `size` and `other` are of one aspect, within `ASPECT_TOLERANCE`: two modes of
    one camera's view, so a crop stated in one is the same region of the other (`FrameView.box`)."""
    return abs((size[0] / size[1]) / (other[0] / other[1]) - 1) <= ASPECT_TOLERANCE


@dataclass(frozen=True)
class FrameView:
    """What a model sees of a frame: `crop` (the whole frame when None) resized to height x width.

    The crop is part of the model: chosen by `train` from the training annotations (a fixed camera's
    workspace), saved inside the .keras file and every exported .tflite (`to_json`), and applied by every
    command and the Pi runtime. It is stated in pixels of frames of `frame_size`; frames of another size
    get the same box scaled per axis (a camera set to another resolution of the same view).

    Example:
        >>> view = FrameView(224, 288, crop=(80, 60, 480, 360), frame_size=(640, 480))
        >>> view.box((480, 640, 3)), view.box((960, 1280, 3))
        ((80, 60, 480, 360), (160, 120, 960, 720))
    """

    height: int
    width: int
    crop: Box | None = None
    frame_size: tuple[int, int] | None = None
    """(width, height) of the frames `crop` is stated in; None with no crop."""

    def __post_init__(self) -> None:
        if self.height < 1 or self.width < 1:
            raise UserError(f"input size must be positive, got {self.height} x {self.width}")
        if (self.crop is None) != (self.frame_size is None):
            raise UserError("a crop needs the frame size it is stated in, and only a crop has one")
        if self.crop is not None:
            x, y, w, h = self.crop
            fw, fh = self.frame_size
            if w < 1 or h < 1 or x < 0 or y < 0 or x + w > fw or y + h > fh:
                raise UserError(f"crop {self.crop} (x, y, width, height) does not lie inside its {fw} x {fh} frame")

    @classmethod
    def of(cls, view: ViewLike) -> FrameView:
        """A view from an int S (the whole frame at S x S), an (H, W) pair, or a view (returned as is)."""
        if isinstance(view, FrameView):
            return view
        if isinstance(view, (tuple, list)) and len(view) == 2:
            return cls(int(view[0]), int(view[1]))
        if isinstance(view, (int, np.integer)) and not isinstance(view, bool):
            return cls(int(view), int(view))
        raise UserError(f"expected an input size S, (height, width) or a FrameView, got {view!r}")

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the model's input."""
        return self.height, self.width

    @property
    def square(self) -> bool:
        return self.height == self.width

    @property
    def size_record(self) -> int | list[int]:
        """The input size as records state it: S for S x S, [H, W] otherwise (the crop is recorded apart, `to_json`)."""
        return self.height if self.square else [self.height, self.width]

    def box(self, frame_shape: tuple[int, ...]) -> Box:
        """The crop in pixels of a frame of `frame_shape` (height, width[, channels]); the whole frame without one."""
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        if self.crop is None:
            return 0, 0, fw, fh
        if self.frame_size == (fw, fh):
            return self.crop
        x, y, w, h = self.crop
        sx, sy = fw / self.frame_size[0], fh / self.frame_size[1]
        x0, y0 = int(round(x * sx)), int(round(y * sy))
        x1, y1 = int(round((x + w) * sx)), int(round((y + h) * sy))
        return x0, y0, max(1, min(fw, x1) - x0), max(1, min(fh, y1) - y0)

    def aspect_note(self, frame_shape: tuple[int, ...]) -> str | None:
        """What to tell a user whose frames differ in aspect (beyond `ASPECT_TOLERANCE`) from the frames the crop is
        stated in, else None: a camera mode of another aspect sees another part of the scene, so the crop, scaled per
        axis (`box`), no longer frames the same workspace."""
        if self.crop is None:
            return None
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        cw, ch = self.frame_size
        if same_aspect((fw, fh), self.frame_size):
            return None
        return (f"frames of {fw}x{fh} are not of the aspect of the {cw}x{ch} frames the model's crop was set on "
                f"({fw / fh:.2f} against {cw / ch:.2f}): the crop is stretched to fit them and may not frame the arm's "
                f"workspace; give it frames of a {cw}x{ch} camera mode (or its aspect), or train on frames of this one")

    def cropped(self, frame: np.ndarray) -> np.ndarray:
        """The part of `frame` the model sees (a numpy view, no copy)."""
        x, y, w, h = self.box(frame.shape)
        return frame if self.crop is None else frame[y:y + h, x:x + w]

    def crop_sample(self, frame: np.ndarray, keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the part of `frame` the view sees, C-contiguous; K x 2 keypoints in its pixels): a training sample as the
        model sees it before the resize. A keypoint outside the crop is not in the picture: NaN (missing), as a
        keypoint outside the frame is in an annotation."""
        if self.crop is None:
            return frame, keypoints
        x, y, w, h = self.box(frame.shape)
        moved = np.asarray(keypoints, np.float64) - (x, y)
        with np.errstate(invalid="ignore"):
            outside = ((moved < -0.5) | (moved > (w - 0.5, h - 0.5))).any(axis=1)
        moved[outside] = np.nan
        return np.ascontiguousarray(self.cropped(frame)), moved

    def scale(self, frame_shape: tuple[int, ...]) -> np.ndarray:
        """(sx, sy) multiplying crop pixel coordinates into model-input pixel coordinates."""
        _, _, w, h = self.box(frame_shape)
        return np.array([self.width / w, self.height / h], np.float64)

    def with_input(self, height: int, width: int) -> FrameView:
        """The same crop at another input size."""
        return FrameView(int(height), int(width), self.crop, self.frame_size)

    def describe(self, whole: str = " over the whole frame") -> str:
        """E.g. `224x288 over the crop x 80-559, y 60-419 of 640x480 frames` or `224x224 over the whole frame` (`whole`
        after the size when there is no crop)."""
        size = f"{self.height}x{self.width}"
        if self.crop is None:
            return f"{size}{whole}"
        x, y, w, h = self.crop
        return (f"{size} over the crop x {x}-{x + w - 1}, y {y}-{y + h - 1} of "
                f"{self.frame_size[0]}x{self.frame_size[1]} frames")

    def to_json(self) -> dict[str, Any]:
        """The view as stored in model files and records: input_height, input_width, crop_xywh, crop_frame_wh."""
        return {"input_height": self.height, "input_width": self.width,
                "crop_xywh": list(self.crop) if self.crop is not None else None,
                "crop_frame_wh": list(self.frame_size) if self.frame_size is not None else None}

    @classmethod
    def from_json(cls, record: Any) -> FrameView:
        """The view of a `to_json` object; UserError for anything else."""
        try:
            crop, frame = record.get("crop_xywh"), record.get("crop_frame_wh")
            return cls(int(record["input_height"]), int(record["input_width"]),
                       tuple(int(v) for v in crop) if crop is not None else None,
                       tuple(int(v) for v in frame) if frame is not None else None)
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise UserError(f"not a frame view record: {json.dumps(record, default=str)[:200]}") from exc


ViewLike = Union[int, tuple[int, int], FrameView]
"""Anything `FrameView.of` takes: an input side S (the whole frame at S x S), (height, width), or a view."""


def preprocess_frame(frame_bgr: np.ndarray, view: ViewLike, out: np.ndarray | None = None) -> np.ndarray:
    """The model's input for a BGR uint8 frame: its view's box resized to H x W, RGB float32 in [0, 1].

    `view` is a `FrameView` or an int S (the whole frame at S x S); `out` (H x W x 3 float32) may be
    given to reuse a buffer.
    """
    view = FrameView.of(view)
    if out is None:
        out = np.empty((view.height, view.width, 3), np.float32)
    np.multiply(preprocess_frame_bytes(frame_bgr, view), np.float32(1.0 / 255.0), out=out, casting="unsafe")
    return out


def preprocess_frame_bytes(frame_bgr: np.ndarray, view: ViewLike, out: np.ndarray | None = None) -> np.ndarray:
    """The resized RGB frame as uint8 bytes: `preprocess_frame` before its scaling to [0, 1].

    ``preprocess_frame(f, v) == preprocess_frame_bytes(f, v) / 255`` exactly, so a model whose
    input is uint8 with scale 1/255 and zero point 0 (the int8 export) takes these bytes as they
    are. `out` (H x W x 3 uint8, C-contiguous, e.g. the interpreter's input tensor) receives them
    without a copy.
    """
    if frame_bgr is None or frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
        shape = None if frame_bgr is None else frame_bgr.shape
        raise UserError(f"expected a colour frame of shape H x W x 3, got {shape}")
    view = FrameView.of(view)
    height, width = view.shape
    small = box_reduce(view.cropped(frame_bgr), (height, width))
    if small.shape[:2] != (height, width):
        small = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR_EXACT)
    if out is None:
        return cv2.cvtColor(small, cv2.COLOR_BGR2RGB)
    if out.shape != (height, width, 3) or out.dtype != np.uint8 or not out.flags.c_contiguous:
        raise UserError(f"expected a C-contiguous {height} x {width} x 3 uint8 buffer, "
                        f"got {out.dtype} {out.shape}")
    result = cv2.cvtColor(small, cv2.COLOR_BGR2RGB, dst=out)
    if result is not out and not np.shares_memory(result, out):  # OpenCV allocated instead of filling `out`
        out[...] = result
    return out


def box_reduce(image: np.ndarray, input_size: int | tuple[int, int]) -> np.ndarray:
    """Average blocks of pixels: per axis the largest factor that divides the side and keeps it >= the input's
    side (`block_factor`); `input_size` is S or (height, width).

    OpenCV's INTER_AREA takes its exact integer path for whole blocks; an image less than twice
    the input on both sides is returned as is.
    """
    height, width = (input_size, input_size) if np.isscalar(input_size) else input_size
    h, w = image.shape[:2]
    fx, fy = block_factor(w, int(width)), block_factor(h, int(height))
    if fx == 1 and fy == 1:
        return image
    return cv2.resize(image, (w // fx, h // fy), interpolation=cv2.INTER_AREA)


def block_factor(side: int, input_size: int) -> int:
    """The box reduction's factor along a side: the largest f <= side // input_size that divides `side`,
    unless the bilinear step after it would then reduce by 2 or more (skipping pixels): then side // input_size.

    A factor that does not divide the side (640 // 192 = 3) sends INTER_AREA to its general fractional
    path: 640 x 480 to 213 x 240 took 1.5 ms on one core against 0.12 ms for the 2 x 2 blocks to 320 x 240
    that this picks instead (the bilinear step then reduces by 1.67 rather than 1.11). A side with no such
    divisor (a prime 601 to 64) keeps the fractional factor, which still averages every pixel, but is neither
    fast nor bit-exact across platforms (a 547-wide crop to 256: 2.9 ms, and 1.2 px of keypoint difference on
    arm64), which is why `data.arm_size.block_friendly` rounds crop sides.

    Example:
        >>> block_factor(640, 224), block_factor(640, 192), block_factor(480, 160), block_factor(601, 64)
        (2, 2, 3, 9)
    """
    most = max(1, side // input_size)
    for factor in range(most, 1, -1):
        if side % factor == 0:
            return factor if side // factor < 2 * input_size else most
    return 1 if side < 2 * input_size else most


def keypoints_to_input(keypoints: np.ndarray, frame_shape: tuple[int, ...], view: ViewLike) -> np.ndarray:
    """Move K x 2 (x, y) frame-pixel keypoints to model-input pixels (NaN stays NaN).

    Coordinates follow the pixel-centre convention of OpenCV and VIA (pixel i's
    centre is at i), so scaling goes through the pixel edges: (x - x0 + 0.5) * s - 0.5
    for a crop starting at column x0, which is how cv2.resize places pixel centres.
    A keypoint outside the view's crop lands outside the input (below 0 or past its side).
    """
    view = FrameView.of(view)
    x, y, _, _ = view.box(frame_shape)
    return (np.asarray(keypoints, np.float64) - (x, y) + 0.5) * view.scale(frame_shape) - 0.5


def keypoints_to_frame(keypoints: np.ndarray, frame_shape: tuple[int, ...], view: ViewLike) -> np.ndarray:
    """Move K x 2 keypoints from map/model-input pixels back to frame pixels (NaN stays NaN): the inverse of
    `keypoints_to_input` for the same view."""
    view = FrameView.of(view)
    x, y, _, _ = view.box(frame_shape)
    return (np.asarray(keypoints, np.float64) + 0.5) / view.scale(frame_shape) - 0.5 + (x, y)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _damaged_png(raw: bytes) -> bool:
    """Whether `raw` is a PNG whose chunks do not all check out: one cut off, one whose CRC-32 does not match its
    bytes, or no IEND. libpng prints its own `libpng error: ...` line for such a file as it fails to decode it. False
    for any other format, and for an intact PNG (about 0.1 ms for a 640 x 480 frame: zlib's CRC)."""
    if not raw.startswith(_PNG_SIGNATURE):
        return False
    view, at = memoryview(raw), len(_PNG_SIGNATURE)
    while at + 12 <= len(raw):
        length = int.from_bytes(view[at:at + 4], "big")
        end = at + 12 + length
        if end > len(raw) or zlib.crc32(view[at + 4:end - 4]) != int.from_bytes(view[end - 4:end], "big"):
            return True
        if view[at + 4:at + 8] == b"IEND":
            return False
        at = end
    return True


def read_image(path: str | os.PathLike, flags: int = cv2.IMREAD_COLOR) -> np.ndarray | None:
    """An image file as `cv2.imread(path, flags)` reads it, None if it is not a readable image.

    The bytes are read by numpy and decoded from memory, so any file name the file system holds works
    (`cv2.imread` passes the name as UTF-8 and crashes the process on a name that is not); an OSError
    (missing, a folder, no permission, a named pipe: `fileio.read_regular_file`) reads as None, as with
    `cv2.imread`, and so does a header OpenCV refuses to decode (one that claims 40000 x 40000 pixels).
    """
    try:
        raw = read_regular_file(path)
    except (OSError, ValueError):
        return None
    if not raw:
        return None
    try:  # libpng prints its own "libpng error: ..." line for a damaged PNG: kept off the terminal (None says it)
        with native_stderr_captured() if _damaged_png(raw) else contextlib.nullcontext():
            return cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), flags)
    except cv2.error:
        return None


