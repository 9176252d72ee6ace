"""The `released` variant against the released network itself.

The referee (tests/fixtures/released/make_reference.py) ran the authors' released code on
trained-like weights regenerated here from a seed; `reference.npz` holds its outputs.
Tolerance: 0.01 mm on every joint, frame and output (poses of metre scale).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

import e3dpsm
from e3dpsm.checkpoint import load_checkpoint
from e3dpsm.cli import main
from tests.fixtures.released.weights import lightning_checkpoint, make_state_dict, tensors_sha256

FIXTURE = Path(__file__).parent / "fixtures" / "released"
TOL_MM = 0.01
RELEASED_NETWORK_PARAMS = 6_640_406  # FACTS section 3, and the referee's own count
KALMAN_PARAMS = 96


@pytest.fixture(scope="module")
def manifest() -> dict:
    return json.loads((FIXTURE / "manifest.json").read_text())


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(FIXTURE / "reference.npz") as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def released_state(manifest) -> dict[str, torch.Tensor]:
    state = make_state_dict(manifest["layout"], manifest["seed"])
    assert tensors_sha256(state) == manifest["sha256"], (
        "the regenerated weights differ from the ones the referee ran: numpy's RandomState stream "
        "changed; re-run tests/fixtures/released/make_reference.py")
    return state


@pytest.fixture(scope="module")
def released_ckpt(released_state, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("released") / "epoch=14.ckpt"
    torch.save(lightning_checkpoint(released_state), path)
    return path


@pytest.fixture(scope="module")
def imported(released_ckpt, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("imported") / "imp"
    assert main(["import", "--released", str(released_ckpt), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def imported_model(imported) -> torch.nn.Module:
    model, _ = load_checkpoint(imported / "checkpoint.pt", variant="released")
    return model


def _max_err(got: torch.Tensor | np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(np.asarray(got, np.float64) - ref.astype(np.float64)).max())


def test_reference_is_not_trivial(reference) -> None:
    """The referee's poses move between frames and the fusion is neither pass-through."""
    pose, direct, delta = reference["pose"], reference["pose_direct"], reference["pose_delta"]
    assert np.abs(direct[:, 1:] - direct[:, :-1]).max() > 10.0
    assert np.abs(pose[:, 1:] - direct[:, 1:]).max() > 10.0  # fused differs from direct after t = 0
    assert np.abs(delta).max() > 1.0
    assert np.abs(pose).max() > 300.0  # metre-scale poses: the 0.01 mm tolerance is ~1e-5 relative


def test_imported_checkpoint_reproduces_released_outputs(imported_model, reference) -> None:
    with torch.no_grad():
        out = imported_model.forward_sequence(torch.from_numpy(reference["lnes"]), causal=False)
    errors = {
        "pose": _max_err(out["pose"], reference["pose"]),
        "pose_direct": _max_err(out["pose_direct"], reference["pose_direct"]),
        # the release computes no delta at a chunk's first frame
        "pose_delta": _max_err(out["pose_delta"][:, 1:], reference["pose_delta"]),
    }
    assert all(e <= TOL_MM for e in errors.values()), errors


@pytest.mark.parametrize("change, min_error_mm", [
    ({"input_norm": "none"}, 1.0),                     # the release rescales its input to [0, 1]
    ({"ssm_backward_first_frame": "scan"}, 0.05),     # its backward branch at t = 0
])
def test_each_released_peculiarity_is_needed(imported, reference, change, min_error_mm) -> None:
    """Each released detail moves the poses by more than the tolerance: the fixture bites."""
    payload = torch.load(imported / "checkpoint.pt", weights_only=True)
    model = e3dpsm.create_model("released", **change).eval()
    model.load_state_dict(payload["model"])
    with torch.no_grad():
        out = model.forward_sequence(torch.from_numpy(reference["lnes"]), causal=False)
    assert _max_err(out["pose"], reference["pose"]) > max(min_error_mm, TOL_MM)


def test_first_step_of_exported_graph_matches_released(imported, imported_model, reference, tmp_path) -> None:
    """One frame from a zero state: where the release and the causal step agree."""
    assert main(["export", "--checkpoint", str(imported / "checkpoint.pt"), "--out", str(tmp_path / "exp")]) == 0
    session = ort.InferenceSession(str(tmp_path / "exp" / "step.onnx"), providers=["CPUExecutionProvider"])
    meta = json.loads(session.get_modelmeta().custom_metadata_map["e3dpsm.states"])
    feeds = {s["input"]: np.zeros([1 if d == "batch" else d for d in s["shape"]], np.float32) if s["init"] == "zeros"
             else np.asarray(s["init"], np.float32).reshape([1] + s["shape"][1:]) for s in meta}
    feeds.update(lnes=reference["lnes"][:, 0], window_ms=np.array([20.0], np.float32))
    pose, direct = session.run(["pose", "pose_direct"], feeds)
    assert _max_err(pose, reference["first_pose"][:, 0]) <= TOL_MM
    assert _max_err(direct, reference["first_pose_direct"][:, 0]) <= TOL_MM
    with torch.no_grad():  # and the PyTorch step agrees with both
        out, _ = imported_model.step(torch.from_numpy(reference["lnes"][:, 0]), imported_model.init_state(1))
    assert _max_err(out["pose"], reference["first_pose"][:, 0]) <= TOL_MM


def test_parameter_counts(manifest) -> None:
    released = e3dpsm.create_model("released")
    assert sum(p.numel() for p in released.parameters()) == RELEASED_NETWORK_PARAMS + KALMAN_PARAMS
    assert manifest["network_parameters"] == RELEASED_NETWORK_PARAMS and manifest["kalman_parameters"] == KALMAN_PARAMS
    # paper = released + the learned 2-D reference grids (2 x tokens per stage)
    paper = e3dpsm.create_model("paper")
    grids = 2 * sum(h * w for h, w in (paper.config.stage_hw(i) for i in range(4)))
    assert sum(p.numel() for p in paper.parameters()) == RELEASED_NETWORK_PARAMS + KALMAN_PARAMS + grids


def test_import_report_accounts_for_every_key(imported, manifest) -> None:
    report = json.loads((imported / "import.json").read_text())
    checks = report["checks"]
    released_keys = {e["key"].split("event_3d_posenet.")[-1] for e in manifest["layout"]}
    used = {k for source in report["mapping"] for k in source.split(" + ")}
    identities = set(checks["kalman_identities_checked"])
    assert used | identities == released_keys
    assert not used & identities
    model_keys = set(e3dpsm.create_model("released").state_dict())
    filled = {k for targets in report["mapping"].values() for k in targets}
    assert filled | set(checks["derived"]) == model_keys and not filled & set(checks["derived"])
    assert checks["network_parameters"] == RELEASED_NETWORK_PARAMS and checks["kalman_parameters"] == KALMAN_PARAMS
    assert report["variant"] == "released" and report["params"] == RELEASED_NETWORK_PARAMS + KALMAN_PARAMS


@pytest.mark.parametrize("layout", ["egohpe_state_dict", "bare_network_and_kalman"])
def test_plain_state_dicts_import(released_state, imported_model, tmp_path, layout) -> None:
    if layout == "egohpe_state_dict":
        plain = dict(released_state)
    else:
        plain = {k.replace("event_3d_posenet.", "").replace("kalman_filter.", ""): v for k, v in released_state.items()}
    torch.save(plain, tmp_path / "plain.pt")
    assert main(["import", "--released", str(tmp_path / "plain.pt"), "--out", str(tmp_path / "out")]) == 0
    model, _ = load_checkpoint(tmp_path / "out" / "checkpoint.pt")
    for key, value in imported_model.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key


def _bad_import(tmp_path, capsys, payload) -> str:
    path = tmp_path / "bad.ckpt"
    if isinstance(payload, bytes):
        path.write_bytes(payload)
    else:
        torch.save(payload, path)
    out = tmp_path / "out"
    assert main(["import", "--released", str(path), "--out", str(out)]) == 2
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]
    err = capsys.readouterr().err.strip()
    assert err.startswith("e3dpsm import: error:") and "\n" not in err
    return err


def test_import_refuses_missing_and_unexpected_keys(released_state, tmp_path, capsys) -> None:
    state = dict(released_state)
    del state["event_3d_posenet.delta_head.bias"]
    state["event_3d_posenet.segmentation_head.weight"] = torch.zeros(3)
    err = _bad_import(tmp_path, capsys, lightning_checkpoint(state))
    assert "1 missing key(s): delta_head.bias" in err and "1 unexpected key(s): segmentation_head.weight" in err


def test_import_refuses_wrong_shapes(released_state, tmp_path, capsys) -> None:
    state = dict(released_state)
    state["event_3d_posenet.query_decoder.joint_queries"] = torch.zeros(15, 192)
    assert "query_decoder.joint_queries [15, 192]" in _bad_import(tmp_path, capsys, lightning_checkpoint(state))


def test_import_refuses_a_kalman_filter_that_is_not_identity(released_state, tmp_path, capsys) -> None:
    state = dict(released_state)
    state["kalman_filter.H"] = 2 * torch.eye(48)
    assert "kalman_filter.H is not the 48x48 identity" in _bad_import(tmp_path, capsys, lightning_checkpoint(state))


def test_import_refuses_pickled_code_without_running_it(released_state, tmp_path, capsys) -> None:
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    err = _bad_import(tmp_path, capsys, {**lightning_checkpoint(released_state), "callbacks": Payload()})
    assert "pickled code" in err and "nothing was executed" in err
    assert not marker.exists()


def test_import_refuses_files_that_are_not_checkpoints(tmp_path, capsys) -> None:
    assert "not a readable PyTorch checkpoint" in _bad_import(tmp_path, capsys, b"not a checkpoint at all")
    assert "neither a Lightning checkpoint" in _bad_import(tmp_path, capsys, {"epoch": 3})
