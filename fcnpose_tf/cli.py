"""The `fcnpose-tf` command: one entry point, one module per subcommand in fcnpose_tf.commands.

Importing this module imports no TensorFlow: each subcommand imports what it
needs when it runs, so `run` and `bench` work on a Pi with only the `pi` extra.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
from typing import Callable, Sequence

from fcnpose_tf import __version__
from fcnpose_tf.commands import COMMAND_MODULES
from fcnpose_tf import fileio, progress, settings
from fcnpose_tf.errors import UserError
from fcnpose_tf.training.tfsetup import import_tensorflow_quietly, set_tensorflow_environment

EXIT_USER_ERROR = 2
"""Bad input, a refused or failed output (a full disk, a name too long): one `error:` line."""
EXIT_SIGNAL = {sig: status for sig, (_, status) in fileio.STOP_SIGNALS.items()}
"""Ctrl-C (SIGINT) ends a command with 130, a `kill` (SIGTERM) with 143, after the same clean-up."""

class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (plus a pointer to --help) and exit status 2, and options spelled out: an
    abbreviation is refused (`export --out x.tflite` would otherwise be `--out-dir`, a folder named x.tflite)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"error: {message} (see `{self.prog} --help`)\n")

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102 - argparse API
        namespace, extras = super().parse_known_args(args, namespace)
        return settings.fill_from_preset(self, namespace), extras  # options left out: the command's --preset

    def parse_args(self, args=None, namespace=None):  # noqa: D102 - argparse API
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:  # refused by the (sub)command that was given, so the pointer names its --help
            self._chosen(namespace).error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace

    def _chosen(self, namespace: argparse.Namespace) -> argparse.ArgumentParser:
        """The innermost subcommand parser that `namespace` went through (`fcnpose-tf data merge`), else this one."""
        parser = self
        while True:
            found = next((action.choices.get(getattr(namespace, action.dest, None)) for action in parser._actions
                          if isinstance(action, argparse._SubParsersAction)), None)
            if found is None:
                return parser
            parser = found


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Examples kept as written; defaults shown only where there is one worth showing."""

    def _get_help_string(self, action: argparse.Action) -> str:
        # `is`, not `in`: 0 == False, and a default of 0 is one worth showing; a help that states its default
        # ("(default 2)", "%(default)s") is not given a second one
        if any(action.default is none for none in (None, False, argparse.SUPPRESS)) or action.default == [] \
                or "%(default)" in (action.help or "") or "(default" in (action.help or ""):
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
        summary = " ".join(doc.split("\n\n")[0].split()) if doc else module_name  # the first sentence, whole
        cmd = sub.add_parser(module.NAME, help=summary, description=doc, formatter_class=_Formatter,
                             epilog="examples:\n" + module.EXAMPLES.rstrip())
        settings.add_command_options(cmd)
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run, _uses_tensorflow=getattr(module, "USES_TENSORFLOW", False),
                         _outputs=getattr(module, "OUTPUTS", ()),
                         _resumable=getattr(module, "RESUMABLE_OUTPUTS", ()),
                         _written=getattr(module, "written_outputs", None)
                         or (lambda args, names=getattr(module, "FILE_OUTPUTS", ()): names),
                         _private_temp=getattr(module, "PRIVATE_TEMP", True))
    return parser


def plan_outputs(args: argparse.Namespace) -> None:
    """Register up front the files and folders the command's output options name (`fileio.plan_output`)."""
    for names, resumable in ((args._outputs, False), (args._resumable, True)):
        for name in names:
            value = getattr(args, name, None)
            for path in value if isinstance(value, (list, tuple)) else [value]:
                if path is not None and os.fspath(path) != "":
                    fileio.plan_output(path, resumable=resumable)


def refuse_existing_outputs(args: argparse.Namespace) -> None:
    """UserError for an output file the command's options name that exists, without --force: every command refuses
    one, and this says so before the command imports anything heavy. Which outputs are files: the command module's
    FILE_OUTPUTS, or its `written_outputs(args)` (train's --out, unless --folds or --resume); folders are left to
    the command."""
    if getattr(args, "force", False):
        return
    for name in args._written(args):
        value = getattr(args, name, None)
        for path in value if isinstance(value, (list, tuple)) else [value]:
            if path is not None and os.fspath(path) != "" and os.path.isfile(path):
                raise UserError(f"{path}: already exists; pass --force to replace it")


def _kept(outputs: fileio.CommandOutputs) -> str:
    from fcnpose_tf.data.synthcache import cache_dir

    cache = cache_dir().resolve()
    kept = [p for p in outputs.kept() if cache not in p.resolve().parents]  # the package's own cache is not an output
    return f"; kept the files completed before it: {', '.join(map(str, kept))}" if kept else ""


def _end(outputs: fileio.CommandOutputs, message: str | None, status: int) -> int:
    """The one exit path of a command that did not finish: remove what it created and did not complete,
    print one line naming what it completed, return the exit status (a stop signal's, if one came)."""
    signum = fileio.stop_signal()
    with fileio.stop_signals_ignored():
        progress.current().end_line()  # a bar being drawn is closed: the line below starts a line of its own
        outputs.clean_up()
        if signum is not None:
            reason, status = fileio.STOP_SIGNALS[signum]
            line = reason + (f": {message}" if message else "")
        else:
            line = f"error: {message}"
        print(line + _kept(outputs), file=sys.stderr, flush=True)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run a subcommand.

    One exit path for every command: a user error (or any OSError, e.g. a full disk or a name too long)
    prints one `error: ...` line and returns 2; Ctrl-C returns 130 and SIGTERM 143, each after one line.
    However it ends, what the command created and did not complete is removed (the outputs its
    options name, the folders it made, its private temporary folder) and what it completed is named.
    """
    set_tensorflow_environment()  # before any command imports TensorFlow
    for stream in (sys.stdout, sys.stderr):  # a file name that is not UTF-8 is printed, not a crash
        with contextlib.suppress(AttributeError, ValueError):
            stream.reconfigure(errors="backslashreplace")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    private_temp = args._private_temp(args) if callable(args._private_temp) else args._private_temp

    def command() -> int:
        plan_outputs(args)
        refuse_existing_outputs(args)  # in a second, not after TensorFlow's import
        uses = args._uses_tensorflow
        if uses(args) if callable(uses) else uses:  # a command may need it only for some inputs (evaluate M.keras)
            import_tensorflow_quietly()
        return args._run(args)

    return run_guarded(command, debug=args.debug, private_temp=private_temp, quiet=args.quiet)


def run_guarded(work: Callable[[], int | None], *, debug: bool = False, private_temp: bool = True,
                quiet: bool = False) -> int:
    """Run `work` through the one exit path (see `main`) and return its exit status.

    A UserError or OSError is one `error:` line and status 2, a stop signal its own line and 130/143; what
    `work` created and did not complete is removed. `debug` re-raises instead (the full traceback);
    `private_temp` gives it a private temporary folder; `quiet` turns progress bars into log lines.
    """
    reporter = progress.Reporter(quiet=quiet)
    with _stdout_past_a_closed_pipe(), progress.using(reporter), fileio.command_outputs() as outputs, \
            fileio.stop_signals_handled(), \
            (fileio.private_temporary_folder() if private_temp else contextlib.nullcontext()):
        try:
            status = int(work() or 0)
        except UserError as exc:
            if debug:
                outputs.clean_up()
                raise
            return _end(outputs, str(exc), EXIT_USER_ERROR)
        except OSError as exc:  # a path the file system refused (a name too long, a full disk, no permission)
            if debug:
                outputs.clean_up()
                raise
            where = f"{os.fsdecode(exc.filename)}: " if isinstance(exc.filename, (str, bytes, os.PathLike)) else ""
            return _end(outputs, where + fileio.os_error_reason(exc), EXIT_USER_ERROR)
        except KeyboardInterrupt as exc:
            if debug:
                outputs.clean_up()
                raise
            if fileio.stop_signal() is None:  # raised without a signal seen here (a library's own handler)
                fileio.note_stop_signal(signal.SIGTERM if "SIGTERM" in str(exc) else signal.SIGINT)
            return _end(outputs, None, EXIT_USER_ERROR)
        except BaseException:
            if fileio.stop_signal() is not None and not debug:
                # the stop signal's KeyboardInterrupt raised inside C code (TensorFlow tracing a graph) can come out
                # as another exception (SystemError "bad argument to internal function"): still the stop
                return _end(outputs, None, EXIT_USER_ERROR)
            outputs.clean_up()  # a defect: its traceback follows, but nothing half-made stays behind
            raise
        signum = fileio.stop_signal()
        if signum is not None:  # a command that finalised its outputs when stopped (run, predict)
            reason, stop_status = fileio.STOP_SIGNALS[signum]
            print(reason + _kept(outputs), file=sys.stderr, flush=True)
            return stop_status
        return status


class _ReportStream:
    """Standard output while a command runs: once the reader of its pipe has gone (`synth ... | head -1`), what is
    still written is dropped instead of raising BrokenPipeError, so the command finishes its files (they are the
    product; the report is what the reader chose to cut short) and ends with its own status."""

    def __init__(self, stream):
        self._stream = stream
        self.reader_gone = False

    def write(self, text: str) -> int:
        if not self.reader_gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._drop_the_rest()
        return len(text)

    def flush(self) -> None:
        if not self.reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._drop_the_rest()

    def _drop_the_rest(self) -> None:
        self.reader_gone = True
        with contextlib.suppress(AttributeError, OSError, ValueError):  # the descriptor too: the interpreter's
            devnull = os.open(os.devnull, os.O_WRONLY)                 # last flush at exit then finds no pipe
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _stdout_past_a_closed_pipe():
    """`sys.stdout` as a `_ReportStream` for the block."""
    stream = sys.stdout
    sys.stdout = _ReportStream(stream)
    try:
        yield
    finally:
        sys.stdout = stream


def run_tool(tool_main: Callable[[], int | None]) -> int:
    """The exit path of a maintainer script in tools/ (`sys.exit(run_tool(main))`): the package's user errors as
    one `error:` line and status 2, not a traceback, and what it created and did not complete removed."""
    set_tensorflow_environment()
    return run_guarded(tool_main, private_temp=False)


def console_main() -> int:
    """The `fcnpose-tf` command and `python -m fcnpose_tf`: `main`, after which a Ctrl-C or SIGTERM that arrives
    while the interpreter winds down (TensorFlow's finalizers, threads joined) ends the process as the signal's
    default action does, not with an `Exception ignored ... KeyboardInterrupt` traceback after the command's line.

    The stop signals are handled from the start: one that arrives while the commands' modules load (before `main`'s
    exit path, a quarter of a second here and longer on a Pi) ends the process with the signal's one line and
    status, not a traceback, and is not lost when the process inherited an ignored SIGINT (`cmd &` in a script)."""
    with fileio.stop_signals_handled():
        try:
            status = main()
        except KeyboardInterrupt:
            if fileio.stop_signal() is None:  # not a signal before `main`'s exit path began (--debug re-raises its own)
                raise
            reason, status = fileio.STOP_SIGNALS[fileio.stop_signal()]  # nothing was created yet
            print(reason, file=sys.stderr, flush=True)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_DFL)
    return status


if __name__ == "__main__":
    sys.exit(console_main())
