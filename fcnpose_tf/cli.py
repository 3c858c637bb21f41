"""The `fcnpose-tf` command: one entry point, one module per subcommand in fcnpose_tf.commands.

Importing this module imports no TensorFlow: each subcommand imports what it
needs when it runs, so `run` and `bench` work on a Pi with only the `pi` extra.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Sequence

from fcnpose_tf import __version__
from fcnpose_tf.commands import COMMAND_MODULES
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import WriteError, command_outputs
from fcnpose_tf.tfsetup import import_tensorflow_quietly


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (plus a pointer to --help) and exit status 2."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"error: {message} (see `{self.prog} --help`)\n")


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Examples kept as written; defaults shown only where there is one worth showing."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default in (None, False, [], argparse.SUPPRESS) or "%(default)" in (action.help or ""):
            return action.help or ""
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    """The full parser; imports only the (TensorFlow-free) command modules."""
    parser = _Parser(prog="fcnpose-tf", formatter_class=_Formatter,
                     description="FCN-Pose robot keypoints: data, training, compression, Raspberry Pi runtime.",
                     epilog="Run `fcnpose-tf COMMAND --help` for a command's options and examples.")
    parser.add_argument("--version", action="version", version=f"fcnpose-tf {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks for errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for module_name in COMMAND_MODULES:
        module = importlib.import_module(f"fcnpose_tf.commands.{module_name}")
        doc = (module.__doc__ or "").strip()
        summary = doc.splitlines()[0] if doc else module_name
        cmd = sub.add_parser(module.NAME, help=summary, description=doc, formatter_class=_Formatter,
                             epilog="examples:\n" + module.EXAMPLES.rstrip())
        cmd.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                         help="show full tracebacks for errors")
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run, _uses_tensorflow=getattr(module, "USES_TENSORFLOW", False))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run a subcommand; user errors print `error: ...` and return 2."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # keep TensorFlow's C++ start-up chatter (CUDA probing) off the terminal
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    with command_outputs() as outputs:
        try:
            if args._uses_tensorflow:
                import_tensorflow_quietly()
            status = args._run(args)
            return int(status or 0)
        except UserError as exc:
            if args.debug:
                raise
            message = str(exc)
            if isinstance(exc, WriteError):  # what a full disk cut short goes; what was completed stays, named
                outputs.remove_created_folders()
                if outputs.completed:
                    message += f"; kept the files completed before it: {', '.join(map(str, outputs.completed))}"
            print(f"error: {message}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            if args.debug:
                raise
            print("interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
