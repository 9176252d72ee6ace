"""`golden record`: step a reference (a PyTorch checkpoint, or an fp32 graph) over prepared
sequences and keep its inputs, outputs and states as a golden record."""
from __future__ import annotations

import hashlib
import itertools
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from e3dpsm.data.prepared import ALL_SPLITS, PreparedData
from e3dpsm.errors import DataError
from e3dpsm.golden.store import GoldenWriter
from e3dpsm.golden.tolerances import PROFILES
from e3dpsm.metrics import mpjpe
from e3dpsm.runtime.stepping import Stepper


@dataclass(frozen=True)
class Reference:
    """A stepper and what the record says about it (the layout it shares with its graphs)."""

    stepper: Stepper
    kind: str  # "checkpoint" | "onnx" | "variant"
    path: Path | None
    variant: str
    frame_shape: tuple[int, ...]
    output_names: tuple[str, ...]
    states: tuple[dict[str, Any], ...]  # StateSpec metadata entries
    joints: tuple[str, ...]


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            digest.update(block)
    return digest.hexdigest()


def onnx_reference(path: str | os.PathLike, threads: int | None = None) -> Reference:
    """An exported fp32 step graph as the reference (no torch needed)."""
    from e3dpsm.errors import InputError
    from e3dpsm.runtime.stepping import open_stepper

    session = open_stepper(path, threads=threads)
    meta = session.meta
    if meta.quantization:
        raise InputError(f"{path} is a {meta.quantization.get('mode')} graph; record the golden from the fp32 "
                         "graph or the checkpoint, then check compressed graphs against it")
    return Reference(session, "onnx", Path(path), str(meta.config.get("variant")),
                     tuple(int(d) for d in meta.frame_input["shape"][1:]), tuple(meta.output_names),
                     tuple(s.to_metadata() for s in meta.states), tuple(meta.joints))


def torch_reference(model: Any, kind: str, path: str | os.PathLike | None) -> Reference:
    """A PyTorch model's `step` as the reference (what `e3dpsm parity` compares graphs with)."""
    from e3dpsm.export.torch_stepper import TorchStepper  # torch: imported only when a checkpoint is the reference
    from e3dpsm.joints import JOINT_NAMES
    from e3dpsm.models import OUTPUT_NAMES

    cfg = model.config
    return Reference(TorchStepper(model), kind, Path(path) if path else None, cfg.variant,
                     (2, cfg.height, cfg.width), tuple(OUTPUT_NAMES),
                     tuple(s.to_metadata() for s in model.state_spec()), tuple(JOINT_NAMES))


def prepared_rollout(data_dir: str | os.PathLike, steps: int, split: str = ALL_SPLITS
                     ) -> tuple[Iterator[tuple[np.ndarray, np.ndarray]], list[dict[str, Any]], PreparedData]:
    """`steps` (float16 frame, ground truth) pairs, sequences in order and replayed from the
    start when the split is shorter (a scene cut, as at every sequence boundary), and the
    segments that say which sequence frames each stretch of steps came from."""
    data = PreparedData.open(data_dir)
    sequences = [s for s in data.split(split) if s.frames]
    if not sequences:
        raise DataError(f"{data_dir} holds no frames in split {split!r}")
    segments: list[dict[str, Any]] = []
    left = steps
    for seq in itertools.cycle(sequences):
        if left <= 0:
            break
        take = min(left, seq.frames)
        segments.append({"sequence": seq.name, "first_frame": 0, "steps": take})
        left -= take

    def frames() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        by_name = {s.name: s for s in sequences}
        for segment in segments:
            seq = by_name[segment["sequence"]]
            for i in range(segment["steps"]):
                yield np.asarray(seq.lnes[i], dtype=np.float16), np.asarray(seq.j3d_mm[i], dtype=np.float32)

    return frames(), segments, data


def record_golden(reference: Reference, data_dir: str | os.PathLike, out_dir: str | os.PathLike, *, steps: int,
                  window_ms: float, split: str = ALL_SPLITS, all_states: bool = False, force: bool = False,
                  header: Mapping[str, Any] | None = None, progress: bool = False) -> dict[str, Any]:
    """Run the reference over `steps` prepared frames and write the record; returns its manifest."""
    started = time.perf_counter()
    frames, segments, data = prepared_rollout(data_dir, steps, split)
    if (2, data.height, data.width) != reference.frame_shape:
        raise DataError(f"{data_dir} holds {data.height} x {data.width} frames, the {reference.variant} model "
                        f"takes {reference.frame_shape[1]} x {reference.frame_shape[2]}; prepare the data for it")
    shapes = {s["name"]: tuple(int(d) for d in s["shape"][1:]) for s in reference.states}
    writer = GoldenWriter(reference.frame_shape, reference.output_names, shapes, steps, all_states)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=steps, desc="golden record", unit="step", leave=False, disable=None)
    state = reference.stepper.init_state(1)
    for frame, gt in frames:
        outputs, state = reference.stepper.step(frame.astype(np.float32)[None], state, window_ms)
        writer.add(frame, window_ms, gt, outputs, state)
    arrays = writer.arrays()
    source: dict[str, Any] = {"kind": reference.kind, "variant": reference.variant}
    if reference.path is not None:
        source.update(file=reference.path.name, sha256=sha256_file(reference.path))
    manifest: dict[str, Any] = {
        **(header or {}),
        "source": source,
        "window_ms": float(window_ms),
        "data": {"path": str(data_dir), "split": split, "segments": segments,
                 "prepared_window_ms": data.window_ms},
        "states": list(reference.states),
        "joints": list(reference.joints),
        "tolerances": {name: p.to_dict() for name, p in PROFILES.items()},
        "mpjpe_scale_mm": mpjpe(arrays["out.pose"], arrays["gt_mm"]) if "gt_mm" in arrays else None,
        "record_seconds": round(time.perf_counter() - started, 2),
    }
    return writer.write(out_dir, manifest, force=force, arrays=arrays)
