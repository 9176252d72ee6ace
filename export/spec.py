"""Declarative I/O spec of the step graph: names, shapes (with the "batch" axis) and dtypes
of every input and output, derived from the model's config and `state_spec()` alone."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import onnx

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.joints import JOINT_NAMES, PARENTS
from e3dpsm.models import OUTPUT_NAMES, E3DPSM
from e3dpsm.state import BATCH_AXIS

FRAME_INPUT = "lnes"
WINDOW_INPUT = "window_ms"

_OUTPUT_DOCS = {
    "pose": "fused 3D pose (the model's output), millimetres, fisheye camera frame",
    "pose_direct": "direct-regression 3D pose, millimetres",
    "pose_delta": "predicted pose change since the previous step, millimetres",
}


@dataclass(frozen=True)
class TensorSpec:
    name: str
    shape: tuple[int | str, ...]
    dtype: str = "float32"

    @property
    def dynamic_axes(self) -> dict[int, str]:
        return {i: d for i, d in enumerate(self.shape) if isinstance(d, str)}


@dataclass(frozen=True)
class StepIOSpec:
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]

    @property
    def input_names(self) -> list[str]:
        return [t.name for t in self.inputs]

    @property
    def output_names(self) -> list[str]:
        return [t.name for t in self.outputs]

    @property
    def dynamic_axes(self) -> dict[str, dict[int, str]]:
        return {t.name: t.dynamic_axes for t in (*self.inputs, *self.outputs) if t.dynamic_axes}

    def declare_on(self, model: onnx.ModelProto) -> None:
        """Write these shapes, axis names included, on the graph inputs and outputs of `model`
        of the same names (in place); element types are left as they are."""
        shapes = {t.name: t.shape for t in (*self.inputs, *self.outputs)}
        for value in (*model.graph.input, *model.graph.output):
            if value.name not in shapes:
                continue
            dims = value.type.tensor_type.shape.dim
            del dims[:]
            for size in shapes[value.name]:
                dim = dims.add()
                if isinstance(size, str):
                    dim.dim_param = size
                else:
                    dim.dim_value = size


def step_io_spec(model: E3DPSM, batch: int | str = BATCH_AXIS) -> StepIOSpec:
    """`batch`: the dynamic "batch" axis, or a fixed batch size (a static-batch graph)."""
    cfg = model.config
    states = model.state_spec()
    pose_shape = (batch, cfg.num_joints, 3)
    inputs = (
        TensorSpec(FRAME_INPUT, (batch, cfg.in_channels, cfg.height, cfg.width)),
        TensorSpec(WINDOW_INPUT, (batch,)),
        *(TensorSpec(s.input_name, (batch, *s.shape), s.dtype) for s in states),
    )
    outputs = (
        *(TensorSpec(name, pose_shape) for name in OUTPUT_NAMES),
        *(TensorSpec(s.output_name, (batch, *s.shape), s.dtype) for s in states),
    )
    return StepIOSpec(inputs, outputs)


def graph_metadata(model: E3DPSM, extra: dict[str, Any] | None = None, batch: int | str = BATCH_AXIS) -> GraphMetadata:
    """The DESIGN.md metadata contract for `model`'s step graph. With a fixed `batch`, the
    frame, window and output shapes say it; state entries keep the "batch" axis of the
    state layout contract (StateSpec), the config records `static_batch`."""
    cfg = model.config
    spec = step_io_spec(model, batch)
    frame = spec.inputs[0]
    inputs = {
        "frame": {
            "name": frame.name, "shape": list(frame.shape), "dtype": frame.dtype,
            "encoding": "LNES: (t - t0) / T of the latest event per pixel in [t0, t0 + T), "
                        "channel = polarity (0 negative, 1 positive), 0 where no event",
            "sensor_hw": [480, 640],
        },
        "window": {
            "name": WINDOW_INPUT, "shape": [batch], "dtype": "float32", "unit": "ms",
            "train_window_ms": cfg.train_window_ms,
            "doc": "length T of the window each frame covers; one graph serves 20, 25 and 50 ms",
        },
    }
    outputs = [
        {"name": t.name, "shape": list(t.shape), "dtype": t.dtype, "unit": "mm", "doc": _OUTPUT_DOCS[t.name]}
        for t in spec.outputs if t.name in OUTPUT_NAMES
    ]
    config = {
        "variant": cfg.variant, "train_window_ms": cfg.train_window_ms, "fusion": cfg.fusion,
        "model_config": cfg.to_dict(), **({} if isinstance(batch, str) else {"static_batch": batch}), **(extra or {}),
    }
    return GraphMetadata(
        states=model.state_spec(), inputs=inputs, outputs=outputs, config=config,
        joints=list(JOINT_NAMES), extra={"e3dpsm.parents": str(list(PARENTS))},
    )
