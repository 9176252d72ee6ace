"""The `released` variant against the released network itself.

The referee (tests/fixtures/released/make_reference.py) ran the authors' released code on
trained-like weights regenerated here from a seed; `reference.npz` holds its outputs in the
release's own unit, metres. They are compared in millimetres, as the release's evaluation
reports them (`abs_poses * 1000`, "scale to mm", modules/pose_estimation.py): every
variant's outputs are millimetres, `released` included.
Tolerance: 0.01 mm on every joint, frame and output (poses of metre scale).
"""
from __future__ import annotations

import json
import os
import sys
import types
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

import e3dpsm
from e3dpsm.checkpoint import load_checkpoint
from e3dpsm.errors import CheckpointError
from e3dpsm.cli import main
from tests.fixtures.released.weights import lightning_checkpoint, make_state_dict, tensors_sha256

FIXTURE = Path(__file__).parent / "fixtures" / "released"
TOL_MM = 0.01
RELEASE_MM_PER_UNIT = 1000.0  # the release's evaluation: outputs x 1000 (metres -> mm)
# The paper's 6.64 M (Table 5), counted exactly on the released network, and the referee's
# own count.
RELEASED_NETWORK_PARAMS = 6_640_406
KALMAN_PARAMS = 96


@pytest.fixture(scope="module")
def manifest() -> dict:
    return json.loads((FIXTURE / "manifest.json").read_text())


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    """The referee's outputs in millimetres (released output x 1000), its input as it was."""
    with np.load(FIXTURE / "reference.npz") as data:
        return {k: data[k] if k == "lnes" else data[k].astype(np.float64) * RELEASE_MM_PER_UNIT for k in data.files}


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
    with np.load(FIXTURE / "reference.npz") as raw:  # stored in the release's unit, metres
        assert 0.3 < np.abs(raw["pose"]).max() < 3.0


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
    ({"pose_unit_mm": 1.0}, 300.0),                   # metres reported as mm: poses ~1000x too small
    ({"kalman_p0": 1.0}, 1.0),                        # P0 left at the release's 1 (m^2) in the mm filter
])
def test_each_released_peculiarity_is_needed(imported, reference, change, min_error_mm) -> None:
    """Each released detail moves the poses by more than the tolerance: the fixture bites."""
    payload = torch.load(imported / "checkpoint.pt", weights_only=True)
    model = e3dpsm.create_model("released", **change).eval()
    model.load_state_dict(payload["model"])
    with torch.no_grad():
        out = model.forward_sequence(torch.from_numpy(reference["lnes"]), causal=False)
    assert _max_err(out["pose"], reference["pose"]) > max(min_error_mm, TOL_MM)


def test_kalman_covariance_state_is_the_released_filter_in_mm2(imported_model, released_state, reference) -> None:
    """The fused pose cannot see Q and R's unit (scaling P0, Q and R together leaves every gain
    unchanged), but the carried covariance can: after each step it must be the release's
    filter run in m^2 (its P0 = I; Joseph form, an explicit numpy loop) times 1000^2."""
    q = released_state["kalman_filter.log_process_var"].double().exp().numpy()
    r = released_state["kalman_filter.log_measurement_var"].double().exp().numpy()
    cov_m2, expected = np.ones_like(q), []
    for _ in range(3):
        predicted = cov_m2 + q
        gain = predicted / (predicted + r)
        cov_m2 = (1 - gain) ** 2 * predicted + gain**2 * r
        expected.append(cov_m2 * 1000.0**2)
    state = imported_model.init_state(1)
    with torch.no_grad():
        for t in range(3):
            _, state = imported_model.step(torch.from_numpy(reference["lnes"][:, t]), state)
            got = state["fusion_cov"].double().numpy().reshape(-1)
            if t == 0:  # the first step starts the filter: P0 = the release's I, in mm^2
                np.testing.assert_allclose(got, 1000.0**2, rtol=1e-6)
            else:
                np.testing.assert_allclose(got, expected[t - 1], rtol=1e-4)


def test_imported_kalman_variances_are_the_released_ones_in_mm2(imported_model, released_state) -> None:
    """Closed form: Q_mm2 = Q_m2 x 1000^2, element for element."""
    for ours, theirs in (("log_q", "log_process_var"), ("log_r", "log_measurement_var")):
        got = getattr(imported_model.fusion, ours).detach().double().exp().reshape(-1)
        expected = released_state[f"kalman_filter.{theirs}"].double().exp() * 1000.0**2
        np.testing.assert_allclose(got.numpy(), expected.numpy(), rtol=1e-6)
    assert imported_model.config.kalman_p0 == 1000.0**2 and imported_model.config.pose_unit_mm == 1000.0


def test_checkpoint_imported_before_the_unit_fix_is_refused(imported, tmp_path) -> None:
    """An import written before the conversion (config without kalman_p0, pose_unit_mm 1)
    would give metres labelled mm: refused with a line saying to re-import."""
    payload = torch.load(imported / "checkpoint.pt", weights_only=True)
    payload["config"] = {k: v for k, v in payload["config"].items() if k != "kalman_p0"} | {"pose_unit_mm": 1.0}
    torch.save(payload, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="re-run e3dpsm import --released"):
        load_checkpoint(tmp_path / "old.pt")


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
    assert "metres" in checks["units"]["released"] and "ln(1e6)" in checks["units"]["imported"]
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


def _fake_lightning_attribute_dict(monkeypatch) -> type:
    """PyTorch Lightning 2.5's AttributeDict, as pickled by name, without Lightning installed."""
    class AttributeDict(dict):
        def __getattr__(self, key):
            return self[key]

    AttributeDict.__module__, AttributeDict.__qualname__ = "lightning_fabric.utilities.data", "AttributeDict"
    for name in ("lightning_fabric", "lightning_fabric.utilities", "lightning_fabric.utilities.data"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    sys.modules["lightning_fabric.utilities.data"].AttributeDict = AttributeDict
    return AttributeDict


def test_lightning_checkpoint_with_attribute_dict_imports(released_state, imported_model, tmp_path, monkeypatch) -> None:
    """Lightning pickles AttributeDict in hyper_parameters: read as a plain dict, nothing run."""
    with monkeypatch.context() as patch:
        attribute_dict = _fake_lightning_attribute_dict(patch)
        payload = {**lightning_checkpoint(released_state), "hparams_name": "kwargs",
                   "hyper_parameters": attribute_dict(lr=1e-3, model=attribute_dict(num_joints=16))}
        torch.save(payload, tmp_path / "pl25.ckpt")
    assert "lightning_fabric.utilities.data" not in sys.modules  # the reader has no Lightning
    with pytest.raises(Exception, match="AttributeDict"):  # what weights_only alone says of it
        torch.load(tmp_path / "pl25.ckpt", weights_only=True)
    assert main(["import", "--released", str(tmp_path / "pl25.ckpt"), "--out", str(tmp_path / "out")]) == 0
    model, _ = load_checkpoint(tmp_path / "out" / "checkpoint.pt")
    for key, value in imported_model.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key


def test_import_refuses_a_pickled_callable_beside_the_attribute_dict(released_state, tmp_path, capsys,
                                                                     monkeypatch) -> None:
    """The allow-list admits AttributeDict, not whatever else sits beside it: a pickled
    function (here `os.system`) is refused, one line, nothing written."""
    with monkeypatch.context() as patch:
        attribute_dict = _fake_lightning_attribute_dict(patch)
        payload = {**lightning_checkpoint(released_state), "hyper_parameters": attribute_dict(hook=os.system)}
        err = _bad_import(tmp_path, capsys, payload)
    assert "pickled code" in err and f"{os.system.__module__}.system" in err and "nothing was executed" in err


def test_import_refuses_files_that_are_not_checkpoints(tmp_path, capsys) -> None:
    assert "not a readable PyTorch checkpoint" in _bad_import(tmp_path, capsys, b"not a checkpoint at all")
    assert "neither a Lightning checkpoint" in _bad_import(tmp_path, capsys, {"epoch": 3})
