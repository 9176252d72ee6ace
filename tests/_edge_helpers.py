"""Session-scoped edge artifacts of the trained tiny (tests/fixtures/tiny_trained): one
conversion per runtime, an ONNX graph of the same checkpoint and a golden recorded from that
graph. A fixture whose extra is missing skips its tests with the install line."""
from __future__ import annotations

from pathlib import Path

import pytest

from _quantize_helpers import TRAINED_TINY

GOLDEN_STEPS = 30


class Judged:
    """What check_stepper returns, as far as the INT8 search and narrowing read it: a fake
    judge's verdict (worst share 0.5 within budget, 2.0 over, unless given)."""

    def __init__(self, within: bool, worst_share: float | None = None) -> None:
        self.within, self.fidelity_pct = within, 1.0
        self.worst_share = (0.5 if within else 2.0) if worst_share is None else worst_share


def skip_without(module: str) -> None:
    from e3dpsm.utils.extras import missing_reason

    reason = missing_reason(module)
    if reason:
        pytest.skip(reason)


def tflite_schema_graph(content: bytes):
    """(schema, model, subgraph 0, {opcode index: operator name}) of a `.tflite`, read with the
    TFLite schema itself: the tests' reference, not the converter's or the quantizer's readers."""
    from ai_edge_litert import schema_py_generated as schema

    names = {v: k for k, v in vars(schema.BuiltinOperator).items() if not k.startswith("_")}
    model = schema.Model.GetRootAs(content, 0)
    codes = {i: names.get(max(model.OperatorCodes(i).BuiltinCode(), model.OperatorCodes(i).DeprecatedBuiltinCode()))
             for i in range(model.OperatorCodesLength())}
    return schema, model, model.Subgraphs(0), codes


def litert_pose_rollout(path: Path, frames, window_ms: float = 20.0):
    """The `pose` output at each frame of a `.tflite` stepped by LiteRTStepSession, states
    carried, every output and state checked to be float32 (a quantised output or a state left
    dangling by a rewrite fails here)."""
    import numpy as np

    from e3dpsm.runtime.litert_session import LiteRTStepSession

    session = LiteRTStepSession(path, threads=1)
    state, poses = session.init_state(1), []
    for frame in frames:
        out, state = session.step(np.ascontiguousarray(frame[None]), state, window_ms)
        assert all(np.asarray(v).dtype == np.float32 for v in (*out.values(), *state.values())), path.name
        poses.append(out["pose"][0])
    return np.stack(poses)


@pytest.fixture(scope="session")
def edge_model():
    from e3dpsm.checkpoint import load_checkpoint

    model, _ = load_checkpoint(TRAINED_TINY, variant="tiny")
    return model


@pytest.fixture(scope="session")
def edge_golden(tmp_path_factory, trained_graph, quant_data) -> Path:
    """GOLDEN_STEPS steps of the trained tiny's fp32 ONNX graph over the test split."""
    from e3dpsm.golden.record import onnx_reference, record_golden

    out = tmp_path_factory.mktemp("edge") / "golden"
    record_golden(onnx_reference(trained_graph, threads=1), quant_data, out, steps=GOLDEN_STEPS, window_ms=20.0,
                  split="test")
    return out


@pytest.fixture(scope="session")
def pte_path(tmp_path_factory, edge_model) -> Path:
    skip_without("executorch")
    from e3dpsm.export.executorch_export import convert_executorch

    path = tmp_path_factory.mktemp("edge_pte") / "step.pte"
    convert_executorch(edge_model, path)
    return path


@pytest.fixture(scope="session")
def tflite_path(tmp_path_factory, edge_model) -> Path:
    skip_without("litert_torch")
    from e3dpsm.export.litert_export import LiteRTOptions, convert_litert

    # litert-torch's tensor names kept: the INT8 tests place 8 bits by them (module paths);
    # test_litert_int8 checks the default short names change nothing else.
    path = tmp_path_factory.mktemp("edge_tflite") / "step.tflite"
    convert_litert(edge_model, path, LiteRTOptions(keep_tensor_names=True))
    return path


@pytest.fixture(scope="session")
def coreml_result(tmp_path_factory, edge_model):
    skip_without("coremltools")
    from e3dpsm.export.coreml_export import convert_coreml

    return convert_coreml(edge_model, tmp_path_factory.mktemp("edge_coreml") / "step.mlpackage")


@pytest.fixture()
def artifact(request) -> Path:
    """The artifact of the runtime the test is parametrised with."""
    return request.getfixturevalue({"executorch": "pte_path", "litert": "tflite_path"}[request.param])
