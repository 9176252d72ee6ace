"""Reader of the public EE3D-R / EE3D-W sequence layout (docs/model.md#citations, Dataset layout).

Sequence folder::

    events.h5                     dataset `event` (N, 5..6): x, y, t_us, p, frame_index[, seg]
    event_meta.json               {"height": 480, "width": 640}
    synced_local_pose_gt.pickle   list per frame of dicts with `ego_j3d` (16x3, metres), `ego_j2d`
    valid_joints/<frame>.json     16 visibility flags (1 = visible)

Conventions applied here, once:
- j3d is rotated by 180 degrees about the x axis, (x, y, z) -> (x, -y, -z), as the public
  EE3D loader does; after it the joints are in the camera frame used everywhere else.
- A pose is timed at the most recent event of its frame index (the paper supervises "the
  ground-truth 3D pose at the most recent event in each window"), plus 1 us so that the
  half-open window [t - T, t) ending at the pose contains that event.
- Frames with no events cannot be timed and are dropped (counted in `meta`); a missing
  valid_joints file means all 16 joints are visible (counted too). EE3D gives actions by
  frame ranges that are not part of this layout, so `action` is -1 (unknown).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.data.readers import read_events_with_frames
from e3dpsm.data.safe_pickle import safe_load_pickle
from e3dpsm.data.sequence import Sequence
from e3dpsm.errors import DataError
from e3dpsm.joints import ACTIONS, NUM_JOINTS

GT_FILE = "synced_local_pose_gt.pickle"
VALID_JOINTS_DIR = "valid_joints"
ROTATE_X_180 = np.array([1.0, -1.0, -1.0], dtype=np.float32)  # diag of R_x(pi)


def read_ee3d_sequence(folder: str | os.PathLike) -> Sequence:
    """Read one EE3D sequence folder into a `Sequence` (see the module doc for conventions)."""
    folder = Path(folder)
    events, frame_index = read_events_with_frames(folder / "events.h5")
    if frame_index is None:
        raise DataError(f"{folder / 'events.h5'}: the EE3D 'event' dataset needs a 5th column, frame_index")
    j3d, j2d = _read_poses(folder / GT_FILE)
    frames = j3d.shape[0]
    visible, missing_visibility = _read_visibility(folder / VALID_JOINTS_DIR, frames)

    t_pose, timed = _frame_times(events.t_us, frame_index, frames)
    kept = np.flatnonzero(timed)
    if kept.size == 0:
        raise DataError(f"{folder}: no event carries a frame_index of the {frames} poses")
    t_kept = t_pose[kept] + 1  # the window ending at the pose includes its last event
    if np.any(np.diff(t_kept) <= 0):
        bad = int(kept[np.flatnonzero(np.diff(t_kept) <= 0)[0] + 1])
        raise DataError(f"{folder}: frame {bad} ends no later than the frame before it; frame_index is not in time order")
    return Sequence(
        name=folder.name,
        events=events,
        j3d_m=(j3d[kept] * ROTATE_X_180).astype(np.float32),
        j2d_px=j2d[kept],
        visible=visible[kept],
        t_us=t_kept.astype(np.int64),
        action=np.full(kept.size, -1, dtype=np.int16),
        action_names=ACTIONS,
        meta={
            "layout": "ee3d",
            "source_frames": kept.astype(np.int64),
            "dropped_frames_without_events": int(frames - kept.size),
            "frames_without_visibility_file": missing_visibility,
        },
    )


def _read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    entries: Any = safe_load_pickle(path)
    if isinstance(entries, dict):  # tolerate {frame: entry}
        entries = [entries[k] for k in sorted(entries)]
    if not isinstance(entries, (list, tuple)) or not entries:
        raise DataError(f"{path}: expected a non-empty list with one pose dict per frame, got {type(entries).__name__}")
    j3d = np.empty((len(entries), NUM_JOINTS, 3), dtype=np.float32)
    j2d = np.empty((len(entries), NUM_JOINTS, 2), dtype=np.float32)
    for f, entry in enumerate(entries):
        try:
            j3d[f] = np.asarray(entry["ego_j3d"], dtype=np.float32).reshape(NUM_JOINTS, 3)
            j2d[f] = np.asarray(entry["ego_j2d"], dtype=np.float32).reshape(NUM_JOINTS, -1)[:, :2]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(
                f"{path}: frame {f} needs 'ego_j3d' (16 x 3) and 'ego_j2d' (16 x 2): {type(exc).__name__}: {exc}"
            ) from exc
    if not (np.isfinite(j3d).all() and np.isfinite(j2d).all()):
        raise DataError(f"{path}: joints contain NaN or inf")
    return j3d, j2d


def _read_visibility(folder: Path, frames: int) -> tuple[np.ndarray, int]:
    visible = np.ones((frames, NUM_JOINTS), dtype=np.uint8)
    if not folder.is_dir():
        return visible, frames
    files: dict[int, Path] = {}
    for path in folder.glob("*.json"):
        try:
            files[int(path.stem)] = path  # "12.json" and "000012.json" both name frame 12
        except ValueError:
            continue
    for f, path in files.items():
        if not 0 <= f < frames:
            continue
        try:
            flags = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(flags, dict) and len(flags) == 1:  # {"valid_joints": [...]}
                flags = next(iter(flags.values()))
            visible[f] = np.asarray(flags, dtype=np.float64).reshape(NUM_JOINTS) > 0
        except (OSError, ValueError, TypeError) as exc:
            raise DataError(f"{path}: expected a list of {NUM_JOINTS} visibility flags: {exc}") from exc
    return visible, frames - sum(1 for f in files if 0 <= f < frames)


def _frame_times(t_us: np.ndarray, frame_index: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Time of the last event of each frame index, and which frames have events at all."""
    ok = (frame_index >= 0) & (frame_index < frames)
    times = np.full(frames, np.iinfo(np.int64).min, dtype=np.int64)
    np.maximum.at(times, frame_index[ok], t_us[ok])
    return times, np.bincount(frame_index[ok], minlength=frames) > 0
