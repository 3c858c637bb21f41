#!/usr/bin/env python
"""Graph pruning (`fcnpose_tf.compression.graph_prune`) on keras.applications networks: does each one prune, and is
the pruned model exact?

    python tools/keras_apps_check.py --keras keras3                 # every network, rates 0.3 and 0.5
    python tools/keras_apps_check.py --keras tf_keras --nets MobileNetV2,ResNet50 --round-to 8

Each network is built with weights=None, a small input (96 x 96 by default), 10 classes and no classifier
activation (logits), its weights made random (BatchNormalization statistics too), then planned and pruned at each
rate. Exactness is checked as tests/test_depgraph.py does, on one random input: the pruned model's output against
(a) the original with the removed channels' readers zeroed (the input slices of the Conv2D, SeparableConv2D and
Dense layers reading them) and (b) the original with the removed filters made dead (kernel slice and bias zero, and
beta and moving mean zero in the BatchNormalization after them), as max |difference| relative to the largest
|output|. One line per network and rate: ok, refused (the one-line message), WRONG (the differences) or CRASH (the
traceback).
"""

from __future__ import annotations

import argparse
import importlib
import time
import traceback

import numpy as np

FLAVOURS = {"tf_keras": "tf_keras", "keras3": "keras"}
NETS = {  # builder -> extra arguments
    "MobileNet": {},
    "MobileNetV2": {},
    "MobileNetV3Small": {},
    "MobileNetV3Large": {},
    "MobileNetV3Small/no-preprocessing": {"include_preprocessing": False},
    "MobileNetV3Small/minimalistic": {"minimalistic": True},
    "ResNet50": {},
    "ResNet50V2": {},
    "DenseNet121": {},
    "EfficientNetB0": {},
    "EfficientNetV2B0": {},
    "ConvNeXtTiny": {},
    "Xception": {},
    "InceptionV3": {},
    "NASNetMobile": {},
    "RegNetX002": {},
    "VGG16": {},
    "MobileNetV2/no-top": {"include_top": False, "pooling": "avg"},
    "ResNet50/no-top": {"include_top": False, "pooling": "avg"},
    "EfficientNetB0/no-top": {"include_top": False, "pooling": "avg"},
}
PRODUCER_INPUT_AXIS = {"Conv2D": 2, "SeparableConv2D": 2, "Dense": 0}
TOLERANCE = 1e-4


def build(keras, name: str, size: int):
    builder = getattr(keras.applications, name.split("/")[0], None)
    if builder is None:
        return None
    options = dict(NETS[name])
    if options.get("include_top", True):
        options.update(classes=10, classifier_activation=None)
    return builder(input_shape=(size, size, 3), weights=None, **options)


def all_layers(model) -> dict:
    """Name -> layer, the layers of nested models (ConvNeXt's Sequential stem) included."""
    layers = {}
    for layer in model.layers:
        layers.update(all_layers(layer) if hasattr(layer, "layers") else {layer.name: layer})
    return layers


def randomize(model, seed: int = 0) -> None:
    """Random weights everywhere, BatchNormalization statistics included (so a BN is not the identity)."""
    rng = np.random.default_rng(seed)
    for layer in all_layers(model).values():
        kind = type(layer).__name__
        weights = layer.get_weights()
        if not weights or kind == "Normalization" or any(w.dtype.kind != "f" for w in weights):
            continue
        if kind == "BatchNormalization":
            new = [rng.normal(0, 0.2, w.shape) for w in weights]
            if layer.scale:
                new[0] = rng.uniform(0.5, 1.5, weights[0].shape)
            new[-1] = rng.uniform(0.5, 2.0, weights[-1].shape)
        else:
            new = [rng.normal(0, np.sqrt(1.0 / max(np.prod(w.shape[:-1]), 1)), w.shape) if w.ndim > 1
                   else rng.normal(0, 0.1, w.shape) for w in weights]
        layer.set_weights([w.astype(np.float32) for w in new])


def changed_output(model, changes: dict, x: np.ndarray) -> np.ndarray:
    layers = all_layers(model)
    saved = {name: layers[name].get_weights() for name in changes}
    try:
        for name, weights in changes.items():
            layers[name].set_weights(weights)
        return np.asarray(model(x, training=False))
    finally:
        for name, weights in saved.items():
            layers[name].set_weights(weights)


def readers_zeroed(model, plan) -> dict:
    changes = {}
    for layer in all_layers(model).values():
        axis = PRODUCER_INPUT_AXIS.get(type(layer).__name__)
        entry = plan.layers.get(layer.name)
        if axis is None or entry is None:
            continue
        weights = layer.get_weights()
        groups = getattr(layer, "groups", 1)
        if groups > 1:  # input channel c is row c % (cin / groups) of the filters of group c // (cin / groups)
            per_in, per_out = weights[0].shape[2], weights[0].shape[3] // groups
            for c in np.setdiff1d(np.arange(per_in * groups), entry.kept_in[0]):
                weights[0][:, :, c % per_in, (c // per_in) * per_out:(c // per_in + 1) * per_out] = 0
        else:
            gone = np.setdiff1d(np.arange(weights[0].shape[axis]), entry.kept_in[0])
            np.moveaxis(weights[0], axis, 0)[gone] = 0
        changes[layer.name] = weights
    return changes


def filters_dead(model, plan) -> dict:
    changes = {}
    for layer in all_layers(model).values():
        kind, entry = type(layer).__name__, plan.layers.get(layer.name)
        if entry is None:
            continue
        weights = layer.get_weights()
        if kind in PRODUCER_INPUT_AXIS:
            kernel = 1 if kind == "SeparableConv2D" else 0
            gone = np.setdiff1d(np.arange(weights[kernel].shape[-1]), entry.kept_out)
            for w in weights[kernel:]:
                w[..., gone] = 0
        elif kind == "BatchNormalization":
            gone = np.setdiff1d(np.arange(weights[-1].shape[0]), entry.kept_out)
            if layer.center:
                weights[1 if layer.scale else 0][gone] = 0
            weights[-2][gone] = 0
        elif kind == "DepthwiseConv2D" and len(weights) > 1:
            weights[1][np.setdiff1d(np.arange(weights[1].shape[0]), entry.kept_out)] = 0
        else:
            continue
        changes[layer.name] = weights
    return changes


def check(keras, name: str, size: int, rates: list[float], round_to: int) -> list[str]:
    from fcnpose_tf.compression.graph_prune import plan_graph, rebuild
    from fcnpose_tf.errors import UserError

    start = time.perf_counter()
    try:
        model = build(keras, name, size)
    except Exception as exc:  # the builder's own refusal (input size, ...)
        return [f"{name}: not built: {type(exc).__name__}: {str(exc).splitlines()[0]}"]
    if model is None:
        return [f"{name}: not in {keras.__name__}.applications"]
    randomize(model)
    x = np.random.default_rng(1).uniform(-1, 1, (1, size, size, 3)).astype(np.float32)
    full = np.asarray(model(x, training=False))
    scale = max(float(np.abs(full).max()), 1e-12)
    lines = []
    for rate in rates:
        label = f"{name} rate {rate} round_to {round_to}"
        try:
            plan = plan_graph(model, rate, round_to=round_to)
            small = rebuild(plan)
            got = np.asarray(small(x, training=False))
            if got.shape != full.shape:
                lines.append(f"{label}: wrong: output shape {got.shape}, expected {full.shape}")
                continue
            diffs = [float(np.abs(got - changed_output(model, changes(model, plan), x)).max()) / scale
                     for changes in (readers_zeroed, filters_dead)]
            pruned = sum(1 for p in plan.groups if not p.group.frozen)
            figures = (f"{pruned}/{len(plan.groups)} groups pruned, params {plan.params[0]:,} -> {plan.params[1]:,}"
                       f", diff readers-zeroed {diffs[0]:.1e} dead-filters {diffs[1]:.1e}"
                       f" (pruning changed the output by {float(np.abs(got - full).max()) / scale:.1e})")
            lines.append(f"{label}: {'ok' if max(diffs) <= TOLERANCE else 'WRONG'}: {figures}")
        except UserError as exc:
            lines.append(f"{label}: refused: {exc}")
        except Exception:
            lines.append(f"{label}: CRASH:\n{traceback.format_exc()}")
    lines.append(f"{name}: {time.perf_counter() - start:.0f} s")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keras", choices=sorted(FLAVOURS), default="keras3", help="the Keras to build with")
    parser.add_argument("--nets", default=",".join(NETS), help=f"comma-separated, of {', '.join(NETS)}")
    parser.add_argument("--size", type=int, default=96, help="input side (default 96)")
    parser.add_argument("--rates", default="0.3,0.5", help="comma-separated rates (default 0.3,0.5)")
    parser.add_argument("--round-to", type=int, default=1, help="kept channels rounded up to a multiple (default 1)")
    parser.add_argument("--threads", type=int, default=1, help="TensorFlow threads (default 1)")
    args = parser.parse_args()
    unknown = [n for n in args.nets.split(",") if n not in NETS]
    if unknown:
        parser.error(f"--nets: unknown {', '.join(unknown)}; known: {', '.join(NETS)}")
    import tensorflow as tf

    tf.config.threading.set_intra_op_parallelism_threads(args.threads)
    tf.config.threading.set_inter_op_parallelism_threads(args.threads)
    keras = importlib.import_module(FLAVOURS[args.keras])
    for name in args.nets.split(","):
        for line in check(keras, name, args.size, [float(r) for r in args.rates.split(",")], args.round_to):
            print(f"[{args.keras}] {line}", flush=True)
        keras.backend.clear_session()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
