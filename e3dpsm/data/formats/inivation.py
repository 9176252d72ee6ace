"""iniVation AEDAT4 recordings, read with iniVation's own `dv-processing` (pip extra `cameras`).

dv-processing is the library DV software and DV cameras are built on, and the same package
gives the live network stream (e3dpsm/data/live.py) and the writer the tests use, so one
dependency covers files, streams and fixtures. Timestamps are kept as written: int64
microseconds since the Unix epoch (the runtime windows from the first event). Sensor size:
the event stream's resolution in the file's stream info.

dv-processing reports damage without a position ("FileDataTable set but not present"), so on
failure the file is walked packet by packet (AEDAT 4.0 layout: the 14-byte "#!AER-DAT4.0\\r\\n"
magic, an int32-sized IO header, then packets of int32 stream id + int32 size + payload) to
name the byte where it breaks.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from e3dpsm.data.formats import require
from e3dpsm.errors import DataError

MAGIC = b"#!AER-DAT4.0\r\n"


def read_aedat4(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    """Events of the (first) event stream of an AEDAT4 file, and the sensor (height, width)."""
    path = Path(path)
    dv = require("dv_processing", "reading AEDAT4")
    batches, hw = [], None
    try:
        recording = dv.io.MonoCameraRecording(str(path))
        if not recording.isEventStreamAvailable():
            raise DataError(f"{path}: the AEDAT4 file has no event stream (streams: {recording.getStreamNames()})")
        resolution = recording.getEventResolution()
        hw = None if resolution is None else (int(resolution[1]), int(resolution[0]))
        while (batch := recording.getNextEventBatch()) is not None:
            batches.append(batch.numpy())
    except RuntimeError as exc:  # dv-processing raises RuntimeError with a C++ stack trace
        raise DataError(f"{path}: {damage(path, str(exc).splitlines()[0])}") from exc
    if not batches:
        return {k: np.zeros(0, np.int64) for k in "xytp"}, hw
    events = np.concatenate(batches)
    return {
        "x": events["x"].astype(np.int32), "y": events["y"].astype(np.int32),
        "t": events["timestamp"].astype(np.int64), "p": events["polarity"].astype(np.uint8),
    }, hw


def damage(path: Path, library_message: str) -> str:
    """Where an AEDAT4 file breaks, by walking its packet headers."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        data = fh.read()
    if not data.startswith(MAGIC):
        return f"not an AEDAT4 file: no {MAGIC!r} at byte 0"
    pos = len(MAGIC)
    if pos + 4 > size:
        return f"truncated: the IO header size at byte {pos} is missing (file ends at byte {size})"
    (header_size,) = struct.unpack_from("<i", data, pos)
    if header_size <= 0 or pos + 4 + header_size > size:
        return f"truncated or corrupted IO header at byte {pos} (declares {header_size} bytes, file ends at byte {size})"
    pos += 4 + header_size
    while pos + 8 <= size:
        stream_id, packet_size = struct.unpack_from("<ii", data, pos)
        if stream_id < 0 or packet_size <= 0 or pos + 8 + packet_size > size:
            break
        pos += 8 + packet_size
    if pos + 8 > size or pos + 8 + struct.unpack_from("<ii", data, pos)[1] > size:
        return (f"truncated or corrupted at byte {pos}: the packet there runs past the end of the file at byte {size} "
                f"(dv-processing: {library_message})")
    return f"corrupted after byte {pos} (dv-processing: {library_message})"
