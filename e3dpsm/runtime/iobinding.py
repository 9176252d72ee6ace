"""A step session whose recurrent states never leave the execution provider's memory.

`StepSession` hands ORT numpy states and gets new numpy states back every step: on CPU a
copy in and out of ORT's tensors, on a GPU a host <-> device round trip of the whole state.
`IOBindingStepSession` keeps, per batch size, two sets of state tensors as OrtValues on the
provider's device ("A" and "B") and two prepared `IOBinding`s: A in -> B out and B in -> A
out. Each step only binds the frame and window inputs and runs the binding whose inputs
hold the current state, so the state outputs of step k are the state inputs of step k + 1
without passing through numpy. Only the pose outputs are copied to the host.

The state a step returns is a `DeviceState`: a read-only mapping that copies a state to
numpy when indexed (so code written for numpy states still works), and that the session
recognises and feeds back without a copy. A pair of buffers is a "lane": stepping from
numpy states (`init_state`, a gathered batch) takes a free lane of that batch size (or
makes one) and copies the states in; stepping from a `DeviceState` stays in its lane. A lane
is free again once no `DeviceState` refers to it, so several estimators can share one
session, each chain of states in its own lane. Within a lane the two buffers are reused:
stepping from state k writes the other buffer, so states k and k + 1 are readable and
state k - 1 is gone. Using an overwritten state raises `InputError`;
`DeviceState.to_numpy()` keeps a copy.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from e3dpsm.errors import InputError
from e3dpsm.runtime.session import StateArrays, StepSession, build_feeds
from e3dpsm.state import check_state_shapes

# OrtValue device names by execution provider; anything else computes on the host.
_PROVIDER_DEVICES = {
    "CUDAExecutionProvider": "cuda",
    "TensorrtExecutionProvider": "cuda",
    "ROCMExecutionProvider": "cuda",  # ORT's ROCm build names its device "cuda" too
    "DmlExecutionProvider": "dml",
}


def provider_device(session: Any) -> tuple[str, int]:
    """(OrtValue device name, device id) where the session's first provider keeps tensors."""
    providers = session.get_providers()
    first = providers[0] if providers else "CPUExecutionProvider"
    device = _PROVIDER_DEVICES.get(first, "cpu")
    device_id = 0
    if device != "cpu":
        options = session.get_provider_options().get(first, {})
        device_id = int(options.get("device_id", 0) or 0)
    return device, device_id


@dataclass(eq=False)
class _Lane:
    """Two state buffer sets of one batch size and the bindings that run between them."""

    batch: int
    values: tuple[dict[str, Any], dict[str, Any]]  # state name -> OrtValue, for buffer 0 and 1
    bindings: tuple[Any, Any]  # bindings[i]: state inputs values[i], state outputs values[1 - i]
    generation: list[int]  # bumped each time a buffer set is written
    holders: int = 0  # DeviceStates referring to this lane; 0: free for the next numpy input


class DeviceState(Mapping[str, np.ndarray]):
    """States held by an `IOBindingStepSession` (read-only; indexing copies to numpy)."""

    def __init__(self, owner: "IOBindingStepSession", lane: _Lane, index: int) -> None:
        self._owner, self._lane, self._index = owner, lane, index
        self._generation = lane.generation[index]
        lane.holders += 1

    def __del__(self) -> None:  # CPython frees at once, so the lane is reused by the next numpy input
        lane = self._lane
        lane.holders -= 1
        if lane.holders == 0:
            self._owner._free.setdefault(lane.batch, []).append(lane)

    @property
    def batch(self) -> int:
        return self._lane.batch

    @property
    def valid(self) -> bool:
        return self._lane.generation[self._index] == self._generation

    def ortvalues(self) -> dict[str, Any]:
        """The OrtValues themselves (on the provider's device); raises if overwritten."""
        if not self.valid:
            raise InputError(
                "this state was overwritten by a later step from the state after it (each chain of states "
                "reuses two buffers); keep state.to_numpy() to hold on to an older state"
            )
        return self._lane.values[self._index]

    def __getitem__(self, name: str) -> np.ndarray:
        # .numpy() of a CPU OrtValue aliases its buffer, which the next steps overwrite: copy.
        return np.array(self.ortvalues()[name].numpy(), copy=True)

    def __iter__(self) -> Iterator[str]:
        return iter(self._owner._state_names)

    def __len__(self) -> int:
        return len(self._owner._state_names)

    def to_numpy(self) -> StateArrays:
        return {name: self[name] for name in self}


class IOBindingStepSession(StepSession):
    """`StepSession` with the states kept as bound OrtValues (module doc).

    Functional use is the same as `StepSession`: `outputs, state = s.step(lnes, state, window_ms)`,
    where `state` is `init_state(batch)` (numpy) or the `DeviceState` of the previous step.
    Stateful use: `reset(batch)`, then `advance(lnes, window_ms) -> outputs`, `states()` to read.
    """

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None,
                 providers: Sequence[str] | None = None, options: Any = None, spin: bool = True) -> None:
        super().__init__(path, threads=threads, providers=providers, options=options, spin=spin)
        self.device, self.device_id = provider_device(self.session)
        self._state_names = [s.name for s in self.meta.states]
        self._pose_names = list(self.meta.output_names)
        self._free: dict[int, list[_Lane]] = {}  # batch size -> lanes no DeviceState refers to
        self._frame_shape = tuple(int(d) for d in self.meta.frame_input["shape"][1:])
        self._current: DeviceState | None = None
        self._reset_batch = 1

    # -- functional API (same as StepSession) -------------------------------------------------
    def feeds(self, lnes: np.ndarray, state: Mapping[str, np.ndarray], window_ms: float | np.ndarray) -> dict[str, Any]:
        """Checked inputs of one step; a `DeviceState` of this session is passed through unread."""
        if not isinstance(state, DeviceState):
            return build_feeds(self.meta, lnes, state, window_ms)
        if state._owner is not self:
            raise InputError("a DeviceState can only be fed to the session that produced it")
        state.ortvalues()  # raises if overwritten
        batch = state.batch
        window = np.asarray(window_ms, dtype=np.float32).reshape(-1)
        if window.shape[0] == 1 and batch > 1:
            window = np.repeat(window, batch)
        frame_ok = isinstance(lnes, np.ndarray) and lnes.dtype == np.float32 and lnes.shape == (batch, *self._frame_shape)
        if frame_ok and window.shape[0] == batch and bool((window > 0).all()):  # the every-step case: cheap
            return {self.frame_name: lnes, self.window_name: window, _DEVICE_STATE_KEY: state}
        # Something is off: let build_feeds name it, with zero-copy stand-ins for the states.
        stand_ins = {s.name: np.broadcast_to(np.float32(0), (batch, *s.shape)) for s in self.meta.states}
        feeds: dict[str, Any] = build_feeds(self.meta, lnes, stand_ins, window_ms)
        for spec in self.meta.states:
            del feeds[spec.input_name]
        feeds[_DEVICE_STATE_KEY] = state
        return feeds

    def run_feeds(self, feeds: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], DeviceState]:  # type: ignore[override]
        lnes, window = feeds[self.frame_name], feeds[self.window_name]
        state = feeds.get(_DEVICE_STATE_KEY)
        if isinstance(state, DeviceState):
            lane, source = state._lane, state._index
            state.ortvalues()  # raises if overwritten
        else:  # numpy states: copy them into a free lane
            numpy_states = {s.name: feeds[s.input_name] for s in self.meta.states}
            batch = check_state_shapes(self.meta.states, {k: v.shape for k, v in numpy_states.items()})
            lane, source = self._free_lane(batch), 0
            for name, value in numpy_states.items():  # a free lane: no DeviceState reads these buffers
                lane.values[source][name].update_inplace(np.ascontiguousarray(value, dtype=np.float32))
        target = 1 - source
        binding = lane.bindings[source]
        binding.bind_cpu_input(self.frame_name, np.ascontiguousarray(lnes, dtype=np.float32))
        binding.bind_cpu_input(self.window_name, np.ascontiguousarray(window, dtype=np.float32))
        lane.generation[target] += 1  # anything that lived in the target is gone from here on
        try:
            self.session.run_with_iobinding(binding)
        except Exception:
            if lane.holders == 0:  # taken for numpy states and not handed out: keep it reusable
                self._free.setdefault(lane.batch, []).append(lane)
            raise
        binding.synchronize_outputs()
        # Bound outputs: the pose outputs first (allocated by ORT each run), then the states.
        values = binding.get_outputs_as_ortvaluevector()  # no Python wrapper per output: only poses are read
        outputs = {name: np.array(values[i].numpy(), copy=True) for i, name in enumerate(self._pose_names)}
        return outputs, DeviceState(self, lane, target)

    def step(  # type: ignore[override]
        self, lnes: np.ndarray, state: Mapping[str, np.ndarray], window_ms: float | np.ndarray,
    ) -> tuple[dict[str, np.ndarray], DeviceState]:
        return self.run_feeds(self.feeds(lnes, state, window_ms))

    def run_raw(self, feeds: Mapping[str, Any]) -> list[np.ndarray]:
        # Its feeds carry a DeviceState that only run_feeds knows how to bind.
        raise NotImplementedError("IOBindingStepSession steps through run_feeds / step only")

    # -- stateful convenience -----------------------------------------------------------------
    def reset(self, batch: int = 1) -> None:
        """Start `batch` fresh streams for `advance`."""
        self._current = None
        self._reset_batch = batch

    def advance(self, lnes: np.ndarray, window_ms: float | np.ndarray) -> dict[str, np.ndarray]:
        """One step from the held state (initial after `reset`); returns the pose outputs."""
        state: Mapping[str, np.ndarray]
        if self._current is None:
            state = self.init_state(self._reset_batch)
        else:
            state = self._current
        outputs, self._current = self.step(lnes, state, window_ms)
        return outputs

    def states(self) -> StateArrays:
        """The held state as numpy (initial values before the first `advance`)."""
        if self._current is None:
            return self.init_state(self._reset_batch)
        return self._current.to_numpy()

    # -- buffers ------------------------------------------------------------------------------
    def _free_lane(self, batch: int) -> _Lane:
        free = self._free.get(batch)
        if free:
            return free.pop()
        import onnxruntime as ort

        values = tuple(
            {s.name: ort.OrtValue.ortvalue_from_shape_and_type(
                [batch, *s.shape], np.float32, self.device, self.device_id) for s in self.meta.states}
            for _ in range(2)
        )
        bindings = []
        for source in (0, 1):
            binding = self.session.io_binding()
            for spec in self.meta.states:
                binding.bind_ortvalue_input(spec.input_name, values[source][spec.name])
            # Pose outputs are small and read on the host every step: let ORT put them there.
            for name in self._pose_names:
                binding.bind_output(name, "cpu")
            for spec in self.meta.states:
                binding.bind_ortvalue_output(spec.output_name, values[1 - source][spec.name])
            bindings.append(binding)
        return _Lane(batch, values, (bindings[0], bindings[1]), [0, 0])  # type: ignore[arg-type]


_DEVICE_STATE_KEY = "__e3dpsm_device_state__"  # not a valid graph input name, so never clashes
