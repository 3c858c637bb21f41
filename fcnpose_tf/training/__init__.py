"""The training side: FCN-Pose itself (`model`), training with checkpoints and early stopping (`train`),
distillation targets (`distill`), evaluation of Keras and TFLite models (`evaluate`) and TensorFlow set-up (`tfsetup`).

Builds on the data side (`fcnpose_tf.data`) and the Pi-side core; imports TensorFlow.
"""
