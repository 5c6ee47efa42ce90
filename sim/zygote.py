"""A fork server for the processes of a run: import once, fork each process.

Starting a mesh process from a fresh interpreter is mostly importing
(numpy, zenoh, the estimators): about 0.6 s of CPU each,
so 50 agents on two cores spent most of their start-up doing nothing else.
``Zygote`` starts one interpreter (``python -m sim.zygote``) that imports all
of it once (``PRELOAD``), with one BLAS thread (``BLAS_ENV``), and then, on
the launcher's request, forks one child per world, agent, router or shard
of the run (``FORKED``: the modules it can stand in for; any other command
line is started with ``subprocess`` as before). It forks before any zenoh
session or other thread exists in it: importing zenoh starts no runtime, and
the zygote checks it is a single thread (``/proc/self/task``) or refuses,
and the launcher falls back to fresh interpreters.

Each child is its own OS process, as if started with ``python -m MODULE
ARGS``: its own pid and process group (``setsid``), the stdin, stdout and
stderr the launcher gives it (passed over the zygote's socket), its own
zenoh session, its own exit status (the zygote reaps it and tells the
launcher: ``ForkedProcess`` has ``subprocess.Popen``'s ``pid``, ``poll``,
``wait``, ``send_signal``, ``returncode`` and ``stdout``), SIGTERM when the
zygote dies (as a ``Popen`` child gets it when the launcher dies: the
zygote itself gets SIGTERM when the launcher dies). ``kill -9`` of one
child acts on it alone, and a killed agent rejoins as one started afresh
does. Its ``/proc/PID/cmdline`` (``ps``, ``pgrep -f``) is the command line
it stands for: the zygote's own command line reserves the room
(``TITLE_SPACE`` bytes; a longer one is cut).

``DISKF_MESH_SPAWN=exec`` in the environment: every child a fresh
interpreter, as before (for comparison and debugging).
"""
from __future__ import annotations

import ctypes
import gc
import json
import os
import runpy
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings

from diskf_mesh.cli import BLAS_ENV
from diskf_mesh.mesh.security import credentials

SPAWN_ENV = "DISKF_MESH_SPAWN"  # "exec": no zygote
FORKED = ("sim.world", "agents.agent", "sim.router", "sim.host")
# not cryptography: only the launcher makes credentials; a child hands its PEMs to zenoh (~70 ms
# less before the first fork)
PRELOAD = ("sim.world", "agents.agent", "sim.router", "sim.host", "zenoh", "tqdm", "diskf_mesh.studies.experiment",
           "diskf_mesh.cli.main")
TITLE_SPACE = 4096  # bytes of command line a child can show
MAX_MESSAGE = 1 << 20
START_TIMEOUT_S = 120.0  # for the zygote's imports (a loaded machine is slow)
PR_SET_PDEATHSIG = 1


def enabled() -> bool:
    return os.environ.get(SPAWN_ENV, "fork") != "exec" and sys.platform.startswith("linux")


def forkable(argv) -> bool:
    """Whether ``argv`` is ``python -m MODULE ...`` of this interpreter for a
    module the zygote stands in for."""
    return len(argv) >= 3 and argv[0] == sys.executable and argv[1] == "-m" and argv[2] in FORKED


def _prctl_deathsig(sig: int) -> None:
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(sig))
    except (OSError, AttributeError):
        pass


# --------------------------------------------------------------------------
# the launcher's side
# --------------------------------------------------------------------------
class ZygoteError(RuntimeError):
    pass


class ForkedProcess:
    """A child the zygote forked, with the part of ``subprocess.Popen`` the
    launcher and the tests use."""

    def __init__(self, zygote: "Zygote", pid: int, args, stdout=None):
        self._zygote, self.pid, self.args, self.stdout = zygote, pid, list(args), stdout
        self.returncode = None

    def poll(self):
        if self.returncode is None:
            self._zygote.pump(0.0)
        return self.returncode

    def wait(self, timeout=None):
        end = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self._zygote.pump(0.1 if left is None else min(left, 0.1))
        return self.returncode

    def send_signal(self, sig) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class Zygote:
    """The zygote process of one launcher. ``Zygote()`` starts it and returns
    at once (its imports go on beside the launcher's work); ``spawn`` waits
    for it the first time. ``usable`` is False once it refused or failed:
    then the caller starts its children with ``subprocess``."""

    def __init__(self):
        self._lock = threading.RLock()
        self._children = {}  # pid -> ForkedProcess
        self._exits = {}     # pid -> status that came before its ForkedProcess existed
        self.usable, self.why = True, ""
        self._ready = False
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = ours
        env = {**os.environ, **BLAS_ENV}
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "sim.zygote", str(theirs.fileno()), " " * TITLE_SPACE],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, pass_fds=(theirs.fileno(),), env=env,
                start_new_session=True, preexec_fn=lambda: _prctl_deathsig(signal.SIGTERM))
        except OSError as e:
            self.usable, self.why = False, f"cannot start the zygote: {e}"
            ours.close()
        theirs.close()

    # -- messages -----------------------------------------------------------
    def _recv(self, timeout: float):
        """One message (a dict), None on timeout; ``ZygoteError`` when the
        zygote is gone."""
        import select

        r, _, _ = select.select([self._sock], [], [], max(timeout, 0.0))
        if not r:
            return None
        data = self._sock.recv(MAX_MESSAGE)
        if not data:
            raise ZygoteError("the zygote ended")
        return json.loads(data)

    def _take(self, msg: dict) -> dict | None:
        """An exit report is applied; anything else is returned."""
        if "exit" in msg:
            pid, rc = msg["exit"], msg["rc"]
            child = self._children.pop(pid, None)
            if child is not None:
                child.returncode = rc
            else:
                self._exits[pid] = rc
            return None
        return msg

    def pump(self, timeout: float) -> None:
        """Take the exit reports that are in (waiting at most ``timeout``)."""
        with self._lock:
            if self._sock is None:
                return
            try:
                msg = self._recv(timeout)
                while msg is not None:
                    self._take(msg)
                    msg = self._recv(0.0)
            except (ZygoteError, OSError):
                self._lost()

    def _lost(self) -> None:
        """The zygote is gone: its children got SIGTERM; the ones that are
        gone too end with that status (their real one is unknown)."""
        self.usable, self.why = False, self.why or "the zygote ended"
        for pid, child in list(self._children.items()):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                child.returncode = -signal.SIGTERM
                del self._children[pid]

    def _reply(self, timeout: float) -> dict:
        end = time.monotonic() + timeout
        while True:
            msg = self._recv(end - time.monotonic())
            if msg is None:
                raise ZygoteError(f"no answer from the zygote in {timeout:g} s")
            msg = self._take(msg)
            if msg is not None:
                return msg

    def _wait_ready(self) -> bool:
        if self._ready or not self.usable:
            return self.usable
        try:
            hello = self._reply(START_TIMEOUT_S)
        except (ZygoteError, OSError) as e:
            hello = {"ready": False, "why": str(e)}
        if not hello.get("ready"):
            self.usable, self.why = False, hello.get("why", "refused")
            self.close()
            return False
        self._ready = True
        return True

    def spawn(self, argv, stdout, stderr) -> ForkedProcess | None:
        """Fork the child ``argv`` (``forkable``) with stdin /dev/null,
        ``stdout`` (``subprocess.DEVNULL``, ``subprocess.PIPE`` or a file) and
        ``stderr`` (a file); None if the zygote cannot (the caller execs)."""
        return self.spawn_all([(argv, stdout, stderr)])[0]

    def spawn_all(self, jobs) -> list:
        """``spawn`` of every (argv, stdout, stderr[, stdin]) of ``jobs`` (stdin:
        a file descriptor, else /dev/null), the requests sent at once (the
        zygote forks them back to back); a list of ``ForkedProcess`` (None
        where it could not: exec that one)."""
        with self._lock:
            if not jobs or not self._wait_ready():
                return [None] * len(jobs)
            sent = []  # (argv, read end of its stdout pipe or None)
            with open(os.devnull, "rb") as null_in, open(os.devnull, "wb") as null_out:
                for argv, stdout, stderr, *stdin in jobs:
                    pipe_r = None
                    if stdout == subprocess.PIPE:
                        pipe_r, out_fd = os.pipe()
                    else:
                        out_fd = os.dup(null_out.fileno() if stdout in (None, subprocess.DEVNULL)
                                        else stdout.fileno())
                    try:
                        request = json.dumps({"argv": list(argv), "cwd": os.getcwd()}).encode()
                        socket.send_fds(self._sock, [request], [stdin[0] if stdin and stdin[0] is not None
                                                                else null_in.fileno(), out_fd, stderr.fileno()])
                    except OSError as e:
                        self.usable, self.why = False, str(e)
                        if pipe_r is not None:
                            os.close(pipe_r)
                        break
                    finally:
                        os.close(out_fd)
                    sent.append((argv, pipe_r))
            out = []
            for argv, pipe_r in sent:
                try:
                    reply = self._reply(30.0)
                except (ZygoteError, OSError) as e:
                    self.usable, self.why = False, str(e)
                    reply = {"error": str(e)}
                if "pid" not in reply:
                    if pipe_r is not None:
                        os.close(pipe_r)
                    out.append(None)
                    continue
                proc = ForkedProcess(self, reply["pid"], argv,
                                     os.fdopen(pipe_r, "rb") if pipe_r is not None else None)
                self._children[proc.pid] = proc
                if proc.pid in self._exits:
                    proc.returncode = self._exits.pop(proc.pid)
                out.append(proc)
            return out + [None] * (len(jobs) - len(out))

    def close(self) -> None:
        """Let the zygote go: it fork no more, and ends once its children have
        (they are the launcher's to stop)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None
            self.usable = False
        if getattr(self, "_proc", None) is not None and not self._children:
            try:
                self._proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(5.0)


_early = []  # the zygote prestart() started, until a launcher takes it


def prestart(argv) -> None:
    """``diskf-mesh up`` (``argv`` its arguments, the command first): start
    the run's zygote before anything else is imported, so that its imports
    go on beside the launcher's own (two cores: half the wait). Not for
    ``--help`` or ``--hosts`` (whose children run elsewhere)."""
    if argv[:1] == ["up"] and enabled() and not _early and not {"-h", "--help", "--hosts"} & set(argv):
        _early.append(Zygote())


def take_prestarted() -> "Zygote | None":
    """The zygote ``prestart`` started (the caller closes it), or None."""
    return _early.pop() if _early else None


def close_prestarted() -> None:
    """Close a zygote ``prestart`` started that no launcher took (bad input)."""
    while _early:
        _early.pop().close()


# --------------------------------------------------------------------------
# the zygote's side
# --------------------------------------------------------------------------
def _threads() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 1


def _title_area():
    """(address, length) of this process's command line in memory (Linux:
    /proc/self/stat's arg_start and arg_end), or None."""
    try:
        fields = open("/proc/self/stat").read().rsplit(")", 1)[1].split()
        start, end = int(fields[45]), int(fields[46])
    except (OSError, ValueError, IndexError):
        return None
    return (start, end - start) if start and end > start else None


def set_title(argv) -> None:
    """Show ``argv`` as this process's command line (cut to the room there
    is; the rest of the room zeroed)."""
    area = _title_area()
    if area is None:
        return
    addr, room = area
    text = b"\0".join(os.fsencode(a) for a in argv)[:room - 1]
    ctypes.memmove(addr, text + b"\0" * (room - len(text)), room)


def _preload() -> str:
    """Import what the children run; '' or why the zygote must not fork."""
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    gc.collect()
    gc.freeze()  # the children do not copy the imported objects' pages when they collect
    n = _threads()
    return "" if n == 1 else f"{n} threads after the imports (a fork copies only one)"


def _fork(request: bytes, fds: list):
    """Fork the child of ``request``; in the parent, return its pid; in the
    child, return (argv, cwd, fds) to run."""
    req = json.loads(request)
    argv, cwd = req["argv"], req["cwd"]
    if not forkable([sys.executable, *argv[1:]]):
        raise ValueError(f"not a command the zygote runs: {argv[:3]}")
    pid = os.fork()
    if pid:
        return pid
    return argv, cwd, fds


def serve(fd: int):
    """The zygote's loop. Returns None when the launcher has gone and every
    child has ended; in a forked child, returns (argv, cwd, fds)."""
    sock = socket.socket(fileno=fd)
    set_title([sys.executable, "-m", "sim.zygote", f"(fork server of process {os.getppid()})"])
    # the files it passes on (a child's identity on its standard input) and every child it forks are closed to
    # the user's other processes from the start (a child is so before it has read its identity)
    credentials.keep_private()
    why = _preload()
    try:
        sock.send(json.dumps({"ready": not why, "why": why}).encode())
    except OSError:  # the launcher has gone already (e.g. bad input)
        why = why or "the launcher has gone"
    if why:
        sock.close()
        return None
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    children, open_ = set(), True
    sel = selectors.DefaultSelector()
    sel.register(sock, selectors.EVENT_READ)
    sel.register(wake_r, selectors.EVENT_READ)
    child = None
    try:
        while open_ or children:
            for key, _ in sel.select():
                if key.fileobj is sock and open_:
                    try:
                        msg, fds, _, _ = socket.recv_fds(sock, MAX_MESSAGE, 3)
                    except OSError:
                        msg, fds = b"", []
                    if not msg:
                        open_ = False
                        sel.unregister(sock)
                        continue
                    try:
                        out = _fork(msg, fds)
                    except (OSError, ValueError, KeyError) as e:
                        out = {"error": str(e)}
                    if isinstance(out, tuple):  # the child: leave the loop (the finally closes the zygote's files)
                        child = out
                        return child
                    for f in fds:
                        os.close(f)
                    if isinstance(out, int):
                        children.add(out)
                        out = {"pid": out}
                    try:
                        sock.send(json.dumps(out).encode())
                    except OSError:
                        open_ = False
                        sel.unregister(sock)
                elif key.fileobj == wake_r:
                    try:
                        os.read(wake_r, 4096)
                    except BlockingIOError:
                        pass
                while children:
                    try:
                        pid, status = os.waitpid(-1, os.WNOHANG)
                    except ChildProcessError:
                        children.clear()
                        break
                    if not pid:
                        break
                    children.discard(pid)
                    if open_:
                        try:
                            sock.send(json.dumps({"exit": pid, "rc": os.waitstatus_to_exitcode(status)}).encode())
                        except OSError:
                            open_ = False
                            sel.unregister(sock)
    finally:
        if child is not None:  # in the forked child: none of the zygote's files stay open
            signal.set_wakeup_fd(-1)
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        sel.close()
        os.close(wake_r)
        os.close(wake_w)
        sock.close()
    return None


def run_child(argv, cwd, fds, zygote: int) -> int:
    """In a forked child: become the process ``argv`` stands for and run it
    as ``python -m`` would (its module as ``__main__``, from the code the
    zygote loaded); returns its exit status."""
    os.setsid()
    _prctl_deathsig(signal.SIGTERM)
    if os.getppid() != zygote:  # the zygote died before the line above
        os._exit(1)
    for target, f in enumerate(fds):
        os.dup2(f, target)
        os.close(f)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    os.chdir(cwd)
    set_title(argv)
    module, args = argv[2], argv[3:]
    sys.argv = [module, *args]
    # the zygote imported the module (PRELOAD): runpy runs it afresh as __main__, as ``python -m``
    # does, and would warn of the imported copy on every child's stderr
    warnings.filterwarnings("ignore", message=f"'{module}' found in sys.modules", category=RuntimeWarning)
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            return e.code or 0
        print(e.code, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    zygote_pid = os.getpid()
    job = serve(int(sys.argv[1]))
    if job is not None:  # a forked child
        sys.exit(run_child(*job, zygote_pid))
