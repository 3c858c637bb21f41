"""TensorFlow set-up for the training side: a quiet import and the CPU thread settings.

Importing this module imports no TensorFlow; each function imports it when called. The Pi-side
core (runtime/) never uses this module.
"""

from __future__ import annotations

import os
import sys

from fcnpose_tf.errors import UserError


TENSORFLOW_ENVIRONMENT = {
    "TF_CPP_MIN_LOG_LEVEL": "3",
    "TF_ENABLE_ONEDNN_OPTS": "1",
}
"""What the commands set before TensorFlow is imported, unless the user set it: no C++ start-up chatter (CUDA
probing), and oneDNN's CPU kernels, which TensorFlow 2.21 turns on by itself only on CPUs with AVX-512-class
features. On an AVX2 AMD EPYC they made a training step 1.31x faster at `--freeze 2` and 1.46x at `--freeze 0`
(`tools/bench_train_step.py`, docs/training.md); TF_ENABLE_ONEDNN_OPTS=0 turns them off."""


def set_tensorflow_environment(environ: dict[str, str] | None = None) -> None:
    """TENSORFLOW_ENVIRONMENT into `environ` where a variable is not set already.

    Takes effect only before TensorFlow is imported; worker processes inherit it.

    Args:
        environ: the environment to complete (default: this process's).
    """
    environ = os.environ if environ is None else environ
    for name, value in TENSORFLOW_ENVIRONMENT.items():
        environ.setdefault(name, value)


def import_tensorflow_quietly() -> None:
    """Import TensorFlow with its native start-up log lines (oneDNN, CUDA probing) sent to /dev/null.

    TensorFlow's C++ logging ignores TF_CPP_MIN_LOG_LEVEL set from inside Python, so the
    file descriptor is silenced for the import only; errors still surface as Python exceptions.
    Set FCNPOSE_TF_VERBOSE to see the lines.

    Raises:
        UserError: TensorFlow is not installed (names the extra to install).
    """
    if "tensorflow" in sys.modules or os.environ.get("FCNPOSE_TF_VERBOSE"):
        return
    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        try:
            import tensorflow

            tensorflow.get_logger().setLevel("ERROR")  # Python-side INFO/WARNING chatter (compile notes)
        except ImportError as exc:
            raise UserError(f"this command needs TensorFlow ({exc}); install the training extra: "
                            "pip install 'fcnpose-tf[train]'") from None
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def set_tensorflow_threads(threads: int | None) -> None:
    """Limit TensorFlow's CPU threads (call before TensorFlow runs anything).

    Intra-op parallelism gets `threads`, inter-op 1, so a timing states one thread count. Once
    TensorFlow has initialised its runtime the settings are fixed; then this keeps what is set.

    Args:
        threads: intra-op threads (None: TensorFlow's default).
    """
    if threads is None:
        return
    import tensorflow as tf

    try:
        tf.config.threading.set_intra_op_parallelism_threads(threads)
        tf.config.threading.set_inter_op_parallelism_threads(1)
    except RuntimeError:  # already initialised: keep what is set
        pass


def tensorflow_threads() -> dict[str, int]:
    """TensorFlow's thread settings as it reports them.

    Returns:
        {"intra_op", "inter_op"}; 0 is its default.
    """
    import tensorflow as tf

    return {"intra_op": tf.config.threading.get_intra_op_parallelism_threads(),
            "inter_op": tf.config.threading.get_inter_op_parallelism_threads()}
