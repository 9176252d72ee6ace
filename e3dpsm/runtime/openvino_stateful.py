"""Drive a *stateful* OpenVINO IR written by `e3dpsm convert openvino --stateful`.

The recurrent states live inside the compiled model as OpenVINO variables (ReadValue /
Assign pairs, one per `e3dpsm.states` entry, variable id = state name), so a step takes only
the frame and the window length. Their initial values (zeros, the Kalman covariance's
non-zero start) are the variables' initialisers inside the IR: a fresh infer request, or one
after `reset()`, starts a stream correctly with nothing set by hand.

The e3dpsm metadata travels in the IR's `rt_info` (section `e3dpsm`, the ONNX
`metadata_props` verbatim), so this module needs neither the ONNX file nor torch.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.errors import ConfigError, InputError
from e3dpsm.graph_metadata import GraphMetadata, MetadataError
from e3dpsm.runtime.openvino_session import compile_config, openvino_available, read_openvino_model
from e3dpsm.state import initial_states, state_input_name, state_output_name

RT_METADATA = "e3dpsm"            # rt_info section: the ONNX metadata_props, key for key
RT_CONVERSION = "e3dpsm_openvino"  # rt_info section: how the IR was made (stateful, batch, source)


def read_rt_section(model: Any, section: str) -> dict[str, str]:
    """One rt_info section of an `openvino.Model` as plain strings ({} when absent)."""
    if not model.has_rt_info([section]):
        return {}
    return {str(key): model.get_rt_info([section, key]).astype(str) for key in model.get_rt_info()[section]}


def metadata_from_ir(model: Any, source: str = "IR") -> GraphMetadata:
    """The e3dpsm graph metadata carried in an IR's rt_info."""
    props = read_rt_section(model, RT_METADATA)
    if not props:
        raise MetadataError(f"{source} carries no e3dpsm metadata in its rt_info; convert the step graph with "
                            "`e3dpsm convert openvino`")
    return GraphMetadata.from_props(props, source)


class OpenVINOStatefulSession:
    """A stateful IR: `step(lnes, window_ms) -> outputs`, `reset()`, `states()`.

    One infer request is one stream (the IR's batch is 1, checked on opening); open one session
    per concurrent stream.
    """

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None, device: str = "CPU",
                 config: dict[str, Any] | None = None) -> None:
        ok, reason = openvino_available()  # before judging the file, as every OpenVINO entry point does
        if not ok:
            raise ConfigError(reason)
        self.path = Path(path)
        if self.path.is_file() and self.path.suffix != ".xml":
            raise InputError(f"{self.path} is not an OpenVINO IR (.xml); convert the step graph first with "
                             "`e3dpsm convert openvino --model STEP.onnx --out DIR --stateful`")
        core, model = read_openvino_model(self.path)
        self.meta = metadata_from_ir(model, str(self.path))
        self.conversion = {k: json.loads(v) for k, v in read_rt_section(model, RT_CONVERSION).items()}
        self._check_stateful(model)
        self._compiled = core.compile_model(model, device, compile_config(threads, config))
        self._request = self._compiled.create_infer_request()
        self.batch = int(model.input(self.meta.frame_input["name"]).get_partial_shape()[0].get_length())
        self._frame_shape = (self.batch, *(int(d) for d in self.meta.frame_input["shape"][1:]))
        # A port may carry several tensor names (OpenVINO merges an Identity's output into
        # its producer's): index every name so each metadata output is found.
        self._output_ports = {name: port for port in self._compiled.outputs for name in port.get_names()}

    @property
    def compiled(self) -> Any:
        """The openvino.CompiledModel (its run-time graph says which kernels run)."""
        return self._compiled

    def _check_stateful(self, model: Any) -> None:
        variables = {v.info.variable_id for v in model.get_variables()}
        expected = {s.name for s in self.meta.states}
        if variables != expected:
            raise InputError(f"{self.path}: variables {sorted(variables)} do not match the metadata's states "
                             f"{sorted(expected)}; is it a stateful IR (`e3dpsm convert openvino --stateful`)?")
        inputs = {name for port in model.inputs for name in port.get_names()}
        wanted = {self.meta.frame_input["name"], self.meta.window_input["name"]}
        if not wanted <= inputs or len(model.inputs) != 2:
            raise InputError(f"{self.path}: inputs {sorted(inputs)}, expected exactly {sorted(wanted)}")
        batch = model.input(self.meta.frame_input["name"]).get_partial_shape()[0]
        if not batch.is_static:
            raise InputError(f"{self.path}: the batch axis is dynamic; a stateful IR needs a fixed batch")
        if batch.get_length() != 1:
            # Measured (OpenVINO 2026.4, CPU, fp32): with a static batch of 2 every step starts
            # again from the initialisers and the request reports empty variables: no error, wrong poses.
            raise InputError(f"{self.path}: a stateful IR of batch {batch.get_length()}, whose variables "
                             "OpenVINO's CPU plugin does not carry from step to step; convert with batch 1 "
                             "(`e3dpsm convert openvino --stateful`) and open one session per stream")

    def input_names(self) -> list[str]:
        return [port.get_any_name() for port in self._compiled.inputs]

    def output_names(self) -> list[str]:
        """The IR's outputs, by the names the metadata gives them."""
        names = [n for n in self.meta.output_names if n in self._output_ports]
        return names + [port.get_any_name() for port in self._compiled.outputs
                        if not port.get_names() & set(self.meta.output_names)]

    def variable_names(self) -> list[str]:
        """The ids of the request's variables (one per recurrent state)."""
        return [q.name for q in self._request.query_state()]

    # -- stepping -------------------------------------------------------------------------
    def step(self, lnes: np.ndarray, window_ms: float | np.ndarray) -> dict[str, np.ndarray]:
        """One window for every stream of the batch; the states advance inside the request."""
        if not isinstance(lnes, np.ndarray) or tuple(lnes.shape) != self._frame_shape:
            got = list(lnes.shape) if isinstance(lnes, np.ndarray) else type(lnes).__name__
            raise InputError(f"LNES has shape {got}, expected {list(self._frame_shape)}")
        if lnes.dtype != np.float32:
            raise InputError(f"LNES has dtype {lnes.dtype}, expected float32")
        window = np.asarray(window_ms, dtype=np.float32).reshape(-1)
        if window.shape != (1,) or not window[0] > 0:
            raise InputError(f"window_ms must be one positive value, got {window.tolist()}")
        self._request.infer({self.meta.frame_input["name"]: np.ascontiguousarray(lnes),
                             self.meta.window_input["name"]: window})
        return {name: self._request.get_tensor(self._output_ports[name]).data.copy()
                for name in self.meta.output_names}

    def reset(self) -> None:
        """Start a new stream: every variable goes back to its initialiser on the next step."""
        self._request.reset_state()

    def states(self) -> dict[str, np.ndarray]:
        """The variables' current values, keyed by state name (copies).

        Before the first step of a fresh request (or after `reset()`) the initialisers have
        not run yet and OpenVINO reports empty arrays; `initial_states()` gives what they hold.
        """
        values = {q.name: np.array(q.state.data, dtype=np.float32) for q in self._request.query_state()}
        return {s.name: values[s.name] for s in self.meta.states}

    def initial_states(self) -> dict[str, np.ndarray]:
        """The initial values named in the metadata (those the IR's initialisers hold)."""
        return initial_states(self.meta.states, self.batch)


class ExplicitStateView:
    """A `GraphStepper` (e3dpsm.runtime.stepping) over a stateful session, for parity.

    `step` ignores the state it is given and returns the variables read back from the
    request, so a parity check compares the runtime's own internal states with PyTorch's.
    Input / output names are the IR's plus one `<state>_in` / `<state>_out` per variable,
    checked to exist, so the name check stays a real check.
    """

    def __init__(self, session: OpenVINOStatefulSession) -> None:
        self.session = session
        self.meta = session.meta

    def input_names(self) -> list[str]:
        return self.session.input_names() + [state_input_name(v) for v in self.session.variable_names()]

    def output_names_all(self) -> list[str]:
        return self.session.output_names() + [state_output_name(v) for v in self.session.variable_names()]

    def init_state(self, batch: int = 1) -> dict[str, np.ndarray]:
        if batch != self.session.batch:
            raise InputError(f"the IR is fixed to batch {self.session.batch}, asked for {batch}")
        self.session.reset()
        return self.session.initial_states()

    def step(self, lnes: np.ndarray, state: Any, window_ms: float) -> tuple[dict, dict]:
        outputs = self.session.step(lnes, window_ms)
        return outputs, self.session.states()
