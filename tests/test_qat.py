"""Quantisation-aware fine-tuning (e3dpsm/training/qat.py): the simulated rounding against a
numpy re-statement of the INT8 graph's arithmetic, the hooks leaving no trace, and
`e3dpsm train --init-from CKPT --qat` writing a plain float checkpoint."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn.utils import parametrize

import e3dpsm
from e3dpsm.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from e3dpsm.cli import main
from e3dpsm.training.trainer import PARAM_DUMP_ENV, _param_digest
from e3dpsm.training.qat import (FLOAT_MODULE_PREFIXES, QATConfig, attach_fake_quant, fake_quantize_weight,
                                 quantised_modules)

from _training_helpers import FAST_TRAIN


def numpy_weight_s8(weight: np.ndarray) -> np.ndarray:
    """Symmetric int8 per output channel: scale = max|w| / 127, round half to even, clip."""
    flat = weight.reshape(weight.shape[0], -1)
    scale = np.abs(flat).max(axis=1, keepdims=True).astype(np.float32) / np.float32(127)
    q = np.clip(np.round(flat / scale), -127, 127)
    return (q * scale).reshape(weight.shape).astype(np.float32)


def test_weight_fake_quant_matches_numpy_per_channel() -> None:
    gen = torch.Generator().manual_seed(0)
    # Channels of very different magnitude: a per-tensor scale would flatten the small one.
    weight = torch.randn(6, 4, 3, 3, generator=gen) * torch.tensor([1e-3, 0.1, 1.0, 3.0, 10.0, 0.5]).view(6, 1, 1, 1)
    weight.requires_grad_(True)
    got = fake_quantize_weight(weight)
    want = numpy_weight_s8(weight.detach().numpy())
    step = np.abs(weight.detach().numpy()).reshape(6, -1).max(axis=1) / 127
    np.testing.assert_allclose(got.detach().numpy(), want, rtol=0, atol=float(step.min()) * 1e-3)
    # It does round: every channel moves by up to half a step, and no further.
    moved = np.abs(got.detach().numpy() - weight.detach().numpy()).reshape(6, -1).max(axis=1)
    assert np.all(moved > 0.1 * step) and np.all(moved <= 0.5 * step * (1 + 1e-5))
    got.sum().backward()  # straight through: the whole range is inside the clip
    assert torch.equal(weight.grad, torch.ones_like(weight))


def test_fake_quant_covers_the_quantised_modules_and_leaves_no_trace() -> None:
    torch.manual_seed(0)
    model = e3dpsm.create_model("tiny", height=96, width=128).eval()
    frames = (torch.rand(1, 3, 2, 96, 128, generator=torch.Generator().manual_seed(2)) < 0.05).float()
    before_state = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        plain = model(frames)["pose"]

    names = [name for name, _ in quantised_modules(model)]
    assert "stem.0" in names and not any(n.startswith(FLOAT_MODULE_PREFIXES) for n in names)
    seen: list[torch.Tensor] = []
    handle = attach_fake_quant(model, QATConfig())
    model.stem[0].register_forward_hook(lambda mod, args, out: seen.append(out.detach()))
    with torch.no_grad():
        simulated = model(frames)["pose"]
    assert (simulated - plain).abs().max() > 1e-3  # the rounding reaches the poses
    # The stem's output, as the later hook sees it, is on its learned uint8 grid.
    index = next(i for i, g in enumerate(handle.groups) if "stem.0:out" in g.sites)
    scale, zero = handle.quantizers[index].qparams()
    codes = seen[0] / scale + zero
    assert torch.allclose(codes, codes.round(), atol=1e-3) and len(torch.unique(codes.round())) <= 256
    assert parametrize.is_parametrized(model.stem[0], "weight")
    assert not parametrize.is_parametrized(model.delta_head, "weight")  # the Kalman path stays float

    with handle.removed() as clean:
        assert set(clean.state_dict()) == set(before_state)
    with torch.no_grad():  # re-attached, with the ranges it had
        assert torch.equal(model(frames)["pose"], simulated)
    handle.remove()
    assert set(model.state_dict()) == set(before_state)
    assert all(torch.equal(v, before_state[k]) for k, v in model.state_dict().items())
    with torch.no_grad():
        assert torch.equal(model(frames)["pose"], plain)
    with handle.removed():  # removed for good: saving through it must not bring the hooks back
        pass
    assert not handle.attached and not parametrize.is_parametrized(model.stem[0], "weight")
    with torch.no_grad():
        assert torch.equal(model(frames)["pose"], plain)


def test_qat_finetune_writes_a_plain_checkpoint(training_runs: dict[str, Path], prepared_small: Path,
                                                tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A prior unlike the data's mean: the fine-tune must keep the checkpoint's, not recompute it.
    model, payload = load_checkpoint(training_runs["step4"], variant="tiny")
    model.set_pose_prior(model.pose_prior_mm + 25.0)
    start = save_checkpoint(tmp_path / "start.pt", model, window_ms=payload["window_ms"])
    out = tmp_path / "qat"
    # The run's own digest of its final parameters (names and values), as the distributed
    # test reads it: it must be the plain checkpoint's, i.e. the model ends without hooks.
    monkeypatch.setenv(PARAM_DUMP_ENV, str(tmp_path / "digest"))
    assert main(["train", "--data", str(prepared_small), "--split", "all", "--out", str(out), "--steps", "2",
                 "--init-from", str(start), "--qat", *FAST_TRAIN]) == 0
    model, payload = load_checkpoint(out / "checkpoint.pt", variant="tiny")  # strict: no fake-quant keys
    assert payload["train_args"]["qat"] is True and payload["train_args"]["init_from"] == str(start)
    ranges = payload["qat_ranges"]["quantizers"]  # the learned ranges travel beside the plain weights
    assert len(ranges) > 50 and all(r["scale"] > 0 and 0 <= r["zero_point"] <= 255 for r in ranges)
    init = read_checkpoint(start)["model"]
    assert set(payload["model"]) == set(init)
    moved = [k for k, v in payload["model"].items() if v.is_floating_point() and not torch.equal(v, init[k])]
    assert any(k.startswith("stem.") for k in moved)  # it trained from the given weights...
    assert torch.equal(payload["model"]["pose_prior_mm"], init["pose_prior_mm"])  # ...and kept their prior
    dumped = json.loads((tmp_path / "digest" / "rank0.json").read_text())
    assert dumped["sha256"] == _param_digest(model)["sha256"]
    # BatchNorm kept the checkpoint's running statistics (the graph folds them)
    stats = [k for k in init if k.endswith(("running_mean", "running_var"))]
    assert stats and all(torch.equal(payload["model"][k], init[k]) for k in stats)


def test_init_from_is_refused_with_resume_or_another_variant(training_runs: dict[str, Path], prepared_small: Path,
                                                              tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    start = str(training_runs["step4"])
    rc = main(["train", "--data", str(prepared_small), "--out", str(training_runs["full"]), "--resume",
               "--init-from", start, "--variant", "tiny", "--no-progress"])
    assert rc != 0 and "--init-from starts a new run" in capsys.readouterr().err
    rc = main(["train", "--data", str(prepared_small), "--out", str(tmp_path / "x"), "--steps", "1",
               "--init-from", start, "--variant", "small", "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0 and "holds variant 'tiny', not 'small'" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x" / "checkpoint.pt").exists()


def test_full_integer_fake_quant_covers_the_recurrent_path_too() -> None:
    """--qat-full-integer simulates `quantize --exclude none`: the delta head and the fusion's
    pose embedding are fake-quantised as well, and the S5 states the readouts read (graph
    outputs, renamed by ONNX Runtime's quantiser) are named as the graph names them."""
    from e3dpsm.training.qat_ranges import GRAPH_OUTPUT_SUFFIX, qat_plan

    model = e3dpsm.create_model("tiny", height=96, width=128).eval()
    full = [name for name, _ in quantised_modules(model, full_integer=True)]
    assert {"delta_head"} <= set(full) and set(n for n, _ in quantised_modules(model)) < set(full)
    default_groups, full_groups = qat_plan(model), qat_plan(model, full_integer=True)
    default_tensors = {t for g in default_groups for t in g.tensors}
    full_tensors = {t for g in full_groups for t in g.tensors}
    assert default_tensors < full_tensors
    assert not any(t.endswith(GRAPH_OUTPUT_SUFFIX) for t in full_tensors)
    # the S5 states the readouts read are hooked (through layers/s5.py Projection)
    sites = {site for g in full_groups for site in g.sites}
    assert any(t.startswith("s5_") for t in full_tensors)
    assert any(".read_re:in" in site for site in sites) and any(".drive_re:out" in site for site in sites)
    handle = attach_fake_quant(model, QATConfig(full_integer=True), groups=full_groups)
    assert parametrize.is_parametrized(model.delta_head, "weight")
    handle.remove()


def test_quantised_activations_name_quantised_graph_outputs_as_the_graph_does(tmp_path: Path) -> None:
    """A graph output read by a MatMul: ONNX Runtime renames its producer's output
    `<name>_QuantizeLinear_Input`; the tensor to learn a range for is `<name>`."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from e3dpsm.training.qat_ranges import quantised_activations

    w = numpy_helper.from_array(np.eye(4, dtype=np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["state"], name="relu"),
         helper.make_node("MatMul", ["state", "w"], ["y"], name="readout")],
        "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4]),
         helper.make_tensor_value_info("state", TensorProto.FLOAT, [1, 4])], [w])
    path = tmp_path / "g.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), str(path))
    names = quantised_activations(path, [], ("MatMul",))
    assert "state" in names and not any(n.endswith("_QuantizeLinear_Input") for n in names)


def test_qat_full_integer_without_qat_is_refused() -> None:
    from e3dpsm.errors import ConfigError
    from e3dpsm.training.trainer import TrainArgs

    with pytest.raises(ConfigError, match="add --qat"):
        TrainArgs(variant="tiny", steps=1, qat_full_integer=True)


@pytest.mark.parametrize("bits, reduce_range", [(8, False), (7, True)])
def test_weight_fake_quant_is_onnx_runtimes_weight_rounding(bits: int, reduce_range: bool) -> None:
    """The weights QAT simulates are the ones `quantize` writes: ONNX Runtime's symmetric S8
    per channel, with `reduce_range` (7-bit, levels -64..64) for a target without int8
    dot-product units. Catches: 7-bit weights simulated on -63..63 or with an 8-bit scale."""
    from onnx import TensorProto
    from onnxruntime.quantization.quant_utils import quantize_data

    from e3dpsm.training.qat import WEIGHT_QMAX_BY_BITS

    gen = torch.Generator().manual_seed(1)
    weight = torch.randn(5, 3, 3, 3, generator=gen) * torch.tensor([1e-2, 0.3, 1.0, 4.0, 0.05]).view(5, 1, 1, 1)
    got = fake_quantize_weight(weight, WEIGHT_QMAX_BY_BITS[bits]).numpy()
    for channel in range(5):
        data = weight[channel].numpy().ravel()
        zero, scale, q = quantize_data(data, TensorProto.INT8, symmetric=True, reduce_range=reduce_range)
        want = (q.astype(np.float32) - float(zero)) * np.float32(scale)
        np.testing.assert_allclose(got[channel].ravel(), want, rtol=0, atol=float(scale) * 1e-4)
        assert np.abs(q).max() == WEIGHT_QMAX_BY_BITS[bits]


@pytest.mark.parametrize("kind, bits", [("avx2", 7), ("other", 7), ("vnni", 8), ("dotprod", 8)])
def test_default_weight_bits_are_those_of_the_hosts_graph(kind: str, bits: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without --qat-weight-bits the fine-tune simulates what `quantize`'s default target, the
    host, gets: 7-bit weights without int8 dot-product units, 8-bit with them; a given value wins."""
    import types

    import e3dpsm.utils.isa as isa

    monkeypatch.setattr(isa, "detect_isa", lambda: types.SimpleNamespace(kind=kind))
    assert QATConfig().simulated_weight_bits == bits
    assert QATConfig(weight_bits=8).simulated_weight_bits == 8 and QATConfig(weight_bits=7).simulated_weight_bits == 7
