"""The stateful OpenVINO IR's Kalman covariance start, seen through behaviour.

Why parity with PyTorch cannot see a wrong covariance initialiser (x0 or x10 passes it): a
stream's first step has `fusion_initialised` = 0, and the fusion then outputs the direct
pose and restarts the filter with `cov = started * cov + (1 - started) * p0`, so the
carried covariance is multiplied by 0: any finite initial covariance gives bit-identical
outputs and states (checked below on onnxruntime). From the second step on the covariance
is the graph's own.

The initial covariance is read only by a step whose flag says the stream has started. A
plain OpenVINO request can set one variable and leave the others to their initialisers:
with the flag set to 1 before the first step, the first fused pose is the Kalman update
from the IR's covariance start, which must match onnxruntime fed the metadata's initial
states with the same flag (6e-5 mm measured; a x10 start moves the pose by ~11 mm, x0 by
~1,000 mm).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ov = pytest.importorskip("openvino", reason="OpenVINO is not installed: the stateful IR cannot be built")

from e3dpsm.export.openvino_ir import convert_step_graph, save_ir  # noqa: E402
from e3dpsm.profiles.inputs import moving_edge_frames  # noqa: E402
from e3dpsm.runtime import StepSession  # noqa: E402

STEPS = 3
POSE_ATOL_MM = 1e-3


@pytest.fixture(scope="module")
def stateful_xml(tmp_path_factory, tiny_step_graph) -> Path:  # noqa: F811
    model, info = convert_step_graph(tiny_step_graph, stateful=True)
    assert "fusion_cov" in info.variables
    xml, _ = save_ir(model, tmp_path_factory.mktemp("ov_init") / "stateful.xml")
    return xml


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return moving_edge_frames(STEPS, 192, 256, 20.0, seed=5).lnes


@pytest.fixture(scope="module")
def reference(tiny_step_graph) -> StepSession:  # noqa: F811
    return StepSession(tiny_step_graph, threads=1)


def _onnx_rollout(session: StepSession, frames: np.ndarray, cov_factor: float = 1.0, started: bool = True):
    """onnxruntime from the metadata's initial states, the covariance start scaled."""
    state = session.init_state(1)
    state["fusion_cov"] = state["fusion_cov"] * np.float32(cov_factor)
    if started:
        state["fusion_initialised"] = np.ones_like(state["fusion_initialised"])
    poses, covs = [], []
    for frame in frames:
        out, state = session.step(frame[None], state, 20.0)
        poses.append(out["pose"][0])
        covs.append(state["fusion_cov"][0])
    return np.stack(poses), np.stack(covs)


def test_the_first_step_ignores_the_covariance_start(reference, frames):
    """Why parity cannot see it: from a fresh stream (flag 0) the start is multiplied by 0."""
    ref_pose, ref_cov = _onnx_rollout(reference, frames, started=False)
    for factor in (0.0, 10.0):
        pose, cov = _onnx_rollout(reference, frames, factor, started=False)
        np.testing.assert_array_equal(pose, ref_pose)
        np.testing.assert_array_equal(cov, ref_cov)
    # while for a started stream the same start moves the pose far beyond the parity tolerance
    started, _ = _onnx_rollout(reference, frames, 1.0)
    for factor, at_least_mm in ((0.0, 100.0), (10.0, 1.0)):
        moved, _ = _onnx_rollout(reference, frames, factor)
        assert np.abs(moved[0] - started[0]).max() > at_least_mm


def test_stateful_ir_kalman_update_from_its_covariance_start(stateful_xml, reference, frames):
    """A fresh plain OpenVINO request, only the flag set: its first Kalman update reads the
    IR's covariance initialiser and must equal onnxruntime's from the metadata's."""
    core = ov.Core()
    request = core.compile_model(core.read_model(str(stateful_xml)), "CPU",
                                 {"INFERENCE_PRECISION_HINT": "f32", "INFERENCE_NUM_THREADS": 1}).create_infer_request()
    flag = next(q for q in request.query_state() if q.name == "fusion_initialised")
    flag.state = ov.Tensor(np.ones((1, 1), np.float32))  # every other variable: its initialiser
    pose_port = next(p for p in request.model_outputs if "pose" in p.get_names())
    poses, covs = [], []
    for frame in frames:
        request.infer({"lnes": frame[None], "window_ms": np.array([20.0], np.float32)})
        poses.append(np.array(request.get_tensor(pose_port).data)[0])
        covs.append(next(np.array(q.state.data)[0] for q in request.query_state() if q.name == "fusion_cov"))
    ref_pose, ref_cov = _onnx_rollout(reference, frames)
    np.testing.assert_allclose(np.stack(poses), ref_pose, rtol=0, atol=POSE_ATOL_MM)
    np.testing.assert_allclose(np.stack(covs), ref_cov, rtol=1e-4, atol=0)
    assert np.all(np.stack(covs) != 1.0)  # the filter ran: no first-step restart to p0
