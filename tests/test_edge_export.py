"""The edge converters' pieces: norms as matmuls against numpy, what folding and the norm
decompositions hand to XNNPACK (on a toy model), the Core ML package's Linux-side checks,
the TensorRT path's skip, the artifact metadata contract and the profile's edge targets."""
from __future__ import annotations

import platform
import sys

import numpy as np
import pytest
import torch

from _edge_helpers import skip_without
from e3dpsm.cli import main
from e3dpsm.export.norm_decompositions import group_norm_as_matmuls, layer_norm_as_matmuls


def _numpy_norm(rows: np.ndarray, eps: float) -> np.ndarray:
    rows = rows.astype(np.float64)
    mean = rows.mean(axis=1, keepdims=True)
    var = ((rows - mean) ** 2).mean(axis=1, keepdims=True)
    return (rows - mean) / np.sqrt(var + eps)


def test_layer_norm_as_matmuls_against_numpy() -> None:
    x = torch.randn(2, 5, 7, 24) * 30 + 5
    weight, bias = torch.randn(24), torch.randn(24)
    want = _numpy_norm(x.numpy().reshape(-1, 24), 1e-5).reshape(x.shape) * weight.numpy() + bias.numpy()
    got = layer_norm_as_matmuls(x, [24], weight, bias, 1e-5).numpy()
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert np.abs(got - want).max() < 1e-2 * np.abs(_numpy_norm(x.numpy().reshape(-1, 24), 1e-1).reshape(x.shape)
                                                     * weight.numpy() + bias.numpy() - want).max()  # eps matters


def test_group_norm_as_matmuls_against_numpy() -> None:
    x = torch.randn(2, 16, 6, 8) * 4 - 3
    weight, bias = torch.randn(16), torch.randn(16)
    groups = _numpy_norm(x.numpy().reshape(2 * 4, -1), 1e-5).reshape(x.shape)
    want = groups * weight.numpy()[None, :, None, None] + bias.numpy()[None, :, None, None]
    np.testing.assert_allclose(group_norm_as_matmuls(x, 4, weight, bias, 1e-5).numpy(), want, atol=2e-5)
    np.testing.assert_allclose(torch.nn.functional.group_norm(x, 4, weight, bias).numpy(), want, atol=2e-5)


class _Toy(torch.nn.Module):
    """A LayerNorm and a matmul by a computed (parameter-only) weight: what XNNPACK refused."""

    def __init__(self) -> None:
        super().__init__()
        self.norm = torch.nn.LayerNorm(16)
        self.weight = torch.nn.Parameter(torch.randn(16, 16))
        self.register_buffer("scale", torch.linspace(0.5, 2.0, 16))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x) @ (self.weight * self.scale[:, None]).t()


@pytest.mark.parametrize("decompose, fold, left", [(True, True, set()), (False, True, {"native_layer_norm"}),
                                                   (True, False, {"mm"})])
def test_folding_and_decomposition_hand_the_toy_to_xnnpack(decompose, fold, left) -> None:
    skip_without("executorch")
    from executorch.backends.xnnpack.partition.xnnpack_partitioner import XnnpackPartitioner
    from executorch.exir import to_edge_transform_and_lower
    from executorch.exir.passes.constant_prop_pass import constant_prop_pass

    from e3dpsm.export.delegation import delegation_summary
    from e3dpsm.export.norm_decompositions import norm_decompositions

    toy = _Toy().eval().requires_grad_(False)
    x = torch.randn(8, 16)
    with torch.no_grad():
        program = torch.export.export(toy, (x,), strict=False)
        program = program.run_decompositions(norm_decompositions()) if decompose else program
        program = constant_prop_pass(program) if fold else program
        summary = delegation_summary(to_edge_transform_and_lower(program, partitioner=[XnnpackPartitioner()]))
    portable = {name.split(".")[1] for name in summary["portable_ops"]}
    assert left <= portable and not ({"native_layer_norm", "mm"} - left) & portable
    assert summary["delegated_share"] == (1.0 if "mm" not in left else 0.0)  # the mm carries the MACs here


def test_coreml_package_passes_the_linux_checks(coreml_result, edge_model) -> None:
    checks = coreml_result.checks
    assert checks["passed"] and checks["io_matches_spec"] and checks["float32_io"]
    assert checks["outputs"]["aliases"] == {"fusion_pose_out": "pose"}
    assert checks["operators"]["resample"] == 4  # grid sampling, one per deformable block
    weights = checks["weights"]
    assert weights["found"] >= 0.75 * weights["checked"]


def test_coreml_weight_check_catches_another_checkpoint(edge_model) -> None:
    """The check against a program whose constants are the model's own weights (fp16-rounded),
    and against another seed's model: all found, then none."""
    from types import SimpleNamespace

    import e3dpsm
    from e3dpsm.export.coreml_export import weights_in_package

    def const(value):
        return SimpleNamespace(op_type="const", outputs=[SimpleNamespace(val=value)])

    operations = [const(p.detach().numpy().astype(np.float16)) for p in edge_model.parameters() if p.dim() >= 2]
    mine = weights_in_package(operations, edge_model, 1e-3)
    assert mine["found"] == mine["checked"] > 20
    other = weights_in_package(operations, e3dpsm.create_model("tiny", seed=1), 1e-3)
    assert other["found"] == 0 and len(other["missing"]) == other["checked"]


def test_coreml_metadata_round_trip(coreml_result, trained_graph) -> None:
    import coremltools as ct

    from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, decode
    from e3dpsm.runtime.stepping import open_stepper

    package = ct.models.MLModel(coreml_result.path, skip_model_load=True)
    meta, record = decode(package.user_defined_metadata[EMBEDDED_NAME], "package")
    assert [s.to_metadata() for s in meta.states] == [s.to_metadata() for s in open_stepper(trained_graph).meta.states]
    assert record["format"] == "coreml" and record["precision"] == "fp16"


@pytest.mark.skipif(platform.system() == "Darwin", reason="the refusal is what Linux and Windows get")
def test_coreml_prediction_is_refused_off_macos(coreml_result, capsys, edge_golden, tmp_path) -> None:
    assert main(["golden", "check", "--model", coreml_result.path, "--golden", str(edge_golden), "--out",
                 str(tmp_path / "c")]) == 2
    assert "macOS only" in capsys.readouterr().err


@pytest.mark.skipif(platform.system() != "Darwin", reason="Core ML predicts on macOS only")
def test_coreml_golden_check_on_macos(coreml_result, edge_golden, tmp_path) -> None:  # pragma: no cover
    assert main(["golden", "check", "--model", coreml_result.path, "--golden", str(edge_golden), "--out",
                 str(tmp_path / "c"), "--profile", "fp16"]) == 0


def _gpu_reason() -> str | None:
    from e3dpsm.utils.extras import missing_reason

    reason = missing_reason("tensorrt")
    if reason:
        return reason
    import tensorrt  # noqa: F401

    return None


@pytest.mark.skipif(_gpu_reason() is not None, reason=f"TensorRT needs an NVIDIA GPU: {_gpu_reason()}")
def test_tensorrt_engine_golden_check(trained_graph, edge_golden, tmp_path) -> None:  # pragma: no cover
    assert main(["convert", "tensorrt", "--model", str(trained_graph), "--out", str(tmp_path / "trt")]) == 0
    assert main(["golden", "check", "--model", str(tmp_path / "trt" / "step.engine"), "--golden", str(edge_golden),
                 "--out", str(tmp_path / "c")]) == 0


def test_tensorrt_without_its_extra(monkeypatch, capsys, trained_graph, tmp_path) -> None:
    monkeypatch.setitem(sys.modules, "tensorrt", None)
    assert main(["convert", "tensorrt", "--model", str(trained_graph), "--out", str(tmp_path / "trt")]) == 2
    assert 'pip install -e ".[tensorrt]"' in capsys.readouterr().err and not (tmp_path / "trt").exists()


def test_broken_artifact_metadata_is_one_error(tmp_path) -> None:
    from e3dpsm.graph_metadata import MetadataError
    from e3dpsm.runtime.artifact_metadata import decode, read_sidecar

    with pytest.raises(MetadataError, match="broken"):
        decode('{"e3dpsm.states": 3}', "x")
    with pytest.raises(MetadataError, match="step.engine.json is not beside it"):
        read_sidecar(tmp_path / "step.engine")


def test_edge_targets_say_what_is_missing(monkeypatch) -> None:
    from e3dpsm.profiles.targets import availability, load_targets

    targets = load_targets()
    pte = targets["executorch-xnnpack-fp32"]
    assert pte.graph_key == "executorch/fp32" and targets["ort-cpu-fp32"].graph_key == "fp32"
    with monkeypatch.context() as blocked:
        blocked.setitem(sys.modules, "executorch", None)
        status = availability(pte, {"executorch/fp32": "step.pte"}, False)
        assert not status.available and 'pip install -e ".[executorch]"' in status.reason
    skip_without("executorch")
    lacking = availability(pte, {}, False)  # the runtime is here: the artifact is asked for
    assert not lacking.available and "--edge-models STEP.pte" in lacking.reason
    assert availability(pte, {"executorch/fp32": "step.pte"}, False).available


def test_norms_without_affine_parameters_and_with_default_eps() -> None:
    """No weight, no bias (`elementwise_affine=False`, `affine=False`), eps left at torch's
    default 1e-5 (a scale near 0 shows it), and a 3-D group norm input [N, C, L]."""
    x = torch.randn(3, 4, 24) * 1e-3
    want = _numpy_norm(x.numpy().reshape(-1, 24), 1e-5).reshape(x.shape)
    np.testing.assert_allclose(layer_norm_as_matmuls(x, [24]).numpy(), want, atol=2e-5)
    np.testing.assert_allclose(torch.nn.functional.layer_norm(x, [24]).numpy(), want, atol=2e-5)
    np.testing.assert_allclose(layer_norm_as_matmuls(x, [4, 24]).numpy(),
                               _numpy_norm(x.numpy().reshape(3, 96), 1e-5).reshape(x.shape), atol=2e-5)
    y = torch.randn(2, 6, 10)
    groups = _numpy_norm(y.numpy().reshape(2 * 3, -1), 1e-5).reshape(y.shape)
    np.testing.assert_allclose(group_norm_as_matmuls(y, 3).numpy(), groups, atol=2e-5)
    weight, bias = torch.randn(6), torch.randn(6)
    np.testing.assert_allclose(group_norm_as_matmuls(y, 3, weight, bias).numpy(),
                               groups * weight.numpy()[None, :, None] + bias.numpy()[None, :, None], atol=2e-5)


def test_the_decomposition_table_holds_the_two_norms_alone() -> None:
    from e3dpsm.export.norm_decompositions import norm_decompositions

    table = norm_decompositions()
    assert table == {torch.ops.aten.layer_norm.default: layer_norm_as_matmuls,
                     torch.ops.aten.group_norm.default: group_norm_as_matmuls}
