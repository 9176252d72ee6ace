"""Loading pickles without running code: the EE3D ground truth ships as Python pickles.

A pickle names the callables that rebuild its objects; the stock unpickler imports and
calls whatever is named, so a crafted file runs arbitrary code. `SafeUnpickler` admits only
the globals that plain containers and numpy arrays need, and refuses everything else before
it is imported.
"""
from __future__ import annotations

import _compat_pickle
import io
import os
import pickle
from pathlib import Path
from typing import Any

from e3dpsm.errors import DataError

# Globals a pickle of plain data can reference. Containers and numbers mostly pickle as
# opcodes; these cover the rest (sets, ordered dicts, bytes in protocol-2 pickles).
_BUILTINS = {
    ("builtins", name)
    for name in ("dict", "list", "tuple", "set", "frozenset", "str", "bytes", "bytearray",
                 "int", "float", "complex", "bool", "slice", "range")
} | {("collections", "OrderedDict"), ("_codecs", "encode")}

# numpy's reconstructors of arrays, scalars and dtypes. numpy 2 moved numpy.core to
# numpy._core; pickles written by either version name their own module.
_NUMPY = {
    (module, name)
    for module in ("numpy.core.multiarray", "numpy._core.multiarray")
    for name in ("_reconstruct", "scalar")
} | {
    (module, "_frombuffer") for module in ("numpy.core.numeric", "numpy._core.numeric")
} | {("numpy", "ndarray"), ("numpy", "dtype")}

_ALLOWED = _BUILTINS | _NUMPY


class RefusedGlobal(pickle.UnpicklingError):
    """The pickle names a callable outside the allow-list."""


class SafeUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the globals in the allow-list."""

    def find_class(self, module: str, name: str) -> Any:
        # Protocol 0-2 pickles name Python 2 modules (__builtin__.set); translate them first,
        # as the stock find_class would.
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        if (module, name) not in _ALLOWED:
            raise RefusedGlobal(f"refusing to unpickle {module}.{name}")
        if module.startswith("numpy.core."):  # old name; numpy 2 warns on import
            import numpy

            if hasattr(numpy, "_core"):
                module = "numpy._core." + module.split(".", 2)[2]
        return super().find_class(module, name)


def safe_loads(data: bytes, *, source: str = "<bytes>") -> Any:
    """Unpickle `data` with `SafeUnpickler`; any refusal or corruption is a `DataError`."""
    try:
        return SafeUnpickler(io.BytesIO(data)).load()
    except RefusedGlobal as exc:
        raise DataError(f"{source}: {exc}") from exc
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
            ImportError) as exc:
        raise DataError(f"{source}: corrupted pickle ({type(exc).__name__}: {exc})") from exc


def safe_load_pickle(path: str | os.PathLike) -> Any:
    """Load a pickle file admitting only plain containers and numpy arrays."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return safe_loads(data, source=str(path))
