"""The keypoint gate: a converted TFLite file run in LiteRT against the Keras model it was made from.

`verify_tflite` loads the flatbuffer in the runtime's interpreter, checks its interface (float32 in and out, or the
int8 file's uint8 pixels in and integer maps out), runs it on sample frames and compares its maps with the Keras
model's: max |difference| within the format's `map_atol`, and the keypoints decoded from both (Algorithm 1's
clusters) within `keypoint_px` for at least `keypoint_share` of them, none found by one and missing in the other.
Each format's tolerances are a row of `settings.TFLITE_FORMATS` (why each is what it is: docs/compression.md,
"Verification: the file is run before it is trusted"). A file that fails raises `ExportVerificationError` and nothing is written
(`fcnpose_tf.compression.export`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError

if TYPE_CHECKING:  # TensorFlow is imported only when converting
    import tf_keras as keras

# Map values within this much of the threshold are "on the threshold": which side they fall on is
# arbitrary for maps only this accurate, so keypoints resting on such pixels are not compared.
THRESHOLD_MARGIN = 1e-2


class ExportVerificationError(UserError):
    """A converted model disagrees with its Keras model (or does not load); nothing was written.

    Attributes:
        facts: what the gate measured before it refused, JSON-ready (e.g. ``max_abs_diff``,
            ``keypoints_compared``, ``keypoints_within_px``, ``keypoints_lost_or_gained``); empty when the
            file was refused before its maps were compared (it did not load, wrong interface).
    """

    def __init__(self, message: str, facts: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.facts = dict(facts or {})

    @property
    def reason(self) -> str:
        """The gate's reason without the trailing "; nothing written": a refused format's row says it."""
        text = str(self)
        return text[:-len(NOTHING_WRITTEN)] if text.endswith(NOTHING_WRITTEN) else text


NOTHING_WRITTEN = "; nothing written"


@dataclass(frozen=True)
class ParityReport:
    """How a converted model compares with its Keras model on the sample frames.

    Attributes:
        frames: sample frames run through both models.
        max_abs_diff: largest |tflite - keras| over all maps and pixels.
        map_atol: the allowed max_abs_diff.
        keypoints_compared: keypoints (frames x keypoint maps) whose positions were compared.
        keypoints_ambiguous: keypoints not compared because the Keras model's own decoding moves
            when the threshold shifts by min(max_abs_diff, 0.01) (a map hovering at the
            threshold); a faithful conversion may legitimately decode those differently.
        max_keypoint_px: largest distance between compared keypoints found by both (0 if none).
        keypoint_px: the allowed keypoint distance in map pixels.
        threshold: the map threshold used for decoding.
        keypoints_within_px: compared keypoints found by both models within keypoint_px of each
            other, or missing in both.
        keypoints_lost_or_gained: compared keypoints found by one model only (always refused).
        min_keypoint_share: the gate: keypoints_within_px / keypoints_compared must reach it
            (1 for the float modes, 0.95 for int8).
    """

    frames: int
    max_abs_diff: float
    map_atol: float
    keypoints_compared: int
    keypoints_ambiguous: int
    max_keypoint_px: float
    keypoint_px: float
    threshold: float
    keypoints_within_px: int = 0
    keypoints_lost_or_gained: int = 0
    min_keypoint_share: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, stable keys (pixel distances in map pixels).

        Returns:
            The fields in order (the report's "parity").
        """
        return asdict(self)

    @classmethod
    def from_dict(cls, entry: dict[str, Any]) -> ParityReport:
        """The report of a parsed `to_dict` (a key written before its field existed reads as the field's default).

        Args:
            entry: the parsed JSON object; a key without a field is dropped.
        Returns:
            The parity report.
        Raises:
            TypeError: a key every parity report holds is missing.
        """
        names = {f.name for f in fields(cls)}
        return cls(**{key: value for key, value in entry.items() if key in names})


def _interpreter(data: bytes, num_threads: int | None = None):
    """An allocated interpreter for flatbuffer bytes, from the runtime's backend order (LiteRT first)."""
    from fcnpose_tf.nativelog import native_stderr_captured
    from fcnpose_tf.runtime.interpreter import find_backend

    kwargs: dict[str, Any] = {"num_threads": num_threads} if num_threads else {}
    with native_stderr_captured():  # LiteRT's `INFO: Created ... XNNPACK delegate`, as `load_interpreter` does
        interpreter = find_backend().interpreter_class(model_content=bytes(data), **kwargs)
        interpreter.allocate_tensors()
    return interpreter


def run_tflite(interpreter, frames: np.ndarray) -> np.ndarray:
    """Run a batch-1 interpreter on each frame, converting quantized inputs and outputs.

    Args:
        interpreter: an allocated TFLite interpreter.
        frames: N x H x W x C float, as the Keras model takes them.
    Returns:
        The stacked N x ... outputs, float32.
    """
    from fcnpose_tf.postprocess import dequantize
    from fcnpose_tf.runtime.interpreter import TensorSpec

    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    spec_in, spec_out = TensorSpec.from_details(inp), TensorSpec.from_details(out)
    results = []
    for frame in frames:
        batch = spec_in.quantize(frame[None]) if spec_in.quantized else np.asarray(frame[None], spec_in.dtype)
        interpreter.set_tensor(spec_in.index, np.ascontiguousarray(batch))
        interpreter.invoke()
        maps = interpreter.get_tensor(spec_out.index)[0]
        results.append(dequantize(maps, spec_out.scale, spec_out.zero_point) if spec_out.quantized
                       else maps.copy())
    return np.stack(results)


def _check_interface(interpreter, frames: np.ndarray, keras_shape: tuple[int, ...], pixel_input: bool,
                     what: str) -> None:
    """The converted file's input and output as the runtime expects them (ExportVerificationError if not)."""
    from fcnpose_tf.runtime.interpreter import TensorSpec

    (inp,), (out,) = interpreter.get_input_details(), interpreter.get_output_details()
    spec_in, spec_out = TensorSpec.from_details(inp), TensorSpec.from_details(out)
    expected_in, expected_out = [1, *frames.shape[1:]], [1, *keras_shape[1:]]
    if pixel_input:
        in_ok, in_type = spec_in.holds_pixel_bytes, "uint8 (scale 1/255, zero point 0)"
        out_ok, out_type = spec_out.quantized, "quantized integer"
    else:
        in_ok, in_type = spec_in.dtype == np.float32, "float32"
        out_ok, out_type = spec_out.dtype == np.float32, "float32"
    if list(spec_in.shape) != expected_in or not in_ok:
        scale = f" (scale {spec_in.scale:.6g}, zero point {spec_in.zero_point})" if spec_in.quantized else ""
        raise ExportVerificationError(f"{what} takes {spec_in.dtype.name} {list(spec_in.shape)}{scale}, "
                                      f"expected {in_type} {expected_in}; nothing written")
    if list(spec_out.shape) != expected_out or not out_ok:
        raise ExportVerificationError(f"{what} gives {spec_out.dtype.name} {list(spec_out.shape)}, "
                                      f"expected {out_type} {expected_out}; nothing written")


def _both_outputs(model: keras.Model, tflite: bytes, inputs: np.ndarray, num_threads: int | None, pixel_input: bool,
                  what: str) -> tuple[np.ndarray, np.ndarray]:
    """(the Keras model's outputs, the file's) on `inputs`, once the file loads, has the interface the runtime
    expects (`_check_interface`) and gives finite values; ExportVerificationError otherwise."""
    try:
        interpreter = _interpreter(tflite, num_threads)
    except Exception as exc:
        detail = str(exc).strip().splitlines()
        raise ExportVerificationError(f"{what} does not load in the interpreter ({type(exc).__name__}: "
                                      f"{detail[0] if detail else 'no detail'}); nothing written") from exc
    expected = np.asarray(model(inputs, training=False), dtype=np.float32)
    _check_interface(interpreter, inputs, expected.shape, pixel_input, what)
    got = run_tflite(interpreter, inputs)
    if not np.isfinite(got).all():
        bad = int(np.count_nonzero(~np.isfinite(got)))
        raise ExportVerificationError(f"{what} outputs {bad} NaN/infinite values where the Keras model's are "
                                      "finite (weights lost in conversion?); nothing written")
    return expected, got


def verify_tflite(model: keras.Model, tflite: bytes, frames: np.ndarray, *, map_atol: float = 1e-2,
                  keypoint_px: float = 1.0, threshold: float = 0.5, check_keypoints: bool = True,
                  num_threads: int | None = None, label: str = "TFLite", keypoint_share: float = 1.0,
                  pixel_input: bool = False) -> ParityReport:
    """Check that a converted model computes what the Keras model computes on `frames`.

    Checks, in order: the flatbuffer loads in the interpreter; its input is float32
    [1, H, W, C] (with `pixel_input`: uint8 with scale 1/255 and zero point 0) and its output
    float32 (with `pixel_input`: quantized integers) of the Keras output's shape with batch 1; all
    outputs are finite; max |tflite - keras| <= map_atol; and, if `check_keypoints`, the
    keypoints decoded from both agree: none found by one model and missing in the other, and at
    least `keypoint_share` of them within `keypoint_px` (or missing in both). A keypoint whose
    Keras decoding itself changes when the threshold moves by the measured max abs difference
    (at most `THRESHOLD_MARGIN`, 0.01) rests on pixels at the threshold, so either decoding is
    right; such keypoints are counted as ambiguous instead of compared. The cap keeps the
    keypoint check meaningful when `map_atol` is loosened (e.g. for int8).

    Args:
        model: the Keras model the file was converted from.
        tflite: the converted flatbuffer.
        frames: N x H x W x C float32 frames as the model takes them.
        map_atol, keypoint_px, threshold, check_keypoints, num_threads: as in `to_tflite`.
        label: what the file is, for messages ("float16").
        keypoint_share: share of the compared keypoints that must agree within keypoint_px.
        pixel_input: the file is a full-integer export (uint8 pixel input, integer maps).
    Returns:
        A `ParityReport`.
    Raises:
        ExportVerificationError: naming what disagreed (max abs difference and where, or which
            keypoint of which frame and by how many pixels).
    """
    what = f"the {label} TFLite model"
    keras_maps, tflite_maps = _both_outputs(model, tflite, frames, num_threads, pixel_input, what)
    diff = np.abs(tflite_maps - keras_maps)
    max_diff = float(diff.max())
    if not max_diff <= map_atol:
        where = np.unravel_index(int(np.argmax(diff)), diff.shape)
        place = f"frame {where[0]}, map {where[-1]}, pixel (x={where[2]}, y={where[1]})" if diff.ndim == 4 \
            else f"index {tuple(int(i) for i in where)}"
        raise ExportVerificationError(
            f"{what} disagrees with the Keras model: max abs map difference {max_diff:.3g} > {map_atol:g} "
            f"at {place} (Keras {keras_maps[where]:.4g}, TFLite {tflite_maps[where]:.4g}); nothing written",
            {"frames": len(frames), "max_abs_diff": max_diff, "map_atol": float(map_atol)})
    agreement = _KeypointAgreement(0, 0, 0.0, 0, 0)
    if check_keypoints and keras_maps.ndim == 4 and keras_maps.shape[-1] >= 2:
        from fcnpose_tf.training.model import schema_of

        agreement = _compare_keypoints(keras_maps, tflite_maps, max_diff, threshold, keypoint_px,
                                       keypoint_share, what, schema_of(model).keypoints)
    return ParityReport(len(frames), max_diff, float(map_atol), agreement.compared, agreement.ambiguous,
                        agreement.max_px, float(keypoint_px), float(threshold), agreement.within,
                        agreement.lost_or_gained, float(keypoint_share))


@dataclass(frozen=True)
class _KeypointAgreement:
    compared: int
    ambiguous: int
    max_px: float
    within: int
    lost_or_gained: int


def _compare_keypoints(keras_maps: np.ndarray, tflite_maps: np.ndarray, max_diff: float, threshold: float,
                       keypoint_px: float, keypoint_share: float, what: str,
                       names: Sequence[str]) -> _KeypointAgreement:
    from fcnpose_tf.postprocess import maps_to_keypoints

    # The gate compares Algorithm 1's clusters (the plain centroid is a function of which pixels a cluster holds);
    # the weighted read also moves with the values inside it, which evaluate measures on the written file.
    ref, _ = maps_to_keypoints(keras_maps, threshold, centroid="plain")
    got, _ = maps_to_keypoints(tflite_maps, threshold, centroid="plain")
    # The Keras decoding with every pixel within `margin` of the threshold switched on / off:
    # where these disagree with `ref`, the keypoint rests on pixels a faithful conversion may flip.
    margin = min(max_diff, THRESHOLD_MARGIN)
    low, _ = maps_to_keypoints(keras_maps, threshold - margin, centroid="plain")
    high, _ = maps_to_keypoints(keras_maps, threshold + margin, centroid="plain")

    def same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        missing_a, missing_b = np.isnan(a).any(-1), np.isnan(b).any(-1)
        close = np.linalg.norm(np.nan_to_num(a - b, nan=np.inf), axis=-1) <= keypoint_px
        return (missing_a & missing_b) | (~missing_a & ~missing_b & close)

    stable = same(ref, low) & same(ref, high)
    agree = same(ref, got)
    lost_or_gained = stable & (np.isnan(ref).any(-1) != np.isnan(got).any(-1))
    compared, within = int(stable.sum()), int((stable & agree).sum())
    share_ok = within >= keypoint_share * compared
    bad = np.argwhere(lost_or_gained if lost_or_gained.any() or share_ok else stable & ~agree)
    if len(bad):
        n, k = (int(i) for i in bad[0])

        def show(p: np.ndarray) -> str:
            return "missing" if np.isnan(p).any() else f"({p[0]:.1f}, {p[1]:.1f})"

        distance = "" if np.isnan(ref[n, k]).any() or np.isnan(got[n, k]).any() else \
            f", {np.linalg.norm(ref[n, k] - got[n, k]):.2f} px > {keypoint_px:g} px"
        gate = (f"{int(lost_or_gained.sum())} keypoint(s) lost or gained" if lost_or_gained.any() else
                f"{within} of {compared} keypoints within {keypoint_px:g} px, "
                f"{keypoint_share:.0%} required" if keypoint_share < 1 else
                f"{compared - within} keypoint(s) disagree")
        raise ExportVerificationError(
            f"{what} decodes {names[k]} (keypoint {k}) of frame {n} at {show(got[n, k])}, the Keras model at "
            f"{show(ref[n, k])}"
            f"{distance} ({gate}; max abs map difference {max_diff:.3g}); nothing written",
            {"frames": len(keras_maps), "max_abs_diff": max_diff, "keypoints_compared": compared,
             "keypoints_within_px": within, "keypoints_lost_or_gained": int(lost_or_gained.sum()),
             "keypoint_px": float(keypoint_px), "min_keypoint_share": float(keypoint_share)})
    both = stable & ~np.isnan(ref).any(-1) & ~np.isnan(got).any(-1)
    max_px = float(np.linalg.norm(ref[both] - got[both], axis=-1).max()) if both.any() else 0.0
    return _KeypointAgreement(compared, int((~stable).sum()), max_px, within, int(lost_or_gained.sum()))


# --------------------------------------------------------------------------------------------
# Models that are not keypoint models: output parity
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class OutputParity:
    """How a converted model that is not a keypoint model (a classifier, any CNN) compares with its Keras model.

    Attributes:
        frames: inputs run through both models.
        max_abs_diff: largest |tflite - keras| over every output value.
        output_scale: what the difference is relative to: 1 for probabilities (every row in [0, 1] summing to 1),
            else the largest |keras output| (1 if that is 0).
        relative_diff: max_abs_diff / output_scale; the gate: at most `output_rtol`.
        output_rtol: the format's bound (`settings.TFLITE_FORMATS`).
        top1_compared: a classifier's (outputs N x K, K >= 2) samples whose Keras top-1 leads its runner-up by more
            than twice max_abs_diff (the others' top-1 is a tie within the measured error); None: not a classifier.
        top1_agree: of those, the samples whose TFLite top-1 is the Keras top-1.
        min_top1_share: the gate: top1_agree / top1_compared must reach it.
    """

    frames: int
    max_abs_diff: float
    output_scale: float
    relative_diff: float
    output_rtol: float
    top1_compared: int | None = None
    top1_agree: int | None = None
    min_top1_share: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, stable keys.

        Returns:
            The fields in order (export_generic's "parity").
        """
        return asdict(self)


def _output_scale(outputs: np.ndarray) -> float:
    rows = outputs.reshape(len(outputs), -1)
    if rows.shape[1] >= 2 and rows.min() >= 0 and rows.max() <= 1 and np.allclose(rows.sum(1), 1, atol=1e-3):
        return 1.0  # probabilities: a difference is a share of the whole
    peak = float(np.abs(outputs).max())
    return peak if peak > 0 else 1.0


def verify_outputs(model: keras.Model, tflite: bytes, inputs: np.ndarray, *, output_rtol: float,
                   top1_share: float = 1.0, num_threads: int | None = None, label: str = "TFLite") -> OutputParity:
    """Check that a converted model computes what the Keras model computes on `inputs`, output value by value.

    For a model whose outputs are not keypoint maps. Checks: the flatbuffer loads; its input is float32
    [1, ...the model's input...] and its output float32 of the Keras output's shape with batch 1 (an int8 file keeps
    a float interface); every output is finite; max |tflite - keras| / `output_scale` <= `output_rtol`; and for a
    classifier (N x K outputs) the top-1 class agrees on at least `top1_share` of the samples whose top-1 is not a
    tie within the measured difference.

    Args:
        model: the Keras model (tf_keras or Keras 3).
        tflite: the converted flatbuffer.
        inputs: N x the model's input.
        output_rtol: the largest difference allowed, relative to the output's scale.
        top1_share: a classifier's share of compared samples whose top-1 must agree.
        num_threads: interpreter threads (None: the interpreter's default).
        label: what the file is, in messages.
    Returns:
        What was compared and found (`OutputParity`).
    Raises:
        ExportVerificationError: naming what disagreed and by how much; nothing is written.
    """
    what = f"the {label} TFLite model"
    expected, got = _both_outputs(model, tflite, inputs, num_threads, False, what)
    max_diff = float(np.abs(got - expected).max())
    scale = _output_scale(expected)
    relative = max_diff / scale
    facts = {"frames": len(inputs), "max_abs_diff": max_diff, "output_scale": scale, "relative_diff": relative,
             "output_rtol": float(output_rtol)}
    if not relative <= output_rtol:
        raise ExportVerificationError(f"{what} disagrees with the Keras model: max abs output difference "
                                      f"{max_diff:.3g} is {relative:.3g} of the output scale {scale:.3g} > "
                                      f"{output_rtol:g}; nothing written", facts)
    compared = agree = None
    if expected.ndim == 2 and expected.shape[1] >= 2:
        top2 = np.sort(expected, axis=1)[:, -2:]
        clear = top2[:, 1] - top2[:, 0] > 2 * max_diff
        compared = int(clear.sum())
        agree = int((clear & (got.argmax(1) == expected.argmax(1))).sum())
        if agree < top1_share * compared:
            raise ExportVerificationError(f"{what} disagrees with the Keras model: top-1 class agrees on {agree} of "
                                          f"{compared} samples, {top1_share:.0%} required; nothing written",
                                          {**facts, "top1_compared": compared, "top1_agree": agree})
    return OutputParity(len(inputs), max_diff, scale, relative, float(output_rtol), compared, agree,
                        float(top1_share))
