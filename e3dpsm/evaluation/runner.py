"""Run a torch model over the sequences of a prepared split -> per-frame predictions.

Causal: each sequence runs from its first frame to its last as one stream whose state is
never reset, in chunks of `chunk` frames that carry the state (bounded memory, same result
as one run). Non-causal (bidirectional S5, as trained): consecutive windows of the training
length, each from a fresh state, stitched end to end.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from e3dpsm.data.prepared import PreparedSequence


@dataclass
class SplitPredictions:
    """Frames of all sequences concatenated; `sequence_ids[i]` indexes `sequence_names`."""

    pred_mm: np.ndarray        # [N, J, 3] fused pose
    pred_direct_mm: np.ndarray  # [N, J, 3]
    gt_mm: np.ndarray          # [N, J, 3]
    visible: np.ndarray        # [N, J]
    action: np.ndarray         # [N]
    sequence_ids: np.ndarray   # [N]
    sequence_names: list[str]


@torch.no_grad()
def predict_sequence(model: torch.nn.Module, seq: PreparedSequence, causal: bool, window_ms: float,
                     chunk: int = 40) -> dict[str, np.ndarray]:
    """Outputs of one sequence, {"pose", "pose_direct", "pose_delta"} each [F, J, 3] mm."""
    device = next(model.parameters()).device
    state = None
    parts: list[dict[str, torch.Tensor]] = []
    for start in range(0, seq.frames, chunk):
        frames = torch.from_numpy(np.asarray(seq.lnes[start:start + chunk], dtype=np.float32))[None].to(device)
        if causal:
            out, state = model.forward_sequence(frames, causal=True, state=state, window_ms=window_ms,
                                                return_state=True)
        else:
            out = model.forward_sequence(frames, causal=False, window_ms=window_ms)
        parts.append({k: v[0].cpu() for k, v in out.items()})
    return {k: torch.cat([p[k] for p in parts]).numpy() for k in parts[0]}


def predict_split(model: torch.nn.Module, sequences: Sequence[PreparedSequence], causal: bool,
                  window_ms: float, chunk: int = 40, progress: bool = False) -> SplitPredictions:
    """Predictions of `model` (eval mode) over whole sequences, concatenated."""
    from tqdm import tqdm

    model.eval()
    preds, directs = [], []
    for seq in tqdm(sequences, desc="evaluate", unit="seq", disable=not progress):
        out = predict_sequence(model, seq, causal, window_ms, chunk)
        preds.append(out["pose"])
        directs.append(out["pose_direct"])
    return SplitPredictions(
        pred_mm=np.concatenate(preds), pred_direct_mm=np.concatenate(directs),
        gt_mm=np.concatenate([np.asarray(s.j3d_mm, np.float32) for s in sequences]),
        visible=np.concatenate([np.asarray(s.visible) for s in sequences]),
        action=np.concatenate([np.asarray(s.action, np.int64) for s in sequences]),
        sequence_ids=np.concatenate([np.full(s.frames, i) for i, s in enumerate(sequences)]),
        sequence_names=[s.name for s in sequences],
    )
