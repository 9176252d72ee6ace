"""A hand-made golden record (GoldenWriter, in memory, with ground truth) and a fake runner
that returns the golden outputs and states with errors chosen per step: what the golden check
tests measure against hand-computed numbers."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from e3dpsm.golden.store import GoldenRecord, GoldenWriter
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, initial_states

J = 16
FRAME = (2, 4, 4)
STATE = "s"
STATE_SHAPE = (6,)
GT_OFFSET_MM = 100.0  # the golden poses sit 100 mm from the ground truth along y: its MPJPE
# ... and a fixed error in shape too, along z (+-10 mm by joint), so that PA-MPJPE is not zero
SHAPE_ERROR = np.stack([np.zeros(J), np.zeros(J), 10.0 * (-1.0) ** np.arange(J)], axis=1).astype(np.float32)
STEPS = 40  # quarters of 10 steps


def golden_pose(step: int) -> np.ndarray:
    base = np.linspace(-800.0, 1200.0, 3 * J, dtype=np.float32).reshape(J, 3)
    return base + np.float32(step + 20.0 * np.sin(step / 3.0))  # moving, with a second difference


def golden_state(step: int) -> np.ndarray:
    return (np.arange(1, 1 + STATE_SHAPE[0], dtype=np.float32) * (1.0 + 0.25 * step)).astype(np.float32)


def make_golden(steps: int = STEPS) -> GoldenRecord:
    writer, manifest = golden_writer(steps)
    return GoldenRecord(manifest, writer.arrays())


def golden_writer(steps: int) -> tuple[GoldenWriter, dict]:
    writer = GoldenWriter(FRAME, ["pose"], {STATE: STATE_SHAPE}, steps)
    rng = np.random.default_rng(0)
    for step in range(steps):
        frame = (rng.random(FRAME) < 0.2).astype(np.float16)
        gt = golden_pose(step) + np.float32([0.0, GT_OFFSET_MM, 0.0]) + SHAPE_ERROR
        writer.add(frame, 20.0, gt, {"pose": golden_pose(step)[None]}, {STATE: golden_state(step)[None]})
    manifest = {"steps": steps, "frame_shape": list(FRAME), "outputs": ["pose"],
                "states": [{"name": STATE, "shape": [-1, *STATE_SHAPE]}],
                "source": {"variant": "fake"}, "mpjpe_scale_mm": GT_OFFSET_MM}
    return writer, manifest


def write_golden(folder: Path, steps: int) -> Path:
    """golden_writer's golden of `steps` steps written to `folder` at 20 ms, 16 joints (the toy
    programs' traces read it)."""
    writer, manifest = golden_writer(steps)
    writer.write(folder, {**manifest, "window_ms": 20.0, "joints": [f"j{i}" for i in range(16)]})
    return folder


def parted_record(trace: dict, step: int, positions: list[int]) -> dict:
    """A device's copy of a trace record (pte_trace, pte_taps) whose values at `positions`
    differ from `step` on."""
    device = json.loads(json.dumps(trace))
    for s in range(step, trace["steps"]):
        for k in positions:
            device["digests"][s][k] = "0" * 16
    return device


class FakeRunner:
    """Returns the golden pose moved by `pose_mm[step]` mm (every joint along x: the mean
    joint distance is exactly that) and the golden state scaled by 1 + `state_rel[step]`
    (its relative RMS error is exactly that)."""

    def __init__(self, pose_mm, state_rel) -> None:
        self.pose_mm, self.state_rel = np.asarray(pose_mm, float), np.asarray(state_rel, float)
        self.step_index = 0
        self.meta = GraphMetadata(
            states=(StateSpec(STATE, STATE_SHAPE),),
            inputs={"frame": {"name": "lnes", "shape": ["batch", *FRAME]}, "window": {"name": "window_ms"}},
            outputs=[{"name": "pose"}], config={"variant": "fake"}, joints=[f"j{i}" for i in range(J)])

    def init_state(self, batch: int = 1):
        self.step_index = 0
        return initial_states(self.meta.states, batch)

    def step(self, lnes, state, window_ms):
        k = self.step_index
        self.step_index += 1
        pose = golden_pose(k).astype(np.float64)
        pose[:, 0] += self.pose_mm[k]
        new_state = golden_state(k).astype(np.float64) * (1.0 + self.state_rel[k])
        return {"pose": pose[None].astype(np.float32)}, {STATE: new_state[None].astype(np.float32)}
