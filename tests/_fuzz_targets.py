"""What the bounded child process (tests/_bounded.py) calls: each reader or command on one
input, returning a small summary (not the data) or raising what the reader raises."""
from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any


def read_events(path: Path) -> int:
    from e3dpsm.data.readers import read_events as read

    return len(read(path))


def drain_live(url: str, timeout_s: float) -> tuple[int, str | None]:
    """(events received, why the stream stopped) of a dv:// source read to its end."""
    from e3dpsm.data.live import open_live_source

    with open_live_source(url, timeout_s=timeout_s) as source:
        events = sum(len(chunk) for chunk in source)
    return events, source.stopped_reason


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `e3dpsm ARGV` in this process. An exception that escapes
    `main` (what would print a traceback) propagates: the worker reports it as "raised"."""
    import logging

    from e3dpsm.cli import main

    logging.root.handlers.clear()  # main's logging.basicConfig binds to the stderr captured below
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse
            code = exc.code if isinstance(exc.code, int) else 2
    return code, out.getvalue(), err.getvalue()


def ping() -> Any:
    return "pong"


# For tests/test_isolate.py: what a reader in the helper process may do.
def typed_arrays(n: str) -> dict[str, Any]:
    import numpy as np

    count = int(n)
    return {"i32": np.arange(count, dtype=np.int32) - 7, "u8": (np.arange(count) % 251).astype(np.uint8),
            "f64_2d": np.arange(2 * count, dtype=np.float64).reshape(count, 2) / 3, "empty": np.zeros(0, np.int64),
            "hw": [480, 640], "name": "x"}


def segfault() -> None:
    import ctypes

    ctypes.string_at(0)  # reads address 0: SIGSEGV


def spin() -> None:
    while True:
        pass


def refuse(message: str) -> None:
    from e3dpsm.errors import DataError

    raise DataError(message)


def buggy() -> None:
    raise KeyError("a bug")


def pid() -> dict[str, Any]:
    import os

    return {"pid": os.getpid(), "parent": os.getppid()}


def helper_of_this_process() -> int:
    """The pid of the isolation helper a call from this process runs in."""
    from e3dpsm.utils.isolate import run_isolated

    return run_isolated("_fuzz_targets:pid", deadline_s=30, what="probe")["parent"]


def read_released(path: str) -> tuple[str, int]:
    """(what the file was, number of tensors) of a released checkpoint read as `import` reads it."""
    from e3dpsm.importers.released import read_released_state_dict

    state, kind = read_released_state_dict(path)
    return kind, len(state)


_RELEASED_MODEL: list = []


def import_released(path: str) -> int:
    """Released tensors mapped onto the `released` variant (the model is built once per process)."""
    import e3dpsm
    from e3dpsm.importers.released import import_released as map_onto, read_released_state_dict

    if not _RELEASED_MODEL:
        _RELEASED_MODEL.append(e3dpsm.create_model("released").eval())
    state, _ = read_released_state_dict(path)
    return len(map_onto(state, _RELEASED_MODEL[0]).state_dict)


def parse_client_message(text: str) -> tuple:
    """("ok", type) or ("closed", close code, reason) for one client message of the viewer."""
    from e3dpsm.serve.protocol import ProtocolError, parse_client_message as parse

    try:
        return "ok", parse(text)[0]
    except ProtocolError as exc:
        return "closed", exc.code, exc.reason
