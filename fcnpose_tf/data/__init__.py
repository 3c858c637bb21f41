"""Training data: VIA import/export, target maps, augmentation, splits and the training feed.

Submodules import what they need; `via`, `masks` and `splits` need only numpy
and OpenCV, `augment` needs Albumentations, and only `TrainingData.sequence`
imports tf_keras.
"""
