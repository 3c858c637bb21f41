"""The `fcnpose-tf` command's entry point (and `python -m fcnpose_tf`'s): the stop signals are taken before the
command-line modules load, so a Ctrl-C or `kill` in the first fraction of a second ends the process with the
signal's one line and status (`cli.console_main` takes over from there), not a traceback, and is not lost when the
process inherited an ignored SIGINT (`cmd &` in a script). Only the standard library is imported here."""

import signal
import sys

_received: list[int] = []


def _stop(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt


def main() -> int:
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop)
    try:
        from fcnpose_tf.cli import console_main
    except KeyboardInterrupt:
        from fcnpose_tf.fileio import STOP_SIGNALS

        reason, status = STOP_SIGNALS[_received[0] if _received else signal.SIGINT]
        print(reason, file=sys.stderr, flush=True)
        return status
    return console_main()
