"""Shared pieces of the `e3dpsm serve` tests: a short recording with ground truth beside it,
and the server started as a subprocess on a free port (what a user runs, signals included)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

from _runtime_helpers import WINDOW_US, synthetic_stream

ROOT = Path(__file__).resolve().parents[1]


def write_recording(folder: Path, windows: int, seed: int = 3) -> Path:
    """folder/events.npz (sorted events over `windows` 20 ms windows, a silent stretch in the
    middle) and folder/gt.npz with a distinct known pose at every window end."""
    folder.mkdir(parents=True, exist_ok=True)
    x, y, t, p = synthetic_stream(seed, windows=windows, events_per_window=300)
    path = folder / "events.npz"
    np.savez(path, x=x, y=y, t=t, p=p)
    ends = int(t[0]) + WINDOW_US * np.arange(1, windows + 1, dtype=np.int64)
    rng = np.random.default_rng(seed)
    np.savez(folder / "gt.npz", t_us=ends, j3d_m=rng.normal(0.0, 0.5, (windows, 16, 3)).astype(np.float32))
    return path


class ServerProcess:
    """`e3dpsm serve ... --port 0` in a subprocess; `url`, `port` and `token` from its first
    stdout line (the URL it prints carries the token). `ws` is the socket's URL with the token
    in its query, as a non-browser client (no cookie, no Origin) must give it."""

    def __init__(self, args: list[str], start_timeout_s: float = 60.0) -> None:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "e3dpsm", "serve", "--port", "0", *args], cwd=ROOT, env=env,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        line = self.proc.stdout.readline()  # blocks until the server is listening (or died)
        if not line.startswith("serving http://"):
            self.proc.kill()
            _, err = self.proc.communicate(timeout=start_timeout_s)
            raise RuntimeError(f"serve did not start: {line!r} {err[-2000:]}")
        self.line = line
        self.url = line.split()[1]
        parts = urlsplit(self.url)
        self.port = parts.port
        self.token = parse_qs(parts.query).get("token", [None])[0]
        self.base = f"http://127.0.0.1:{self.port}"
        self.ws = f"{self.base}/ws" + (f"?token={self.token}" if self.token else "")

    def interrupt(self) -> None:
        self.proc.send_signal(signal.SIGINT)

    def wait(self, timeout_s: float = 60.0) -> tuple[int, str, str]:
        out, err = self.proc.communicate(timeout=timeout_s)
        return self.proc.returncode, out, err

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate(timeout=30)

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
