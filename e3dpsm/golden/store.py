"""The golden record on disk: a reference rollout a device can check a graph against.

    DIR/golden.json    manifest: format, steps, window, source (kind, file name, sha256),
                       data provenance, output and state layout, snapshot steps, the
                       tolerance profiles it was recorded for, versions and machine
    DIR/rollout.npz    numpy arrays (zip-deflated; read with allow_pickle=False):
      lnes.mask        uint8 [N, ceil(C*H*W / 8)]  packed non-zero mask of each frame
      lnes.values      float16 [sum nnz]           the non-zero values, frame after frame
      lnes.nnz         int64 [N]
      window_ms        float32 [N]
      gt_mm            float32 [N, J, 3]           ground truth of each frame (prepared data)
      out.<name>       float32 [N, J, 3]           every output at every step
      state_absmax.<s> float32 [N]                 max |state| at every step
      state_index.<s>  int64 [K]                   flat indices (one batch element) sampled
      state_sample.<s> float32 [N, K]              those elements at every step
      snapshot_steps   int64 [S]
      snapshot.<s>     float32 [S, *shape]         the whole state at the snapshot steps

Inputs are stored exactly: the prepared cache is float16, so its frames are kept as float16
values (sparse: LNES frames are a few per cent non-zero). States are what make a record big
(`small` carries 53,857 numbers per step, 215 MB over 1,000 steps): every step keeps K
sampled elements and the maximum magnitude of each state, and whole states are kept at the
snapshot steps (a 1-2-5 series by default, every step with `all_states=True`).
"""
from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from e3dpsm.errors import DataError
from e3dpsm.utils.io import atomic_dir, write_json_atomic

GOLDEN_FORMAT = "e3dpsm-golden/1"
MANIFEST_FILE = "golden.json"
ARRAYS_FILE = "rollout.npz"
STATE_SAMPLES = 32  # sampled elements per state and step; states this small or smaller are kept whole


def snapshot_steps(steps: int, every_step: bool = False) -> list[int]:
    """Steps whose whole state is kept: 0, 1, 2, 5, 10, 20, 50, ... and the last step."""
    if every_step:
        return list(range(steps))
    chosen, decade = set(), 1
    chosen.add(0)
    while decade < steps:
        chosen.update(m * decade for m in (1, 2, 5) if m * decade < steps)
        decade *= 10
    chosen.add(steps - 1)
    return sorted(chosen)


def sample_indices(name: str, size: int, count: int = STATE_SAMPLES) -> np.ndarray:
    """A fixed pseudo-random subset of a state's flat indices (seeded by the state's name)."""
    if size <= 2 * count:
        return np.arange(size, dtype=np.int64)
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    return np.sort(rng.choice(size, size=count, replace=False)).astype(np.int64)


@dataclass
class GoldenRecord:
    """A loaded (or recorded) golden rollout; frames are decoded one step at a time."""

    manifest: dict[str, Any]
    arrays: dict[str, np.ndarray]
    folder: Path | None = None  # where it was loaded from
    _offsets: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._offsets = np.concatenate([[0], np.cumsum(self.arrays["lnes.nnz"])]).astype(np.int64)

    @property
    def steps(self) -> int:
        return int(self.manifest["steps"])

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self.manifest["frame_shape"])

    @property
    def output_names(self) -> list[str]:
        return list(self.manifest["outputs"])

    @property
    def state_names(self) -> list[str]:
        return [s["name"] for s in self.manifest["states"]]

    @property
    def snapshot_steps(self) -> np.ndarray:
        return self.arrays["snapshot_steps"]

    def frame(self, step: int) -> np.ndarray:
        """The exact input frame of `step`, float32 [1, C, H, W]."""
        size = int(np.prod(self.frame_shape))
        mask = np.unpackbits(self.arrays["lnes.mask"][step], count=size).astype(bool)
        flat = np.zeros(size, dtype=np.float32)
        flat[mask] = self.arrays["lnes.values"][self._offsets[step]: self._offsets[step + 1]]
        return flat.reshape(1, *self.frame_shape)

    def window_ms(self, step: int) -> float:
        return float(self.arrays["window_ms"][step])

    def output(self, name: str) -> np.ndarray:
        return self.arrays[f"out.{name}"]

    def state_absmax(self, name: str) -> np.ndarray:
        return self.arrays[f"state_absmax.{name}"]

    def state_index(self, name: str) -> np.ndarray:
        return self.arrays[f"state_index.{name}"]

    def state_sample(self, name: str) -> np.ndarray:
        return self.arrays[f"state_sample.{name}"]

    def snapshot(self, name: str) -> np.ndarray:
        return self.arrays[f"snapshot.{name}"]

    @property
    def gt_mm(self) -> np.ndarray | None:
        return self.arrays.get("gt_mm")


class GoldenWriter:
    """Collects one rollout step by step, then writes the record folder atomically."""

    def __init__(self, frame_shape: tuple[int, ...], output_names: Iterable[str],
                 state_shapes: Mapping[str, tuple[int, ...]], steps: int, all_states: bool = False) -> None:
        self.frame_shape = tuple(frame_shape)
        self.output_names = list(output_names)
        self.state_shapes = dict(state_shapes)
        self.snapshots = snapshot_steps(steps, all_states)
        self._snapshot_set = set(self.snapshots)
        self.index = {n: sample_indices(n, int(np.prod(s))) for n, s in self.state_shapes.items()}
        self._masks: list[np.ndarray] = []
        self._values: list[np.ndarray] = []
        self._windows: list[float] = []
        self._gt: list[np.ndarray] = []
        self._outputs: dict[str, list[np.ndarray]] = {n: [] for n in self.output_names}
        self._absmax: dict[str, list[float]] = {n: [] for n in self.state_shapes}
        self._samples: dict[str, list[np.ndarray]] = {n: [] for n in self.state_shapes}
        self._full: dict[str, list[np.ndarray]] = {n: [] for n in self.state_shapes}

    @property
    def steps(self) -> int:
        return len(self._windows)

    def add(self, frame_f16: np.ndarray, window_ms: float, gt_mm: np.ndarray | None,
            outputs: Mapping[str, np.ndarray], state: Mapping[str, np.ndarray]) -> None:
        """One step: its float16 input frame [C, H, W], and batch-of-one outputs and states."""
        if frame_f16.dtype != np.float16 or tuple(frame_f16.shape) != self.frame_shape:
            raise DataError(f"golden frames must be float16 {list(self.frame_shape)}, got "
                            f"{frame_f16.dtype} {list(frame_f16.shape)}")
        flat = frame_f16.reshape(-1)
        nonzero = flat != 0
        self._masks.append(np.packbits(nonzero))
        self._values.append(flat[nonzero])
        self._windows.append(float(window_ms))
        if gt_mm is not None:
            self._gt.append(np.asarray(gt_mm, dtype=np.float32))
        for name in self.output_names:
            self._outputs[name].append(np.asarray(outputs[name], dtype=np.float32)[0])
        step = self.steps - 1
        for name, shape in self.state_shapes.items():
            one = np.asarray(state[name], dtype=np.float32)[0]
            self._absmax[name].append(float(np.max(np.abs(one))) if one.size else 0.0)
            self._samples[name].append(one.reshape(-1)[self.index[name]])
            if step in self._snapshot_set:
                self._full[name].append(one.copy())

    def arrays(self) -> dict[str, np.ndarray]:
        if self.steps != self.snapshots[-1] + 1:
            raise DataError(f"the rollout has {self.steps} steps, {self.snapshots[-1] + 1} were planned")
        arrays: dict[str, np.ndarray] = {
            "lnes.mask": np.stack(self._masks),
            "lnes.values": np.concatenate(self._values).astype(np.float16),
            "lnes.nnz": np.array([len(v) for v in self._values], dtype=np.int64),
            "window_ms": np.array(self._windows, dtype=np.float32),
            "snapshot_steps": np.array(self.snapshots, dtype=np.int64),
        }
        if len(self._gt) == self.steps:
            arrays["gt_mm"] = np.stack(self._gt)
        for name in self.output_names:
            arrays[f"out.{name}"] = np.stack(self._outputs[name])
        for name, shape in self.state_shapes.items():
            arrays[f"state_absmax.{name}"] = np.array(self._absmax[name], dtype=np.float32)
            arrays[f"state_index.{name}"] = self.index[name]
            arrays[f"state_sample.{name}"] = np.stack(self._samples[name]).astype(np.float32)
            arrays[f"snapshot.{name}"] = np.stack(self._full[name]).reshape(len(self.snapshots), *shape)
        return arrays

    def write(self, out_dir: str | os.PathLike, manifest: dict[str, Any], *, force: bool = False,
              arrays: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
        """Write the folder atomically; returns the manifest as written."""
        arrays = arrays if arrays is not None else self.arrays()
        manifest = {**manifest, "format": GOLDEN_FORMAT, "steps": self.steps, "frame_shape": list(self.frame_shape),
                    "outputs": self.output_names, "snapshot_steps": self.snapshots,
                    "state_samples": STATE_SAMPLES, "arrays": ARRAYS_FILE}
        with atomic_dir(out_dir, force=force) as tmp:
            np.savez_compressed(tmp / ARRAYS_FILE, **arrays)
            manifest["bytes"] = {"arrays": (tmp / ARRAYS_FILE).stat().st_size}
            write_json_atomic(tmp / MANIFEST_FILE, manifest)
        return manifest


def load_golden(folder: str | os.PathLike) -> GoldenRecord:
    """Open and check a golden folder (e3dpsm/golden/store_checks.py); `DataError` with what is
    wrong and how to fix it."""
    from e3dpsm.data.formats.npz import load_arrays
    from e3dpsm.golden.store_checks import check_arrays, check_manifest

    folder = Path(folder)
    manifest_path, arrays_path = folder / MANIFEST_FILE, folder / ARRAYS_FILE
    if not manifest_path.is_file() or not arrays_path.is_file():
        raise DataError(f"{folder} is not a golden record (needs {MANIFEST_FILE} and {ARRAYS_FILE}); "
                        "write one with `e3dpsm golden record`")
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: JSON nested thousands deep
        raise DataError(f"{manifest_path}: cannot read JSON ({str(exc).splitlines()[0][:200]})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != GOLDEN_FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise DataError(f"{manifest_path}: format {found!r}, this e3dpsm reads {GOLDEN_FORMAT!r}")
    check_manifest(manifest, manifest_path)
    arrays = load_arrays(arrays_path, what="the arrays")
    expected = ["lnes.mask", "lnes.values", "lnes.nnz", "window_ms", "snapshot_steps",
                *(f"out.{n}" for n in manifest["outputs"]),
                *(f"{kind}.{s['name']}" for s in manifest["states"]
                  for kind in ("state_absmax", "state_index", "state_sample", "snapshot"))]
    missing = [k for k in expected if k not in arrays]
    if missing:
        raise DataError(f"{arrays_path} lacks {', '.join(missing[:4])}; record the golden again")
    check_arrays(manifest, arrays, arrays_path)
    return GoldenRecord(manifest, arrays, folder)
