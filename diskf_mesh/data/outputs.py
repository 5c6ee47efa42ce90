"""Output files: checked before any work starts, written atomically.

Every command that writes a file checks its path first (``check_output``,
``check_output_dir``), so a path that cannot be written ends the command
with one ``error:`` line and exit status 2 before a long run, not after it:

- the folder must exist (or be creatable, for folders the command makes)
  and be writable (a probe file is created and removed);
- the target must be a regular file or absent. A device (``/dev/null``,
  ``/dev/full``), a pipe, a symbolic link or a folder is refused: the write
  replaces the target's node by rename, which would turn ``/dev/null`` into
  a plain file, or a link into a copy;
- ``-`` is standard output, where the command supports it.

``atomic_open`` writes a temporary file in the target's folder and renames
it over the target, so a reader never sees half a file. The temporary file
is removed on every exit path: an exception, Ctrl-C, and SIGTERM (turned into
a clean ``SystemExit`` for the duration of the write when nobody else
handles it). Only SIGKILL can leave one behind: it exists only while the
bytes are written, never during the run. Files are created with mode
0666 & ~umask, like any file the user's shell would create.
"""
from __future__ import annotations

import json
import math
import os
import secrets
import signal
import stat
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from diskf_mesh.core.errors import InputError

STDOUT = "-"


def _why(e: OSError) -> str:
    return e.strerror or str(e)


def _refuse_special(path: Path, text: str, option: str) -> None:
    """The target must be absent or a regular file (not followed if a link)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as e:  # e.g. a parent that is a plain file (ENOTDIR)
        raise InputError(option, f"cannot write {text}: {_why(e)}") from None
    if stat.S_ISLNK(st.st_mode):
        raise InputError(option, f"{text} is a symbolic link; give the path it points to")
    if stat.S_ISDIR(st.st_mode):
        raise InputError(option, f"{text} is a folder; give a file name")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(option, f"{text} is not a regular file (a device, pipe or socket); refusing to replace it")


def _temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")


def _create(path: Path) -> int:
    """A new file, mode 0666 & ~umask; never follows or reuses a path."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)


def _probe(folder: Path, text: str, option: str) -> None:
    """Create and remove a file in ``folder``: the only sure test of writing
    (permissions, read-only mounts, quotas of inodes)."""
    probe = _temp_name(folder / "probe")
    try:
        os.close(_create(probe))
    except OSError as e:
        raise InputError(option, f"cannot write {text}: {_why(e)}") from None
    os.unlink(probe)


def check_output(path, option: str, *, stdout: bool = True, make_parent: bool = False) -> None:
    """Raise ``InputError(option, ...)`` unless ``path`` can be written.

    ``None`` (option not given) passes; ``-`` passes only when ``stdout``;
    ``make_parent`` creates a missing folder (for a default path)."""
    if path is None:
        return
    text = str(path)
    if text == "":
        raise InputError(option, "needs a file name")
    if text == STDOUT:
        if not stdout:
            raise InputError(option, "'-' (standard output) is not supported here; give a file name")
        return
    p = Path(text)
    _refuse_special(p, text, option)
    folder = p.parent
    if make_parent:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise InputError(option, f"cannot create folder {folder}: {_why(e)}") from None
    if not folder.is_dir():
        raise InputError(option, f"cannot write {text}: folder {folder} does not exist")
    _probe(folder, text, option)


def check_output_dir(path, option: str) -> Path:
    """The output folder ``path``, created if absent and checked writable."""
    text = str(path)
    if text == "":
        raise InputError(option, "needs a folder name")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise InputError(option, f"{text} exists and is not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(option, f"cannot create folder {text}: {_why(e)}") from None
    _probe(p, text, option)
    return p


@contextmanager
def _sigterm_exits():
    """SIGTERM raises ``SystemExit(143)`` inside the block (so ``finally``
    clauses run), when this is the main thread and SIGTERM has no handler."""
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def exit_cleanly(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, exit_cleanly)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


@contextmanager
def atomic_open(path, mode: str = "w", option: str = "out"):
    """A file object whose content replaces ``path`` when the block ends
    without an exception; on any exception (or signal) nothing changes and
    the temporary file is gone."""
    path = Path(path)
    _refuse_special(path, str(path), option)
    with _sigterm_exits():
        tmp = _temp_name(path)
        fd = _create(tmp)
        try:
            with os.fdopen(fd, mode) as f:
                yield f
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def json_safe(obj):
    """``obj`` with non-finite floats as None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def save_json(path, doc, option: str = "out") -> None:
    """Write ``doc`` as JSON to ``path`` atomically, or to standard output
    for ``-``; a path that cannot be written is bad input (``option``)."""
    text = json.dumps(json_safe(doc), allow_nan=False)
    if str(path) == STDOUT:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
        return
    try:
        with atomic_open(path, "w", option) as f:
            f.write(text)
    except OSError as e:
        raise InputError(option, f"cannot write {path}: {_why(e)}") from None


def human_stream(*paths):
    """Where a command prints its text: standard error when one of its
    outputs is standard output (which then carries only that output)."""
    return sys.stderr if any(str(p) == STDOUT for p in paths if p is not None) else sys.stdout
