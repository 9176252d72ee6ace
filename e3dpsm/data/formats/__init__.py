"""Vendor event-file formats, one module per vendor (docs/cameras.md).

- `prophesee`: RAW (EVT 2.0, EVT 3.0) and DAT, decoded with numpy from Prophesee's public
  format specification (no dependency);
- `inivation`: AEDAT4 (and the dv:// network stream's packets), decoded in the project from
  iniVation's public format description, bounds-checked (`flatbuffer`); LZ4 and Zstd packets
  need `lz4` / `zstandard` (pip extra `cameras`).

Each reader returns `(columns, sensor_hw)`: a dict of raw arrays `x`, `y`, `t`, `p` and the
sensor size the file states (None when it states none). `e3dpsm.data.readers` holds the
suffix dispatch table and validates every stream the same way.
"""
from __future__ import annotations

import importlib
from types import ModuleType

from e3dpsm.errors import DataError

CAMERAS_EXTRA = 'pip install "e3dpsm[cameras]"'


def require(module: str, what: str) -> ModuleType:
    """Import an optional camera library, or fail with one line naming the pip extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DataError(f"{what} needs the {module!r} package, which is not installed: {CAMERAS_EXTRA}") from exc
