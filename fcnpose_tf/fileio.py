"""Safe output files: write to a temporary file beside the target, then rename into place.

Nothing a user wrote is overwritten without force=True, and a failed or
interrupted write leaves no partial file behind. A temporary file is named for
its target and for the process writing it (`.NAME.PID-HOST.XXXXXXXX.tmp.EXT`),
so one stranded by a kill that no handler sees (SIGKILL, a power cut) is removed
the next time a temporary for the same target is made, once that process is gone.
numpy-free, TensorFlow-free.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import glob
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import stat
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator, Sequence

from fcnpose_tf.errors import UserError


class WriteError(UserError):
    """Writing an output failed (a full disk, a lost mount): `PATH: reason`, e.g. `no space left on device`."""


class CommandOutputs:
    """What one command creates: the paths it planned up front, the folders it made, the files it completed.

    `command_outputs()` records them while a command runs, so its one exit path (`clean_up`) can remove
    what the command created and did not complete, and name the completed files it keeps.
    """

    def __init__(self) -> None:
        self.created_folders: list[Path] = []
        self.completed: list[Path] = []
        self.planned: list[Path] = []
        self.resumable: list[Path] = []

    def plan(self, path: str | os.PathLike, resumable: bool = False) -> None:
        """Register a file or folder the command will create (and the folders above it not there yet).

        Those that do not exist now are removed by `clean_up` unless completed; a `resumable` folder (a
        sweep's results) is kept as it is once it holds anything. UserError for a path the file system
        refuses to look at (a name too long, a file used as a folder): `PATH: reason`.
        """
        path = Path(path)
        missing = []
        for candidate in (path, *path.parents):
            try:
                os.lstat(candidate)
                break
            except FileNotFoundError:
                missing.append(candidate)
                continue
            except OSError as exc:  # a name too long, a file where a folder should be, no permission
                raise UserError(f"{candidate}: {os_error_reason(exc)}") from None
        for candidate in missing:  # the walk stops at the first missing folder: check the names below it too
            if len(os.fsencode(candidate.name)) > _name_max(candidate.parent):
                too_long = OSError(errno.ENAMETOOLONG, os.strerror(errno.ENAMETOOLONG))
                raise UserError(f"{candidate}: {os_error_reason(too_long)}")
        self.planned.extend(missing)
        if resumable:
            self.resumable.append(path)

    def kept(self) -> list[Path]:
        """The completed outputs, then the resumable folders that hold anything: what a failed command keeps."""
        resumable = [p for p in self.resumable if p.is_dir() and any(p.iterdir())]
        completed = [p for p in self.completed if os.path.lexists(p)]  # not one moved away or discarded since
        return [*completed, *(p for p in resumable if p not in completed)]

    def clean_up(self) -> None:
        """Remove every planned path and created folder that exists, deepest first, unless it is, holds or is
        part of a completed output (or a resumable folder that holds anything). Never raises."""
        kept = []
        for path in self.kept():
            with contextlib.suppress(OSError):
                kept.append(path.resolve())
        for path in sorted(set(self.created_folders + self.planned), key=lambda p: len(p.parts), reverse=True):
            try:
                if not os.path.lexists(path):
                    continue
                resolved = path.parent.resolve() / path.name
                if any(resolved == f or resolved in f.parents or f in resolved.parents for f in kept):
                    continue
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink()
            except OSError:
                continue

    def remove_created_folders(self) -> None:
        """`clean_up` (the name the full-disk path used first)."""
        self.clean_up()


def _name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of `folder`, or of its nearest existing parent, takes."""
    for candidate in (folder, *folder.parents):
        try:
            return os.pathconf(candidate if str(candidate) else ".", "PC_NAME_MAX")
        except (OSError, ValueError, AttributeError):
            continue
    return 255


_outputs: CommandOutputs | None = None


@contextlib.contextmanager
def command_outputs() -> Iterator[CommandOutputs]:
    """Record the paths planned, folders created and files completed while a command runs (see CommandOutputs)."""
    global _outputs
    outer, _outputs = _outputs, CommandOutputs()
    try:
        yield _outputs
    finally:
        _outputs = outer


def plan_output(path: str | os.PathLike, resumable: bool = False) -> None:
    """Register with the running command a file or folder it will create (`CommandOutputs.plan`)."""
    if _outputs is not None:
        _outputs.plan(path, resumable)


def record_completed(path: str | os.PathLike) -> None:
    """Name `path` as a completed output of the running command: kept, and named, however the command ends
    (a stream of records written under its final name, once it holds a complete one)."""
    _record_completed(Path(path))


def _record_completed(path: Path) -> None:
    if _outputs is not None and path not in _outputs.completed:
        _outputs.completed.append(path)


@contextlib.contextmanager
def parts_of(output: str | os.PathLike | None) -> Iterator[None]:
    """Run a block whose files are parts of one output (a dataset's frames, a checkpoint's files).

    Files completed inside are not kept as outputs of their own: if the block fails, none of them
    is named or keeps its folder from the failed command's cleanup; if it ends well, `output` (the
    whole) is recorded as completed (None: not yet, the caller records the whole when it is).
    Folders made inside are recorded as usual.
    """
    global _outputs
    outer = _outputs
    if outer is None:
        yield
        return
    _outputs = CommandOutputs()
    try:
        yield
    finally:
        inner, _outputs = _outputs, outer
        outer.created_folders.extend(inner.created_folders)
    if output is not None:
        _record_completed(Path(output))


def remove_tree(folder: str | os.PathLike) -> None:
    """Delete a folder this command wrote (a finished run's checkpoint) and forget it and its files as outputs."""
    folder = Path(folder)
    shutil.rmtree(folder, ignore_errors=True)
    if _outputs is not None:
        gone = folder.resolve()
        _outputs.completed = [p for p in _outputs.completed if gone != p.resolve() and gone not in p.resolve().parents]


def make_folder(folder: str | os.PathLike) -> Path:
    """mkdir -p, recording the folders it creates for `command_outputs`; UserError naming the folder and reason."""
    folder = Path(folder)
    missing = [p for p in (folder, *folder.parents) if not p.exists()]
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WriteError(f"{folder}: cannot create output folder ({os_error_reason(exc)})") from None
    if _outputs is not None:
        _outputs.created_folders.extend(missing)
    return folder


def os_error_reason(exc: OSError) -> str:
    """Why an OSError happened, as the end of a one-line error: e.g. `no space left on device`."""
    if exc.strerror:
        text = exc.strerror
    elif exc.errno:
        text = os.strerror(exc.errno)
    else:  # a library's own text (HDF5's runs over several lines and names the errno inside)
        found = re.search(r"\berrno = (\d+)", str(exc))
        text = os.strerror(int(found.group(1))) if found else (str(exc).strip().splitlines() or [""])[0]
    text = text or type(exc).__name__
    return text[:1].lower() + text[1:]


def native_name(path: str | os.PathLike) -> str:
    """A name for `path` that native code taking UTF-8 names can open: OpenCV's VideoCapture and VideoWriter,
    LiteRT's and TensorFlow's model loaders.

    They pass names as UTF-8, and crash the process (OpenCV) or raise TypeError (pybind11) on one that is not
    (`clip\\xe9.mp4`): such a path is reached through a symbolic link of a plain name, its suffix kept, in a new
    temporary folder (the command's own, removed when it ends; outside the CLI, removed at exit).
    """
    text = os.fspath(path)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    folder = tempfile.mkdtemp(prefix="fcnpose-tf-name.")
    atexit.register(shutil.rmtree, folder, True)
    suffix = os.path.splitext(text)[1]
    try:
        suffix.encode("utf-8")
    except UnicodeEncodeError:
        suffix = ""
    link = os.path.join(folder, "file" + suffix)  # the suffix picks the format (a container, .keras or .h5)
    os.symlink(os.path.abspath(text), link)
    return link


MAX_JSON_DEPTH = 64
"""JSON this package reads is nested a few levels (a VIA project: 6); deeper is refused, before code that walks it
recursively (a deep copy, the indented writer) meets Python's recursion limit."""


class JsonTooDeep(ValueError):
    """A JSON document nested more than MAX_JSON_DEPTH levels."""


def parse_json(text: str) -> Any:
    """`json.loads(text)`, or JsonTooDeep for a document nested more than MAX_JSON_DEPTH levels (checked without
    recursion); json.JSONDecodeError as json.loads raises it."""
    too_deep = JsonTooDeep(f"JSON nested more than {MAX_JSON_DEPTH} levels deep")
    try:
        value = json.loads(text)
    except RecursionError:
        raise too_deep from None
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
        if children and depth >= MAX_JSON_DEPTH:
            raise too_deep
        stack.extend((child, depth + 1) for child in children)
    return value


def entry_problem(exc: BaseException) -> str:
    """What was wrong in a file of ours whose reader met `exc`, in words rather than Python's: a KeyError is
    `no 'num_frames' entry`, a TypeError or AttributeError `an entry holds the wrong kind of value`, a ValueError
    its message's first line."""
    if isinstance(exc, KeyError) and exc.args:
        return f"no {str(exc.args[0])!r} entry"
    python_words = ("invalid literal", "not enough values", "too many values", "could not convert")
    if isinstance(exc, (TypeError, AttributeError, IndexError)) or str(exc).startswith(python_words):
        return "an entry holds the wrong kind of value"
    if isinstance(exc, RecursionError):
        return f"JSON nested more than {MAX_JSON_DEPTH} levels deep"
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


_FILE_KINDS = ((stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
               (stat.S_ISBLK, "a block device"), (stat.S_ISDIR, "a folder"))


def special_file_kind(path: str | os.PathLike) -> str | None:
    """What `path` is when it exists and is not a regular file (`a named pipe`, `a socket`, `a character device`,
    `a block device`, `a folder`), else None. Opening a named pipe waits for a writer, in native code that no
    signal interrupts: inputs are checked with this before a library opens them."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return next((kind for test, kind in _FILE_KINDS if test(mode)), None)


def read_regular_file(path: str | os.PathLike) -> bytes:
    """The bytes of a regular file. OSError for anything else, found without blocking: a named pipe is opened
    non-blocking and refused (EINVAL, `not a regular file`), so a signal still ends the command."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "not a regular file", os.fspath(path))
        with os.fdopen(fd, "rb", closefd=False) as file:
            return file.read()
    finally:
        os.close(fd)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold back SIGINT and SIGTERM during a block; a signal that arrives is re-raised when it ends.

    A step that must not be cut in two by Ctrl-C or a `kill` (a record written and counted) runs
    inside. Python runs signal handlers in the main thread between bytecodes, so the handlers are
    swapped for recording ones there (a thread's signal mask would not do: LiteRT's threads would
    still take the signal); in other threads the block simply runs. A signal taken by the old handler
    while the swap itself runs (before the block) leaves every handler as it was.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = [(sig, signal.getsignal(sig)) for sig in held]  # read first: nothing is changed yet
    try:
        for sig in held:
            signal.signal(sig, lambda signum, frame: arrived.append(signum))
        yield
    finally:
        _handlers_reinstalled(previous)
        for sig in dict.fromkeys(arrived):
            signal.raise_signal(sig)


def _handlers_reinstalled(previous: list[tuple[int, object]]) -> None:
    """Put each (signal, handler) back; a signal taken while doing so does not stop the rest."""
    if previous:
        (sig, handler), rest = previous[0], previous[1:]
        try:
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)  # None: set outside Python
        finally:
            _handlers_reinstalled(rest)


STOP_SIGNALS = {signal.SIGINT: ("interrupted (Ctrl-C)", 130), signal.SIGTERM: ("terminated (SIGTERM)", 143)}
"""What each stop signal ends a command with: the line it prints and its exit status (128 + the signal's number)."""

_stopped_by: list[int] = []


def _on_stop_signal(signum, frame):
    """SIGINT and SIGTERM: remembered for the exit status, then KeyboardInterrupt ("terminated (SIGTERM)")."""
    _stopped_by.append(signum)
    raise KeyboardInterrupt("" if signum == signal.SIGINT else STOP_SIGNALS[signum][0])


def note_stop_signal(signum: int) -> None:
    """Remember a stop signal another handler took (a sweep's executor), for the exit line and status."""
    _stopped_by.append(signum)


def stop_signal() -> int | None:
    """The first SIGINT or SIGTERM received since `stop_signals_handled` began (None: none)."""
    return _stopped_by[0] if _stopped_by else None


@contextlib.contextmanager
def _stop_handlers(handler) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():  # only the main thread may set handlers
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    try:
        for sig in STOP_SIGNALS:
            signal.signal(sig, handler)
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)  # None: set outside Python


@contextlib.contextmanager
def stop_signals_as_interrupt() -> Iterator[None]:
    """Within the block Ctrl-C (SIGINT) and a `kill` (SIGTERM) end the work with KeyboardInterrupt.

    The CLI runs every command so (`stop_signals_handled`); a block that finalises its outputs when
    stopped (`run`'s records and video, `predict`'s VIA file) also installs both handlers itself rather
    than relying on what it inherited: a command started in the background from a script (`cmd &` in
    `sh -c`, or a test suite started so) inherits an ignored SIGINT, and a camera run would then ignore
    Ctrl-C and `kill -INT` for ever. SIGTERM raises KeyboardInterrupt("terminated (SIGTERM)"); the
    signal is remembered (`stop_signal`) for the exit status; the previous handlers come back when the
    block ends.
    """
    with _stop_handlers(_on_stop_signal):
        yield


@contextlib.contextmanager
def stop_signals_handled() -> Iterator[None]:
    """A command's whole run: SIGINT and SIGTERM raise KeyboardInterrupt and are remembered (`stop_signal`)."""
    del _stopped_by[:]
    try:
        with _stop_handlers(_on_stop_signal):
            yield
    finally:
        del _stopped_by[:]


@contextlib.contextmanager
def stop_signals_ignored() -> Iterator[None]:
    """A command's exit path: a further Ctrl-C or `kill` is remembered but does not cut the clean-up short."""
    def remember(signum, frame):
        _stopped_by.append(signum)

    with _stop_handlers(remember):
        yield


_TEMPORARY_PREFIX = "fcnpose-tf."


@contextlib.contextmanager
def private_temporary_folder() -> Iterator[Path | None]:
    """Run a block with Python's (and child processes') temporary folder set to one this process owns,
    removed when the block ends, however it ends: what libraries leave in $TMPDIR (the TFLite
    converter's SavedModel, autograph's modules) goes with it. Folders a killed (SIGKILL) earlier
    command left are removed first, once their process is gone. Yields None (and changes nothing)
    where the temporary folder takes no new folder.
    """
    base = Path(tempfile.gettempdir())
    host = _host_tag()
    pattern = re.compile(rf"{re.escape(_TEMPORARY_PREFIX)}(\d+)-([0-9a-f]{{6}})\.[a-z0-9_]+")
    with contextlib.suppress(OSError):
        for stale in base.glob(glob.escape(_TEMPORARY_PREFIX) + "*"):
            match = pattern.fullmatch(stale.name)
            if match and match.group(2) == host and not _process_alive(int(match.group(1))):
                shutil.rmtree(stale, ignore_errors=True)
    try:
        folder = Path(tempfile.mkdtemp(prefix=f"{_TEMPORARY_PREFIX}{os.getpid()}-{host}.", dir=base))
    except OSError:
        yield None
        return
    saved_tempdir, saved_env = tempfile.tempdir, os.environ.get("TMPDIR")
    tempfile.tempdir = os.environ["TMPDIR"] = str(folder)
    try:
        yield folder
    finally:
        tempfile.tempdir = saved_tempdir
        if saved_env is None:
            os.environ.pop("TMPDIR", None)
        else:
            os.environ["TMPDIR"] = saved_env
        shutil.rmtree(folder, ignore_errors=True)


def check_writable(path: str | os.PathLike, force: bool = False) -> Path:
    """Raise UserError if `path` exists (and not force) or its folder cannot be created or written."""
    path = Path(path)
    if path.is_dir():  # before "exists": --force would not help
        raise UserError(f"{path}: is a folder, expected a file path")
    if path.exists() and not force:
        raise UserError(f"{path}: already exists; pass --force to replace it")
    make_folder(path.parent)
    try:  # os.access says yes to root everywhere; only a real file proves the folder takes files
        with tempfile.TemporaryFile(dir=path.parent):
            pass
    except OSError as exc:
        raise UserError(f"{path.parent}: output folder is not writable ({exc.strerror})") from None
    return path


def check_output_folder(folder: str | os.PathLike, force: bool = False) -> Path:
    """Raise UserError, before any work, for an output folder that is a file, or holds files (and not force)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not force:
        raise UserError(f"{folder}: already holds files; pass --force to write the pictures among them")
    return folder


@contextlib.contextmanager
def removed_if_left_empty(folder: str | os.PathLike) -> Iterator[Path]:
    """Run a block that may create `folder`; if the block fails and leaves it created but empty, remove it."""
    folder = Path(folder)
    existed = folder.exists()
    try:
        yield folder
    except BaseException:
        if not existed and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise


def _host_tag() -> str:
    """Six hex digits naming this host in temporary names (a shared folder may be written from several)."""
    return hashlib.sha256(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]


def _temporary_pattern(path: Path) -> re.Pattern[str]:
    """The names `temporary_path(path)` makes, and only those: `.STEM.PID-HOST.RANDOM.tmp.SUFFIX`."""
    return re.compile(rf"\.{re.escape(path.stem)}\.(\d+)-([0-9a-f]{{6}})\.[a-z0-9_]+\.tmp{re.escape(path.suffix)}")


def _process_alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (when in doubt: yes, so its file is kept)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: another user's live process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Delete the temporaries of `path` whose writer (a process on this host) is gone; returns them.

    Only names `temporary_path(path)` makes are considered, so another target's temporaries, a
    live writer's, and those written from another host are left alone.
    """
    path = Path(path)
    pattern, host = _temporary_pattern(path), _host_tag()
    removed = []
    for candidate in path.parent.glob(glob.escape(f".{path.stem}.") + "*" + glob.escape(f".tmp{path.suffix}")):
        match = pattern.fullmatch(candidate.name)
        if match and match.group(2) == host and not _process_alive(int(match.group(1))):
            try:
                candidate.unlink()
            except OSError:
                continue
            removed.append(candidate)
    return removed


def _new_temporary(path: Path) -> Path:
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.{os.getpid()}-{_host_tag()}.", suffix=f".tmp{path.suffix}",
                                   dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise WriteError(f"{path}: {os_error_reason(exc)}") from None
    return Path(tmp)


def temporary_path(path: str | os.PathLike) -> Path:
    """Create an empty temporary file beside `path` for this process, first removing stale ones of `path`.

    The name keeps the target's suffix, so libraries that pick a format from the extension
    (Keras .keras/.h5, OpenCV .png/.mp4) work unchanged. The caller renames or deletes it.
    """
    path = Path(path)
    remove_stale_temporaries(path)
    return _new_temporary(path)


def set_default_permissions(path: str | os.PathLike) -> None:
    """mkstemp makes 0600 files; give an output the permissions of a file the user creates (umask)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def full_disk_error(path: str | os.PathLike, quick: bool = False) -> WriteError | None:
    """The WriteError a write beside `path` meets now (`PATH: no space left on device`), or None.

    Tells a full disk (or any other refusal of the folder to take data) from other failures, such
    as a codec OpenCV lacks: a probe file of one block is written and removed. `quick=True` skips the
    probe while the file system reports free blocks for this user, so it can be called per frame.
    """
    path = Path(path)
    if quick:
        try:
            if os.statvfs(path.parent).f_bavail > 0:
                return None
        except (OSError, AttributeError):
            pass
    try:
        probe = _new_temporary(path)
    except WriteError as exc:
        return exc
    try:
        with open(probe, "wb", buffering=0) as fh:
            view = memoryview(bytes(4096))
            while view:
                written = fh.write(view)
                if not written:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                view = view[written:]
    except OSError as exc:
        return WriteError(f"{path}: {os_error_reason(exc)}")
    finally:
        probe.unlink(missing_ok=True)
    return None


@contextlib.contextmanager
def atomic_paths(paths: Sequence[str | os.PathLike], force: bool = False) -> Iterator[list[Path]]:
    """Yield temporary paths for files written as one: renamed into place (in the given order) only once
    the block has written every one of them; on any error all are deleted and no target is touched.

    Each temporary is `temporary_path(target)`'s (target's suffix kept; stale ones of a killed earlier
    writer removed first). The renames run with Ctrl-C and SIGTERM held back (`signals_deferred`), so
    an interrupt does not split the set. An OSError becomes a WriteError naming the target it hit (the
    targets' common folder when that is unknown) and the reason, e.g. `no space left on device`.
    """
    targets = [check_writable(path, force) for path in paths]
    temporaries: list[Path] = []
    current: Path | None = None
    try:
        for target in targets:
            temporaries.append(temporary_path(target))
        yield list(temporaries)
        with signals_deferred():
            for tmp, target in zip(temporaries, targets):
                current = target
                if tmp.exists():
                    set_default_permissions(tmp)
                os.replace(tmp, target)
                _record_completed(target)
    except OSError as exc:  # any failure while writing: the path and the reason, one line
        if current is None:
            named = {os.fspath(t): target for t, target in zip(temporaries, targets)}
            current = named.get(os.fspath(exc.filename)) if isinstance(exc.filename, (str, os.PathLike)) else None
        if current is None:
            current = targets[0] if len(targets) == 1 else Path(os.path.commonpath(targets))
        raise WriteError(f"{current}: {os_error_reason(exc)}") from None
    finally:
        for tmp in temporaries:
            if tmp.exists():
                tmp.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success rename it to `path`, on error delete it
    (`atomic_paths` for one file)."""
    with atomic_paths([path], force) as (tmp_path,):
        yield tmp_path


def write_bytes(path: str | os.PathLike, data: bytes, force: bool = False) -> Path:
    """Atomically write bytes to path."""
    with atomic_path(path, force) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str, force: bool = False) -> Path:
    """Atomically write UTF-8 text to path."""
    return write_bytes(path, text.encode("utf-8"), force)


def json_text(data: Any) -> str:
    """The text `write_json` writes: indented JSON, keys in the given order, no NaN, numpy values converted."""
    return json.dumps(data, indent=2, allow_nan=False, default=json_default) + "\n"


def write_json(path: str | os.PathLike, data: Any, force: bool = False) -> Path:
    """Atomically write JSON (indented, keys in the given order) to path."""
    return write_text(path, json_text(data), force)


def json_default(value: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars and arrays (without importing numpy) and paths."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")
