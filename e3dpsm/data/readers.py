"""Reading and writing raw event streams: HDF5 (EE3D layout), .npz and camera recordings.

HDF5 files hold either one dataset `event` of shape (N, >=4) with columns
x, y, t (microseconds), p[, frame_index, ...] — the EE3D layout — or separate datasets
`x`, `y`, `t`, `p`. `.npz` files hold arrays `x`, `y`, `t`, `p`. Camera recordings
(AEDAT4, Prophesee RAW EVT 2.0 / 3.0, DAT) are decoded by `e3dpsm.data.formats`; `READERS`
maps a suffix to its reader. Every stream passes through `validate_events`, so readers
return canonical dtypes or raise.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from e3dpsm.data.sequence import SENSOR_HW, EventStream
from e3dpsm.errors import DataError, InputError
from e3dpsm.events import validate_events
from e3dpsm.utils.io import atomic_path

EVENT_DATASET = "event"
EVENT_COLUMNS = ("x", "y", "t", "p", "frame_index")
HDF5_SUFFIXES = (".h5", ".hdf5")
NO_FRAME = -1  # frame_index written when a stream carries no pose frames


def read_events(path: str | os.PathLike, sensor_hw: tuple[int, int] | None = None) -> EventStream:
    """Read and validate an event stream from any suffix in `READERS`.

    `sensor_hw` (height, width) defaults to the size the file states (HDF5
    `sensor_height`/`sensor_width` attributes, AEDAT4 stream resolution, RAW `% format` or
    `% geometry`, DAT `% Width`/`% Height`), else an `event_meta.json` beside the file, else
    the EE3D sensor 480 x 640.
    """
    return read_events_with_frames(path, sensor_hw)[0]


def read_events_with_frames(
    path: str | os.PathLike, sensor_hw: tuple[int, int] | None = None
) -> tuple[EventStream, np.ndarray | None]:
    """Like `read_events`, also returning the EE3D frame_index column (None if absent).

    HDF5 files are read, and validated, in a separate process with a deadline
    (e3dpsm/utils/isolate.py): the HDF5 C library segfaulted on a file with one byte changed in
    a compressed chunk. Validating there too means only the canonical columns travel back."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"event file {path} does not exist")
    if path.suffix.lower() not in READERS:
        raise DataError(f"{path}: unsupported event file type {path.suffix!r}; expected one of {', '.join(READERS)}")
    if path.suffix.lower() in HDF5_SUFFIXES:
        from e3dpsm.utils.isolate import deadline_for, run_isolated

        got = run_isolated("e3dpsm.data.readers:read_validated_columns", str(path), json.dumps(sensor_hw),
                           deadline_s=deadline_for(path.stat().st_size), what=str(path), preload=("h5py",))
    else:
        got = read_validated_columns(path, sensor_hw)
    stream = EventStream(x=got["x"], y=got["y"], t_us=got["t"], p=got["p"], sensor_hw=tuple(got["sensor_hw"]))
    return stream, got.get("frame_index")


def read_validated_columns(path: str | os.PathLike, sensor_hw: tuple[int, int] | str | None = None) -> dict:
    """The columns `read_events_with_frames` returns (x, y, t, p, frame_index if present, sensor_hw),
    read and validated in this process. `sensor_hw` may come JSON-encoded (from another process)."""
    path = Path(path)
    if isinstance(sensor_hw, str):
        sensor_hw = json.loads(sensor_hw)
    try:
        columns, file_hw = READERS[path.suffix.lower()](path)
    except MemoryError as exc:
        raise DataError(f"{path}: too large to read into memory") from exc
    hw = sensor_hw or file_hw or _meta_json_hw(path.parent / "event_meta.json") or SENSOR_HW
    try:
        x, y, t, p = validate_events(columns["x"], columns["y"], columns["t"], columns["p"], hw)
    except InputError as exc:
        raise DataError(f"{path}: {exc}") from exc
    out = {"x": x, "y": y, "t": t, "p": p, "sensor_hw": [int(hw[0]), int(hw[1])]}
    if columns.get("frame_index") is not None:
        out["frame_index"] = np.asarray(columns["frame_index"], dtype=np.int64)
    return out


def _read_h5(path: Path) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    """HDF5 in this process: `read_events_with_frames` calls it in a separate one."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            hw = None
            if "sensor_height" in f.attrs and "sensor_width" in f.attrs:
                hw = (int(f.attrs["sensor_height"]), int(f.attrs["sensor_width"]))
            return _h5_columns(f, path), hw
    except DataError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:  # h5py reports damage as these
        raise DataError(f"{path}: cannot read HDF5 file (truncated or corrupted?): {exc}") from exc


def _h5_columns(f, path: Path) -> dict[str, np.ndarray]:
    if EVENT_DATASET in f:
        table = f[EVENT_DATASET][()]
        if table.ndim != 2 or table.shape[1] < 4:
            raise DataError(
                f"{path}: dataset '{EVENT_DATASET}' has shape {table.shape}; "
                "expected (N, >=4) with columns x, y, t, p[, frame_index]"
            )
        return {name: table[:, i] for i, name in enumerate(EVENT_COLUMNS[: table.shape[1]])}
    missing = [k for k in ("x", "y", "t", "p") if k not in f]
    if missing:
        raise DataError(
            f"{path}: no '{EVENT_DATASET}' dataset and missing datasets {missing}; "
            "expected 'event' (N, >=4) or separate 'x', 'y', 't', 'p'"
        )
    return {k: f[k][()] for k in ("x", "y", "t", "p")}


def _read_npz(path: Path) -> tuple[dict[str, np.ndarray], None]:
    from e3dpsm.data.formats.npz import read_npz

    return read_npz(path), None


def _read_aedat4(path: Path) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    from e3dpsm.data.formats.inivation import read_aedat4

    return read_aedat4(path)


def _read_raw(path: Path) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    from e3dpsm.data.formats.prophesee import read_raw

    return read_raw(path)


def _read_dat(path: Path) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    from e3dpsm.data.formats.prophesee import read_dat

    return read_dat(path)


Reader = Callable[[Path], "tuple[dict[str, np.ndarray], tuple[int, int] | None]"]
# suffix -> reader returning (raw columns x, y, t, p[, frame_index], sensor (h, w) the file states)
READERS: dict[str, Reader] = {
    ".h5": _read_h5, ".hdf5": _read_h5, ".npz": _read_npz,
    ".aedat4": _read_aedat4, ".raw": _read_raw, ".dat": _read_dat,
}
EVENT_SUFFIXES = tuple(READERS)


def _meta_json_hw(path: Path) -> tuple[int, int] | None:
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
        return int(meta["height"]), int(meta["width"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path}: expected JSON {{\"height\": H, \"width\": W}}: {exc}") from exc


def write_events_h5(
    path: str | os.PathLike, stream: EventStream, frame_index: np.ndarray | None = None
) -> Path:
    """Write `stream` as the EE3D `event` dataset, int64 (N, 5): x, y, t, p, frame_index.

    Written to a temporary file and renamed, so a failure leaves no partial file.
    `frame_index` defaults to -1 (no pose frame). Compressed with LZF + shuffle, which
    keeps reading fast while shrinking the mostly-small integers several-fold.
    """
    import h5py

    n = len(stream)
    table = np.empty((n, len(EVENT_COLUMNS)), dtype=np.int64)
    table[:, 0], table[:, 1], table[:, 2], table[:, 3] = stream.x, stream.y, stream.t_us, stream.p
    if frame_index is None:
        table[:, 4] = NO_FRAME
    else:
        frame_index = np.asarray(frame_index)
        if frame_index.shape != (n,):
            raise InputError(f"frame_index has shape {frame_index.shape}, expected ({n},)")
        table[:, 4] = frame_index
    with atomic_path(path, suffix=".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset(
                EVENT_DATASET, data=table, chunks=(min(max(n, 1), 65536), len(EVENT_COLUMNS)),
                compression="lzf", shuffle=True,
            )
            f[EVENT_DATASET].attrs["columns"] = ",".join(EVENT_COLUMNS)
            f.attrs["sensor_height"], f.attrs["sensor_width"] = stream.sensor_hw
    return Path(path)
