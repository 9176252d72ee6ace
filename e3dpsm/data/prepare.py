"""Cut sequences into T-ms windows, build one LNES frame per window, align ground truth to
the window ends, and write the prepared cache (layout in `e3dpsm.data.prepared`).

Windows: a regular grid of period T whose ends start at the sequence's first pose,
    window k = [t_pose[0] + (k - 1) T, t_pose[0] + k T),   k = 0 .. K-1,
with the last end at or before the last pose (`e3dpsm.events.window_bounds` is the one
definition of the grid, shared with the streaming runtime). The model predicts the pose at
the end of each window, so ground truth is taken at the window END. When poses are sampled
every T (synthetic data at T = 20 ms) the ends coincide with the pose times and the ground
truth is copied exactly; otherwise (EE3D's own pose clock, or T = 40 / 50 ms) it is
resampled to the ends: linear interpolation of j3d and j2d between the two poses around
each end, nearest pose for visibility and action (ties go to the later pose).
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.data import prepared
from e3dpsm.data.layout import detect_layout, list_sequences, read_sequence
from e3dpsm.data.sequence import Sequence
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.events import LNES_CHANNELS, events_to_lnes, window_bounds, window_us_from_ms
from e3dpsm.joints import JOINT_NAMES
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import atomic_dir, write_json_atomic

log = logging.getLogger(__name__)


def sequence_windows(seq: Sequence, window_us: int) -> tuple[np.ndarray, np.ndarray]:
    """(window ends int64[K], event index ranges int64[K, 2]) of the module-doc grid."""
    t_pose = np.asarray(seq.t_us, dtype=np.int64)
    starts, ranges = window_bounds(seq.events.t_us, window_us, int(t_pose[0]) - window_us, int(t_pose[-1]))
    return starts + window_us, ranges


def ground_truth_at(seq: Sequence, t_us: np.ndarray) -> dict[str, np.ndarray]:
    """Ground truth of `seq` at times `t_us` inside [t_pose[0], t_pose[-1]] (module doc)."""
    t_pose = np.asarray(seq.t_us, dtype=np.int64)
    if t_pose.size == 1:
        below, weight = np.zeros(len(t_us), np.intp), np.zeros(len(t_us))
        above = below
    else:
        below = np.clip(np.searchsorted(t_pose, t_us, side="right") - 1, 0, t_pose.size - 2)
        above = below + 1
        weight = (t_us - t_pose[below]) / (t_pose[above] - t_pose[below])  # 0 or 1 on a pose: exact copy
    nearest = np.where(weight >= 0.5, above, below)

    def lerp(a: np.ndarray) -> np.ndarray:
        w = weight.reshape(-1, *([1] * (a.ndim - 1)))
        return ((1.0 - w) * a[below] + w * a[above]).astype(np.float32)

    return {
        "j3d_m": lerp(np.asarray(seq.j3d_m, np.float64)),
        "j2d_px": lerp(np.asarray(seq.j2d_px, np.float64)),
        "visible": np.asarray(seq.visible, np.uint8)[nearest],
        "action": np.asarray(seq.action, np.int16)[nearest],
    }


def prepare_sequence(
    seq: Sequence, folder: Path, window_us: int, height: int, width: int, progress: bool = True
) -> dict[str, Any]:
    """Write `folder/lnes.npy` and `folder/pose.npz` for one sequence; return its counts."""
    from tqdm import tqdm

    ends, ranges = sequence_windows(seq, window_us)
    gt = ground_truth_at(seq, ends)
    sensor_h, sensor_w = seq.events.sensor_hw
    folder.mkdir(parents=True)
    np.savez(
        folder / prepared.POSE_FILE,
        j3d_mm=gt["j3d_m"] * np.float32(1000.0),
        j2d_px=gt["j2d_px"] * np.array([width / sensor_w, height / sensor_h], np.float32),  # as the events
        visible=gt["visible"], action=gt["action"], t_us=ends.astype(np.int64),
    )
    lnes = np.lib.format.open_memmap(
        folder / prepared.LNES_FILE, mode="w+", dtype=prepared.LNES_DTYPE,
        shape=(len(ends), LNES_CHANNELS, height, width),
    )
    ev = seq.events
    for k, (lo, hi) in enumerate(tqdm(ranges.tolist(), desc=seq.name, unit="win", leave=False, disable=not progress)):
        lnes[k] = events_to_lnes(
            ev.x[lo:hi], ev.y[lo:hi], ev.t_us[lo:hi], ev.p[lo:hi], int(ends[k]) - window_us, window_us,
            height, width, ev.sensor_hw,
        )
    lnes.flush()
    del lnes
    counts = ranges[:, 1] - ranges[:, 0]
    return {
        "frames": int(len(ends)),
        "poses": int(len(seq.t_us)),
        "ground_truth": "copied" if np.array_equal(ends, seq.t_us) else "resampled",
        "events": int(len(ev)),
        "events_in_windows": int(counts.sum()),
        "empty_windows": int(np.count_nonzero(counts == 0)),
        "sensor_hw": [int(sensor_h), int(sensor_w)],
        "_counts": counts,
    }


_PrepareJob = tuple[Path, str, Path, int, int, int]  # sequence folder, layout, output folder, T, H, W


def _prepare_one(job: _PrepareJob, progress: bool) -> tuple[dict[str, Any], tuple[str, ...]]:
    folder, source, target, window_us, height, width = job
    seq = read_sequence(folder, source)
    return prepare_sequence(seq, target, window_us, height, width, progress), tuple(seq.action_names)


def _prepare_all(jobs: list[_PrepareJob], workers: int, progress: bool):
    """Each job's (stats, action names), in the jobs' order: in this process, or one
    sequence per worker process (the first failure is raised once the pool has stopped)."""
    if workers == 1 or len(jobs) < 2:
        for job in jobs:
            yield _prepare_one(job, progress)
        return
    import concurrent.futures as cf

    from threadpoolctl import threadpool_limits

    # One BLAS thread per worker: the workers already fill the cores (as `synth` does).
    with threadpool_limits(limits=1, user_api="blas"), \
            cf.ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
        futures = [pool.submit(_prepare_one, job, False) for job in jobs]
        try:
            results = [future.result() for future in futures]
        except BaseException:
            for future in futures:
                future.cancel()
            raise
    yield from results


def prepare_dataset(
    data: str | os.PathLike,
    out: str | os.PathLike,
    window_ms: float = 20.0,
    height: int = 192,
    width: int = 256,
    *,
    force: bool = False,
    progress: bool = True,
    workers: int = 1,
) -> dict[str, Any]:
    """Prepare every sequence of the data set at `data` into `out`; return the report dict.

    The whole output is built under a temporary name and renamed at the end, so a failure
    (e.g. a corrupt sequence) leaves no partial folder; an existing `out` needs `force`.
    `workers` > 1 prepares that many sequences at once, one per process; the output is the
    same frames and poses (each sequence's files depend on that sequence alone).
    """
    window_us = window_us_from_ms(window_ms)
    if height < 1 or width < 1:
        raise ConfigError(f"--height and --width must be positive, got {height} x {width}")
    if workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    started = time.perf_counter()
    source = detect_layout(data)
    listed = list_sequences(data)
    config = {"data": str(data), "window_ms": window_ms, "height": height, "width": width}
    entries: list[dict[str, Any]] = []
    all_counts: list[np.ndarray] = []
    sensor_hw: list[int] | None = None
    action_names: tuple[str, ...] | None = None
    with atomic_dir(out, force=force) as tmp:
        jobs = [(Path(data) / name, source, tmp / name, window_us, height, width) for name, _ in listed]
        for i, ((name, split), (stats, seq_actions)) in enumerate(zip(listed, _prepare_all(jobs, workers, progress)), 1):
            all_counts.append(stats.pop("_counts"))
            sensor_hw = sensor_hw or stats["sensor_hw"]
            action_names = action_names if action_names is not None else seq_actions
            if stats["sensor_hw"] != sensor_hw or seq_actions != action_names:
                raise DataError(f"{Path(data) / name}: sensor size or action names differ from the first sequence's")
            entries.append({"name": name, "split": split, **stats})
            log.info("[%d/%d] %s (%s): %d windows, %d empty", i, len(listed), name, split,
                     stats["frames"], stats["empty_windows"])
        counts = np.concatenate(all_counts)
        report = {
            **report_header("prepare", config),
            "source": source,
            "frames": int(counts.size),
            "events_per_window": {
                "mean": float(counts.mean()), "median": float(np.median(counts)),
                "p90": float(np.percentile(counts, 90)), "max": int(counts.max()),
            },
            "empty_windows": int(np.count_nonzero(counts == 0)),
            "seconds": round(time.perf_counter() - started, 3),
            "workers": workers,
            "sequences": entries,
        }
        meta = {
            **report_header("prepare", config),
            "format": prepared.PREPARED_FORMAT,
            "window_ms": window_us / 1000.0, "window_us": window_us, "height": height, "width": width,
            "sensor_hw": sensor_hw, "source": source, "joints": list(JOINT_NAMES),
            "action_names": list(action_names or ()),
            "units": {"j3d": "mm, fisheye camera frame", "j2d": f"pixels of the {height} x {width} LNES frame",
                      "t_us": "window end, microseconds"},
            "ground_truth_alignment": "window end; linear interpolation of joints, nearest pose for "
                                      "visibility and action where poses are not on the window grid",
            "sequences": [{"name": e["name"], "frames": e["frames"], "split": e["split"]} for e in entries],
        }
        write_json_atomic(tmp / prepared.REPORT_FILE, report)
        write_json_atomic(tmp / prepared.META_FILE, meta)
    return report
