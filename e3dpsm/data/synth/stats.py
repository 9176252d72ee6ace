"""Realism figures of a synthetic data set, to compare with what the paper reports for
EE3D (its preprocessing groups about 8,000 events per 20 ms pose window)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from e3dpsm.data.sequence import Sequence
from e3dpsm.data.synth.generator import SequenceExtras
from e3dpsm.joints import JOINT_NAMES

WINDOW_US = 20_000


@dataclass
class SequenceStats:
    window_counts: np.ndarray  # events in each whole 20 ms window
    events: int
    body_events: int
    noise_events: int
    frames: int
    occluded_frames: np.ndarray  # [16]
    in_image_frames: np.ndarray  # [16]
    actions: list[str]


def sequence_stats(seq: Sequence, extras: SequenceExtras) -> SequenceStats:
    t = seq.events.t_us
    n_windows = int(seq.t_us[-1] // WINDOW_US)
    counts = np.bincount(t // WINDOW_US, minlength=n_windows)[:n_windows]
    return SequenceStats(
        window_counts=counts, events=len(seq.events), body_events=int(extras.is_body.sum()),
        noise_events=int(extras.is_noise.sum()), frames=int(seq.t_us.size),
        occluded_frames=extras.occluded.sum(0), in_image_frames=extras.in_image.sum(0),
        actions=sorted({seq.action_names[a] for a in np.unique(seq.action)}),
    )


def summarize(stats: list[SequenceStats]) -> dict:
    counts = np.concatenate([s.window_counts for s in stats])
    events = sum(s.events for s in stats)
    frames = sum(s.frames for s in stats)
    occluded = sum(s.occluded_frames for s in stats) / frames
    in_image = sum(s.in_image_frames for s in stats) / frames
    return {
        "events_per_20ms": {
            "mean": float(counts.mean()), "median": float(np.median(counts)),
            "p90": float(np.percentile(counts, 90)), "min": int(counts.min()), "max": int(counts.max()),
            "windows": int(counts.size),
        },
        "events_total": events,
        "background_share": 1.0 - sum(s.body_events for s in stats) / max(events, 1),
        "noise_share": sum(s.noise_events for s in stats) / max(events, 1),
        "occluded_fraction": {n: float(v) for n, v in zip(JOINT_NAMES, occluded)},
        "in_image_fraction": {n: float(v) for n, v in zip(JOINT_NAMES, in_image)},
        "joints_in_image": float(in_image.mean()),
        "visible_fraction": float((in_image - occluded).mean()),
        "actions": sorted({a for s in stats for a in s.actions}),
        "frames": frames,
    }
