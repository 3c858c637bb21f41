"""Shared test helper: random weights for untrained models (imported by test modules)."""

import math

import numpy as np


def randomize(model, seed=0):
    """He-normal kernels and small non-zero biases, so maps are O(1) and not saturated."""
    rng = np.random.default_rng(seed)
    for layer in model.layers:
        weights = layer.get_weights()
        if weights:
            fan_in = np.prod(weights[0].shape[:-1])
            layer.set_weights([rng.normal(0, math.sqrt(2 / fan_in), weights[0].shape).astype(np.float32)]
                              + [rng.normal(0, 0.1, w.shape).astype(np.float32) for w in weights[1:]])
    return model
