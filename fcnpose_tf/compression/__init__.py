"""Compression: filter importance (`importance`), L1-norm filter surgery (`prune`) and its generalisation to
branching tf_keras and Keras 3 models through a dependency graph of coupled channels (`depgraph`, with each layer
type's channel rule in `layer_rules`, what a rule is in `channel_rules`), the `compress` pipeline
(prune, retrain, export, measure), quantization-aware training (`qat`), TFLite export verified on keypoints
(`export`) and the inference graph the converter sees (`inference_graph`).

Builds on the training side (`fcnpose_tf.training`); its .tflite files run on the Pi side (`fcnpose_tf.runtime`).
"""
