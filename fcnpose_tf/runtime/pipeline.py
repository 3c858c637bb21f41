"""The pipelined frame loop's second thread: the interpreter's invoke, one frame at a time.

`run_stream(..., pipelined=True)` keeps everything but the forward pass on the main thread (reading
frames, preprocessing, decoding, smoothing, writing records, drawing, signals) and hands the forward
pass to an `InvokeWorker`. While the worker invokes frame n, the main thread decodes and writes frame
n-1 and reads and preprocesses frame n+1; LiteRT releases the GIL during an invoke, so the two run
on separate cores. The queue is bounded by construction: one frame in the interpreter, one staged
beside it (two staging buffers each way). A file's frames are all processed, in order; a camera's
are taken newest-first by its grab thread (`sources.LiveSource`), so a frame waits for at most the
invoke in progress. Only the main thread handles signals (`fileio.signals_deferred`); the worker is
a daemon thread that `close` joins after its current invoke.
"""

from __future__ import annotations

import queue
import threading

import numpy as np

from fcnpose_tf.runtime.estimator import KeypointPredictor

WORKER_NAME = "fcnpose-invoke"


class InvokeWorker:
    """Runs `model.forward` on staged inputs in its own thread; `start(slot)`, then `wait()` for it.

    `inputs[slot]` is copied into the interpreter when the invoke starts and `outputs[slot]` receives
    its raw maps; the caller fills the other slot's input and decodes the other slot's output meanwhile.

    Args:
        model: a predictor with the staged-frame methods (`pipelinable`).
        slots: staged inputs and outputs to alternate between.
    Raises:
        TypeError: a predictor that is not pipelinable.
    """

    def __init__(self, model: KeypointPredictor, slots: int = 2):
        if not model.pipelinable:
            raise TypeError(f"{type(model).__name__} has no staged-frame methods to pipeline")
        self.model = model
        self.inputs: list[np.ndarray] = [model.new_input() for _ in range(slots)]
        self.outputs: list[np.ndarray] = [model.new_output() for _ in range(slots)]
        self._todo: queue.SimpleQueue = queue.SimpleQueue()
        self._done: queue.SimpleQueue = queue.SimpleQueue()
        self._finished = threading.Event()  # set when the frame in flight is done (its result waiting)
        self.busy = False
        self._thread = threading.Thread(target=self._loop, name=WORKER_NAME, daemon=True)
        self._thread.start()

    def start(self, slot: int) -> None:
        """Begin the forward pass of `inputs[slot]`.

        Args:
            slot: which staged input to run.
        Raises:
            RuntimeError: the previous frame was not waited for.
        """
        if self.busy:
            raise RuntimeError("InvokeWorker.start while a frame is in flight")
        self.busy = True
        self._finished.clear()
        self._todo.put(slot)

    def finished(self, timeout: float) -> bool:
        """Whether the frame in flight is done (`wait` then returns at once), waiting up to `timeout` seconds."""
        return self._finished.wait(timeout)

    def wait(self) -> tuple[int, float]:
        """Wait for the frame in flight.

        Returns:
            (slot, invoke ms) once its output is in `outputs[slot]`.
        Raises:
            BaseException: whatever the forward pass raised, re-raised here.
        """
        result = self._done.get()  # interruptible: Ctrl-C / SIGTERM reach the main thread while it waits
        self.busy = False
        if isinstance(result, BaseException):
            raise result
        return result

    def _loop(self) -> None:
        while True:
            slot = self._todo.get()
            if slot is None:
                return
            try:
                self._done.put((slot, self.model.forward(self.inputs[slot], self.outputs[slot])))
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread, raised there
                self._done.put(exc)
            self._finished.set()

    def close(self) -> None:
        """Stop the thread after the invoke in progress (its result is dropped); safe to call twice."""
        if self._thread.is_alive():
            self._todo.put(None)
            self._thread.join()
        self.busy = False


__all__ = ["InvokeWorker", "WORKER_NAME"]
