"""fcnpose-tf: FCN-Pose robot keypoints, from training to a Raspberry Pi.

Importing this package never imports TensorFlow: the training side is loaded
on demand by the modules that need it.
"""

__version__ = "0.1.0"
