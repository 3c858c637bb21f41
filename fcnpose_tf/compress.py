"""The paper's whole compression for one rate: prune, retrain, quantize, and measure every step.

    base model ──► L1 filter surgery at rate r (or tfmot magnitude pruning) ──► retrain
               ──► TFLite export (float16 by default), verified against Keras
    measured at each step on the same frames: PCK@0.5/0.2/0.05 (bbox), EPE, PCK-AUC,
    parameters, MACs, file sizes, inference time and FPS (Keras and TFLite, thread count stated).

`compress_model` is the library entry point (the `compress` and `sweep` commands call it).
"""

from __future__ import annotations

import gzip
import os
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.evaluate import KerasKeypointModel, evaluate_predictor
from fcnpose_tf.fileio import check_writable, write_json
from fcnpose_tf.records import file_sha256, training_record

if TYPE_CHECKING:
    import tf_keras as keras

# TensorFlow is imported inside the functions: the CLI reads this module's defaults to build
# its parser, and the parser must load on a Pi without TensorFlow.

METHODS = ("l1", "magnitude")
DEFAULT_RETRAIN_EPOCHS = 25
"""Default retraining budget: keeps `compress --rate 0.7` within ~10 minutes on 2 cores (measured:
11 min 55 s wall with a sweep job sharing one of the two cores; held-out PCK@0.5 0.946 against the
base's 0.966, the same as 40 epochs). The paper retrains up to 100 epochs until convergence; pass
--retrain-epochs 100 for that."""


@dataclass
class CompressOptions:
    """Settings of one compression run."""

    rate: float
    method: str = "l1"
    strategy: str = "independent"
    quantize: str = "float16"
    retrain_epochs: int = DEFAULT_RETRAIN_EPOCHS
    patience: int = 5
    batch_size: int = 8
    learning_rate: float = 1e-3
    augment_copies: int = 2
    seed: int = 0
    fold: int | None = None
    threads: int | None = None
    positive_weight: float = 1.0
    """Weight of keypoint-disc pixels in the retraining loss (1 = plain BCE; use the base model's)."""
    lr_patience: int = 0
    """While retraining, halve Adam's rate after this many epochs without a better validation loss
    (floor 1e-5); 0 keeps it constant."""

    def validate(self) -> None:
        if not self.positive_weight >= 1:
            raise UserError(f"positive weight must be >= 1, got {self.positive_weight}")
        if isinstance(self.lr_patience, bool) or not isinstance(self.lr_patience, int) or self.lr_patience < 0:
            raise UserError(f"learning-rate patience must be 0 (off) or more epochs, got {self.lr_patience!r}")
        if self.method not in METHODS:
            raise UserError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if isinstance(self.rate, bool) or not isinstance(self.rate, (int, float)) or not 0 <= self.rate < 1:
            raise UserError(f"pruning rate must be in [0, 1) (e.g. 0.7 for 70%), got {self.rate!r}")
        if self.retrain_epochs < 0:
            raise UserError(f"retrain epochs must be >= 0, got {self.retrain_epochs}")
        if self.augment_copies < 0:
            raise UserError(f"augmented copies must be >= 0, got {self.augment_copies}")


def output_names(base_name: str, options: CompressOptions) -> dict[str, str]:
    """File names of a run: NAME_p70.keras, NAME_p70_fp16.tflite, NAME_p70_report.json (m70 for magnitude)."""
    tag = f"{'p' if options.method == 'l1' else 'm'}{round(options.rate * 100):02d}"
    quant = {"float16": "fp16", "float32": "fp32", "int8-weights": "int8w"}[options.quantize]
    stem = f"{base_name}_{tag}"
    return {"stem": stem, "keras": f"{stem}.keras", "tflite": f"{stem}_{quant}.tflite",
            "report": f"{stem}_report.json"}


def file_sizes(model: keras.Model, keras_path: Path | None = None) -> dict[str, int]:
    """Bytes of the model as .keras and .h5 (no optimizer state), and gzip-compressed .h5."""
    from fcnpose_tf.model import save_for_inference

    sizes: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        h5 = Path(tmp) / "m.h5"
        with warnings.catch_warnings():  # the paper's size is the .h5; Keras calls the format legacy
            warnings.simplefilter("ignore", UserWarning)
            save_for_inference(model, h5)
        sizes["h5_size_bytes"] = h5.stat().st_size
        sizes["h5_gzip_size_bytes"] = len(gzip.compress(h5.read_bytes(), 9))
        if keras_path is None:
            keras_path = Path(tmp) / "m.keras"
            save_for_inference(model, keras_path)
        sizes["keras_size_bytes"] = keras_path.stat().st_size
    return sizes


def model_facts(model: keras.Model) -> dict[str, Any]:
    """Widths, parameters and MACs (FLOPs = 2 x MACs) of a model."""
    from fcnpose_tf.model import conv_widths, describe

    rows = describe(model)
    macs = sum(r.macs for r in rows)
    return {"widths": list(conv_widths(model)), "params": int(model.count_params()), "macs": int(macs),
            "flops": int(2 * macs), "nonzero_weights": int(sum(np.count_nonzero(w) for w in model.get_weights()))}


def _measure(predictor: Any, dataset: Any, indices: Sequence[int], label: str, timing: bool = True) -> dict:
    print(f"  evaluating {label} on {len(indices)} frames ...", flush=True)
    result = evaluate_predictor(predictor, dataset, indices, dataset.schema,
                                min_timed_frames=50 if timing else 1, warmup=5 if timing else 1)
    out = {"metrics": result["metrics"]}
    if timing:
        out["timing"] = result["timing"]
    return out


def compress_model(base_path: str | os.PathLike, train_dataset: Any, eval_dataset: Any, eval_indices: Sequence[int],
                   out_dir: str | os.PathLike, options: CompressOptions, *, force: bool = False,
                   eval_description: str = "", verbose: int = 1) -> dict[str, Any]:
    """Prune, retrain, export and measure one model at one rate; write the files; return the report.

    Args:
        base_path: the unpruned (or any) .keras/.h5 FCN-Pose.
        train_dataset: dataset to retrain on (its hold-out split, or `options.fold`).
        eval_dataset, eval_indices: the frames every step is measured on.
        out_dir: where NAME_p70.keras, NAME_p70_fp16.tflite and NAME_p70_report.json go.
        options: rate, method, strategy, quantize, retraining settings, threads.
        force: replace existing output files.
        verbose: 0 silent training; 1 progress bars while preparing data and one line per epoch; 2 one
            line per epoch without progress bars (logs: `sweep --quiet`).
    Returns:
        The report dict (also written as NAME_pXX_report.json).
    Raises:
        UserError: bad options, existing outputs without force, unwritable folder, a model whose
            maps do not match the dataset, or an export that fails verification (nothing written).
    """
    import tf_keras as keras

    from fcnpose_tf.data.dataset import fold_data
    from fcnpose_tf.export import inspect_tflite, write_tflite
    from fcnpose_tf.model import load_model, save_for_inference
    from fcnpose_tf.prune import magnitude_prune, prune_model
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.train import MIN_LEARNING_RATE, FitConfig, compile_for_training, fit

    options.validate()
    start = time.perf_counter()
    base_path = Path(base_path)
    out_dir = Path(out_dir)
    names = output_names(base_path.stem, options)
    paths = {k: out_dir / v for k, v in names.items() if k != "stem"}
    base = load_model(base_path)
    if base.output_shape[-1] != train_dataset.schema.num_maps:
        raise UserError(f"{base_path}: {base.output_shape[-1]} output maps, but the data's schema needs "
                        f"{train_dataset.schema.num_maps}")
    surgery = prune_model(base, options.rate, strategy=options.strategy)  # an unsupported layer fails here, first
    for path in paths.values():
        check_writable(path, force)
    input_size = int(base.input_shape[1])
    steps = 6
    print(f"[1/{steps}] base model {base_path} ({input_size}x{input_size})", flush=True)
    report: dict[str, Any] = {
        "base_model": str(base_path), "method": options.method, "options": asdict(options),
        "evaluation_frames": eval_description or f"{len(eval_indices)} frames of {eval_dataset.via_path}",
        "pck_normalisation": "max(w, h) of the ground-truth keypoints' bounding box",
        "threads": options.threads,
    }
    base_facts = model_facts(base)
    base_eval = _measure(KerasKeypointModel(base, base_path, num_threads=options.threads), eval_dataset,
                         eval_indices, "the base model (Keras)")
    report["base"] = {**base_facts, **file_sizes(base, base_path if base_path.suffix == ".keras" else None),
                      **base_eval}

    print(f"[2/{steps}] pruning: {options.method} at rate {options.rate:g}"
          + (f" ({options.strategy})" if options.method == "l1" else ""), flush=True)
    train_data = val_data = None
    record = training_record(base_path) or {}
    fit_config = FitConfig(epochs=max(options.retrain_epochs, 1), patience=options.patience,
                           batch_size=options.batch_size, learning_rate=options.learning_rate, seed=options.seed,
                           positive_weight=options.positive_weight, lr_patience=options.lr_patience)
    if options.retrain_epochs > 0:
        fold = options.fold if options.fold is not None else (
            record.get("fold") if record.get("data_sha256") == file_sha256(train_dataset.via_path) else None)
        train_data, val_data = fold_data(train_dataset, fold, input_size, options.augment_copies, options.seed,
                                         progress=verbose == 1)
        report["retrain_data"] = {"data": str(train_dataset.via_path), "fold": fold,
                                  "train_samples": len(train_data), "val_frames": len(val_data)}
    if options.method == "l1":
        pruned = surgery
    else:
        sparsity = 1.0 - model_facts(surgery)["params"] / base_facts["params"]
        report["magnitude_sparsity"] = round(sparsity, 6)

        def train_fn(wrapped: keras.Model, callbacks: list) -> None:
            # the same loss and optimizer as the l1 path's `fit` (weighted BCE when positive_weight > 1)
            compile_for_training(wrapped, options.learning_rate, options.positive_weight)
            if train_data is None:
                return
            extra = [keras.callbacks.EarlyStopping(patience=options.patience, restore_best_weights=True)]
            if options.lr_patience:  # as fit's: halve after lr_patience epochs without a lower val loss
                extra.append(keras.callbacks.ReduceLROnPlateau(factor=0.5, patience=options.lr_patience,
                                                               min_delta=0.0, min_lr=MIN_LEARNING_RATE))
            keras.utils.set_random_seed(options.seed)
            started = time.perf_counter()
            history = wrapped.fit(train_data.sequence(options.batch_size, seed=options.seed),
                                  validation_data=val_data.arrays(), validation_batch_size=options.batch_size,
                                  epochs=options.retrain_epochs, callbacks=callbacks + extra,
                                  verbose=2 if verbose else 0).history
            val = [float(v) for v in history.get("val_loss", [])]
            best = int(np.argmin(val)) if val else -1
            report["retraining"] = {"epochs_run": len(val), "best_epoch": best + 1 if val else 0,
                                    "best_val_loss": val[best] if val else None,
                                    "seconds": round(time.perf_counter() - started, 1),
                                    "loss": _loss_name(wrapped),
                                    "positive_weight": options.positive_weight,
                                    "learning_rates": [float(f"{v:.6g}") for v in history.get("lr", [])]}

        pruned = magnitude_prune(base, sparsity, train_fn=train_fn)
    report["pruned_before_retraining"] = {**model_facts(pruned), **_measure(
        KerasKeypointModel(pruned, num_threads=options.threads), eval_dataset, eval_indices,
        "the pruned model before retraining", timing=False)}

    print(f"[3/{steps}] retraining: up to {options.retrain_epochs} epochs", flush=True)
    if options.method == "l1" and options.retrain_epochs > 0:
        result = fit(pruned, train_data.sequence(options.batch_size, seed=options.seed), val_data.arrays(),
                     paths["keras"], fit_config, force=force, verbose=2 if verbose else 0,
                     metadata={"data": str(train_dataset.via_path),
                               "data_sha256": file_sha256(train_dataset.via_path),
                               "fold": report["retrain_data"]["fold"], "pruned_from": str(base_path),
                               "rate": options.rate, "strategy": options.strategy, "input_size": input_size})
        retrained = load_model(paths["keras"])
        report["retraining"] = {"epochs_run": result.epochs_run, "best_epoch": result.best_epoch,
                                "best_val_loss": result.best_val_loss, "seconds": round(result.seconds, 1),
                                "loss": _loss_name(pruned), "positive_weight": options.positive_weight,
                                "learning_rates": [float(f"{h['lr']:.6g}") for h in result.history if "lr" in h]}
    else:
        retrained = pruned
        from fcnpose_tf.fileio import atomic_path

        with atomic_path(paths["keras"], force) as tmp:
            save_for_inference(retrained, tmp)

    print(f"[4/{steps}] measuring the retrained Keras model", flush=True)
    report["retrained"] = {**model_facts(retrained), **file_sizes(retrained, paths["keras"]), **_measure(
        KerasKeypointModel(retrained, paths["keras"], num_threads=options.threads), eval_dataset, eval_indices,
        "the retrained model (Keras)")}

    print(f"[5/{steps}] exporting {options.quantize} TFLite (verified against Keras)", flush=True)
    from fcnpose_tf.preprocess import preprocess_frame

    samples = np.stack([preprocess_frame(eval_dataset.load_image(int(i)), input_size)
                        for i in list(eval_indices)[:4]])
    export = write_tflite(retrained, paths["tflite"], options.quantize, force=force, sample_frames=samples,
                          num_threads=options.threads)
    tflite_info = inspect_tflite(paths["tflite"])

    print(f"[6/{steps}] measuring the TFLite model", flush=True)
    tfl = KeypointModel(paths["tflite"], num_threads=options.threads)
    report["quantized"] = {
        "params": report["retrained"]["params"], "macs": report["retrained"]["macs"],
        "flops": report["retrained"]["flops"], "tflite_size_bytes": export.size_bytes,
        "tflite_gzip_size_bytes": len(gzip.compress(export.data, 9)), "export": export.to_dict(),
        "tflite_ops": tflite_info.get("op_counts", tflite_info.get("ops")),
        **_measure(tfl, eval_dataset, eval_indices, f"the {options.quantize} TFLite model")}
    report["files"] = {k: str(v) for k, v in paths.items()}
    report["seconds"] = round(time.perf_counter() - start, 1)
    write_json(paths["report"], report, force=force)
    return report


def _loss_name(model: Any) -> str:
    """The compiled loss's name: binary_crossentropy (plain BCE) or keypoint_bce (weighted)."""
    loss = getattr(model, "loss", None)
    return str(getattr(loss, "name", loss))


def report_table(report: dict[str, Any], markdown: bool = False) -> str:
    """The compression report as a table: the unpruned model beside each step of the compressed one.

    Sizes are of the file each row's model ships as (.h5 for Keras, .tflite), in KB (1000 bytes);
    "infer ms" is the forward pass alone, FPS the whole frame (preprocess, inference, keypoints).
    """
    from fcnpose_tf.tables import format_table

    def row(label: str, step: dict, size_key: str) -> list:
        m = step["metrics"]
        t = step.get("timing")
        size = step.get(size_key) if size_key else None
        return [label, step["params"], step["macs"] / 1e6, size / 1e3 if size else None,
                m["pck@0.5_bbox"], m["pck@0.2_bbox"], m["pck@0.05_bbox"], m["epe_px"],
                t["inference_ms"]["mean"] if t else None, t["fps"] if t else None]

    quantize = report["options"]["quantize"]
    rows = [row("unpruned (Keras, .h5)", report["base"], "h5_size_bytes"),
            row("pruned, before retraining", report["pruned_before_retraining"], ""),
            row("pruned + retrained (Keras, .h5)", report["retrained"], "h5_size_bytes"),
            row(f"{quantize} TFLite (.tflite)", report["quantized"], "tflite_size_bytes")]
    return format_table(["model", "params", "MMACs", "size KB", "PCK@0.5", "PCK@0.2", "PCK@0.05", "EPE px",
                         "infer ms", "FPS e2e"], rows, markdown=markdown,
                        digits=[None, None, 1, 1, 3, 3, 3, 2, 2, 1])
