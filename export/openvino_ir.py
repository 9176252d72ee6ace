"""ONNX step graph -> OpenVINO IR (xml + bin), optionally stateful.

Plain: the graph as OpenVINO reads it, states still explicit inputs / outputs, batch as in
the ONNX file unless fixed.

Stateful: every `<state>_in` / `<state>_out` pair named in the metadata's `e3dpsm.states`
becomes one OpenVINO variable (ReadValue -> ... -> Assign, variable id = state name);
`window_ms` and the frame stay inputs. Two choices make the IR run as it is in any
OpenVINO application, C++ included:

- the frame and window inputs get a fixed batch of 1 (a stateful request is one stream), and
- each ReadValue gets an initialiser of constants holding that many copies of the
  metadata's `init` values (zeros, the Kalman covariance's start), so a fresh request (or
  one after reset_state) starts correctly with no state set by hand. Without initialisers
  (MakeStateful alone) the variables of a dynamic-batch graph have no shape and a fresh
  request returns empty outputs.

The ONNX `metadata_props` travel verbatim in the IR's rt_info (section `e3dpsm`), and the IR
carries `runtime_options` that keep OpenVINO from quantising 16-bit and float activations to 8
bits at run time (`runtime.openvino_session.DYNAMIC_QUANTIZATION_OFF`).
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from e3dpsm.errors import ConfigError, DataError, InputError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_graph import read_onnx
from e3dpsm.runtime.openvino_session import DYNAMIC_QUANTIZATION_OFF, read_openvino_model
from e3dpsm.runtime.openvino_stateful import RT_CONVERSION, RT_METADATA


@dataclass
class ConversionInfo:
    """What a conversion did; recorded in the IR's rt_info and in convert.json."""

    source: str
    stateful: bool
    batch: int | None  # None: left as in the ONNX graph (dynamic)
    precision: str     # "fp32" | "int8" | "fp16", from the graph's quantisation metadata
    inputs: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)
    variables: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def read_step_graph(path: str | os.PathLike) -> tuple[Any, GraphMetadata, dict[str, str]]:
    """(openvino.Model, metadata, raw metadata_props) of an exported ONNX step graph."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    if path.suffix != ".onnx":
        raise InputError(f"{path} is not an ONNX step graph (.onnx), as written by e3dpsm export / quantize")
    proto = read_onnx(path, load_external_data=False)
    props = {p.key: p.value for p in proto.metadata_props}
    meta = GraphMetadata.from_props(props, str(path))  # MetadataError (exit 2) without e3dpsm metadata
    _, model = read_openvino_model(path)  # e3dpsm's OpenVINO read: its errors, the INT8 graph protected
    return model, meta, props


def _params_by_name(model: Any) -> dict[str, Any]:
    return {name: p for p in model.get_parameters() for name in p.get_output_tensor(0).get_names()}


def _results_by_name(model: Any) -> dict[str, Any]:
    return {name: r for r in model.get_results() for name in r.get_output_tensor(0).get_names()}


def fix_batch(model: Any, meta: GraphMetadata, batch: int, *, states: bool = True) -> None:
    """Reshape the frame and window inputs (and, with `states`, the state inputs) to a static batch."""
    import openvino as ov

    shapes = {meta.frame_input["name"]: [batch, *meta.frame_input["shape"][1:]], meta.window_input["name"]: [batch]}
    if states:
        shapes.update({s.input_name: [batch, *s.shape] for s in meta.states})
    present = _params_by_name(model)
    missing = sorted(set(shapes) - set(present))
    if missing:
        raise InputError(f"the graph lacks the inputs {missing} its metadata names")
    model.reshape({name: ov.PartialShape([int(d) for d in shape]) for name, shape in shapes.items()})


def make_stateful(model: Any, meta: GraphMetadata, batch: int) -> list[str]:
    """Turn the state pairs into variables whose initialisers hold `batch` copies of the
    metadata's initial values; returns the variable ids (= state names).

    The frame and window inputs must already be fixed to `batch` (fix_batch(states=False)).
    The variables' own batch axis stays dynamic: their initialisers give it its size on the
    first read. Fully static variables were measured to break two ways on the OpenVINO 2026.4
    CPU plugin: the INT8 QDQ graph no longer compiles ("Gemm_87/WithoutBiases/
    DequantizationSubtract contains empty child edge"), and an Assign whose value folds to a
    constant (the Kalman "initialised" flag: ones of the state's shape) is dropped, so every
    step looks like a stream's first.
    """
    import openvino as ov
    import openvino.opset13 as ops
    from openvino.op import assign
    from openvino.op.util import Variable, VariableInfo

    params, results = _params_by_name(model), _results_by_name(model)
    for spec in meta.states:
        for name, table in ((spec.input_name, params), (spec.output_name, results)):
            if name not in table:
                raise InputError(f"state {spec.name!r}: the graph has no tensor {name!r}")
        if spec.dtype != "float32":
            raise InputError(f"state {spec.name!r} has dtype {spec.dtype}; only float32 states are supported")
    for spec in meta.states:
        info = VariableInfo()
        info.variable_id = spec.name
        info.data_type = ov.Type.f32
        info.data_shape = ov.PartialShape([-1, *spec.shape])
        variable = Variable(info)
        init = ops.constant(spec.initial_value(batch), name=f"{spec.name}/init")
        read = ops.read_value(init, variable, name=f"{spec.name}/read")
        param = params[spec.input_name]
        for consumer in list(param.output(0).get_target_inputs()):
            consumer.replace_source_output(read.output(0))
        result = results[spec.output_name]
        # Assign takes a node: build it on the read (right type), then point its input at
        # the state's next value, whichever port of its producer that is.
        node = assign(read, variable)
        node.input(0).replace_source_output(result.input_value(0))
        node.set_friendly_name(f"{spec.name}/assign")
        model.remove_result(result)
        model.remove_parameter(param)
        model.add_variables([variable])
        model.add_sinks([node])
    model.validate_nodes_and_infer_types()
    return [s.name for s in meta.states]


# The rt_info section OpenVINO's CPU plugin reads compile options from (since 2024.5), so that
# an application compiling the IR with no options of its own runs the graph's arithmetic.
RT_RUNTIME_OPTIONS = "runtime_options"


def attach_metadata(model: Any, props: dict[str, str], info: ConversionInfo) -> None:
    for key, value in props.items():
        model.set_rt_info(value, [RT_METADATA, key])
    for key, value in info.to_dict().items():
        model.set_rt_info(json.dumps(value), [RT_CONVERSION, key])
    for key, value in DYNAMIC_QUANTIZATION_OFF.items():
        model.set_rt_info(str(value), [RT_RUNTIME_OPTIONS, key])


def _precision(meta: GraphMetadata) -> str:
    quant = meta.quantization or {}
    return str(quant.get("mode") or quant.get("precision") or "fp32")


def convert_step_graph(path: str | os.PathLike, *, stateful: bool,
                       batch: int | None = None) -> tuple[Any, ConversionInfo]:
    """The openvino.Model of an ONNX step graph (not yet saved) and what was done to it."""
    if batch is not None and batch < 1:
        raise ConfigError(f"batch must be >= 1, got {batch}")
    if stateful and batch is None:
        batch = 1
    if stateful and batch != 1:
        # Measured on OpenVINO 2026.4 CPU: variables with a dynamic batch axis fail at run time
        # for batch > 1 ("Can't reorder data with dynamic shapes" at an Assign), and static
        # ones break the INT8 graph (see make_stateful). One request per stream works for all.
        raise ConfigError(f"--stateful supports batch 1 (one stream per infer request), got {batch}; "
                          "open one request per stream")
    model, meta, props = read_step_graph(path)
    if batch is not None:
        fix_batch(model, meta, batch, states=not stateful)
    variables = make_stateful(model, meta, int(batch)) if stateful else []
    info = ConversionInfo(
        source=Path(path).name, stateful=stateful, batch=batch, precision=_precision(meta),
        inputs=[p.get_any_name() for p in model.inputs], outputs=[p.get_any_name() for p in model.outputs],
        variables=variables,
    )
    attach_metadata(model, props, info)
    return model, info


def save_ir(model: Any, xml_path: str | os.PathLike) -> tuple[Path, Path]:
    """Write xml + bin; weights stay as they are (no fp16 compression of an fp32 graph)."""
    import openvino as ov

    xml_path = Path(xml_path)
    ov.save_model(model, str(xml_path), compress_to_fp16=False)
    return xml_path, xml_path.with_suffix(".bin")
