"""What `load_golden` checks before a golden record is used: every manifest field the check reads
has its type, and every array the shape the manifest implies, so that a damaged or hand-edited
record is one DataError line naming the first thing wrong instead of an IndexError deep in
`golden check` (the fuzz tests found a deleted state name, a damaged CRC, ...).

The layout (e3dpsm/golden/store.py): N steps of frames of `frame_shape` (size values each),
S snapshot steps, J joints, and per state a shape [batch, *dims] with K sampled elements.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.errors import DataError, InputError
from e3dpsm.golden.tolerances import ToleranceProfile

FIX = "record the golden again"
# popcount of every byte value: non-zero values a packed mask row marks
BITS_SET = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1)


def _positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _finite_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_manifest(manifest: Any, path: Path) -> None:
    """The fields `golden check` reads: steps, frame_shape, outputs, joints, states, source,
    tolerances, mpjpe_scale_mm."""
    def bad(field: str, expected: str) -> DataError:
        shown = repr(manifest.get(field))[:60]
        return DataError(f"{path}: '{field}' is {shown}, expected {expected}; {FIX}")

    if not isinstance(manifest, dict):
        raise DataError(f"{path}: expected a JSON object, got {type(manifest).__name__}; {FIX}")
    if not _positive_int(manifest.get("steps")):
        raise bad("steps", "a positive whole number")
    frame = manifest.get("frame_shape")
    if not isinstance(frame, list) or not frame or not all(_positive_int(d) for d in frame):
        raise bad("frame_shape", "a list of positive whole numbers")
    for field in ("outputs", "joints"):
        names = manifest.get(field)
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names) or \
                len(set(names)) != len(names):
            raise bad(field, "a list of distinct names")
    states = manifest.get("states")
    if not isinstance(states, list) or not all(
            isinstance(s, dict) and isinstance(s.get("name"), str) and isinstance(s.get("shape"), list)
            and len(s["shape"]) >= 1 and all(_positive_int(d) for d in s["shape"][1:]) for s in states) or \
            len({s["name"] for s in states}) != len(states):
        raise bad("states", "a list of {name, shape: [batch, dims...]} with distinct names")
    if not isinstance(manifest.get("source"), dict):
        raise bad("source", "an object naming the variant")
    scale = manifest.get("mpjpe_scale_mm")
    if scale is not None and not (_finite_number(scale) and scale > 0):
        raise bad("mpjpe_scale_mm", "a positive number or null")
    _check_tolerances(manifest.get("tolerances", {}), path)
    _check_host_rollouts(manifest.get("host_rollouts", []), path)


# golden record --also writes host/<graph stem>-<runtime>.npz: nothing else is read.
_HOST_FILE = re.compile(r"host/[A-Za-z0-9_.+-]+\.npz")


def _check_host_rollouts(entries: Any, path: Path) -> None:
    fields = ("file", "sha256", "runtime")
    if not isinstance(entries, list) or not all(
            isinstance(e, dict) and all(isinstance(e.get(k), str) for k in fields)
            and _HOST_FILE.fullmatch(e["file"]) for e in entries):
        raise DataError(f"{path}: 'host_rollouts' must list {{file: host/NAME.npz, sha256, runtime}} objects; {FIX}")


def _check_tolerances(tolerances: Any, path: Path) -> None:
    if not isinstance(tolerances, dict) or not all(isinstance(e, dict) for e in tolerances.values()):
        raise DataError(f"{path}: 'tolerances' must map profile names to objects; {FIX}")
    for name, entry in tolerances.items():
        try:
            profile = ToleranceProfile.from_dict(entry)
        except InputError as exc:
            raise DataError(f"{path}: tolerance profile {name!r}: {exc}; {FIX}") from exc
        numbers = (profile.pose_atol_mm, profile.state_rtol, profile.max_growth, profile.growth_floor)
        if profile.kind not in ("exact", "budget") or (profile.kind == "exact" and profile.pose_atol_mm is None) or \
                not all(v is None or (_finite_number(v) and v >= 0) for v in numbers):
            raise DataError(f"{path}: tolerance profile {name!r} is broken ({entry}); {FIX}")


def check_arrays(manifest: dict[str, Any], arrays: dict[str, np.ndarray], path: Path) -> None:
    """Every array has the shape (and kind) the manifest implies; the packed masks agree with
    the non-zero counts; indices stay inside their states and steps."""
    steps, size = manifest["steps"], math.prod(manifest["frame_shape"])
    snapshots = arrays["snapshot_steps"]
    joints = len(manifest["joints"])
    expected: dict[str, tuple[tuple[int, ...], str]] = {
        "lnes.mask": ((steps, -(-size // 8)), "u"), "lnes.nnz": ((steps,), "iu"),
        "window_ms": ((steps,), "f"), "snapshot_steps": ((len(snapshots),), "iu"),
        **{f"out.{n}": ((steps, joints, 3), "f") for n in manifest["outputs"]},
    }
    if "gt_mm" in arrays:
        expected["gt_mm"] = ((steps, joints, 3), "f")
    for state in manifest["states"]:
        dims, name = tuple(state["shape"][1:]), state["name"]
        samples = len(arrays.get(f"state_index.{name}", ()))
        expected.update({f"state_absmax.{name}": ((steps,), "f"), f"state_index.{name}": ((samples,), "iu"),
                         f"state_sample.{name}": ((steps, samples), "f"),
                         f"snapshot.{name}": ((len(snapshots), *dims), "f")})
    for key, (shape, kinds) in expected.items():
        array = arrays[key]
        if array.shape != shape or array.dtype.kind not in kinds:
            raise DataError(f"{path}: array {key} is {array.dtype} {list(array.shape)}, the manifest implies "
                            f"{list(shape)}; {FIX}")
    _check_frames(arrays, steps, size, path)
    if not np.all(np.isfinite(arrays["window_ms"])) or np.any(arrays["window_ms"] <= 0):
        raise DataError(f"{path}: window_ms holds values that are not positive numbers; {FIX}")
    if len(snapshots) and (np.any(np.diff(snapshots) <= 0) or snapshots[0] < 0 or snapshots[-1] >= steps):
        raise DataError(f"{path}: snapshot_steps {snapshots.tolist()[:8]} are not increasing steps of 0..{steps - 1}; "
                        f"{FIX}")
    for state in manifest["states"]:
        index, elements = arrays[f"state_index.{state['name']}"], math.prod(state["shape"][1:])
        if len(index) and (index.min() < 0 or index.max() >= elements):
            raise DataError(f"{path}: state_index.{state['name']} points outside its {elements} elements; {FIX}")


def _check_frames(arrays: dict[str, np.ndarray], steps: int, size: int, path: Path) -> None:
    """Each frame's packed mask marks as many values as its count says, and the counts add up
    to the values stored (what GoldenRecord.frame relies on)."""
    mask, nnz = arrays["lnes.mask"], arrays["lnes.nnz"]
    marked = BITS_SET[mask].sum(axis=1)
    spare = mask.shape[1] * 8 - size  # pad bits of the last byte, always 0 as written
    pad_set = BITS_SET[mask[:, -1] & ((1 << spare) - 1)] if spare else np.zeros(steps, np.int64)
    if np.any(pad_set) or np.any(marked != nnz):
        step = int(np.flatnonzero(pad_set | (marked != nnz))[0])
        raise DataError(f"{path}: frame {step}'s mask marks {int(marked[step])} values, lnes.nnz says "
                        f"{int(nnz[step])}; "
                        f"{FIX}")
    values = arrays["lnes.values"]
    if values.ndim != 1 or values.dtype.kind != "f":
        raise DataError(f"{path}: array lnes.values is {values.dtype} {list(values.shape)}, expected float values; "
                        f"{FIX}")
    if int(nnz.sum()) != len(values):
        raise DataError(f"{path}: lnes.nnz adds up to {int(nnz.sum())} values, {len(arrays['lnes.values'])} are "
                        f"stored; {FIX}")
