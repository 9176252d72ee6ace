"""A step `.pte` small enough to read in one line, written with ExecuTorch's own API (not the
project's converter): the golden fakes' frame (2 x 4 x 4) and state `s` [6], the e3dpsm
contract as the constant method `e3dpsm convert executorch` writes, and

    pose      = 2 * lnes + window_ms
    state_out = state_in + window_ms

and, as a taps program (`taps=True`), two int8 taps after them (TAPS): `toy.frame:codes`, lnes * 4
rounded and saturated, and `toy.state:codes`, state_out rounded and saturated (toy_taps).
"""
from __future__ import annotations

import numpy as np

from _golden_fakes import FRAME, STATE, STATE_SHAPE


def toy_pose(lnes: np.ndarray, window_ms: float | np.ndarray) -> np.ndarray:
    return (2 * np.asarray(lnes, np.float32) + np.float32(window_ms)).astype(np.float32)


TAPS = [{"tap": "toy.frame:codes", "segment": ["mul", "round", "clamp"]},
        {"tap": "toy.state:codes", "segment": ["add", "round", "clamp"]}]


def toy_taps(lnes: np.ndarray, state_out: np.ndarray) -> list[np.ndarray]:
    """The taps program's two taps, in numpy (round half to even, as torch.round)."""
    return [np.clip(np.round(np.asarray(v, np.float32) * k), -128, 127).astype(np.int8)
            for v, k in ((lnes, 4), (state_out, 1))]


def toy_pte(version: str | None = None, precision: str = "fp32", with_metadata: bool = True,
            delegated: bool = False, taps: bool = False, pose_offset: float = 0.0,
            declared_taps: list[dict] | None = None) -> bytes:
    """The toy program's bytes; `version`: the ExecuTorch release its record names (default
    this one's); `delegated`: its arithmetic lowered to one XNNPACK partition; `taps`: the taps
    program (TAPS in its taps method, or `declared_taps`); `pose_offset`: added to the pose (another
    program)."""
    import torch
    from executorch.exir import to_edge_transform_and_lower

    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.runtime.artifact_metadata import PTE_METHOD, encode
    from e3dpsm.runtime.executorch_session import executorch_version
    from e3dpsm.state import StateSpec, state_input_name, state_output_name

    class Toy(torch.nn.Module):
        def forward(self, lnes, window_ms, state):
            pose, state_out = 2 * lnes + window_ms.reshape(1, 1, 1, 1) + pose_offset, state + window_ms.reshape(1, 1)
            if not taps:
                return pose, state_out
            codes = [torch.clamp(torch.round(v * k), -128, 127).to(torch.int8) for v, k in ((lnes, 4), (state_out, 1))]
            return pose, state_out, *codes

    frame, state = (1, *FRAME), (1, *STATE_SHAPE)
    example = (torch.zeros(frame), torch.zeros(1), torch.zeros(state))
    meta = GraphMetadata(states=(StateSpec(STATE, STATE_SHAPE),),
                         inputs={"frame": {"name": "lnes", "shape": list(frame)},
                                 "window": {"name": "window_ms", "shape": [1]}},
                         outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=[f"j{i}" for i in range(16)])
    record = {"format": "executorch", "precision": precision,
              "versions": {"executorch": version or executorch_version()},
              "inputs": ["lnes", "window_ms", state_input_name(STATE)], "outputs": ["pose", state_output_name(STATE)]}
    program = torch.export.export(Toy(), example)
    methods = {PTE_METHOD: encode(meta, record)} if with_metadata else {}
    if taps:
        from e3dpsm.runtime.artifact_metadata import TAPS_METHOD, encode_taps

        methods[TAPS_METHOD] = encode_taps(TAPS if declared_taps is None else declared_taps)
    partitioner = []
    if delegated:
        from executorch.backends.xnnpack.partition.xnnpack_partitioner import XnnpackPartitioner

        partitioner = [XnnpackPartitioner()]
    return to_edge_transform_and_lower(program, partitioner=partitioner,
                                       constant_methods=methods).to_executorch().buffer
