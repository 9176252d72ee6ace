"""Run a model over one sequence as a continuous stream: states start from the graph's
initial values and are carried from frame to frame, never reset (paper Sec. 5.1; App. E.2,
Table 8)."""
from __future__ import annotations

from typing import Any

import numpy as np

from e3dpsm.runtime import StepSession


def onnx_stream_outputs(session: StepSession, lnes: np.ndarray, window_ms: float,
                        frames: int | None = None) -> dict[str, np.ndarray]:
    """Every output of an exported step graph over `lnes [F, 2, H, W]`: {name: [F, ...]}
    (`pose`, `pose_direct`, `pose_delta`, mm)."""
    count = len(lnes) if frames is None else min(frames, len(lnes))
    state = session.init_state(1)
    steps: list[dict[str, np.ndarray]] = []
    for f in range(count):
        outputs, state = session.step(np.asarray(lnes[f : f + 1], dtype=np.float32), state, window_ms)
        steps.append({name: value[0] for name, value in outputs.items()})
    return {name: np.stack([s[name] for s in steps]).astype(np.float32) for name in steps[0]}


def onnx_stream(session: StepSession, lnes: np.ndarray, window_ms: float, frames: int | None = None) -> np.ndarray:
    """Fused poses `[F, 16, 3]` mm of an exported step graph over `lnes [F, 2, H, W]`."""
    return onnx_stream_outputs(session, lnes, window_ms, frames)["pose"]


def torch_stream(model: Any, lnes: np.ndarray, window_ms: float, frames: int | None = None,
                 chunk: int = 64) -> np.ndarray:
    """Fused poses of the PyTorch model, causal, in chunks that carry the state (chunked
    runs reproduce whole runs, DESIGN.md), so memory stays bounded on long sequences."""
    import torch

    count = len(lnes) if frames is None else min(frames, len(lnes))
    state = None
    poses = []
    with torch.no_grad():
        for start in range(0, count, chunk):
            block = torch.from_numpy(np.asarray(lnes[start : min(count, start + chunk)], dtype=np.float32))[None]
            out, state = model.forward_sequence(block, causal=True, state=state, window_ms=window_ms,
                                                return_state=True)
            poses.append(out["pose"][0].numpy())
    return np.concatenate(poses).astype(np.float32)
