"""Calls that must end within a time bound, run in a child process so that a hang fails a test
instead of hanging the suite.

A Python-level timeout (signal.alarm, a thread's join) cannot stop C code that spins holding
the GIL (dv-processing did, on damaged AEDAT4 files), and a crash in C (the HDF5 library
segfaulted on a damaged chunk) would take the test process with it. So each call goes to a
long-lived child process; a call that has not answered within its bound has the child killed
(and a fresh one started for the next call) and comes back as "hung", one that kills the child
comes back as "crashed".

    with BoundedWorker(preload=("e3dpsm.data.readers",)) as worker:
        outcome = worker.call("e3dpsm.data.readers:read_events", path, bound_s=10)
        assert outcome.kind in ("returned", "refused"), outcome

Targets are "module:function" names, resolved in the child; arguments and results must pickle.
"""
from __future__ import annotations

import importlib
import multiprocessing as mp
import time
import traceback
from dataclasses import dataclass
from typing import Any

STARTUP_S = 120.0  # imports in a fresh interpreter (torch, onnxruntime) on a loaded machine


@dataclass(frozen=True)
class Outcome:
    """How one call ended: "returned" (value), "refused" (an E3DPSMError: detail is its
    type and message), "raised" (any other exception: detail is the traceback), "hung" (no
    answer within the bound) or "crashed" (the child died: detail is its exit code)."""

    kind: str
    value: Any = None
    detail: str = ""
    seconds: float = 0.0


def resolve(target: str) -> Any:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def _serve(conn: Any, preload: tuple[str, ...]) -> None:  # the child's loop
    from e3dpsm.errors import E3DPSMError

    for module in preload:
        importlib.import_module(module)
    conn.send("ready")
    while True:
        message = conn.recv()
        if message is None:
            return
        target, args = message
        start = time.perf_counter()
        try:
            value = resolve(target)(*args)
            reply = ("returned", value, "")
        except E3DPSMError as exc:
            reply = ("refused", None, f"{type(exc).__name__}: {exc}")
        except BaseException:  # noqa: BLE001 - everything else is what the tests look for
            reply = ("raised", None, traceback.format_exc())
        conn.send((*reply, time.perf_counter() - start))


class BoundedWorker:
    """A child process (spawned: no state shared with the test process) running one call at a time."""

    def __init__(self, preload: tuple[str, ...] = ()) -> None:
        self.preload = tuple(preload)
        self._process: Any = None
        self._conn: Any = None

    def _start(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        # not a daemon: a call may start processes of its own (the HDF5 reader does)
        self._process = ctx.Process(target=_serve, args=(child, self.preload))
        self._process.start()
        child.close()
        if not self._conn.poll(STARTUP_S) or self._conn.recv() != "ready":
            self.close(kill=True)
            raise RuntimeError(f"the bounded worker did not start within {STARTUP_S:g} s")

    def call(self, target: str, *args: Any, bound_s: float) -> Outcome:
        if self._process is None or not self._process.is_alive():
            self._start()
        start = time.perf_counter()
        self._conn.send((target, args))
        if not self._conn.poll(bound_s):
            self.close(kill=True)
            return Outcome("hung", detail=f"{target} did not end within {bound_s:g} s", seconds=bound_s)
        try:
            kind, value, detail, seconds = self._conn.recv()
        except (EOFError, ConnectionError):
            self._process.join(5)
            code = self._process.exitcode
            self.close(kill=True)
            return Outcome("crashed", detail=f"{target}: the child exited with code {code}",
                           seconds=time.perf_counter() - start)
        return Outcome(kind, value, detail, seconds)

    def close(self, kill: bool = False) -> None:
        """End the child: asked to stop, or killed (`kill`, or when it does not stop)."""
        if self._process is None:
            return
        if not kill and self._process.is_alive():
            try:
                self._conn.send(None)
            except (OSError, ValueError):
                pass
            self._process.join(5)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(5)
        self._conn.close()
        self._process = self._conn = None

    def __enter__(self) -> BoundedWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
