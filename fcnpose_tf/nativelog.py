"""Native libraries' own log lines kept off the terminal around the calls that print them.

LiteRT prints `INFO: Created TensorFlow Lite XNNPACK delegate for CPU.` when an interpreter is
made, and FFmpeg (inside OpenCV) lines such as `[mov,mp4,... @ 0x...] moov atom not found` when a
video does not open; both write straight to file descriptor 2, ahead of the one-line error the CLI
prints for the same failure. Neither offers a log level that works once loaded (LiteRT has none;
OpenCV reads OPENCV_FFMPEG_LOGLEVEL once per process, at its first FFmpeg call), so
`native_stderr_captured()` points descriptor 2 at a temporary file for the duration of such a call
and hands the text to the caller, which may quote it in its own error. Our own errors are
exceptions raised inside the block and printed after it, so they are never hidden.
Standard library only (and fileio's signals_deferred).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
from typing import IO, Iterator

from fcnpose_tf.fileio import signals_deferred

_lock = threading.RLock()  # descriptor 2 is process-wide: one capture at a time (nesting in one thread is fine)


class NativeOutput:
    """What native code wrote to descriptor 2 inside `native_stderr_captured()` (filled when the block ends)."""

    def __init__(self) -> None:
        self.text = ""

    def lines(self) -> list[str]:
        """The non-empty lines, without FFmpeg's `[component @ 0x...]` prefix."""
        return [re.sub(r"^\[[^\]]* @ 0x[0-9a-fA-F]+\]\s*", "", line.strip()) for line in self.text.splitlines()
                if line.strip()]

    def last_line(self) -> str:
        """The last non-empty line, without FFmpeg's prefix ('' if nothing was printed)."""
        lines = self.lines()
        return lines[-1] if lines else ""


@contextlib.contextmanager
def native_stderr_captured(sink: IO[bytes] | None = None) -> Iterator[NativeOutput]:
    """Run a block with file descriptor 2 redirected to a temporary file; yields its NativeOutput.

    Keep the block to the native call: other threads' stderr output is captured too while it runs.
    `sink`: a temporary file (`tempfile.TemporaryFile()`) to reuse, emptied first, for a call made
    once per frame; by default each block makes its own. If the redirection cannot be set up, the
    block simply runs with stderr as it was.
    """
    output = NativeOutput()
    with _lock:
        try:
            sys.stderr.flush()  # what Python printed before goes out first, where it belongs
        except (AttributeError, OSError, ValueError):
            pass
        own: IO[bytes] | None = None
        saved: int | None = None

        def restore() -> None:  # idempotent: run again if a signal cut a first run short
            nonlocal saved, own
            if saved is not None:
                with contextlib.suppress(OSError):
                    os.dup2(saved, 2)
                    os.close(saved)
                saved = None
                try:
                    sink.seek(0)
                    output.text = sink.read().decode("utf-8", "replace")
                except OSError:
                    pass
            if own is not None:
                own.close()
                own = None

        try:
            with signals_deferred():  # Ctrl-C or a kill arriving mid-switch must not leave descriptor 2 redirected
                try:
                    if sink is None:
                        sink = own = tempfile.TemporaryFile()
                    else:
                        sink.seek(0)
                        sink.truncate()
                    saved = os.dup(2)
                    os.dup2(sink.fileno(), 2)
                except OSError:  # no redirection: the block runs with stderr as it was
                    if saved is not None:
                        os.close(saved)
                        saved = None
            yield output
        finally:
            try:
                with signals_deferred():
                    restore()
            finally:  # a signal taken before the deferral above began: descriptor 2 still comes back
                restore()
