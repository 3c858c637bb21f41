"""Frame preprocessing shared by training and the Pi runtime (numpy + OpenCV only).

A frame (H x W x 3, uint8, BGR as OpenCV reads it) is resized to the model's
square input (no letterbox: the paper resizes the whole frame), converted to
RGB and scaled to [0, 1] float32. Keypoints scale with the same factors, so a
keypoint found in map pixels maps back to frame pixels exactly.

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

import os

import cv2
import numpy as np

from fcnpose_tf.errors import UserError


def preprocess_frame(frame_bgr: np.ndarray, input_size: int, out: np.ndarray | None = None) -> np.ndarray:
    """Resize a BGR uint8 frame to input_size x input_size RGB float32 in [0, 1].

    `out` (input_size x input_size x 3 float32) may be given to reuse a buffer.
    """
    if out is None:
        out = np.empty((input_size, input_size, 3), np.float32)
    np.multiply(preprocess_frame_bytes(frame_bgr, input_size), np.float32(1.0 / 255.0), out=out, casting="unsafe")
    return out


def preprocess_frame_bytes(frame_bgr: np.ndarray, input_size: int, out: np.ndarray | None = None) -> np.ndarray:
    """The resized RGB frame as uint8 bytes: `preprocess_frame` before its scaling to [0, 1].

    ``preprocess_frame(f, s) == preprocess_frame_bytes(f, s) / 255`` exactly, so a model whose
    input is uint8 with scale 1/255 and zero point 0 (the int8 export) takes these bytes as they
    are. `out` (input_size x input_size x 3 uint8, C-contiguous, e.g. the interpreter's input
    tensor) receives them without a copy.
    """
    if frame_bgr is None or frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
        shape = None if frame_bgr is None else frame_bgr.shape
        raise UserError(f"expected a colour frame of shape H x W x 3, got {shape}")
    small = box_reduce(frame_bgr, input_size)
    if small.shape[:2] != (input_size, input_size):
        small = cv2.resize(small, (input_size, input_size), interpolation=cv2.INTER_LINEAR_EXACT)
    if out is None:
        return cv2.cvtColor(small, cv2.COLOR_BGR2RGB)
    if out.shape != (input_size, input_size, 3) or out.dtype != np.uint8 or not out.flags.c_contiguous:
        raise UserError(f"expected a C-contiguous {input_size} x {input_size} x 3 uint8 buffer, "
                        f"got {out.dtype} {out.shape}")
    result = cv2.cvtColor(small, cv2.COLOR_BGR2RGB, dst=out)
    if result is not out and not np.shares_memory(result, out):  # OpenCV allocated instead of filling `out`
        out[...] = result
    return out


def box_reduce(image: np.ndarray, input_size: int) -> np.ndarray:
    """Average blocks of pixels: per axis the largest factor that divides the side and keeps it >= input_size
    (`block_factor`).

    OpenCV's INTER_AREA takes its exact integer path for whole blocks; an image less than twice
    input_size on both sides is returned as is.
    """
    h, w = image.shape[:2]
    fx, fy = block_factor(w, input_size), block_factor(h, input_size)
    if fx == 1 and fy == 1:
        return image
    return cv2.resize(image, (w // fx, h // fy), interpolation=cv2.INTER_AREA)


def block_factor(side: int, input_size: int) -> int:
    """The box reduction's factor along a side: the largest f <= side // input_size that divides `side`,
    unless the bilinear step after it would then reduce by 2 or more (skipping pixels): then side // input_size.

    A factor that does not divide the side (640 // 192 = 3) sends INTER_AREA to its general fractional
    path: 640 x 480 to 213 x 240 took 1.5 ms on one core against 0.12 ms for the 2 x 2 blocks to 320 x 240
    that this picks instead (the bilinear step then reduces by 1.67 rather than 1.11). A side with no such
    divisor (a prime 601 to 64) keeps the fractional factor, which still averages every pixel.

    Example:
        >>> block_factor(640, 224), block_factor(640, 192), block_factor(480, 160), block_factor(601, 64)
        (2, 2, 3, 9)
    """
    most = max(1, side // input_size)
    for factor in range(most, 1, -1):
        if side % factor == 0:
            return factor if side // factor < 2 * input_size else most
    return 1 if side < 2 * input_size else most


def frame_to_input_scale(frame_shape: tuple[int, ...], input_size: int) -> np.ndarray:
    """(sx, sy) multiplying frame pixel coordinates into model-input pixel coordinates."""
    h, w = frame_shape[:2]
    return np.array([input_size / w, input_size / h], np.float64)


def keypoints_to_input(keypoints: np.ndarray, frame_shape: tuple[int, ...], input_size: int) -> np.ndarray:
    """Scale K x 2 (x, y) frame-pixel keypoints to model-input pixels (NaN stays NaN).

    Coordinates follow the pixel-centre convention of OpenCV and VIA (pixel i's
    centre is at i), so scaling goes through the pixel edges: (x + 0.5) * s - 0.5,
    which is how cv2.resize places pixel centres.
    """
    return (np.asarray(keypoints, np.float64) + 0.5) * frame_to_input_scale(frame_shape, input_size) - 0.5


def keypoints_to_frame(keypoints: np.ndarray, frame_shape: tuple[int, ...], map_size: int) -> np.ndarray:
    """Scale K x 2 keypoints from map/model-input pixels back to frame pixels (NaN stays NaN)."""
    return (np.asarray(keypoints, np.float64) + 0.5) / frame_to_input_scale(frame_shape, map_size) - 0.5


def read_image(path: str | os.PathLike, flags: int = cv2.IMREAD_COLOR) -> np.ndarray | None:
    """An image file as `cv2.imread(path, flags)` reads it, None if it is not a readable image.

    The bytes are read by numpy and decoded from memory, so any file name the file system holds works
    (`cv2.imread` passes the name as UTF-8 and crashes the process on a name that is not); an OSError
    (missing, a folder, no permission) reads as None, as with `cv2.imread`.
    """
    try:
        data = np.fromfile(os.fspath(path), dtype=np.uint8)
    except (OSError, ValueError):
        return None
    if data.size == 0:
        return None
    return cv2.imdecode(data, flags)


def opencv_name(path: str | os.PathLike) -> str:
    """A name for `path` that OpenCV's VideoCapture and VideoWriter can take.

    OpenCV passes names to its native code as UTF-8 and crashes the process on one that is not
    (`clip\\xe9.mp4`): such a path is reached through a symbolic link of a plain name in a new
    temporary folder (the command's own, removed when it ends; outside the CLI, removed at exit).
    """
    text = os.fspath(path)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    import atexit
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="fcnpose-tf-name.")
    atexit.register(shutil.rmtree, folder, True)
    suffix = os.path.splitext(text)[1]
    try:
        suffix.encode("utf-8")
    except UnicodeEncodeError:
        suffix = ""
    link = os.path.join(folder, "file" + suffix)  # the suffix picks OpenCV's container
    os.symlink(os.path.abspath(text), link)
    return link
