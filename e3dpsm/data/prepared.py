"""The prepared LNES cache: the only data format training, evaluation, calibration and
validation read. Written by `e3dpsm.data.prepare`; opened and checked here.

    OUT/meta.json       {"format": "e3dpsm-prepared/1", "window_ms", "window_us", "height",
                         "width", "sensor_hw", "source", "joints", "action_names",
                         "sequences": [{"name", "frames", "split", ...}], + report header}
    OUT/<seq>/lnes.npy  float16 [F, 2, H, W], window f = [t_us[f] - T, t_us[f])
    OUT/<seq>/pose.npz  j3d_mm float32 [F,16,3], j2d_px float32 [F,16,2] (H x W frame pixels),
                        visible uint8 [F,16], action int16 [F], t_us int64 [F] (window ends)
    OUT/report.json     counts and timings of the prepare run
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.data.formats.npz import READ_ERRORS
from e3dpsm.errors import DataError
from e3dpsm.events import LNES_CHANNELS
from e3dpsm.joints import NUM_JOINTS

PREPARED_FORMAT = "e3dpsm-prepared/1"
META_FILE = "meta.json"
REPORT_FILE = "report.json"
LNES_FILE = "lnes.npy"
POSE_FILE = "pose.npz"
LNES_DTYPE = np.float16
POSE_ARRAYS: dict[str, tuple[Any, tuple[int, ...]]] = {  # name -> (dtype, shape after F)
    "j3d_mm": (np.float32, (NUM_JOINTS, 3)),
    "j2d_px": (np.float32, (NUM_JOINTS, 2)),
    "visible": (np.uint8, (NUM_JOINTS,)),
    "action": (np.int16, ()),
    "t_us": (np.int64, ()),
}
_RUN_PREPARE = "run `e3dpsm prepare --data DATA --out {root}` to create it"


ALL_SPLITS = "all"


@dataclass(frozen=True)
class PreparedSequence:
    """One prepared sequence; `lnes` is a read-only memory map, the pose arrays are loaded."""

    name: str
    split: str
    frames: int
    lnes: np.ndarray
    j3d_mm: np.ndarray
    j2d_px: np.ndarray
    visible: np.ndarray
    action: np.ndarray
    t_us: np.ndarray


class PreparedData:
    """A validated prepared folder. Open with `PreparedData.open(path)`."""

    def __init__(self, root: Path, meta: dict[str, Any], sequences: list[PreparedSequence]):
        self.root = root
        self.meta = meta
        self.sequences = sequences

    @classmethod
    def open(cls, root: str | os.PathLike) -> "PreparedData":
        root = Path(root)
        if not root.is_dir():
            raise DataError(f"prepared folder {root} does not exist: {_RUN_PREPARE.format(root=root)}")
        meta_path = root / META_FILE
        if not meta_path.is_file():
            what = "is empty" if not any(root.iterdir()) else f"has no {META_FILE}"
            raise DataError(f"{root} is not a prepared folder ({what}): {_RUN_PREPARE.format(root=root)}")
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise DataError(f"{meta_path}: cannot read JSON ({exc}); re-run `e3dpsm prepare`") from exc
        if not isinstance(meta, dict) or meta.get("format") != PREPARED_FORMAT:
            found = meta.get("format") if isinstance(meta, dict) else None
            raise DataError(
                f"{root} is not a prepared folder (format {found!r}, expected {PREPARED_FORMAT!r}): "
                + _RUN_PREPARE.format(root=root)
            )
        missing = [k for k in ("window_us", "height", "width", "sequences") if k not in meta]
        if missing:
            raise DataError(f"{meta_path}: missing fields {missing}; re-run `e3dpsm prepare`")
        shape = (LNES_CHANNELS, int(meta["height"]), int(meta["width"]))
        sequences = [_open_sequence(root, entry, shape) for entry in meta["sequences"]]
        if not sequences:
            raise DataError(f"{root}: the prepared folder lists no sequences")
        return cls(root, meta, sequences)

    @property
    def window_us(self) -> int:
        return int(self.meta["window_us"])

    @property
    def window_ms(self) -> float:
        return self.window_us / 1000.0

    @property
    def height(self) -> int:
        return int(self.meta["height"])

    @property
    def width(self) -> int:
        return int(self.meta["width"])

    @property
    def source(self) -> str:
        return str(self.meta.get("source", "unknown"))

    @property
    def action_names(self) -> tuple[str, ...]:
        return tuple(self.meta.get("action_names", ()))

    @property
    def splits(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(s.split for s in self.sequences))

    def split(self, name: str) -> list[PreparedSequence]:
        """The sequences of split `name` ("all" for every sequence); a `DataError` naming the
        present splits if none."""
        if name == ALL_SPLITS:
            return list(self.sequences)
        chosen = [s for s in self.sequences if s.split == name]
        if not chosen:
            raise DataError(f"{self.root} has no sequences in split {name!r}; present splits: {list(self.splits)} (or 'all')")
        return chosen

    def check_compatible(
        self, window_ms: float | None = None, height: int | None = None, width: int | None = None
    ) -> None:
        """Raise `DataError` saying how to re-run prepare if the cache does not fit a model/graph."""
        if window_ms is not None and round(window_ms * 1000) != self.window_us:
            raise DataError(
                f"{self.root} was prepared with {self.window_ms:g} ms windows, but the model/graph expects "
                f"{window_ms:g} ms; re-run prepare with --window-ms {window_ms:g}"
            )
        if (height is not None and height != self.height) or (width is not None and width != self.width):
            want_h, want_w = height or self.height, width or self.width
            raise DataError(
                f"{self.root} was prepared with {self.height} x {self.width} LNES frames, but the model/graph "
                f"expects {want_h} x {want_w}; re-run prepare with --height {want_h} --width {want_w}"
            )


def _open_sequence(root: Path, entry: dict[str, Any], frame_shape: tuple[int, int, int]) -> PreparedSequence:
    try:
        name, split, frames = str(entry["name"]), str(entry["split"]), int(entry["frames"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{root / META_FILE}: malformed sequence entry {entry!r}") from exc
    folder = root / name
    lnes_path, pose_path = folder / LNES_FILE, folder / POSE_FILE
    for path in (lnes_path, pose_path):
        if not path.is_file():
            raise DataError(f"{path} is missing; the prepared folder is incomplete, re-run `e3dpsm prepare`")
    try:
        lnes = np.load(lnes_path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DataError(f"{lnes_path}: cannot map ({exc}); truncated? re-run `e3dpsm prepare`") from exc
    if lnes.shape != (frames, *frame_shape) or lnes.dtype != LNES_DTYPE:
        raise DataError(
            f"{lnes_path}: {lnes.dtype} {lnes.shape}, expected {np.dtype(LNES_DTYPE)} {(frames, *frame_shape)}"
        )
    try:
        with np.load(pose_path, allow_pickle=False) as archive:
            pose = {k: archive[k] for k in POSE_ARRAYS}
    except READ_ERRORS as exc:  # what numpy, zipfile and zlib raise on a damaged archive
        raise DataError(f"{pose_path}: cannot read ({exc}); re-run `e3dpsm prepare`") from exc
    for key, (dtype, tail) in POSE_ARRAYS.items():
        if pose[key].shape != (frames, *tail) or pose[key].dtype != dtype:
            raise DataError(
                f"{pose_path}: {key} is {pose[key].dtype} {pose[key].shape}, expected {np.dtype(dtype)} {(frames, *tail)}"
            )
    return PreparedSequence(name=name, split=split, frames=frames, lnes=lnes, **pose)
