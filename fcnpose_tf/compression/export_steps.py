"""The export steps of one compression run (`compress.compress_model` runs them after the retraining, through
`export_formats`, per --quantize format): export_step writes one verified TFLite file, qat_step is quantization-aware
training when post-training int8 is refused (`export_or_refusal` decides), measure_quantized measures a written file.
Each reads the run's `steps.Run`.
"""

from __future__ import annotations

import gzip
from typing import TYPE_CHECKING, Any

import numpy as np

from fcnpose_tf.compression.report import ModelStep, QATFacts, RefusedFormat, TFLiteStep

if TYPE_CHECKING:
    import tf_keras as keras

    from fcnpose_tf.compression.export import TFLiteExport
    from fcnpose_tf.compression.qat import QATResult
    from fcnpose_tf.compression.steps import Run

# TensorFlow is imported inside the functions: the CLI imports this module (through compress) without needing
# TensorFlow until a compression runs.


def _export_frames(run: Run, quantize: str) -> tuple[np.ndarray, np.ndarray | None]:
    from fcnpose_tf.compression.frames import export_frames

    return export_frames(quantize, run.input_size, run.train_dataset, run.training_frames, run.eval_dataset,
                         run.eval_indices, run.options.calibration_frames, run.options.seed)


def _trained_on(run: Run) -> dict[str, Any] | None:
    """What the files keep of the retrained model's training record (`records.TrainingRecord.deployed`): the
    retraining's (or the polish's) NAME_pXX_train.json, or with 0 retraining epochs the base model's NAME_train.json."""
    from fcnpose_tf.records import training_record

    record = training_record(run.files.paths["keras"]) or training_record(run.base_path)
    return record.deployed() if record is not None else None


def export_step(run: Run, retrained: keras.Model, quantize: str) -> TFLiteExport:
    """Write one TFLite file, verified against Keras on real frames (`frames.export_frames`: the
    first evaluation frames; int8 calibrated on the training frames of the run's fold, `Run.fold`).

    Args:
        run: the compression run.
        retrained: the model to convert.
        quantize: the format (`settings.TFLITE_FORMATS`).
    Returns:
        The export (`export.TFLiteExport`).
    Raises:
        ExportVerificationError: the file failed its gate (nothing written).
    """
    from fcnpose_tf.compression.export import write_tflite

    samples, calibration = _export_frames(run, quantize)
    return write_tflite(retrained, run.files.tflite[quantize], quantize, force=run.force,
                        sample_frames=samples, calibration_frames=calibration, num_threads=run.options.threads,
                        trained_on=_trained_on(run))


def qat_step(run: Run, retrained: keras.Model) -> QATResult:
    """Quantization-aware training from the retrained model on the retraining's training frames, until its int8
    file passes the same gate against the retrained model (`fcnpose_tf.compression.qat`); the file is written when one
    passes.

    Args:
        run: the compression run.
        retrained: the float model the int8 file is held to.
    Returns:
        The `qat.QATResult` (its export None when every epoch's file was refused).
    """
    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.compression.export import export_tflite
    from fcnpose_tf.fileio import write_bytes
    from fcnpose_tf.compression.qat import train_until_gate

    options = run.options
    if run.fit_data is None:  # not retrained in this run (--retrain-epochs 0): the same split's frames
        run.fit_data, _ = fold_data(run.train_dataset, run.fold, run.input_size, options.augment_copies, options.seed,
                                    options.augment, progress=run.reporter)
    samples, calibration = _export_frames(run, "int8")

    def convert(qat_model: keras.Model) -> Any:
        return export_tflite(qat_model, "int8", sample_frames=samples, calibration_frames=calibration,
                             num_threads=options.threads, fold_upsampling=False, reference=retrained,
                             trained_on=_trained_on(run))

    sequence = run.fit_data.sequence(options.batch_size, seed=options.seed)
    result = train_until_gate(retrained, sequence, calibration, convert, epochs=options.qat_epochs,
                              learning_rate=options.qat_learning_rate, seed=options.seed,
                              reporter=run.reporter)
    if result.export is not None:
        write_bytes(run.files.tflite["int8"], result.export.data, run.force)
    return result


def measure_quantized(run: Run, export: TFLiteExport, retrained_facts: ModelStep,
                      qat: QATFacts | None = None) -> TFLiteStep:
    """One TFLite file measured: its format, how it was quantized, size (plain and gzip), export facts, operators,
    metrics and timing.

    Args:
        run: the compression run.
        export: the written file's export (`export.TFLiteExport`).
        retrained_facts: the retrained model's step (the file's parameters and MACs are its).
        qat: the quantization-aware training that made the file, with the post-training refusal it replaced (None:
            post-training).
    Returns:
        The file's step of the report.
    """
    from fcnpose_tf.compression.tflite_file import inspect_tflite
    from fcnpose_tf.runtime.estimator import KeypointModel

    path = run.files.tflite[export.quantize]
    tflite_info = inspect_tflite(path)
    tfl = KeypointModel(path, num_threads=run.options.threads, decoding=run.decoding)
    measurement = run.measure(tfl, f"the {export.quantize} TFLite model")
    return TFLiteStep(quantize=export.quantize, status="written",
                      quantization="quantization-aware training" if qat is not None else "post-training", qat=qat,
                      params=retrained_facts.params, macs=retrained_facts.macs, flops=retrained_facts.flops,
                      tflite_size_bytes=export.size_bytes, tflite_gzip_size_bytes=len(gzip.compress(export.data, 9)),
                      export=export.to_dict(), tflite_ops=tflite_info.get("op_counts", tflite_info.get("ops")),
                      metrics=measurement.metrics, timing=measurement.timing)


def export_or_refusal(run: Run, retrained: keras.Model, quantize: str, refused: list[RefusedFormat]
                      ) -> tuple[TFLiteExport | None, QATFacts | None]:
    """One format's file written, or its refusal recorded: a format refused by its gate is a row of the report, not
    the end of the run. Post-training int8 refused falls back to quantization-aware training (`options.qat_epochs`
    > 0).

    Args:
        run: the compression run.
        retrained: the model to convert.
        quantize: the format.
        refused: the run's refusals, to which this format's is appended when no file passed.
    Returns:
        (the written export, quantization-aware training's facts when it made the file), or (None, None).
    """
    from fcnpose_tf.compression.export import FULL_INTEGER
    from fcnpose_tf.compression.verify import ExportVerificationError

    try:
        return export_step(run, retrained, quantize), None
    except ExportVerificationError as exc:
        ptq = {"reason": exc.reason, **exc.facts}
    run.log(f"  {quantize} refused by its gate: {ptq['reason']}")
    reason, qat = ptq["reason"], None
    if quantize == FULL_INTEGER and run.options.qat_epochs > 0:
        run.log(f"  post-training int8 refused: quantization-aware training (tfmot), up to {run.options.qat_epochs} "
                f"epoch(s) from the retrained model on the same training frames, the gate after each")
        result = qat_step(run, retrained)
        qat = QATFacts.of(result, run.options.qat_learning_rate, ptq)
        if result.export is not None:
            run.log(f"  quantization-aware int8 passes the gate after {result.epochs_run} epoch(s), "
                    f"{result.seconds / 60:.1f} min")
            return result.export, qat
        reason = f"after {result.epochs_run} epoch(s) of quantization-aware training: {result.reason}"
        run.log(f"  quantization-aware int8 refused too ({result.seconds / 60:.1f} min): {result.reason}")
    refused.append(RefusedFormat(quantize, reason, post_training=ptq, qat=qat))
    return None, None


def remove_stale(run: Run, quantize: str) -> None:
    """With --force, an earlier run's file of a format this run refused goes: it is not this model's.

    Args:
        run: the compression run.
        quantize: the refused format.
    """
    path = run.files.tflite[quantize]
    if run.force and path.is_file():
        path.unlink()
        run.log(f"  removed {path}: an earlier file of the format this run refused")


def export_formats(run: Run, retrained: keras.Model, retrained_step: ModelStep, steps: int
                   ) -> tuple[list[TFLiteStep], list[RefusedFormat]]:
    """Every --quantize format in turn: its file written and measured, or its refusal recorded (the run's steps from
    5 on, two a format).

    Args:
        run: the compression run.
        retrained: the model to convert.
        retrained_step: the retrained model's step (`steps.measure_retrained`).
        steps: the run's number of steps, for the progress lines.
    Returns:
        (the files written, measured, in the formats' order; the formats refused).
    """
    files: list[TFLiteStep] = []
    refused: list[RefusedFormat] = []
    for i, quantize in enumerate(run.options.quantize):
        run.log(f"[{5 + 2 * i}/{steps}] exporting {quantize} TFLite (verified against Keras)")
        export, qat = export_or_refusal(run, retrained, quantize, refused)
        if export is None:
            remove_stale(run, quantize)
            continue
        run.log(f"[{6 + 2 * i}/{steps}] measuring the {quantize} TFLite model")
        files.append(measure_quantized(run, export, retrained_step, qat))
    return files, refused
