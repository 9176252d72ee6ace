"""`e3dpsm run` as a library call: a RunRequest in, a RunResult (the JSON report as written,
and the summary lines the command prints) out.

One entry point, `run_poses`, over three forms: one event file (run_file.py), several files
as independent streams batched through one session (run_many.py), and a live dv://HOST:PORT
stream (run_live.py). Every form writes under temporary names and renames only once the whole
stream ran, so a failure leaves nothing behind; a stream that yields no complete window is an
error rather than an empty CSV. Torch-free: numpy, onnxruntime and the standard library.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from e3dpsm.errors import ConfigError, DataError, OutputExistsError

DEFAULT_CHUNK_EVENTS = 100_000
# An event camera's background activity never leaves it silent for a minute; every empty
# window of a silence is stepped, so a corrupted timestamp would keep `run` stepping for hours.
MAX_GAP_S = 60.0
LIVE_TIMEOUT_S = 5.0  # connect timeout, and how long a silent live stream counts as stopped


@dataclass(frozen=True)
class RunRequest:
    """What to run and where to write it. `events`: one file, several files (`out` is then a
    folder), or one dv://HOST:PORT source. Option values and combinations the runtime cannot
    use are refused on construction (ConfigError), before any file is opened; the messages
    name the command's options."""

    model: str
    events: tuple[str, ...]
    out: Path
    window_ms: float | None = None  # None: the graph's training window
    threads: int | None = None  # None: the runtime's own choice
    start_us: int | None = None  # None: the first event
    chunk_events: int = DEFAULT_CHUNK_EVENTS
    max_gap_s: float = MAX_GAP_S
    force: bool = False
    progress: bool = False  # a progress bar on stderr (one-file form)
    render: str | None = None  # video of the LNES frames with the skeleton (one recording only)
    render_max_frames: int | None = None
    max_seconds: float | None = None  # live source: wall-time limit
    live_timeout_s: float = LIVE_TIMEOUT_S

    def __post_init__(self) -> None:
        object.__setattr__(self, "events", tuple(str(e) for e in self.events))
        object.__setattr__(self, "out", Path(self.out))
        if not self.events:
            raise ConfigError("give at least one --events file")
        many = len(self.events) > 1
        # The one --render check for both forms: the many-file form never sees --render.
        if many and (self.render is not None or self.render_max_frames is not None):
            raise ConfigError("--render draws one stream: pass a single --events file")
        if self.chunk_events <= 0:
            raise ConfigError(f"--chunk-events must be positive, got {self.chunk_events}")
        if self.threads is not None and self.threads <= 0:
            raise ConfigError(f"--threads must be positive, got {self.threads}")
        if not self.max_gap_s > 0:
            raise ConfigError(f"--max-gap-s must be positive, got {self.max_gap_s}")
        if many and any(_is_live(e) for e in self.events):
            raise ConfigError("a live dv:// source runs alone: pass it as the only --events")
        if self.live:
            self._check_live_options()
        elif self.render is None and self.render_max_frames is not None:
            raise ConfigError("--render-max-frames needs --render PATH")

    @property
    def live(self) -> bool:
        return len(self.events) == 1 and _is_live(self.events[0])

    def _check_live_options(self) -> None:
        if self.render is not None:
            raise ConfigError("--render draws a recording; it is not available for a live dv:// source")
        if self.max_seconds is not None and self.max_seconds <= 0:
            raise ConfigError(f"--max-seconds must be positive, got {self.max_seconds}")


@dataclass(frozen=True)
class RunResult:
    report: dict[str, Any]  # exactly what the report file holds
    summary: tuple[str, ...]  # what the command prints, one line each


def run_poses(request: RunRequest) -> RunResult:
    """Run the request's form: several files, one live source, or one file."""
    if len(request.events) > 1:
        from e3dpsm.runtime.run_many import run_many

        return run_many(request)
    _check_single_out(request.out, request.force)
    if request.live:
        from e3dpsm.runtime.run_live import run_live

        return run_live(request)
    from e3dpsm.runtime.run_file import run_file

    return run_file(request)


def _check_single_out(out: Path, force: bool) -> None:
    from e3dpsm.utils.io import check_writable_folder

    if out.is_dir():
        raise DataError(f"--out {out} is a folder; expected a CSV file path")
    if out.exists() and not force:
        raise OutputExistsError(f"{out} exists; pass --force to replace it")
    check_writable_folder(out.parent)  # fail before minutes of inference, not after


def _is_live(source: str) -> bool:
    from e3dpsm.data.live import is_live_url

    return is_live_url(source)
