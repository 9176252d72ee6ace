"""Continuous LNES frame streams for rollouts (parity, profiling, calibration)."""
from __future__ import annotations

import itertools
import os
from typing import Iterator

import numpy as np

from e3dpsm.errors import DataError


def prepared_frames(data_dir: str | os.PathLike, steps: int, split: str | None = None) -> Iterator[np.ndarray]:
    """`steps` float32 [2, H, W] frames from a prepared folder, sequences in order; when the
    folder holds fewer frames, it is replayed from the start (a scene cut, as at any
    sequence boundary)."""
    from e3dpsm.data.prepared import PreparedData

    data = PreparedData.open(data_dir)
    sequences = data.split(split) if split else data.sequences
    if not sequences or sum(s.frames for s in sequences) == 0:
        raise DataError(f"{data_dir} holds no frames{f' in split {split!r}' if split else ''}")

    def all_frames() -> Iterator[np.ndarray]:
        for seq in sequences:
            for i in range(seq.frames):
                yield np.asarray(seq.lnes[i], dtype=np.float32)

    return itertools.islice(itertools.chain.from_iterable(all_frames() for _ in itertools.count()), steps)


def synthetic_frames(
    steps: int, window_ms: float, height: int = 192, width: int = 256, seed: int = 0, max_seconds: float = 8.0
) -> Iterator[np.ndarray]:
    """Frames from one synthetic egocentric sequence made on the fly (no data folder needed);
    at most `max_seconds` are generated and replayed if `steps` asks for more."""
    from e3dpsm.data.synth.generator import SynthConfig, generate_sequence
    from e3dpsm.events import events_to_lnes, window_bounds

    window_us = int(round(window_ms * 1000))
    seconds = min(max_seconds, steps * window_ms / 1000.0 + 2 * window_ms / 1000.0)
    seq, _ = generate_sequence(SynthConfig(seed=seed, seconds=seconds), 0)
    ev = seq.events
    starts, ranges = window_bounds(ev.t_us, window_us)
    frames = [
        events_to_lnes(ev.x[a:b], ev.y[a:b], ev.t_us[a:b], ev.p[a:b], t0, window_us, height, width, ev.sensor_hw)
        for t0, (a, b) in zip(starts, ranges)
    ]
    if not frames:
        raise DataError("the synthetic sequence produced no complete window")
    return itertools.islice(itertools.cycle(frames), steps)
