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
