"""Crash-safe file output: write to a temporary name beside the target, then rename.

A failed or interrupted command never leaves a half-written artifact under the final
name, because `os.replace` is atomic on one file system."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

from e3dpsm.errors import DataError, OutputExistsError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it to `path` on success.

    On any exception the temporary file is removed and the target is left untouched.
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.name}.", suffix=suffix or target.suffix or ".tmp", dir=target.parent
        )
    except OSError as exc:
        raise DataError(f"cannot write to {target.parent}: {exc.strerror or exc}") from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    return write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def write_benchmark_report(prefix: str | os.PathLike, report: dict[str, Any], markdown: str) -> Path:
    """PREFIX_<ISA kind>.json and .md (each atomically; folders made): a benchmark's report,
    named by the kind of CPU it ran on (report["isa"]["kind"]) so that hosts do not overwrite
    each other's figures; a PREFIX that already ends in _<kind> (a results file's name, passed
    back to rewrite it) is not suffixed twice. Returns the .md path."""
    prefix, suffix = Path(prefix), f"_{report['isa']['kind']}"
    stem = prefix if prefix.name.endswith(suffix) else prefix.with_name(prefix.name + suffix)
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(stem.with_name(stem.name + ".json"), report)
    return write_text_atomic(stem.with_name(stem.name + ".md"), markdown)


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def refuse_existing_output(path: str | os.PathLike, force: bool) -> Path:
    """`path` as a Path; an existing one is refused unless `force`. Commands call it before
    a long run as well, so that the refusal comes first, not after the work."""
    target = Path(path)
    if target.exists() and not force:
        raise OutputExistsError(f"output folder {target} exists; pass --force to replace it")
    return target


def check_writable_folder(folder: str | os.PathLike) -> None:
    """The nearest existing ancestor of `folder` must be a writable directory; commands call it
    before minutes of work, so that an output they cannot write fails first, not last."""
    probe = Path(folder).absolute()
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise DataError(f"cannot write to {folder}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise DataError(f"cannot write to {folder}: {probe} is not writable")


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, force: bool = False) -> Iterator[Path]:
    """Build an output folder under a temporary name and rename it into place at the end.

    An existing folder is refused unless `force`, in which case it is replaced only once the
    new one is complete.
    """
    target = refuse_existing_output(path, force)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    except OSError as exc:
        raise DataError(f"cannot write to {target.parent}: {exc.strerror or exc}") from exc
    try:
        yield tmp
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
