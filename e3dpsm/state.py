"""The recurrent state layout: one source of truth for the PyTorch step, the exporter, the
ONNX metadata, the parity checker, the calibration reader and the streaming runtime.

Torch-free on purpose: the runtime on an edge device imports this module (or only reads
the same layout back from the graph's metadata) with numpy alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Mapping, Sequence, Union

import numpy as np

from e3dpsm.errors import InputError

BATCH_AXIS = "batch"
STATE_INPUT_SUFFIX = "_in"
STATE_OUTPUT_SUFFIX = "_out"

Init = Union[Literal["zeros"], tuple[float, ...]]


def state_input_name(name: str) -> str:
    return name + STATE_INPUT_SUFFIX


def state_output_name(name: str) -> str:
    return name + STATE_OUTPUT_SUFFIX


@dataclass(frozen=True)
class StateSpec:
    """One recurrent state tensor of shape [batch, *shape].

    `init` is "zeros" or the flat list of initial values of one batch element (row-major,
    `prod(shape)` numbers), broadcast over the batch.
    """

    name: str
    shape: tuple[int, ...]
    init: Init = "zeros"
    dtype: str = "float32"
    doc: str = ""

    @property
    def input_name(self) -> str:
        return state_input_name(self.name)

    @property
    def output_name(self) -> str:
        return state_output_name(self.name)

    def initial_value(self, batch: int) -> np.ndarray:
        if self.init == "zeros":
            one = np.zeros(self.shape, dtype=self.dtype)
        else:
            one = np.asarray(self.init, dtype=self.dtype).reshape(self.shape)
        return np.broadcast_to(one, (batch, *self.shape)).copy()

    def to_metadata(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "input": self.input_name,
            "output": self.output_name,
            "shape": [BATCH_AXIS, *self.shape],
            "dtype": self.dtype,
            "init": "zeros" if self.init == "zeros" else [float(v) for v in self.init],
            "doc": self.doc,
        }

    @classmethod
    def from_metadata(cls, entry: Mapping[str, Any]) -> "StateSpec":
        shape = list(entry["shape"])
        if not shape or shape[0] != BATCH_AXIS:
            raise InputError(f"state {entry.get('name')!r}: shape must start with {BATCH_AXIS!r}, got {shape}")
        init = entry.get("init", "zeros")
        name = entry.get("name") or str(entry["input"])[: -len(STATE_INPUT_SUFFIX)]
        return cls(
            name=name,
            shape=tuple(int(d) for d in shape[1:]),
            init="zeros" if init == "zeros" else tuple(float(v) for v in init),
            dtype=str(entry.get("dtype", "float32")),
            doc=str(entry.get("doc", "")),
        )


def initial_states(specs: Sequence[StateSpec], batch: int) -> dict[str, np.ndarray]:
    """The initial value of every state, keyed by state name, for `batch` streams."""
    return {s.name: s.initial_value(batch) for s in specs}


def check_state_shapes(
    specs: Sequence[StateSpec], shapes: Mapping[str, Sequence[int]], batch: int | None = None
) -> int:
    """Check a state dict's keys and shapes against `specs`; returns the batch size.

    Raises InputError naming the missing / unexpected key or the expected shape.
    """
    expected = {s.name for s in specs}
    missing = sorted(expected - set(shapes))
    if missing:
        raise InputError(f"state is missing {missing}; expected keys {sorted(expected)} (use init_state(batch))")
    unexpected = sorted(set(shapes) - expected)
    if unexpected:
        raise InputError(f"state has unexpected keys {unexpected}; expected keys {sorted(expected)}")
    for spec in specs:
        shape = tuple(int(d) for d in shapes[spec.name])
        if batch is None and shape:
            batch = shape[0]
        if shape != (batch, *spec.shape):
            raise InputError(
                f"state {spec.name!r} has shape {list(shape)}, expected [{batch}, "
                + ", ".join(str(d) for d in spec.shape) + "]"
            )
    return int(batch or 0)
