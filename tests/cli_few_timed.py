"""`python tests/cli_few_timed.py ARGS`: `python -m fcnpose_tf ARGS` in a new process whose evaluations time
`conftest.FEW_TIMED_FRAMES` frames after one of warm-up (`conftest.cut_timed_frames`) instead of 50 after 5.

For tests that need a fresh process (a sweep sets TensorFlow's threads before it runs anything) but assert no
timing figure beyond its presence. Every frame is still scored once; TensorFlow is set up and imported as the CLI
does it (its environment first), before the evaluations are patched.
"""

import sys

import pytest

from conftest import cut_timed_frames
from fcnpose_tf.cli import console_main
from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_environment

if __name__ == "__main__":
    set_tensorflow_environment()
    import_tensorflow_quietly()
    cut_timed_frames(pytest.MonkeyPatch())
    sys.exit(console_main())
