"""On-disk data set layouts: the synthetic one (defined here, the single source of truth for
the generator that writes it and for `prepare` that reads it) and dispatch to EE3D.

Synthetic data set root::

    dataset.json            {"format": "e3dpsm-synthetic/1", "seed": ..., ...}
    train.txt val.txt test.txt   sequence folder names, one per line
    <sequence>/events.h5    EE3D `event` dataset int64 (N, 5): x, y, t_us, p, frame_index
                            (or a camera recording events.aedat4 / .raw / .dat on the clock of
                            gt.npz's t_us: docs/cameras.md)
    <sequence>/event_meta.json   {"height": 480, "width": 640}
    <sequence>/gt.npz       j3d_m float32 [F,16,3], j2d_px float32 [F,16,2] (sensor pixels),
                            visible uint8 [F,16], t_us int64 [F], action int16 [F],
                            action_names unicode [A]   (np.savez: no pickles)
    <sequence>/camera.json  fisheye calibration used to render the sequence

frame_index of an event is the pose it precedes: f such that t_(f-1) <= t < t_f, i.e. the
pose at the end of the window holding the event; -1 after the last pose. This matches the
EE3D convention read by `e3dpsm.data.ee3d` (a pose is timed by its frame's last event).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from e3dpsm.data.formats.npz import READ_ERRORS
from e3dpsm.data.readers import read_events_with_frames, write_events_h5
from e3dpsm.data.sequence import Sequence
from e3dpsm.errors import DataError, InputError
from e3dpsm.events import validate_events
from e3dpsm.joints import NUM_JOINTS
from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic

SYNTHETIC_FORMAT = "e3dpsm-synthetic/1"
SPLITS: tuple[str, ...] = ("train", "val", "test")
UNASSIGNED_SPLIT = "none"  # sequences present on disk but named by no split list
EVENTS_FILE = "events.h5"
# what a synthetic-layout sequence folder may hold its events in (one of them)
EVENT_FILES: tuple[str, ...] = (EVENTS_FILE, "events.aedat4", "events.raw", "events.dat")
EVENT_META_FILE = "event_meta.json"
GT_FILE = "gt.npz"
CAMERA_FILE = "camera.json"
DATASET_FILE = "dataset.json"
EE3D_GT_FILE = "synced_local_pose_gt.pickle"


def check_sequence(seq: Sequence) -> None:
    """Raise `InputError` unless the ground-truth arrays of `seq` agree in shape and time."""
    frames = int(np.shape(seq.t_us)[0]) if np.ndim(seq.t_us) == 1 else -1
    expected = {
        "j3d_m": (frames, NUM_JOINTS, 3), "j2d_px": (frames, NUM_JOINTS, 2),
        "visible": (frames, NUM_JOINTS), "action": (frames,),
    }
    if frames < 1:
        raise InputError(f"sequence {seq.name!r}: t_us must be a non-empty 1-D array, got shape {np.shape(seq.t_us)}")
    for name, shape in expected.items():
        if np.shape(getattr(seq, name)) != shape:
            raise InputError(f"sequence {seq.name!r}: {name} has shape {np.shape(getattr(seq, name))}, expected {shape}")
    if not np.isfinite(seq.j3d_m).all() or not np.isfinite(seq.j2d_px).all():
        raise InputError(f"sequence {seq.name!r}: joints contain NaN or inf")
    if frames > 1 and np.any(np.diff(np.asarray(seq.t_us, dtype=np.int64)) <= 0):
        raise InputError(f"sequence {seq.name!r}: pose timestamps t_us must be strictly increasing")
    _check_name(seq.name)


def _check_name(name: str) -> None:
    if not name or name in (".", "..") or "/" in name or "\\" in name or name != name.strip():
        raise InputError(f"sequence name {name!r} cannot be a folder name")


def pose_frame_index(t_events_us: np.ndarray, t_pose_us: np.ndarray) -> np.ndarray:
    """frame_index column: the pose each event precedes (see module doc), -1 after the last."""
    index = np.searchsorted(np.asarray(t_pose_us), t_events_us, side="right").astype(np.int64)
    index[index >= len(t_pose_us)] = -1
    return index


def write_synthetic_sequence(
    folder: str | os.PathLike, seq: Sequence, camera_json: Mapping[str, Any], *, force: bool = False
) -> Path:
    """Write one sequence folder of the synthetic layout (built under a temporary name)."""
    check_sequence(seq)
    ev = seq.events
    validate_events(ev.x, ev.y, ev.t_us, ev.p, ev.sensor_hw, repair_polarity=False)
    folder = Path(folder)
    with atomic_dir(folder, force=force) as tmp:
        write_events_h5(tmp / EVENTS_FILE, ev, pose_frame_index(ev.t_us, seq.t_us))
        write_json_atomic(tmp / EVENT_META_FILE, {"height": ev.sensor_hw[0], "width": ev.sensor_hw[1]})
        write_json_atomic(tmp / CAMERA_FILE, dict(camera_json))
        np.savez(
            tmp / GT_FILE,
            j3d_m=np.asarray(seq.j3d_m, np.float32), j2d_px=np.asarray(seq.j2d_px, np.float32),
            visible=np.asarray(seq.visible, np.uint8), t_us=np.asarray(seq.t_us, np.int64),
            action=np.asarray(seq.action, np.int16), action_names=np.array(seq.action_names, dtype=np.str_),
        )
    return folder


def read_synthetic_sequence(folder: str | os.PathLike) -> Sequence:
    """Read one synthetic-layout sequence folder; any damage is a `DataError` naming the file."""
    folder = Path(folder)
    events, _ = read_events_with_frames(events_file(folder))
    gt_path = folder / GT_FILE
    try:
        with np.load(gt_path, allow_pickle=False) as gt:
            arrays = {k: gt[k] for k in ("j3d_m", "j2d_px", "visible", "t_us", "action", "action_names")}
    except FileNotFoundError as exc:
        raise DataError(f"{gt_path} does not exist") from exc
    except READ_ERRORS as exc:  # what numpy, zipfile and zlib raise on a damaged archive
        raise DataError(f"{gt_path}: cannot read ground truth (truncated or corrupted?): {exc}") from exc
    camera = _read_json(folder / CAMERA_FILE) if (folder / CAMERA_FILE).is_file() else None
    seq = Sequence(
        name=folder.name, events=events,
        j3d_m=arrays["j3d_m"].astype(np.float32), j2d_px=arrays["j2d_px"].astype(np.float32),
        visible=arrays["visible"].astype(np.uint8), t_us=arrays["t_us"].astype(np.int64),
        action=arrays["action"].astype(np.int16),
        action_names=tuple(str(a) for a in arrays["action_names"].tolist()),
        meta={"layout": "synthetic", "camera": camera},
    )
    try:
        check_sequence(seq)
    except InputError as exc:
        raise DataError(f"{gt_path}: {exc}") from exc
    return seq


def write_dataset_index(root: str | os.PathLike, splits: Mapping[str, list[str]], info: Mapping[str, Any]) -> None:
    """Write the split lists and `dataset.json` of a synthetic data set root."""
    root = Path(root)
    unknown = set(splits) - set(SPLITS)
    if unknown:
        raise InputError(f"unknown split names {sorted(unknown)}; expected some of {list(SPLITS)}")
    for split in SPLITS:
        names = list(splits.get(split, []))
        for name in names:
            _check_name(name)
        write_text_atomic(root / f"{split}.txt", "".join(f"{n}\n" for n in names))
    write_json_atomic(root / DATASET_FILE, {"format": SYNTHETIC_FORMAT, **dict(info)})


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read JSON: {exc}") from exc


def events_file(folder: Path) -> Path:
    """The sequence folder's one event file among EVENT_FILES (events.h5 when none is there,
    so the error names the usual file)."""
    present = [folder / name for name in EVENT_FILES if (folder / name).is_file()]
    if len(present) > 1:
        raise DataError(f"{folder}: holds {', '.join(p.name for p in present)}; keep one event file per sequence")
    return present[0] if present else folder / EVENTS_FILE


def list_sequences(root: str | os.PathLike) -> list[tuple[str, str]]:
    """(name, split) of every sequence in a data set root, in split-list order.

    Names come from train.txt / val.txt / test.txt; folders holding `events.h5` that no list
    names are included with split "none". A name listed twice or without its folder is an error.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"data folder {root} does not exist")
    found: dict[str, str] = {}
    for split in SPLITS:
        path = root / f"{split}.txt"
        if not path.is_file():
            continue
        for line in path.read_text(encoding="utf-8").splitlines():
            name = line.strip().rstrip("/")
            if not name or name.startswith("#"):
                continue
            if name in found:
                raise DataError(f"{path}: sequence {name!r} is already listed in {found[name]}.txt")
            if not (root / name).is_dir():
                raise DataError(f"{path}: lists sequence {name!r}, but {root / name} is not a folder")
            found[name] = split
    for child in sorted(root.iterdir()):
        if child.is_dir() and child.name not in found and any((child / n).is_file() for n in EVENT_FILES):
            found[child.name] = UNASSIGNED_SPLIT
    if not found:
        raise DataError(f"{root} holds no sequences (no split lists, no folders with {EVENTS_FILE})")
    return list(found.items())


def detect_layout(root: str | os.PathLike) -> str:
    """"synthetic" or "ee3d", from dataset.json or the first sequence folder's files."""
    root = Path(root)
    if (root / DATASET_FILE).is_file():
        fmt = _read_json(root / DATASET_FILE).get("format")
        if fmt != SYNTHETIC_FORMAT:
            raise DataError(f"{root / DATASET_FILE}: format {fmt!r}, expected {SYNTHETIC_FORMAT!r}")
        return "synthetic"
    name = list_sequences(root)[0][0]
    if (root / name / GT_FILE).is_file():
        return "synthetic"
    if (root / name / EE3D_GT_FILE).is_file():
        return "ee3d"
    raise DataError(
        f"{root / name} has neither {GT_FILE} (synthetic layout) nor {EE3D_GT_FILE} (EE3D layout)"
    )


def read_sequence(folder: str | os.PathLike, layout: str) -> Sequence:
    if layout == "synthetic":
        return read_synthetic_sequence(folder)
    if layout == "ee3d":
        from e3dpsm.data.ee3d import read_ee3d_sequence

        return read_ee3d_sequence(folder)
    raise InputError(f"unknown layout {layout!r}; expected 'synthetic' or 'ee3d'")


def load_sequences(root: str | os.PathLike, split: str | None = None) -> Iterator[tuple[Sequence, str]]:
    """Yield (sequence, split) one at a time (sequences are large), optionally one split only."""
    layout = detect_layout(root)
    for name, seq_split in list_sequences(root):
        if split is None or seq_split == split:
            yield read_sequence(Path(root) / name, layout), seq_split


__all__ = [
    "SYNTHETIC_FORMAT", "SPLITS", "check_sequence", "pose_frame_index",
    "write_synthetic_sequence", "read_synthetic_sequence", "write_dataset_index",
    "list_sequences", "detect_layout", "read_sequence", "load_sequences",
]
