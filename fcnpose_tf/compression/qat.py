"""Quantization-aware training (QAT): the int8 file when post-training int8 is refused by its gate.

Post-training int8 (`fcnpose_tf.compression.export`, ``quantize="int8"``) gives every activation tensor one
scale, calibrated on training frames. On models fine-tuned on a user's frames this can move maps
far enough that keypoints are lost (docs/compression.md, "int8 on a user's model"). QAT trains a
copy of the model with the int8 rounding simulated in its forward pass
(`tensorflow_model_optimization`'s default 8-bit scheme: per-channel int8 weights, per-tensor int8
activations whose ranges are learned as moving averages), so the weights adapt to the rounding.

The copy learns the float model's own maps on the training frames (distillation with weight 1:
its target is what the float model computes, which is what the file is verified against), a few
epochs at a small learning rate. After every epoch it is converted by the same full-integer path
as post-training int8 (uint8 pixel input, int8 maps, built-in int8 kernels only) and the file is
verified against the float model with the same keypoint gate; training stops at the first epoch
whose file passes.

As post-training int8 does by default, the copy is made of the network with its upsampling folded
(`fcnpose_tf.compression.inference_graph.fold_upsampling`: each nearest UpSampling2D + Conv2D pair becomes a
low-resolution Conv2D + DepthToSpace, 1.37x faster in int8), so the file runs the same graph.
FCN-Pose's layers (Conv2D, MaxPooling2D, UpSampling2D) are all in tfmot's default 8-bit registry;
the folded graph's `DepthToSpace` is our own layer, which only moves values, so it is annotated with
a configuration that quantizes nothing (its int8 output keeps its input's scale, as TFLite's
DEPTH_TO_SPACE does). A model with another layer outside the registry is refused with the layer's
name (`quantize_aware`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

from fcnpose_tf import progress
from fcnpose_tf.errors import UserError

if TYPE_CHECKING:
    import tf_keras as keras

    from fcnpose_tf.compression.export import TFLiteExport

QAT_TEACHER_WEIGHT = 1.0
"""Weight of the float model's maps in the QAT loss (`train.DistillationLoss`); 1: the float model's maps only.
The loss is plain binary cross-entropy whatever keypoint weight the model was trained with: against the teacher's
soft maps a keypoint weight (20 for our fine-tuned models) pushes the copy's maps above the teacher's, and on a
model fine-tuned on random views one epoch of it gave a file with 4 keypoints gained (max map difference 0.88)
where plain BCE passed the gate after 2 epochs."""
LOGIT_RANGE = 8.0
"""The output sigmoid's input is quantized on [-8, 8]. The int8 sigmoid's output has 256 levels of 1/256, so
every logit below about -6.2 gives level 0 and every one above +6.2 the top level: clamping at +-8 loses nothing
the file can represent, while the calibrated range of a trained model's logits (about [-65, 15] on a model
fine-tuned on a user's frames) makes each int8 step 0.31 logit, 0.08 in map value at the 0.5 threshold."""



@dataclass
class QATResult:
    """What quantization-aware training gave: the verified export (or None) and what it cost.

    Attributes:
        export: the first epoch's int8 file that passed the gate; None if none did.
        epochs_run: epochs trained (0: the calibrated copy passed before any training).
        seconds: training plus the per-epoch conversions and gates.
        epochs: per epoch: {"epoch", "loss", "passed", "reason" (the gate's, when refused),
            "max_abs_diff", ...the gate's facts}.
        reason: the last refusal's reason when no epoch passed ("" otherwise).
        refusal_facts: the last refusal's measured facts (empty otherwise).
    """

    export: TFLiteExport | None
    epochs_run: int
    seconds: float
    epochs: list[dict[str, Any]] = field(default_factory=list)
    reason: str = ""
    refusal_facts: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (without the file's bytes): passed, epochs_run, seconds, minutes, per-epoch gates.

        Returns:
            {"passed", "epochs_run", "seconds", "minutes", "epochs"[, "reason" when no epoch passed]}.
        """
        return {"passed": self.export is not None, "epochs_run": self.epochs_run, "seconds": round(self.seconds, 1),
                "minutes": round(self.seconds / 60, 2), "epochs": self.epochs,
                **({"reason": self.reason} if self.reason else {})}


def _no_op_config() -> Any:
    """A tfmot QuantizeConfig that quantizes nothing (for layers that only move values: DepthToSpace)."""
    import tensorflow_model_optimization as tfmot

    class MovesValuesOnly(tfmot.quantization.keras.QuantizeConfig):
        def get_weights_and_quantizers(self, layer):
            return []

        def get_activations_and_quantizers(self, layer):
            return []

        def set_quantize_weights(self, layer, quantize_weights):
            pass

        def set_quantize_activations(self, layer, quantize_activations):
            pass

        def get_output_quantizers(self, layer):
            return []

        def get_config(self):
            return {}

    return MovesValuesOnly


def quantize_aware(graph: keras.Model) -> keras.Model:
    """A quantization-aware copy of `graph` (tfmot's default 8-bit scheme), its weights copied; `DepthToSpace`
    layers (a folded graph's, `fcnpose_tf.compression.inference_graph`) quantize nothing.

    Args:
        graph: the float tf_keras model (folded or not).
    Returns:
        The quantization-aware model.
    Raises:
        UserError: when a layer is outside tfmot's default 8-bit registry (naming it and its type).
    """
    import tensorflow_model_optimization as tfmot
    import tf_keras as keras

    from fcnpose_tf.compression.inference_graph import DepthToSpace

    qk = tfmot.quantization.keras
    no_op = _no_op_config()

    def annotate(layer):
        if isinstance(layer, DepthToSpace):
            return qk.quantize_annotate_layer(layer, quantize_config=no_op())
        return layer

    try:
        if any(isinstance(layer, DepthToSpace) for layer in graph.layers):
            annotated = keras.models.clone_model(graph, clone_function=annotate)
            annotated.set_weights(graph.get_weights())
            with qk.quantize_scope({"DepthToSpace": DepthToSpace, "MovesValuesOnly": no_op}):
                return qk.quantize_apply(qk.quantize_annotate_model(annotated))
        return qk.quantize_model(graph)
    except (RuntimeError, ValueError) as exc:  # tfmot: "Layer X:<class ...> is not supported ..."
        detail = str(exc).strip().splitlines()
        raise UserError(f"model {graph.name}: quantization-aware training cannot wrap it "
                        f"({detail[0] if detail else type(exc).__name__})") from exc


def calibrate_ranges(qat: keras.Model, graph: keras.Model, frames: Any) -> dict[str, tuple[float, float]]:
    """Set the quantization-aware copy's activation ranges from the float graph's activations on `frames`.

    tfmot starts every range at [-6, 6] and moves it as an exponential average with decay 0.999 per
    training step: a few epochs (a few hundred steps) leave ranges a quarter of the way to the data's,
    clipping ReLU outputs above 6 (a fine-tuned FCN-Pose's conv9 reaches 30). Starting from the
    calibration frames' min/max, as post-training int8 does, QAT starts where PTQ is, except for the
    output sigmoid's input, clamped to +-`LOGIT_RANGE` (see there).

    Args:
        qat: the quantization-aware copy (`quantize_aware`), changed in place.
        graph: the float graph it was made from.
        frames: the calibration frames (N x H x W x 3, as the model takes them).
    Returns:
        {layer: (min, max)} as set.
    """
    import numpy as np
    import tf_keras as keras

    from tensorflow_model_optimization.python.core.quantization.keras.quantize_layer import QuantizeLayer

    frames = np.asarray(frames, np.float32)
    # One training-mode pass sets the weights' per-channel ranges (tfmot sets them from the kernels only while
    # training); its 0.1 % step on the activation ranges is overwritten below.
    qat(frames[:8], training=True)
    inner = {layer.name: layer for layer in graph.layers}
    wrapped = {layer.layer.name: layer for layer in qat.layers if hasattr(layer, "layer")}
    wanted = [name for name in wrapped if name in inner and getattr(inner[name], "activation", None) is not None]
    probe = keras.Model(graph.input, [inner[name].output for name in wanted])
    # running min/max over batches: all layers' outputs of 100 frames at 224 would take ~4 GB (unpruned model)
    lows, highs = [np.inf] * len(wanted), [-np.inf] * len(wanted)
    for start in range(0, len(frames), 8):
        batch = probe(frames[start:start + 8], training=False)
        for i, values in enumerate(batch if isinstance(batch, (list, tuple)) else [batch]):
            lows[i], highs[i] = min(lows[i], float(np.min(values))), max(highs[i], float(np.max(values)))
    ranges: dict[str, tuple[float, float]] = {}
    for layer in qat.layers:  # the input: pixels (the file's input scale is pinned to 1/255 anyway)
        if isinstance(layer, QuantizeLayer):
            for variable in layer.non_trainable_weights:
                short = variable.name.split("/")[-1].split(":")[0]
                if short.endswith("_min") or short.endswith("_max"):
                    variable.assign(min(0.0, float(frames.min())) if short.endswith("_min") else float(frames.max()))
    for name, value_min, value_max in zip(wanted, lows, highs):
        layer = wrapped[name]
        for variable in layer.non_trainable_weights:
            short = variable.name.split("/")[-1].split(":")[0]
            if short in ("post_activation_min", "post_activation_max"):
                low, high = min(0.0, value_min), max(0.0, value_max)
            elif short in ("pre_activation_min", "pre_activation_max"):
                low, high = -LOGIT_RANGE, LOGIT_RANGE
            else:
                continue
            variable.assign(low if short.endswith("_min") else high)
            ranges[name] = (low, high)
    _pin_logit_range(qat)
    return ranges


def _pin_logit_range(qat: keras.Model) -> None:
    """The sigmoid's input range back to +-LOGIT_RANGE (training moves it towards the logits' min and max)."""
    for layer in qat.layers:
        for variable in layer.non_trainable_weights:
            short = variable.name.split("/")[-1].split(":")[0]
            if short == "pre_activation_min":
                variable.assign(-LOGIT_RANGE)
            elif short == "pre_activation_max":
                variable.assign(LOGIT_RANGE)


def train_until_gate(model: keras.Model, sequence: Any, calibration: Any,
                     convert: Callable[[keras.Model], TFLiteExport], *, epochs: int, learning_rate: float,
                     seed: int = 0, fold_upsampling: bool = True, reporter: progress.Reporter | None = None) -> QATResult:
    """Quantization-aware training of `model` on `sequence`, one epoch at a time, until `convert` passes.

    The copy's ranges are first set from `calibration` (`calibrate_ranges`) and converted once before any
    training (epoch 0: post-training ranges with the sigmoid's input clamped); then at most `epochs` epochs,
    the gate after each.

    Args:
        model: the float model (retrained, pruned or not); it is not changed.
        sequence: its training batches (`TrainingData.sequence`), whose targets are the ground-truth maps;
            the float model's maps are added to them as the teacher's (`distill.TeacherTargets`).
        calibration: preprocessed training frames (N x H x W x C) for the starting ranges.
        convert: converts the quantization-aware model to int8 and verifies it against `model`
            (e.g. `export_tflite(qat, "int8", reference=model, fold_upsampling=False, ...)`: the copy is
            already folded); raises ExportVerificationError when the gate refuses the file.
        epochs: at most this many epochs (0: only the calibrated copy).
        learning_rate: Adam's rate.
        seed: TensorFlow's seed for the run.
        fold_upsampling: train the folded graph (`fcnpose_tf.compression.inference_graph`), as the int8 export converts it.
        reporter: where the per-epoch gate lines and Keras' epoch lines go (`fcnpose_tf.progress`; default: the
            current one), drawn as lines: the gate's line follows each epoch's.
    Returns:
        A `QATResult` (its export None when no epoch's file passed).
    """
    import tf_keras as keras

    from fcnpose_tf.training.distill import TeacherTargets
    from fcnpose_tf.compression.export import _inference_graph
    from fcnpose_tf.compression.verify import ExportVerificationError
    from fcnpose_tf.training.train import training_loss

    if isinstance(epochs, bool) or not isinstance(epochs, int) or epochs < 0:
        raise UserError(f"quantization-aware training epochs must be a whole number >= 0, got {epochs!r}")
    reporter = progress.resolve(reporter).lines()
    log = reporter.say
    start = time.perf_counter()
    keras.utils.set_random_seed(seed)
    graph, rewrites = _inference_graph(model) if fold_upsampling else (model, ())
    qat = quantize_aware(graph)
    calibrate_ranges(qat, graph, calibration)
    qat.compile(optimizer=keras.optimizers.Adam(learning_rate),
                loss=training_loss(1.0, QAT_TEACHER_WEIGHT), jit_compile=False)
    batches = TeacherTargets(sequence, model)
    result = QATResult(None, 0, 0.0)
    for epoch in range(epochs + 1):
        row: dict[str, Any] = {"epoch": epoch}
        if epoch:
            history = qat.fit(batches, epochs=epoch, initial_epoch=epoch - 1, verbose=reporter.keras_verbose, shuffle=False)
            _pin_logit_range(qat)
            row["loss"] = round(float(history.history["loss"][-1]), 6)
            result.epochs_run = epoch
        what = f"QAT epoch {epoch}/{epochs} (loss {row['loss']:.4f})" if epoch else \
            "QAT epoch 0 (calibrated ranges, sigmoid input clamped, not trained)"
        try:
            export = dataclasses.replace(convert(qat), graph_rewrites=rewrites)
        except ExportVerificationError as exc:
            row.update({"passed": False, "reason": exc.reason, **exc.facts})
            result.reason, result.refusal_facts = exc.reason, dict(exc.facts)
            log(f"  {what}: int8 refused: {exc.reason}")
        else:
            p = export.parity
            row.update({"passed": True, "max_abs_diff": p.max_abs_diff, "keypoints_compared": p.keypoints_compared,
                        "keypoints_within_px": p.keypoints_within_px,
                        "keypoints_lost_or_gained": p.keypoints_lost_or_gained})
            result.export, result.reason, result.refusal_facts = export, "", {}
            log(f"  {what}: int8 passes the gate ({p.keypoints_within_px} of {p.keypoints_compared} keypoints "
                f"within {p.keypoint_px:g} px, {p.keypoints_lost_or_gained} lost or gained, max abs map difference "
                f"{p.max_abs_diff:.3g})")
        result.epochs.append(row)
        if result.export is not None:
            break
    result.seconds = time.perf_counter() - start
    return result


__all__ = ["LOGIT_RANGE", "QAT_TEACHER_WEIGHT", "QATResult", "calibrate_ranges", "quantize_aware", "train_until_gate"]
