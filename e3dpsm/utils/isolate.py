"""Run a reader in a separate process with a deadline: for C libraries that can crash, loop or
corrupt memory on a damaged file, so that the command ends with one error line instead.

The HDF5 library is one: a single flipped byte in an LZF-compressed chunk of a file e3dpsm
itself wrote made h5py 3.16 / HDF5 2.0.0 segfault in `Dataset.__getitem__` in one process and
return garbage in another (a heap overflow; found by the fuzz tests). Neither a crash nor a
loop in C can be caught or interrupted from Python in the same process.

A helper `python -m e3dpsm.utils.isolate` is started on first use and kept (an interpreter
start costs about half a second). It imports the reader's module, then forks one child per
call: the child reads and replies, so whatever a damaged file does to its memory dies with
it, and forking the helper is safe where forking the caller is not (the helper has one
thread; the caller may run ONNX Runtime or PyTorch threads holding locks). The helper kills
a child at the deadline and reports a crash by its signal. Not multiprocessing: its "spawn"
and "forkserver" children re-run the caller's `__main__` (`python -m e3dpsm` would run the
command again). Requests and replies are JSON; the child writes the arrays' raw bytes into one
file in /dev/shm (tmpfs) that the caller maps copy-on-write and unlinks: no copy through a
pipe, nothing unpickled. Without os.fork (Windows) the helper reads itself, still apart from
the caller.
"""
from __future__ import annotations

import atexit
import importlib
import json
import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from e3dpsm.errors import DataError

SHARED_MEMORY = "/dev/shm"  # tmpfs: the arrays file never touches a disk (else the temp folder)
STARTUP_S = 60.0  # the helper's interpreter start and imports, on a loaded machine
MARGIN_S = 10.0  # the caller waits this much past the deadline the helper enforces


class IsolatedError(RuntimeError):
    """The call raised something other than DataError: a bug, reported with its type."""


def deadline_for(size_bytes: int, base_s: float = 30.0, bytes_per_s: float = 20e6) -> float:
    """A reading deadline that grows with the file: `base_s` plus the file at `bytes_per_s`
    (the readers go at 100-400 MB/s of input; 20 MB/s leaves room for a loaded machine)."""
    return base_s + size_bytes / bytes_per_s


class _Helper:
    def __init__(self, preload: tuple[str, ...]) -> None:
        req_r, req_w = os.pipe()
        res_r, res_w = os.pipe()
        # The caller's sys.path (as multiprocessing gives its children): the target imports the
        # same. Its own process group: killing the group also ends a child it forked.
        # stdout/stderr to /dev/null: a command's output stays its own (one error line on failure).
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "e3dpsm.utils.isolate", str(req_r), str(res_w), *preload],
            pass_fds=(req_r, res_w), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True, env=env)
        os.close(req_r)
        os.close(res_w)
        self.requests, self.replies = Connection(req_w, readable=False), Connection(res_r, writable=False)
        try:
            ready = self.replies.poll(STARTUP_S) and json.loads(self.replies.recv_bytes()) == {"ready": True}
        except (EOFError, OSError, ValueError):
            ready = False
        if not ready:
            self.kill()
            raise DataError("the reader's helper process (python -m e3dpsm.utils.isolate) did not start within "
                            f"{STARTUP_S:g} s")

    def kill(self) -> None:
        if self.process.poll() is None:
            try:
                os.killpg(self.process.pid, signal.SIGKILL)
            except OSError:
                self.process.kill()
        self.process.wait()
        self.requests.close()
        self.replies.close()


_lock = threading.Lock()
_helper: _Helper | None = None


def _forget_helper_after_fork() -> None:
    """A forked copy of the caller (a process pool's worker) starts its own helper: the
    inherited one answers the parent, and its lock may have been held by a parent's thread."""
    global _helper, _lock
    _helper, _lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_helper_after_fork)


def run_isolated(target: str, *args: str, deadline_s: float, what: str,
                 preload: tuple[str, ...] = ()) -> dict[str, Any]:
    """`module:function` called with string `args` in a child of the helper process; its value,
    a dict of numpy arrays and JSON values. DataError raised there is raised here; a crash and
    a call past `deadline_s` raise DataError too, each starting with `what`. A new helper
    imports the target's module and `preload` first (each call then forks with them loaded).
    Calls from several threads take turns."""
    global _helper
    with _lock:
        if _helper is None or _helper.process.poll() is not None:
            _helper = _Helper((target.partition(":")[0], *preload))
        helper = _helper
        shared = SHARED_MEMORY if os.path.isdir(SHARED_MEMORY) else None
        fd, arrays_file = tempfile.mkstemp(prefix="e3dpsm-isolate-", dir=shared)
        os.close(fd)
        try:
            helper.requests.send_bytes(json.dumps({"target": target, "args": list(args), "deadline_s": deadline_s,
                                                   "arrays_file": arrays_file}).encode())
            if helper.replies.poll(deadline_s + MARGIN_S):
                return _receive(helper.replies, what, deadline_s, arrays_file)
        except (EOFError, OSError):
            pass  # the helper itself died: start a fresh one next time
        finally:
            os.unlink(arrays_file)  # its pages stay mapped by the arrays returned
        helper.kill()
        _helper = None
        raise DataError(f"{what}: the reader's helper process stopped answering; the file may be damaged")


def _receive(replies: Connection, what: str, deadline_s: float, arrays_file: str) -> dict[str, Any]:
    header = json.loads(replies.recv_bytes())
    if "error" in header:
        if header["error"] == "crashed":
            raise DataError(f"{what}: the reader crashed ({header['message']}) on this file; it is damaged")
        if header["error"] == "deadline":
            raise DataError(f"{what}: reading did not end within {deadline_s:.0f} s (the file is damaged, or too "
                            "large to read in that time); stopped")
        if header["error"] == "DataError":
            raise DataError(header["message"])
        raise IsolatedError(f"{header['error']}: {header['message']}")
    value = dict(header["values"])
    for key, dtype, shape, offset in header["arrays"]:
        if math.prod(shape):  # copy-on-write pages of the file: no copy, writable here
            value[key] = np.asarray(np.memmap(arrays_file, np.dtype(dtype), "c", offset, tuple(shape)))
        else:
            value[key] = np.empty(shape, np.dtype(dtype))
    return value


@atexit.register
def _stop_helper() -> None:
    if _helper is not None:
        _helper.kill()


# -- the helper process ------------------------------------------------------------------------
def _call(request: dict[str, Any], replies: Connection) -> None:
    module, _, name = request["target"].partition(":")
    try:
        value = getattr(importlib.import_module(module), name)(*request["args"])
    except Exception as exc:  # noqa: BLE001 - every failure goes back as one line
        replies.send_bytes(json.dumps({"error": type(exc).__name__, "message": str(exc)}).encode())
        return
    arrays = {k: np.ascontiguousarray(v) for k, v in value.items() if isinstance(v, np.ndarray)}
    layout, offset = [], 0
    with open(request["arrays_file"], "wb") as fh:  # one file in shared memory: a copy, not a pipe's many
        for key, array in arrays.items():
            layout.append([key, array.dtype.str, list(array.shape), offset])
            fh.write(memoryview(array).cast("B") if array.nbytes else b"")
            offset += array.nbytes
    values = {k: v for k, v in value.items() if k not in arrays}
    replies.send_bytes(json.dumps({"values": values, "arrays": layout}).encode())


def _wait(pid: int, deadline_s: float) -> int | None:
    """The child's wait status, or None once it was killed at the deadline."""
    end = time.monotonic() + deadline_s
    pidfd = os.pidfd_open(pid) if hasattr(os, "pidfd_open") else None
    try:
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                return status
            left = end - time.monotonic()
            if left <= 0:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return None
            if pidfd is not None:
                select.select([pidfd], [], [], left)
            else:
                time.sleep(min(left, 0.005))
    finally:
        if pidfd is not None:
            os.close(pidfd)


def _serve(requests: Connection, replies: Connection) -> None:
    while True:
        try:
            request = json.loads(requests.recv_bytes())
        except EOFError:  # the caller is gone
            return
        if not hasattr(os, "fork"):
            _call(request, replies)
            continue
        helper = os.getpid()
        pid = os.fork()
        if pid == 0:  # the child: read, reply, leave without running any cleanup of the helper's
            code = 1
            try:
                _die_with(helper)
                _call(request, replies)
                code = 0
            finally:
                os._exit(code)
        status = _wait(pid, float(request["deadline_s"]))
        if status is None:
            replies.send_bytes(json.dumps({"error": "deadline", "message": ""}).encode())
        elif os.WIFSIGNALED(status) or os.WEXITSTATUS(status):  # it died before replying
            replies.send_bytes(json.dumps({"error": "crashed", "message": _status_name(status)}).encode())


def _die_with(helper: int) -> None:
    """Have the kernel kill this child when the helper dies, however it dies (Linux: prctl
    PR_SET_PDEATHSIG), so that no read outlives its helper; leave if it is already gone."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != helper:
        os._exit(1)


def _status_name(status: int) -> str:
    if not os.WIFSIGNALED(status):
        return f"exit code {os.WEXITSTATUS(status)}"
    try:
        return signal.Signals(os.WTERMSIG(status)).name
    except ValueError:
        return f"signal {os.WTERMSIG(status)}"


def main(argv: list[str]) -> int:
    requests, replies = Connection(int(argv[0]), writable=False), Connection(int(argv[1]), readable=False)
    for module in argv[2:]:
        importlib.import_module(module)
    replies.send_bytes(json.dumps({"ready": True}).encode())
    _serve(requests, replies)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
