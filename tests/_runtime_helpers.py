"""Shared pieces of the streaming-runtime tests: one exported tiny graph per test session,
synthetic event streams, and the reference computation the runtime must reproduce."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from e3dpsm.events import events_to_lnes, window_bounds
from e3dpsm.runtime import StepSession

WINDOW_US = 20_000
SENSOR_HW = (480, 640)


@functools.lru_cache(maxsize=1)
def exported_tiny(basetemp: str):
    """(torch model, graph path): exported once per session even when two test modules ask
    (both pass the session's base temp folder, the cache key)."""
    import torch

    import e3dpsm
    from e3dpsm.export import export_step

    torch.manual_seed(0)
    model = e3dpsm.create_model("tiny").eval()
    # Poses of realistic magnitude (mm), so the tolerances are checked where they matter.
    model.set_pose_prior(torch.linspace(-800.0, 1200.0, 48).view(16, 3))
    folder = Path(basetemp) / "runtime_graph"
    folder.mkdir(exist_ok=True)
    path = export_step(model, folder / "tiny_step.onnx")
    return model, path


@functools.lru_cache(maxsize=1)
def shared_session(path: str) -> StepSession:
    return StepSession(path, threads=1)


def synthetic_stream(
    seed: int, windows: int = 10, events_per_window: int = 400, t0_us: int = 1_234_567,
    boundary_bursts: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sorted events over `windows` windows with a silent gap of ~2.5 windows in the middle,
    so the stream has empty windows; repeated timestamps occur (integer microseconds).

    `boundary_bursts` adds bursts of equal timestamps on the last microsecond of every
    window and on the first of the next (the first event sits at t0_us, so the window grid
    is known): the cases where emitting a window one microsecond early would show.
    """
    rng = np.random.default_rng(seed)
    span = windows * WINDOW_US
    t = np.sort(rng.integers(0, span, windows * events_per_window))
    gap_lo = int(rng.integers(2, windows - 4)) * WINDOW_US + WINDOW_US // 2
    t = t[(t < gap_lo) | (t >= gap_lo + 5 * WINDOW_US // 2)]
    if boundary_bursts:
        ends = np.arange(1, windows) * WINDOW_US
        t = np.sort(np.concatenate([[0], t, np.repeat(ends - 1, 4), np.repeat(ends, 4)]))
    t = t + t0_us
    n = t.size
    return (
        rng.integers(0, SENSOR_HW[1], n), rng.integers(0, SENSOR_HW[0], n), t.astype(np.int64),
        rng.integers(0, 2, n),
    )


def reference_frames(
    x, y, t, p, start_us: int | None = None, end_us: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(window starts, event counts, LNES frames [K, 2, 192, 256]) computed directly from
    the one window definition, as a batch consumer (`prepare`) would."""
    if start_us is None and end_us is not None:
        start_us = int(t[0])
    starts, ranges = window_bounds(t, WINDOW_US, start_us, end_us)
    frames = np.stack([
        events_to_lnes(x[lo:hi], y[lo:hi], t[lo:hi], p[lo:hi], s, WINDOW_US, 192, 256, SENSOR_HW)
        for s, (lo, hi) in zip(starts.tolist(), ranges.tolist())
    ]) if starts.size else np.zeros((0, 2, 192, 256), np.float32)
    return starts, ranges[:, 1] - ranges[:, 0], frames


def step_frames(session: StepSession, frames: np.ndarray, window_ms: float = WINDOW_US / 1000):
    """Poses [K, 16, 3] and final state of stepping `session` over `frames` from a fresh state."""
    state = session.init_state(1)
    poses = []
    for frame in frames:
        outputs, state = session.step(frame[None], state, window_ms)
        poses.append(outputs["pose"][0])
    return np.asarray(poses).reshape(-1, 16, 3), state


def chunked(arrays, cuts) -> list[tuple[np.ndarray, ...]]:
    """The event arrays split at the (sorted, possibly repeated) indices `cuts`."""
    bounds = [0, *sorted(cuts), len(arrays[2])]
    return [tuple(a[lo:hi] for a in arrays) for lo, hi in zip(bounds[:-1], bounds[1:])]
