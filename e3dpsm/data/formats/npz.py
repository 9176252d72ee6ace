"""Event arrays in .npz files (x, y, t, p), read by numpy without pickles and with bounded work.

`np.load(allow_pickle=False)` refuses object arrays (a pickle inside an .npy). Before an array
is read, its npy header is checked against the zip's own sizes: one dimension, a plain
numeric dtype, exactly as many bytes as the member declares uncompressed, and a member that
claims no more than deflate can expand (DEFLATE_MAX_RATIO). So the memory and time a file
costs stay proportional to its size, and a damaged header or size is named instead of
allocated. Damage that zip or zlib detect while reading comes back as one DataError line.
"""
from __future__ import annotations

import lzma
import math
import os
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npy

from e3dpsm.errors import DataError

KEYS = ("x", "y", "t", "p")
DEFLATE_MAX_RATIO = 1032  # deflate's limit: 258 bytes from a 2-bit code, at best
# what zipfile, zlib, lzma and numpy raise on a damaged archive (RuntimeError: "encrypted";
# TokenError: numpy tokenises an .npy header with unbalanced brackets and lets the error out)
READ_ERRORS = (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error, lzma.LZMAError, KeyError,
               NotImplementedError, RuntimeError, tokenize.TokenError, SyntaxError)


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The one-dimensional arrays x, y, t, p of an events .npz file, checked before they are read."""
    return load_arrays(path, KEYS, ndim=1)


def load_arrays(path: str | os.PathLike, keys: tuple[str, ...] | None = None, ndim: int | None = None,
                what: str = ".npz file") -> dict[str, np.ndarray]:
    """Arrays of an .npz (`keys`, default all), each checked against its zip member before it
    is read (module docstring); `ndim` fixes their number of dimensions. DataError names the
    file, as `what`, and the damage."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive:
            members = {info.filename.removesuffix(".npy"): info for info in archive.infolist()}
            missing = [k for k in keys if k not in members] if keys is not None else []
            if missing:
                raise DataError(f"{path}: missing arrays {missing}; expected {', '.join(keys)}")
            for key in keys if keys is not None else list(members):
                _check_member(archive, members[key], key, ndim, path)
        with np.load(path, allow_pickle=False) as archive:
            return {k: archive[k] for k in (keys if keys is not None else archive.files)}
    except DataError:
        raise
    except READ_ERRORS as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DataError(f"{path}: cannot read {what} (truncated or corrupted?): {reason}") from exc


def _check_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, key: str, ndim: int | None, path: Path) -> None:
    if info.compress_type != zipfile.ZIP_STORED and info.file_size > DEFLATE_MAX_RATIO * info.compress_size + 1024:
        raise DataError(f"{path}: array {key} claims {info.file_size} bytes from {info.compress_size} compressed; "
                        "more than deflate can expand (corrupted?)")
    with archive.open(info) as member:
        version = npy.read_magic(member)
        if version not in ((1, 0), (2, 0)):
            raise DataError(f"{path}: array {key} has .npy format version {version}; expected 1.0 or 2.0")
        read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, _, dtype = read_header(member)
        header_bytes = member.tell()
    if dtype.hasobject or dtype.kind not in "biuf":
        raise DataError(f"{path}: array {key} has dtype {dtype}; expected numbers (object arrays would be pickles)")
    if ndim is not None and len(shape) != ndim:
        dims = "one dimension" if ndim == 1 else f"{ndim} dimensions"
        raise DataError(f"{path}: array {key} has shape {shape}; expected {dims}")
    values = math.prod(shape)
    if header_bytes + values * dtype.itemsize != info.file_size:
        raise DataError(f"{path}: array {key} declares {values} values of {dtype} but its member holds "
                        f"{info.file_size - header_bytes} bytes of data (truncated or corrupted?)")
