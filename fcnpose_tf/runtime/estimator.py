"""Predictors: a BGR frame in, keypoints in the frame's pixels out, with per-stage timings.

`KeypointPredictor` is the one frame path (preprocess -> forward -> decode) every backend shares;
the stages are the ones the FPS definition adds up (docs/runtime.md): preprocessing (the training
side's `preprocess_frame`), the network's forward pass, and post-processing (`postprocess.decode`:
`maps_to_keypoints`, then scaling back to the frame). A backend supplies only the forward pass and
its buffers. `KeypointModel` is the LiteRT one (preprocessing writes straight into the
interpreter's input buffer); the tf_keras one is `fcnpose_tf.training.evaluate.KerasKeypointModel`.
No per-frame allocation of model-sized buffers; not thread-safe (one model per thread).
"""

from __future__ import annotations

import abc
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TypedDict

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema, schema_for_maps
from fcnpose_tf.postprocess import Decoding
from fcnpose_tf.postprocess import dequantize
from fcnpose_tf.preprocess import Box, FrameView, preprocess_frame, preprocess_frame_bytes
from fcnpose_tf.runtime.interpreter import (Backend, ModelIO, ModelStats, default_num_threads, inspect_io,
                                            load_interpreter, model_stats, read_schema, read_view)

logger = logging.getLogger(__name__)


class KeypointRecord(TypedDict):
    """One keypoint as record files hold it (`Prediction.records`), in frame pixels."""

    name: str
    x: float | None
    """None: not found."""
    y: float | None
    confidence: float | int | None
    """Post-processing's confidence (`Prediction.confidence`: the winning cluster's pixel count, 0 when not found), an
    int when whole; None when not finite."""


@dataclass(frozen=True)
class StageTimes:
    """Milliseconds spent in each stage for one frame."""

    preprocess_ms: float
    invoke_ms: float
    postprocess_ms: float

    @property
    def total_ms(self) -> float:
        """End-to-end model time: preprocess + invoke + postprocess (the FPS denominator)."""
        return self.preprocess_ms + self.invoke_ms + self.postprocess_ms


CROP_EDGE_SHARE = 0.04
"""A found keypoint this share of the crop's width (height) from its left or right (top or bottom) border is "at the
crop's edge" (`Prediction.at_crop_edge`): beyond every keypoint the model was trained on, since `train`'s workspace
crop adds `data.arm_size.WORKSPACE_MARGIN` (0.05) of the keypoints' box on each side, 0.045 of the crop (a test ties
the two). At 0.10 a fixed camera's base, which never moves, flagged every frame where it sat near an inner border (the
new cell: 9.4 % from the crop's bottom, 298 of 300 test frames). Rarely set: a keypoint past the crop is lost or
placed elsewhere in it more often than at its border (docs/results.md, "The crop's edge, and the time budget's epoch
warning")."""


@dataclass(frozen=True)
class Prediction:
    """Keypoints of one frame: K x 2 (x, y) in frame pixels (NaN = not found) and K confidences.

    The confidence is post-processing's: the pixel count of the keypoint's
    winning cluster in the output map (0 when not found).
    """

    keypoints: np.ndarray
    confidence: np.ndarray
    times: StageTimes
    frame_shape: tuple[int, ...]
    crop: Box | None = None
    """The box of the frame the model saw (x, y, width, height), when the model reads a crop (`preprocess.FrameView`):
    no keypoint can be found outside it."""

    @property
    def found(self) -> np.ndarray:
        """Boolean mask of the keypoints that were found."""
        return ~np.isnan(self.keypoints).any(axis=1)

    def at_crop_edge(self, share: float = CROP_EDGE_SHARE) -> np.ndarray:
        """Boolean mask of the found keypoints within `share` of the crop's size from one of its borders that lies
        inside the frame: the arm may reach past the crop there (a pose outside the workspace the model was trained
        on), and a keypoint beyond it is placed at the border or not found. A border on the frame's own edge does
        not count (the whole frame ends there too).

        Args:
            share: the margin, as a share of the crop's width (for x) and height (for y).
        Returns:
            K booleans; all False without a crop.
        """
        if self.crop is None:
            return np.zeros(len(self.keypoints), bool)
        x, y, w, h = self.crop
        frame_h, frame_w = self.frame_shape[:2]
        margin = share * np.array([w, h], np.float64)
        inner_low = np.array([x > 0, y > 0])  # the crop's left/top border lies inside the frame
        inner_high = np.array([x + w < frame_w, y + h < frame_h])
        with np.errstate(invalid="ignore"):
            low = (self.keypoints < np.array([x - 0.5, y - 0.5]) + margin) & inner_low
            high = (self.keypoints > np.array([x + w - 0.5, y + h - 0.5]) - margin) & inner_high
        return self.found & (low | high).any(axis=1)

    def records(self, schema: KeypointSchema, decimals: int = 2) -> list[KeypointRecord]:
        """The keypoints as records for JSON and CSV outputs.

        Args:
            schema: the keypoint names, in the order of the rows of `keypoints`.
            decimals: x and y are rounded to this many decimals (confidences to 4 unless whole).
        Returns:
            One {name, x, y, confidence} per keypoint; x and y are None for a keypoint not found, confidence None
            when it is not finite.
        """
        out: list[KeypointRecord] = []
        for i, name in enumerate(schema.keypoints):
            x, y = (float(v) for v in self.keypoints[i])
            c = float(self.confidence[i])
            found = math.isfinite(x) and math.isfinite(y)
            if not math.isfinite(c):
                conf: float | int | None = None
            else:
                conf = int(c) if c.is_integer() else round(c, 4)
            out.append({"name": name,
                        "x": round(x, decimals) if found else None,
                        "y": round(y, decimals) if found else None,
                        "confidence": conf})
        return out


class KeypointPredictor(abc.ABC):
    """An FCN-Pose ready to run on frames: preprocess -> forward -> decode, each stage timed.

    A backend implements `set_input` (preprocess a frame into the model's input), `invoke` (the
    forward pass), `read_maps` (the output maps of the last forward pass) and `backend_label`; it
    sets `view`, `num_maps`, `decoding` and `num_threads`. Decoding and `predict` are
    shared, so every backend maps keypoints back to frame pixels and times its stages the same way.
    """

    view: FrameView
    """What the model sees of a frame: its crop (or the whole frame) resized to the H x W input."""
    num_maps: int
    """Output maps: one per keypoint, then the skeleton map."""
    decoding: Decoding = Decoding()
    """How maps become keypoints: threshold, fallback and centroid (`postprocess.Decoding`)."""
    num_threads: int | None
    """Threads of the forward pass (None: the library's default)."""
    schema: KeypointSchema
    """Keypoint names and skeleton of the output maps: the model's own, else `keypoints.schema_for_maps`."""
    names_keypoints: bool = False
    """Whether `schema` is the model's own (given, or stored in its file or its training record), not the default for
    its number of maps: `training.evaluate.evaluate_predictor` then reads the data's keypoints by these names."""
    pipelinable: bool = False
    """True when the backend implements the staged-frame methods (`new_input`, `preprocess_into`,
    `new_output`, `forward`, `decode_output`) that `runtime.pipeline` runs on two threads."""

    @property
    @abc.abstractmethod
    def backend_label(self) -> str:
        """What runs the forward pass, for reports (e.g. `ai_edge_litert 2.3.0`)."""

    @abc.abstractmethod
    def set_input(self, frame_bgr: np.ndarray) -> None:
        """Preprocess a BGR uint8 frame into the model's input (the training preprocessing).

        Args:
            frame_bgr: H x W x 3 uint8, any size (the model's view crops and resizes it).
        """

    @abc.abstractmethod
    def invoke(self) -> None:
        """Run the network on the current input."""

    @abc.abstractmethod
    def read_maps(self, copy: bool = True) -> np.ndarray:
        """The output maps of the last invoke.

        Args:
            copy: False may return a view of a buffer the next invoke overwrites; drop it before then.
        Returns:
            M x M x C float32 probabilities.
        """

    def describe(self) -> str:
        """One line for progress and reports: model, shapes, backend and threads.

        Returns:
            "NAME (HxWx3 -> C maps[; crop ...]), BACKEND, N threads"; "model" when the predictor has no path.
        """
        threads = "default threads" if self.num_threads is None else \
            f"{self.num_threads} thread{'s' if self.num_threads != 1 else ''}"
        name = getattr(self, "path", None)
        return (f"{Path(name).name if name else 'model'} ({self.view.height}x{self.view.width}x3 -> "
                f"{self.num_maps} maps{self._crop_words()}), {self.backend_label}, {threads}")

    def run_note(self) -> str | None:
        """A line for a run's summary on how its frames were read (`runtime.tracking`); None: nothing to add.

        Returns:
            The line, or None.
        """
        return None

    def _crop_words(self) -> str:
        if self.view.crop is None:
            return ""
        x, y, w, h = self.view.crop
        return f"; crop {w}x{h} at ({x}, {y}) of {self.view.frame_size[0]}x{self.view.frame_size[1]}"

    def decode(self, frame_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Post-process the last output with the predictor's `decoding`.

        Args:
            frame_shape: the shape of the frame the input was made from (keypoints are mapped back to it).
        Returns:
            (K x 2 keypoints in frame pixels, NaN when not found; K confidences, float64).
        """
        maps = self.read_maps(copy=False)
        keypoints, confidence = self.decoding.in_frame(maps, frame_shape, view=self.view, schema=self.schema)
        del maps
        return keypoints, np.array(confidence, dtype=np.float64, copy=True)

    def predict(self, frame_bgr: np.ndarray) -> Prediction:
        """Keypoints of one frame, with the time of each stage (preprocess, invoke, postprocess).

        Args:
            frame_bgr: H x W x 3 uint8, any size.
        Returns:
            The `Prediction`: keypoints in frame pixels, confidences, stage times, the frame's shape and the crop read.
        """
        if not isinstance(frame_bgr, np.ndarray):  # a `sources.Frame`: its image is the frame
            raise TypeError(f"predict takes an H x W x 3 uint8 image, not {type(frame_bgr).__name__}"
                            + (" (pass frame.image)" if hasattr(frame_bgr, "image") else ""))
        t0 = time.perf_counter()
        self.set_input(frame_bgr)
        t1 = time.perf_counter()
        self.invoke()
        t2 = time.perf_counter()
        keypoints, confidence = self.decode(frame_bgr.shape)
        t3 = time.perf_counter()
        times = StageTimes((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3)
        return Prediction(keypoints, confidence, times, tuple(frame_bgr.shape), self.crop_box(frame_bgr.shape))

    def crop_box(self, frame_shape: tuple[int, ...]) -> Box | None:
        """The part of a frame the model reads. The first frame of each size whose aspect is not that of the frames
        the crop was set on gets a warning on stderr (`preprocess.FrameView.aspect_note`).

        Args:
            frame_shape: the frame's shape (height, width, ...).
        Returns:
            (x, y, width, height) of the crop in that frame; None when the model reads the whole frame.
        """
        if self.view.crop is None:
            return None
        size = tuple(frame_shape[:2])
        noted = self.__dict__.setdefault("_sizes_seen", set())
        if size not in noted:
            noted.add(size)
            if (note := self.view.aspect_note(frame_shape)) is not None:
                logger.warning("%s: %s", self.path.name if getattr(self, "path", None) else "the model", note)
        return self.view.box(frame_shape)

    def warmup(self, frame_shape: tuple[int, int, int] = (480, 640, 3), runs: int = 1) -> None:
        """Predict untimed blank frames, so the first real frame pays no start-up cost (XNNPACK weight packing,
        OpenCV's first resize).

        Args:
            frame_shape: the shape of the frames that will follow.
            runs: how many blank frames.
        """
        blank = np.zeros(frame_shape, np.uint8)
        for _ in range(runs):
            self.predict(blank)


class KeypointModel(KeypointPredictor):
    """An FCN-Pose .tflite model ready to run on frames (LiteRT).

    Args:
        model_path: the .tflite file (1 x H x W x 3 image in, 1 x H x W x C maps out; its crop, when it has one,
            in its metadata: `runtime.interpreter.read_view`).
        num_threads: interpreter threads; None = all cores.
        decoding: how maps become keypoints (`postprocess.Decoding`: threshold, fallback, centroid); default the
            commands' (settings).
        schema: keypoint names; default the file's (`runtime.interpreter.read_schema`).
        backend: `auto`, `ai_edge_litert`, `tflite_runtime` or `tensorflow`.
    Raises:
        UserError: missing, corrupt or non-FCN-Pose file; no interpreter installed.
    Example:
        >>> model = KeypointModel("p70_fp16.tflite", num_threads=2)  # doctest: +SKIP
        >>> pred = model.predict(cv2.imread("frame.png"))  # doctest: +SKIP
        >>> pred.keypoints, pred.confidence, pred.times.total_ms  # doctest: +SKIP
    """

    def __init__(self, model_path: str | os.PathLike, num_threads: int | None = None,
                 decoding: Decoding | None = None, schema: KeypointSchema | None = None, backend: str = "auto"):
        self.decoding = decoding if decoding is not None else Decoding()
        self.path = Path(model_path)
        self.num_threads: int = default_num_threads() if num_threads is None else num_threads
        self.backend: Backend
        self.interpreter, self.backend = load_interpreter(self.path, self.num_threads, backend)
        self.io: ModelIO = inspect_io(self.interpreter, self.path)
        named = schema or read_schema(self.path, self.io)
        self.schema = named or schema_for_maps(self.io.num_maps)
        self.names_keypoints = named is not None
        if self.schema.num_maps != self.io.num_maps:
            raise UserError(f"{self.path}: {self.io.num_maps} output maps, but schema {self.schema.name!r} "
                            f"needs {self.schema.num_maps} ({self.schema.num_keypoints} keypoints + skeleton)")
        self.view = read_view(self.path, self.io)
        self._input = self.interpreter.tensor(self.io.input.index)
        self._output = self.interpreter.tensor(self.io.output.index)
        # Float32 input, or uint8 holding pixel / 255 (the int8 export): preprocessing writes straight into
        # the interpreter's buffer. Any other input type goes through one float32 scratch buffer.
        direct = self.io.input.dtype == np.float32 or self.io.input.holds_pixel_bytes
        self._scratch_in = None if direct else np.empty((*self.view.shape, 3), np.float32)
        self._scratch_out = (np.empty(self.io.output.shape[1:], np.float32)
                             if self.io.output.quantized else None)
        self._stats: ModelStats | None = None

    # -- properties ----------------------------------------------------------------------------------
    @property
    def num_maps(self) -> int:
        """Output maps of the file (one per keypoint, then the skeleton map)."""
        return self.io.num_maps

    def stats(self) -> ModelStats:
        """Parameters, MACs and file size of the model, computed on the first call.

        Returns:
            The `interpreter.ModelStats`.
        """
        if self._stats is None:
            self._stats = model_stats(self.interpreter, self.path)
        return self._stats

    @property
    def backend_label(self) -> str:
        """The interpreter package and its version, e.g. `ai_edge_litert 2.3.0`."""
        return self.backend.label

    def describe(self) -> str:
        """One line for progress and reports: file, shapes, crop, backend and threads.

        Returns:
            The line.
        """
        return (f"{self.path.name} ({self.io.describe()}{self._crop_words()}), {self.backend_label}, "
                f"{self.num_threads} thread{'s' if self.num_threads != 1 else ''}")

    # -- the three stages ----------------------------------------------------------------------------
    def set_input(self, frame_bgr: np.ndarray) -> None:
        """Preprocess a frame into the interpreter's input tensor (the training preprocessing).

        Args:
            frame_bgr: H x W x 3 uint8, any size.
        """
        view = self._input()
        self.preprocess_into(frame_bgr, view[0])
        del view  # the interpreter refuses to invoke while a view of its buffers is alive

    def preprocess_into(self, frame_bgr: np.ndarray, buffer: np.ndarray) -> None:
        """The model's input for a frame, written into `buffer`.

        Args:
            frame_bgr: H x W x 3 uint8, any size.
            buffer: H x W x 3 of the input's dtype: the interpreter's own tensor, or a `new_input` staging buffer of
                the pipelined run.
        """
        size = self.view
        spec = self.io.input
        if spec.holds_pixel_bytes:
            preprocess_frame_bytes(frame_bgr, size, out=buffer)
        elif self._scratch_in is None:
            preprocess_frame(frame_bgr, size, out=buffer)
        else:
            preprocess_frame(frame_bgr, size, out=self._scratch_in)
            buffer[...] = spec.quantize(self._scratch_in) if spec.quantized else self._scratch_in

    def invoke(self) -> None:
        """Run the network on the current input."""
        self.interpreter.invoke()

    def read_maps(self, copy: bool = True) -> np.ndarray:
        """The output maps of the last invoke, dequantized when the file's output is integer.

        Args:
            copy: False returns a view of the interpreter's buffer (or of a reused scratch buffer) that must be
                dropped before the next invoke.
        Returns:
            M x M x C float32 probabilities.
        """
        view = self._output()[0]
        spec = self.io.output
        if self._scratch_out is not None:
            maps = dequantize(view, spec.scale, spec.zero_point, out=self._scratch_out)
        elif view.dtype != np.float32:
            maps = view.astype(np.float32)
        else:
            maps = view
        del view
        return maps.copy() if copy else maps

    def decode(self, frame_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Post-process the last output; quantized maps are thresholded as the integers they are
        (`postprocess.quantized_cut`: the same keypoints as thresholding `read_maps`, without
        dequantizing M x M x C values).

        Args:
            frame_shape: the shape of the frame the input was made from.
        Returns:
            (K x 2 keypoints in frame pixels, NaN when not found; K confidences, float64).
        """
        view = self._output()[0]
        result = self.decode_output(view, frame_shape)
        del view  # the interpreter refuses to invoke while a view of its buffers is alive
        return result

    # -- staged frames: the pipelined `run` (runtime.pipeline) -------------------------------------------
    # The interpreter's buffers belong to the thread that invokes; the other thread preprocesses into and
    # decodes from copies of them. The stages are the ones above, so the keypoints are the same.
    pipelinable = True

    def new_input(self) -> np.ndarray:
        """A staging buffer for `preprocess_into`.

        Returns:
            An uninitialised H x W x 3 array of the input tensor's dtype.
        """
        return np.empty(self.io.input.shape[1:], self.io.input.dtype)

    def new_output(self) -> np.ndarray:
        """A buffer for the raw output `forward` copies out.

        Returns:
            An uninitialised H x W x C array of the output tensor's dtype.
        """
        return np.empty(self.io.output.shape[1:], self.io.output.dtype)

    def forward(self, staged: np.ndarray, raw_output: np.ndarray) -> float:
        """Copy a staged input into the interpreter, invoke, copy its raw output out.

        Args:
            staged: a `new_input` buffer `preprocess_into` filled.
            raw_output: a `new_output` buffer, overwritten with the output tensor.
        Returns:
            The invoke's milliseconds.
        """
        view = self._input()
        view[0] = staged
        del view
        t0 = time.perf_counter()
        self.interpreter.invoke()
        invoke_ms = (time.perf_counter() - t0) * 1e3
        view = self._output()
        raw_output[...] = view[0]
        del view
        return invoke_ms

    def decode_output(self, raw: np.ndarray, frame_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints and confidences from raw output maps.

        Args:
            raw: H x W x C of the output tensor's dtype (the interpreter's tensor or a `forward` copy).
            frame_shape: the shape of the frame the input was made from.
        Returns:
            (K x 2 keypoints in frame pixels, NaN when not found; K confidences, float64).
        """
        spec = self.io.output
        if spec.quantized:
            keypoints, confidence = self.decoding.in_frame(raw, frame_shape, view=self.view, schema=self.schema,
                                                           quantization=(spec.scale, spec.zero_point))
        else:
            maps = raw if raw.dtype == np.float32 else raw.astype(np.float32)
            keypoints, confidence = self.decoding.in_frame(maps, frame_shape, view=self.view, schema=self.schema)
        return keypoints, np.array(confidence, dtype=np.float64, copy=True)

    def predict_maps(self, frame_bgr: np.ndarray) -> np.ndarray:
        """The output maps for a frame, for debugging and parity checks.

        Args:
            frame_bgr: H x W x 3 uint8, any size.
        Returns:
            A copy of the M x M x C float32 maps (dequantized).
        """
        self.set_input(frame_bgr)
        self.interpreter.invoke()
        return self.read_maps(copy=True)

