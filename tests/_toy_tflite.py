"""A step `.tflite` small enough to write out in numpy, built with the TFLite schema's object API
(no converter): the golden fakes' frame (2 x 4 x 4) and state `s` [6], the e3dpsm contract
embedded as `e3dpsm convert litert` embeds it, and two QUANTIZE operators whose 8-bit codes
tensors tests can compute by hand:

    state_out = state_in + window_ms                       (ADD)
    code 0    = QUANTIZE(state_out), scale 0.5, zero 0       read by nothing (an exposed-only code)
    code 1    = QUANTIZE(lnes), scale 1/127, zero -1         read by DEQUANTIZE
    pose      = DEQUANTIZE(code 1)
"""
from __future__ import annotations

import numpy as np

from _golden_fakes import FRAME, STATE, STATE_SHAPE

STATE_SCALE, STATE_ZERO = 0.5, 0
LNES_SCALE, LNES_ZERO = 1.0 / 127.0, -1


def quantize_i8(values: np.ndarray, scale: float, zero: int) -> np.ndarray:
    """TFLite's QUANTIZE in numpy: round half away from zero of value / scale, plus the zero point."""
    scaled = np.asarray(values, np.float32) / np.float32(scale)
    return np.clip(np.sign(scaled) * np.floor(np.abs(scaled) + 0.5) + zero, -128, 127).astype(np.int8)


def toy_pose(lnes: np.ndarray) -> np.ndarray:
    """The toy's pose output in numpy: the LNES quantised (code 1) and dequantised."""
    return (quantize_i8(lnes, LNES_SCALE, LNES_ZERO).astype(np.float32) - LNES_ZERO) * np.float32(LNES_SCALE)


def toy_tflite() -> bytes:
    import flatbuffers
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, encode
    from e3dpsm.runtime.tflite_metadata import with_metadata
    from e3dpsm.state import StateSpec, state_input_name, state_output_name

    ops = schema.BuiltinOperator
    codes = []
    for builtin in (ops.ADD, ops.QUANTIZE, ops.DEQUANTIZE):
        code = schema.OperatorCodeT()
        code.builtinCode, code.deprecatedBuiltinCode, code.version = builtin, min(builtin, 127), 1
        codes.append(code)

    def tensor(name: str, shape: tuple[int, ...], kind: int, scale: float | None = None, zero: int = 0) -> object:
        t = schema.TensorT()
        t.name, t.shape, t.type, t.buffer = name.encode(), np.array(shape, np.int32), kind, 0
        if scale is not None:
            t.quantization = schema.QuantizationParametersT()
            t.quantization.scale, t.quantization.zeroPoint = np.array([scale], np.float32), np.array([zero], np.int64)
        return t

    def operator(code: int, inputs: list[int], outputs: list[int]) -> object:
        op = schema.OperatorT()
        op.opcodeIndex, op.inputs, op.outputs = code, np.array(inputs, np.int32), np.array(outputs, np.int32)
        return op

    f32, i8 = schema.TensorType.FLOAT32, schema.TensorType.INT8
    frame, state = (1, *FRAME), (1, *STATE_SHAPE)
    names = ["lnes", "window_ms", state_input_name(STATE), state_output_name(STATE), "s_codes", "lnes_codes", "pose"]
    graph = schema.SubGraphT()
    graph.name = b"main"
    graph.tensors = [tensor(names[0], frame, f32), tensor(names[1], (1,), f32), tensor(names[2], state, f32),
                     tensor(names[3], state, f32), tensor(names[4], state, i8, STATE_SCALE, STATE_ZERO),
                     tensor(names[5], frame, i8, LNES_SCALE, LNES_ZERO), tensor(names[6], frame, f32)]
    graph.inputs, graph.outputs = np.array([0, 1, 2], np.int32), np.array([6, 3], np.int32)
    graph.operators = [operator(0, [2, 1], [3]), operator(1, [3], [4]), operator(1, [0], [5]), operator(2, [5], [6])]

    def entry(index: int) -> object:
        mapping = schema.TensorMapT()
        mapping.name, mapping.tensorIndex = names[index].encode(), index
        return mapping
    signature = schema.SignatureDefT()
    signature.signatureKey, signature.subgraphIndex = b"serving_default", 0
    signature.inputs, signature.outputs = [entry(0), entry(1), entry(2)], [entry(6), entry(3)]
    model = schema.ModelT()
    model.version, model.description = 3, b"e3dpsm toy"
    model.operatorCodes, model.subgraphs, model.buffers, model.signatureDefs = codes, [graph], [schema.BufferT()], [signature]
    builder = flatbuffers.Builder(4096)
    builder.Finish(model.Pack(builder), file_identifier=b"TFL3")
    meta = GraphMetadata(states=(StateSpec(STATE, STATE_SHAPE),),
                         inputs={"frame": {"name": "lnes", "shape": list(frame)}, "window": {"name": "window_ms", "shape": [1]}},
                         outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=[f"j{i}" for i in range(16)])
    return with_metadata(bytes(builder.Output()), EMBEDDED_NAME, encode(meta, {"format": "tflite", "precision": "int8"})
                         .encode("utf-8"))
