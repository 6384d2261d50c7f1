"""Read CAD files in a child process, so that OpenCASCADE cannot take this one down.

OpenCASCADE crashes (segmentation faults) or loops on some malformed STEP
and IGES files; inside the user's (possibly MPI) process that would be fatal.
:func:`read_cad` therefore sends the request to a reader server: a plain
Python process started once per session (``python worker.py``, without the
package, so it never initialises MPI) that has imported OCP and forks a
fresh reader child for every file.  The child runs
:func:`nagata_snap.cad.read.read_shape` on that one file and sends back its
plain-data result; if it crashes or does not answer within the time-out,
the server kills it and reports :class:`~nagata_snap.cad.CadError` naming
the file.  One file per child makes every read independent of the files
read before it: OpenCASCADE keeps state across reads inside a process (a
malformed IGES file read twice in one process can give a geometry, then an
empty shape).  The child for the next file is forked after each reply, so
the fork is not paid in the request's time.  The server freezes its heap
(``gc.freeze``) before it starts forking, and a reader runs without the cyclic
garbage collector (it reads one file and exits): a collection in a forked
child walks every object it inherited and so copies the parent's pages, which
made a read in a reader up to 1.5 times the same read in a long-lived process.
A reply is passed on by the server as the reader framed it (not unpickled and
pickled again).  ``isolate=False`` reads in
this process (faster to start, but neither protected nor independent of
earlier reads).

Protocol on the server's stdin/stdout: length-prefixed pickles, request
``(path, kwargs, timeout)``, reply ``(status, payload)`` with status
``"ok"``, ``"error"``, ``"crash"`` or ``"timeout"``.  OpenCASCADE's own
printing goes to ``/dev/null``.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import os
import pickle
import select
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator

__all__ = ["read_cad", "shutdown", "collector_paused"]

#: environment variables of MPI process managers, not passed to the server
_MPI_ENV = ("PMI_", "PMIX_", "MPI_", "HYDRA_", "OMPI_", "MPICH_", "I_MPI_", "SLURM_")


def _frame(obj) -> bytes:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return struct.pack("<Q", len(data)) + data


def _send(f, obj) -> None:
    f.write(_frame(obj))
    f.flush()


def _read_exactly(fd: int, n: int, deadline: float | None) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        wait = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select([fd], [], [], wait)
        if not ready:
            return None
        chunk = os.read(fd, min(1 << 20, n - len(buf)))
        if not chunk:  # the other side closed the pipe
            return None
        buf += chunk
    return bytes(buf)


def _recv_frame(fd: int, deadline: float | None = None) -> bytes | None:
    """One whole frame (length prefix and pickle) from ``fd``, or None (closed, or past ``deadline``)."""
    head = _read_exactly(fd, 8, deadline)
    if head is None or len(head) < 8:
        return None
    (n,) = struct.unpack("<Q", head)
    body = _read_exactly(fd, n, deadline)
    return None if body is None else head + body


def _recv(fd: int, deadline: float | None = None):
    frame = _recv_frame(fd, deadline)
    return None if frame is None else pickle.loads(memoryview(frame)[8:])


# ----------------------------------------------------------------------
# the server (runs as a script)
# ----------------------------------------------------------------------
def _load_reader():
    import importlib.util

    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "read.py")
    spec = importlib.util.spec_from_file_location("_nagata_snap_cad_read", here)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _child(reader, r: int, w: int) -> None:
    """A forked reader: answer one request on ``r`` with a reply on ``w``, then return (without
    the cyclic garbage collector: see the module docstring)."""
    gc.disable()
    msg = _recv(r)
    if msg is None:
        return
    path, kwargs, _ = msg
    try:
        res = ("ok", reader.read_shape(path, **kwargs))
    except reader.ReadError as e:
        res = ("error", str(e))
    except BaseException as e:  # OpenCASCADE's exceptions arrive as Python exceptions
        res = ("error", f"{path}: OpenCASCADE failed: {type(e).__name__}: {e}")
    with os.fdopen(w, "wb") as out:
        _send(out, res)


_PID = struct.Struct("<q")


def _zygote(reader, ctl: socket.socket) -> None:
    """Fork readers on request, from a state that reading never changes.

    OpenCASCADE's result on some malformed files depends on the memory of the
    process reading them (not only on files read before in the same process:
    also on what the process did with earlier replies), so readers are forked
    from this process, which only forks and reaps.  Commands on ``ctl``:
    ``b"f"``: fork a reader, answer its pid with its request and reply pipe
    ends (``SCM_RIGHTS``); ``b"w" + pid``: reap the reader, answer its wait status.
    """
    while True:
        cmd = ctl.recv(1)
        if cmd == b"f":
            req_r, req_w = os.pipe()
            res_r, res_w = os.pipe()
            pid = os.fork()
            if pid == 0:  # the reader: serve one request, exit without cleanup
                try:
                    ctl.close()
                    os.close(req_w)
                    os.close(res_r)
                    _child(reader, req_r, res_w)
                finally:
                    os._exit(0)
            for fd in (req_r, res_w):
                os.close(fd)
            socket.send_fds(ctl, [_PID.pack(pid)], [req_w, res_r])
            for fd in (req_w, res_r):
                os.close(fd)
        elif cmd == b"w":
            (pid,) = _PID.unpack(ctl.recv(_PID.size, socket.MSG_WAITALL))
            try:
                status = os.waitpid(pid, 0)[1]
            except ChildProcessError:
                status = 0
            ctl.sendall(_PID.pack(status))
        else:  # the server closed its end
            return


def _start_zygote(reader, keep: tuple[int, ...]) -> tuple[int, socket.socket]:
    """Fork the :func:`_zygote`: ``(pid, control socket)``; it closes the fds ``keep``."""
    ours, theirs = socket.socketpair()
    pid = os.fork()
    if pid == 0:
        try:
            ours.close()
            for fd in keep:
                os.close(fd)
            _zygote(reader, theirs)
        finally:
            os._exit(0)
    theirs.close()
    return pid, ours


def _spare(ctl: socket.socket) -> tuple[int, int, int]:
    """A fresh reader forked by the zygote: ``(pid, request fd, reply fd)``."""
    ctl.sendall(b"f")
    data, fds, _, _ = socket.recv_fds(ctl, _PID.size, 2)
    return _PID.unpack(data)[0], fds[0], fds[1]


def _kill(ctl: socket.socket, child) -> int:
    """Close a reader's pipes, kill it (if still running) and reap it: its wait status."""
    pid, req_w, res_r = child
    for fd in (req_w, res_r):
        with contextlib.suppress(OSError):
            os.close(fd)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    ctl.sendall(b"w" + _PID.pack(pid))
    return _PID.unpack(ctl.recv(_PID.size, socket.MSG_WAITALL))[0]


def _ask(child, msg) -> bytes | tuple:
    """A reader's framed reply to ``msg`` (bytes, passed on as they are); ``("crash" |
    "timeout", ...)`` if it died or hung."""
    _, req_w, res_r = child
    with contextlib.suppress(OSError):  # a dead reader: its reply pipe tells
        os.write(req_w, _frame(msg))
    deadline = time.monotonic() + msg[2]
    reply = _recv_frame(res_r, deadline)
    if reply is not None:
        return reply
    if time.monotonic() >= deadline:  # still running: hung
        return ("timeout", msg[2])
    return ("crash", None)  # it closed the pipe: it died (the status comes from the zygote)


def _crash_reason(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"signal {os.WTERMSIG(status)} ({signal.Signals(os.WTERMSIG(status)).name})"
    return f"exit status {os.WEXITSTATUS(status)} without a result"


def serve() -> None:
    """Server main loop: requests on stdin, replies on (the original) stdout.

    Every request is answered by a fresh reader forked by the zygote; the
    next reader is forked after each reply, so that the fork is not paid in
    the request's time.
    """
    out = os.fdopen(os.dup(1), "wb")
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    reader = _load_reader()
    reader.preload()
    gc.collect()
    gc.freeze()  # the readers forked from here do not copy these objects' pages
    fd = sys.stdin.fileno()
    zpid, ctl = _start_zygote(reader, (out.fileno(), fd))
    child = _spare(ctl)
    _send(out, ("ready", None))
    try:
        while True:
            msg = _recv(fd)
            if msg is None:
                break
            reply = _ask(child, msg)
            if isinstance(reply, bytes):  # the reader's own frame
                out.write(reply)
                out.flush()
                _kill(ctl, child)
            elif reply[0] == "crash":  # the reason is the reader's wait status
                _send(out, ("crash", _crash_reason(_kill(ctl, child))))
            else:
                _send(out, reply)
                _kill(ctl, child)
            child = _spare(ctl)
    finally:
        _kill(ctl, child)
        ctl.close()
        os.waitpid(zpid, 0)


# ----------------------------------------------------------------------
# the client
# ----------------------------------------------------------------------
class _Client:
    def __init__(self):
        self.proc = None

    def start(self) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith(_MPI_ENV)}
        self.proc = subprocess.Popen([sys.executable, os.path.abspath(__file__)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, env=env, close_fds=True)
        msg = _recv(self.proc.stdout.fileno(), time.monotonic() + 300.0)
        if msg is None or msg[0] != "ready":
            self.stop()
            from nagata_snap.errors import missing_extra  # (the client side runs in the package)

            raise RuntimeError("the CAD reader process did not start: "
                               f"{missing_extra('OCP', 'to read CAD files')}")

    def stop(self) -> None:
        if self.proc is not None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=5)
            except Exception:
                self.proc.kill()
            self.proc = None

    def request(self, path: str, kwargs: dict, timeout: float) -> tuple:
        for _ in range(2):  # a dead server is restarted once
            if self.proc is None or self.proc.poll() is not None:
                self.start()
            try:
                _send(self.proc.stdin, (path, kwargs, timeout))
                reply = _recv(self.proc.stdout.fileno(), time.monotonic() + timeout + 60.0)
            except (BrokenPipeError, OSError):
                reply = None
            if reply is not None:
                return reply
            self.stop()
        return ("crash", "the reader process died")


_CLIENT = _Client()
atexit.register(lambda: _CLIENT.stop())


def shutdown() -> None:
    """Stop the reader server (it is restarted on the next isolated read)."""
    _CLIENT.stop()


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """The cyclic garbage collector off while a file's data, model and geometry are built
    (restored after, if it was on).

    Reading a file makes tens of thousands of small containers (the reply's dicts and lists,
    the model's and the geometry's arrays), none of them garbage: in a process that holds a
    large heap (DOLFINx, numba) the collections they trigger walk that heap again and again
    (on the 375-face frame, about a tenth of the read in process).  Cycles made meanwhile are
    collected on the next collection after it.
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def read_cad(path, *, unit: str = "MM", heal: bool = True, isolate: bool = True,
             timeout: float | None = None, fallback: dict[int, str] | None = None,
             check: bool = True) -> dict:
    """Read a CAD file with OpenCASCADE: :func:`nagata_snap.cad.read.read_shape`'s data.

    Args:
        path: STEP, IGES or BREP file.
        unit, heal, fallback, check: see :func:`~nagata_snap.cad.read.read_shape`.
        isolate: read in a forked child of the reader server (see the module
            docstring); ``False`` reads in this process.
        timeout: seconds (isolated reads only); default 60 s plus 30 s per MB.

    Raises:
        CadError: the file is missing or not a CAD file, OpenCASCADE cannot
            read or convert it, crashed or did not finish in time.
    """
    from nagata_snap.errors import CadError

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CadError(f"CAD file {path} does not exist")
    if not isolate:
        from nagata_snap.cad import read

        try:
            return read.read_shape(path, unit=unit, heal=heal, fallback=fallback, check=check)
        except read.ReadError as e:
            raise CadError(str(e)) from None
        except Exception as e:  # OpenCASCADE's exceptions arrive as Python exceptions
            raise CadError(f"{path}: OpenCASCADE failed: {type(e).__name__}: {e}") from None
    if timeout is None:
        timeout = 60.0 + 30.0 * os.path.getsize(path) / 1e6
    try:
        kwargs = {"unit": unit, "heal": heal, "fallback": fallback, "check": check}
        status, payload = _CLIENT.request(os.path.abspath(path), kwargs, float(timeout))
    except RuntimeError as e:
        raise CadError(f"{path}: {e}") from None
    if status == "ok":
        return payload
    if status == "error":
        raise CadError(payload)
    if status == "timeout":
        raise CadError(f"{path}: OpenCASCADE did not finish reading it within {payload:g} s "
                       "(malformed file?)")
    raise CadError(f"{path}: OpenCASCADE crashed reading it ({payload}); the file is malformed "
                   "or uses something OpenCASCADE cannot handle")


if __name__ == "__main__":
    serve()
