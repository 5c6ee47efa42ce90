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

``atomic_open`` writes a file with no name in the target's folder (Linux:
``O_TMPFILE``), gives it a name once every byte is written (or, where the
system cannot name it, copies it in the kernel to a named temporary file)
and renames it over the target, so a reader never sees half a file and a
process killed while it writes (SIGKILL included) leaves no temporary file:
an unnamed file is gone with the process. Where the file system has no
unnamed files, a named temporary file is written instead and removed on
every exit path but SIGKILL: an exception, Ctrl-C, and SIGTERM (turned into
a clean ``SystemExit`` for the duration of the write when nobody else
handles it). The probe of ``check_output`` is an unnamed file too. Files are created
with mode 0666 & ~umask, like any file the user's shell would create.
"""
from __future__ import annotations

import errno
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


def _unnamed(folder: Path) -> int | None:
    """A new file with no name in ``folder`` (``O_TMPFILE``), mode 0666 &
    ~umask; None where the platform or the file system has none. A
    permission error is raised."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None or not os.path.isdir("/proc/self/fd"):  # naming it later goes through /proc
        return None
    try:
        return os.open(folder, flag | os.O_RDWR | getattr(os, "O_CLOEXEC", 0), 0o666)
    except OSError as e:
        if e.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            return None  # no unnamed files there (ENOENT: some kernels, for a folder that exists)
        raise


def _name(fd: int, path: Path) -> None:
    """Give the unnamed file ``fd`` the name ``path`` (which must not exist),
    or where the kernel refuses to (EXDEV on some systems), a copy of it made in
    the kernel: the named file exists only for the copy."""
    try:
        os.link(f"/proc/self/fd/{fd}", path, follow_symlinks=True)
        return
    except OSError as e:
        if e.errno not in (errno.EXDEV, errno.ENOENT, errno.EPERM, errno.EINVAL, errno.EOPNOTSUPP):
            raise
    out = _create(path)
    try:
        size, done = os.fstat(fd).st_size, 0
        while done < size:
            try:
                n = os.copy_file_range(fd, out, size - done, done, done)
            except (AttributeError, OSError):
                n = 0
            if not n:  # no copy in the kernel here: read and write
                n = os.pwrite(out, os.pread(fd, min(size - done, 1 << 20), done), done)
            done += n
    finally:
        os.close(out)


def _probe(folder: Path, text: str, option: str) -> None:
    """Create a file in ``folder`` (an unnamed one, else one removed at
    once): the only sure test of writing (permissions, read-only mounts,
    quotas of inodes)."""
    try:
        fd = _unnamed(folder)
        if fd is not None:
            os.close(fd)
            return
        probe = _temp_name(folder / "probe")
        os.close(_create(probe))
    except OSError as e:
        raise InputError(option, f"cannot write {text}: {_why(e)}") from None
    os.unlink(probe)


def check_output(path, option: str, *, stdout: bool = True, make_parent: bool = False) -> None:
    """Raise ``InputError(option, ...)`` unless ``path`` can be written.

    ``None`` (option not given) passes; ``-`` passes only when ``stdout``;
    with ``make_parent`` (a default path) a missing folder is one the
    caller creates once the work starts (``make_folder``): the nearest
    folder that exists must take it."""
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
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
    if not folder.is_dir():
        raise InputError(option, f"cannot write {text}: folder {folder} does not exist")
    _probe(folder, text, option)


def make_folder(path, option: str) -> None:
    """The folder of the output ``path`` (``check_output`` with
    ``make_parent``), created when the work starts."""
    folder = Path(path).parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(option, f"cannot create folder {folder}: {_why(e)}") from None


def check_output_dir(path, option: str, create: bool = True) -> Path:
    """The output folder ``path``, created if absent (not with ``create``
    False: then a folder that can be created later) and checked writable."""
    text = str(path)
    if text == "":
        raise InputError(option, "needs a folder name")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise InputError(option, f"{text} exists and is not a folder")
    if not create and not p.exists():
        check_output(p / "probe", option, stdout=False, make_parent=True)
        return p
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
        fd = _unnamed(path.parent)
        unnamed = fd is not None
        if not unnamed:  # no unnamed files here: a named one from the start
            fd = _create(tmp)
        try:
            with os.fdopen(fd, mode) as f:
                yield f
                if unnamed:  # every byte is in: a name now, the target's next
                    f.flush()
                    _name(fd, tmp)
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
