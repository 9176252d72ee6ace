"""QAT ranges that reach the graph: the learned fake-quant against ONNX Runtime's QDQ and a
numpy re-statement, the site matching, and a QAT graph whose QuantizeLinear parameters are
exactly the learned ones."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from e3dpsm.training.qat import QATConfig, attach_fake_quant
from e3dpsm.training.qat_lsq import LearnedQuantizer
from e3dpsm.training.qat_sites import match_groups

from _quantize_helpers import TRAINED_TINY, fast


def numpy_qdq_u8(x: np.ndarray, scale: np.float32, zero: int) -> np.ndarray:
    """QuantizeLinear (divide, round half to even, add the zero point, saturate to [0, 255])
    then DequantizeLinear ((q - zero) * scale), in float32 as the ONNX spec states them."""
    q = np.clip(np.round(x.astype(np.float32) / np.float32(scale)) + zero, 0, 255)
    return ((q - zero).astype(np.float32) * np.float32(scale)).astype(np.float32)


def ort_qdq_u8(x: np.ndarray, scale: np.float32, zero: int) -> np.ndarray:
    import onnxruntime as ort

    graph = helper.make_graph(
        [helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]), helper.make_node("DequantizeLinear", ["q", "s", "z"], ["y"])],
        "qdq", [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(x.shape))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, list(x.shape))],
        [numpy_helper.from_array(np.array(scale, np.float32), "s"), numpy_helper.from_array(np.array(zero, np.uint8), "z")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL  # no Q/DQ folding
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return session.run(["y"], {"x": x})[0]


def test_learned_fake_quant_is_ort_qdq_and_learns_by_lsq_gradients() -> None:
    gen = torch.Generator().manual_seed(0)
    # Heavy tails and exact ties (k + 0.5 steps) so rounding mode and saturation both matter.
    x = torch.cat([torch.randn(4000, generator=gen) * 3, torch.tensor([0.5, 1.5, 2.5, -0.5, -1.5]) * 0.0625, torch.tensor([40.0, -40.0])])
    quantizer = LearnedQuantizer()
    quantizer.set_qparams(0.0625, 100)
    scale, zero = quantizer.qparams()
    assert zero == 100 and scale == pytest.approx(0.0625, rel=1e-6)
    got = quantizer(x).detach().numpy()
    want = numpy_qdq_u8(x.numpy(), np.float32(scale), zero)
    np.testing.assert_array_equal(got, want)                                  # exactly the spec's arithmetic
    np.testing.assert_array_equal(got, ort_qdq_u8(x.numpy(), np.float32(scale), zero))  # and ONNX Runtime's

    # Gradients, against the LSQ / LSQ+ formulas in numpy.
    xg = x.clone().requires_grad_(True)
    quantizer(xg).sum().backward()
    s = np.float32(scale)
    v = x.numpy() / s
    inside = (np.round(v) + zero >= 0) & (np.round(v) + zero <= 255)
    np.testing.assert_array_equal(xg.grad.numpy(), inside.astype(np.float32))
    low_sat = np.round(v) + zero < 0
    d_scale = np.where(inside, np.round(v) - v, np.where(low_sat, 0 - zero, 255 - zero)).sum()
    # The parameter is log(scale): d/dlog s = s * d/ds.
    assert float(quantizer.log_scale.grad) == pytest.approx(float(d_scale) * float(s), rel=1e-4)
    assert float(quantizer.zero_point.grad) == pytest.approx(-float(s) * float((~inside).sum()), rel=1e-5)


def test_match_groups_by_value_up_to_layout() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 8, 4, 4)).astype(np.float32), rng.normal(size=(2, 32)).astype(np.float32)
    tensors = {"conv_out": a, "reshaped": a.reshape(2, 128).T.copy(), "other": b, "zeros": np.zeros(64, np.float32)}
    sites = {"m1:out": a + 1e-7, "m2:in": a.copy(), "lin:in": b, "z:out": np.zeros((8, 8), np.float32),
             "unrelated:out": rng.normal(size=(2, 8, 4, 4)).astype(np.float32)}
    groups = {g.tensors: g.sites for g in match_groups(tensors, sites)}
    assert groups == {("conv_out", "reshaped"): ("m1:out", "m2:in"), ("other",): ("lin:in",)}


def test_a_constant_first_batch_does_not_initialise_the_range() -> None:
    """Catches: a range started from a constant batch (the fusion's pose input is all zeros
    before the first frame) at the minimum scale, which zeroes the tensor from then on."""
    q = LearnedQuantizer()
    zeros = torch.zeros(4, 3)
    assert torch.equal(q(zeros), zeros) and not bool(q.initialised)
    x = torch.linspace(-1.0, 3.0, 12).view(4, 3)
    y = q(x)
    assert bool(q.initialised)
    scale, zero = q.qparams()
    assert scale == pytest.approx(4.0 / 255, rel=1e-6) and zero == 64
    assert torch.allclose(y, x, atol=scale / 2 + 1e-6)


def _qat_tiny(tmp_path_factory, config: QATConfig, name: str) -> dict:
    """The trained tiny after 3 QAT steps under `config` (learned ranges moved from their
    start), saved as a checkpoint with its `qat_ranges`, and its fp32 export."""
    from e3dpsm.export import export_step

    torch.manual_seed(0)
    model, _ = load_checkpoint(TRAINED_TINY, variant="tiny")
    model.train()
    handle = attach_fake_quant(model, config)
    cfg = model.config
    frames = (torch.rand(1, 4, cfg.in_channels, cfg.height, cfg.width, generator=torch.Generator().manual_seed(1)) < 0.05).float()
    frames = frames * torch.rand(frames.shape, generator=torch.Generator().manual_seed(2))
    optimizer = torch.optim.Adam([{"params": model.parameters(), "lr": 1e-4},
                                  {"params": handle.parameters(), "lr": 1e-2}])
    start = None
    for step in range(3):
        loss = model.forward_sequence(frames, causal=False)["pose"].pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        if start is None:  # initialised by the first forward pass
            start = {i: q.qparams() for i, q in enumerate(handle.quantizers)}
        optimizer.step()
    learned = {i: q.qparams() for i, q in enumerate(handle.quantizers)}
    root = tmp_path_factory.mktemp(name)
    ranges = handle.ranges_payload()
    with handle.removed():
        ckpt = save_checkpoint(root / "checkpoint.pt", model, qat_ranges=ranges)
        graph = export_step(model.eval(), root / "step.onnx")
    return {"checkpoint": ckpt, "graph": graph, "start": start, "learned": learned, "handle": handle}


@pytest.fixture(scope="module")
def qat_tiny_full_integer(tmp_path_factory) -> dict:
    """As qat_tiny, simulating the full-integer graph (QATConfig(full_integer=True))."""
    return _qat_tiny(tmp_path_factory, QATConfig(full_integer=True, weight_bits=8), "qat_tiny_full")


def _quantised_tensor(name: str) -> str:
    """The graph tensor a QuantizeLinear input stands for: an S5 readout quantises its copy of
    the state (`<node>/<state>/state_read`, graph_groups.isolate_state_reads), not the state."""
    from e3dpsm.quantize.graph_groups import STATE_READ_SUFFIX
    from e3dpsm.training.qat_ranges import GRAPH_OUTPUT_SUFFIX

    if name.endswith(STATE_READ_SUFFIX):
        return name.removesuffix(STATE_READ_SUFFIX).rsplit("/", 1)[1]
    return name.removesuffix(GRAPH_OUTPUT_SUFFIX)


def _recurrent_ranges(run: dict, quant_data: Path, work: Path) -> tuple[list[str], list[str]]:
    """Quantise the full-integer QAT tiny with `--exclude none --ranges-from-checkpoint`:
    (the recurrent path's learned tensors, those whose graph range is not the learned one)."""
    from e3dpsm.quantize import quantize_graph

    report = quantize_graph(run["graph"], quant_data, work / "q", fast(
        mode="int8", exclude="none", holdout_frames=20, ranges_from_checkpoint=str(run["checkpoint"])))
    groups = list(zip(run["handle"].groups, run["handle"].quantizers))
    by_tensor = {t: q.qparams() for g, q in groups for t in g.tensors}
    recurrent = [t for g, _ in groups for t in g.tensors
                 if any(s.startswith(("delta_head", "pose_embed")) or ".read_" in s for s in g.sites)]
    model = onnx.load(str(work / "q" / report["artifact"]))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    written = {_quantised_tensor(n.input[0]): (inits[n.input[1]], inits[n.input[2]]) for n in model.graph.node
               if n.op_type == "QuantizeLinear" and n.input[1] in inits and n.input[0] not in inits}
    wrong = [t for t in recurrent if not (written[t][0] == np.float32(by_tensor[t][0])
                                          and int(written[t][1]) == by_tensor[t][1])]
    # The fine-tune simulated `--float-outputs matmul` (QATConfig's default for the full-integer
    # graph), the checkpoint says so, and it is quantize's default too.
    assert report["learned_ranges"]["float_outputs"] == report["quantization"]["float_outputs"] == "matmul"
    return recurrent, wrong


def test_full_integer_graph_takes_the_recurrent_paths_learned_ranges(qat_tiny_full_integer, quant_data: Path,
                                                                     tmp_path: Path) -> None:
    """Catches: `--exclude none --ranges-from-checkpoint` matching only the default graph's
    tensors, so the recurrent path (S5 readouts, the delta head) kept calibrated ranges
    where training had learned others; and matching on a stream's first frame, where the
    S5 states (graph outputs) equal the input projection they start from and took its range,
    and the fusion's previous pose is all zeros and matched nothing."""
    recurrent, wrong = _recurrent_ranges(qat_tiny_full_integer, quant_data, tmp_path)
    states = [t for t in recurrent if t.startswith("s5_")]
    # Fewer than the graph's recurrent Q/DQ pairs: the MatMul/Gemm outputs only float code
    # reads have none (--float-outputs matmul), and training learned no range for them.
    assert len(recurrent) > 8 and len(states) == 4, recurrent
    assert wrong == [], f"{len(wrong)} of {len(recurrent)} keep other ranges than the learned: {wrong}"


@pytest.fixture(scope="module")
def qat_tiny(tmp_path_factory) -> dict:
    return _qat_tiny(tmp_path_factory, QATConfig(weight_bits=8), "qat_tiny")


def test_qat_checkpoint_carries_learned_ranges_that_moved(qat_tiny) -> None:
    payload = read_checkpoint(qat_tiny["checkpoint"])
    quantizers = payload["qat_ranges"]["quantizers"]
    assert len(quantizers) == len(qat_tiny["handle"].groups) > 50
    moved = [i for i in qat_tiny["learned"] if qat_tiny["learned"][i][0] != qat_tiny["start"][i][0]]
    assert len(moved) > len(quantizers) // 2  # the scales trained
    load_checkpoint(qat_tiny["checkpoint"], variant="tiny")  # strict load: no fake-quant keys in the weights


def test_qat_graph_quantisation_parameters_equal_the_learned_ones(qat_tiny, quant_data: Path, tmp_path: Path) -> None:
    from e3dpsm.quantize import quantize_graph

    out = tmp_path / "q"
    report = quantize_graph(qat_tiny["graph"], quant_data, out, fast(
        mode="int8", exclude="recurrent", holdout_frames=20, ranges_from_checkpoint=str(qat_tiny["checkpoint"])))
    block = report["learned_ranges"]
    assert block["calibrated_tensors"] == 0 and block["uncovered"] == [], block["uncovered"]  # every range learned
    assert (f"{block['learned_tensors']} of the {block['learned_tensors']} 8-bit activations take"
            in (out / "report.md").read_text())
    assert block["weights_frozen"] is False
    learned = {}
    for q in read_checkpoint(qat_tiny["checkpoint"])["qat_ranges"]["quantizers"]:
        for site in q["sites"]:
            learned[site] = (np.float32(q["scale"]), q["zero_point"])
    handle = qat_tiny["handle"]
    by_tensor = {}  # tensor of the training-time export -> the live quantiser's (scale, zp)
    for group, quantizer in zip(handle.groups, handle.quantizers):
        for tensor in group.tensors:
            by_tensor[tensor] = quantizer.qparams()

    model = onnx.load(str(out / report["artifact"]))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    checked = 0
    for node in model.graph.node:
        if node.op_type != "QuantizeLinear" or node.input[0] not in by_tensor or node.input[0] in inits:
            continue
        scale, zero = inits[node.input[1]], inits[node.input[2]]
        want_scale, want_zero = by_tensor[node.input[0]]
        assert scale.dtype == np.float32 and zero.dtype == np.uint8
        assert scale == np.float32(want_scale), node.input[0]   # exactly: written, not recomputed
        assert int(zero) == want_zero, node.input[0]
        checked += 1
    assert checked >= block["learned_tensors"] * 0.9 and checked > 50


def test_ranges_learned_with_the_weights_frozen_are_told_from_a_fine_tune() -> None:
    from e3dpsm.training.qat_ranges import learned_with_weights_frozen

    assert learned_with_weights_frozen({"distill_config": {"qat": True, "qat_ranges_only": True}})
    assert not learned_with_weights_frozen({"distill_config": {"qat": True}})
    assert not learned_with_weights_frozen({"train_args": {}})  # `train --qat` has no distill_config


COMMITTED_QAT = Path(__file__).resolve().parents[1] / "benchmarks" / "checkpoints" / "small_qat" / "checkpoint.pt"


def test_committed_qat_checkpoint_names_only_modules_the_model_has() -> None:
    """A module renamed after a QAT fine-tune silently returns its tensors to calibrated
    ranges (the deformable offsets did, 2026-12-01): the committed fine-tune must name only
    sites this version has, and a renamed one is found."""
    from e3dpsm.training.qat_ranges import read_ranges, unknown_sites

    model, payload = load_checkpoint(COMMITTED_QAT)
    learned = read_ranges(payload, str(COMMITTED_QAT))
    assert unknown_sites(model, learned) == []
    renamed = [{**q, "sites": [s.replace("offset_projection", "offset_product") for s in q["sites"]]} for q in learned]
    stale = unknown_sites(model, renamed)
    # 4 layers x their input (the output before the bias is float under --float-outputs
    # matmul, which the committed fine-tune simulated: no range learned for it).
    assert len(stale) == 4 and all("offset_product" in s for s in stale), stale


def test_a_renamed_site_is_reported_and_keeps_a_calibrated_range(qat_tiny, quant_data: Path, tmp_path: Path) -> None:
    from e3dpsm.quantize import quantize_graph

    payload = read_checkpoint(qat_tiny["checkpoint"])
    quantizers = payload["qat_ranges"]["quantizers"]
    victim = next(q for q in quantizers if len(q["sites"]) == 1 and q["sites"][0].endswith(":out"))
    victim["sites"] = [victim["sites"][0].replace(":out", "_renamed:out").replace(".", "_", 1)]
    stale_ckpt = tmp_path / "stale.pt"
    torch.save(payload, stale_ckpt)
    out = tmp_path / "q"
    report = quantize_graph(qat_tiny["graph"], quant_data, out, fast(
        mode="int8", exclude="recurrent", holdout_frames=20, ranges_from_checkpoint=str(stale_ckpt)))
    block = report["learned_ranges"]
    assert block["unknown_sites"] == victim["sites"]
    assert block["calibrated_tensors"] >= 1
    assert "repeat the QAT fine-tune" in (out / "report.md").read_text()


def test_ranges_from_a_checkpoint_without_them_is_one_clear_line(trained_graph: Path, quant_data: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture) -> None:
    from e3dpsm.cli import main

    out = tmp_path / "q"
    rc = main(["quantize", "--model", str(trained_graph), "--data", str(quant_data), "--out", str(out),
               "--exclude", "none", "--ranges-from-checkpoint", str(TRAINED_TINY)])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "carries no learned QAT ranges" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_quantised_activations_include_the_state_read_copies(trained_graph: Path, tmp_path: Path) -> None:
    """The default search with --ranges-from-checkpoint lists the tensors its graphs may
    quantise on the pre-processed graph whose S5 readouts read a copy of the state (an
    Identity added after the pre-pass, without a value_info): ONNX Runtime failed with
    "Quantization parameters are not specified for param .../state_read" before the copies
    were found (the ladder's QAT default-search row, 2026-12-01)."""
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import STATE_READ_SUFFIX, isolate_state_reads, recurrent_groups
    from e3dpsm.training.qat_ranges import quantised_activations
    from e3dpsm.quantize.static import DEFAULT_OP_TYPES, preprocess

    pre = tmp_path / "pre.onnx"
    preprocess(trained_graph, pre)
    model = onnx.load(str(pre))
    recurrent = {n for g in recurrent_groups(model, GraphMetadata.from_onnx(model)) for n in g.nodes}
    projections = [n.name for n in model.graph.node if n.name in recurrent and n.op_type in DEFAULT_OP_TYPES]
    assert isolate_state_reads(model, projections)
    onnx.save(model, str(pre))
    copies = {t for n in model.graph.node if n.name.endswith(STATE_READ_SUFFIX) for t in n.output}
    quantised = set(quantised_activations(pre, [], DEFAULT_OP_TYPES))
    assert len(copies) == 4 and copies <= quantised  # two S5 stages, a real and an imaginary readout each


@pytest.mark.parametrize("fixture", ["qat_tiny", "qat_tiny_full_integer"])
def test_qat_covers_every_tensor_the_graph_quantises(fixture: str, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """Catches: products written inline (attention scores and mixing, the deformable offsets)
    whose tensors have no module and so kept calibrated ranges (layers/products.py)."""
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import recurrent_groups
    from e3dpsm.training.qat_ranges import quantised_activations
    from e3dpsm.quantize.static import DEFAULT_OP_TYPES, preprocess

    run = request.getfixturevalue(fixture)
    pre = tmp_path / "pre.onnx"
    preprocess(run["graph"], pre)
    model = onnx.load(str(pre))
    keep = [] if run["handle"].config.full_integer else [
        n for g in recurrent_groups(model, GraphMetadata.from_onnx(model)) for n in g.nodes]
    quantised = set(quantised_activations(pre, keep, DEFAULT_OP_TYPES, run["handle"].config.simulated_float_outputs))
    covered = {t for g in run["handle"].groups for t in g.tensors}
    assert quantised and quantised == covered, sorted(quantised - covered)
    sites = {s for g in run["handle"].groups for s in g.sites}
    assert any(s.endswith(".scores:in1") for s in sites) and any(s.endswith(".mix:in1") for s in sites)


def test_projection_weights_are_rounded_where_the_graph_quantises_them(qat_tiny, qat_tiny_full_integer) -> None:
    """A `Projection`'s weight is an argument, not a parameter; the graph quantises it S8 per
    output channel wherever it quantises the MatMul: the offsets and the S5 backward readout
    (causal: no recurrence) always, the S5 drive and forward readout (the recurrent group) in
    the full-integer graph only."""
    default = {n for n, _ in qat_tiny["handle"].projections}
    full = {n for n, _ in qat_tiny_full_integer["handle"].projections}
    recurrent = {n for n in full if ".s5.read_re" in n or ".s5.read_im" in n or ".s5.drive_" in n}
    assert any(n.endswith("offset_projection") for n in default) and any(".s5.read_back_" in n for n in default)
    assert recurrent and not recurrent & default and full == default | recurrent



@pytest.mark.parametrize("bits, levels", [(8, 127), (7, 64)])
def test_a_projections_weight_is_rounded_s8_per_output_channel(bits: int, levels: int) -> None:
    from e3dpsm.layers.products import Projection
    from e3dpsm.training.qat import FakeQuantHandle
    from e3dpsm.training.qat_sites import QuantGroup

    holder = torch.nn.Module()
    holder.proj = Projection()
    handle = FakeQuantHandle(holder, QATConfig(activations=False, weight_bits=bits),
                             [QuantGroup(("w",), ("proj:weight",))]).attach()
    gen = torch.Generator().manual_seed(3)
    x, weight = torch.randn(5, 7, generator=gen), torch.randn(4, 7, generator=gen)
    step = weight.abs().amax(dim=1, keepdim=True).numpy() / levels
    rounded = np.clip(np.round(weight.numpy() / step), -levels, levels) * step  # numpy, per row (output channel)
    with torch.no_grad():
        got = holder.proj(x, weight).numpy()
        handle.remove()
        plain = holder.proj(x, weight).numpy()
    np.testing.assert_allclose(got, x.numpy() @ rounded.T, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(plain, x.numpy() @ weight.numpy().T, rtol=1e-5, atol=1e-6)
    assert np.abs(got - plain).max() > 1e-4


def test_a_products_second_activation_is_fake_quantised() -> None:
    """Catches: an `in1` site (attention k and v) matched but never quantised."""
    from e3dpsm.layers.products import MatMul
    from e3dpsm.training.qat import FakeQuantHandle
    from e3dpsm.training.qat_sites import QuantGroup

    holder = torch.nn.Module()
    holder.mm = MatMul()
    handle = FakeQuantHandle(holder, QATConfig(weights=False), [QuantGroup(("v",), ("mm:in1",))]).attach()
    handle.quantizers[0].set_qparams(0.05, 120)
    gen = torch.Generator().manual_seed(4)
    a, b = torch.randn(3, 5, generator=gen), torch.randn(5, 6, generator=gen) * 4
    with torch.no_grad():
        got = holder.mm(a, b).numpy()
    want = a.numpy() @ numpy_qdq_u8(b.numpy(), np.float32(0.05), 120)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    assert np.abs(got - a.numpy() @ b.numpy()).max() > 0.1  # b saturates at (255 - 120) * 0.05


# The full-integer graph against the fake-quantised model it was trained as, one step from the
# same inputs and states: rounding flips (a value on a step boundary, float32 order of
# operations) leave some difference; a range or a rounding the graph has and training did not
# simulate leaves about as much as quantisation itself. The bar: the pose outputs' distance
# from the simulation, summed over the feeds, is at most this fraction of the simulation's
# distance from the float model (measured: 0.03-0.19 with learned ranges, above 1 with
# calibrated ones, on the trained tiny after 3 QAT steps).
SIMULATION_TOLERANCE = 0.3


def _simulation_gap(run: dict, graph: Path) -> dict[str, float]:
    from e3dpsm.training.qat_ranges import probe_feed, tensor_values

    model, handle = run["handle"].model, run["handle"]
    outputs = ("pose", "pose_direct", "pose_delta")
    gap = {k: 0.0 for k in outputs}
    effect = {k: 0.0 for k in outputs}
    model.eval()
    for seed in range(3):
        feed = probe_feed(model, steps=3, seed=seed)
        ort_out = tensor_values(graph, outputs, feed)
        state = {s.name: torch.from_numpy(feed[s.input_name]) for s in model.state_spec()}
        args = (torch.from_numpy(feed["lnes"]), state, torch.from_numpy(feed["window_ms"]))
        with torch.no_grad():
            simulated, _ = model.step(*args)
            with handle.removed():
                plain, _ = model.step(*args)
        for k in outputs:
            gap[k] += float(np.linalg.norm(simulated[k].numpy() - ort_out[k], axis=-1).mean())
            effect[k] += float(np.linalg.norm(simulated[k].numpy() - plain[k].numpy(), axis=-1).mean())
    return {k: gap[k] / effect[k] for k in outputs}


def _largest_weight_integer(graph: Path) -> int:
    """The largest |q| of the int8 initializers the graph dequantises (its weights)."""
    model = onnx.load(str(graph))
    inits = {i.name: i for i in model.graph.initializer}
    weights = [numpy_helper.to_array(inits[n.input[0]]) for n in model.graph.node
               if n.op_type == "DequantizeLinear" and n.input[0] in inits]
    return max(int(np.abs(w.astype(np.int32)).max()) for w in weights if w.dtype == np.int8)


def test_fake_quantised_step_is_the_full_integer_graphs_step(qat_tiny_full_integer, quant_data: Path,
                                                              tmp_path: Path) -> None:
    from e3dpsm.quantize import quantize_graph

    run = qat_tiny_full_integer
    graphs, reports = {}, {}
    # The fine-tune simulated 8-bit weights, the graph of a `vnni` target has them; on a host
    # without int8 dot-product units the default target (its own kind) gets 7-bit weights,
    # tested below. tensor_values runs the graph's own arithmetic (no fused integer kernel),
    # so the comparison holds on either kind of host.
    for name, ranges, isa in (("learned", str(run["checkpoint"]), "vnni"), ("calibrated", None, "vnni"),
                              ("learned_avx2", str(run["checkpoint"]), "avx2")):
        reports[name] = quantize_graph(run["graph"], quant_data, tmp_path / name, fast(
            mode="int8", exclude="none", holdout_frames=20, ranges_from_checkpoint=ranges, target=isa))
        graphs[name] = tmp_path / name / reports[name]["artifact"]
    assert reports["learned"]["learned_ranges"]["trained_weight_bits"] == 8
    assert _largest_weight_integer(graphs["learned"]) == 127
    assert _largest_weight_integer(graphs["learned_avx2"]) <= 64
    learned = _simulation_gap(run, graphs["learned"])
    assert max(learned.values()) <= SIMULATION_TOLERANCE, learned
    # The same check on the graph calibrated afresh (what `quantize` made of a QAT model before
    # its ranges reached the graph) fails: the tolerance bites.
    calibrated = _simulation_gap(run, graphs["calibrated"])
    assert max(calibrated.values()) > SIMULATION_TOLERANCE, calibrated


@pytest.mark.parametrize("rule", ["minmax", "mse"])
def test_calibrated_start_is_the_range_quantize_chooses_on_the_same_values(rule: str) -> None:
    """Catches: learned ranges started from one batch instead of every calibration window, a
    histogram that is not the values' (quantize --calibration mse chooses on it), or a start
    other than the range ONNX Runtime would write for those values (widened to hold 0)."""
    from e3dpsm.quantize.ranges import HISTOGRAM_BINS, Histogram, choose_range

    model, _ = load_checkpoint(TRAINED_TINY, variant="tiny")
    model.eval()
    handle = attach_fake_quant(model, QATConfig())
    cfg = model.config
    gen = torch.Generator().manual_seed(3)
    windows = [(torch.rand(1, 3, cfg.in_channels, cfg.height, cfg.width, generator=gen) < 0.05).float()
               * (k + 1) for k in range(3)]  # each window's values reach further: all must count
    seen: dict[int, list[np.ndarray]] = {i: [] for i in range(len(handle.quantizers))}
    hooks = [q.register_forward_pre_hook(lambda mod, args, i=i: seen[i].append(args[0].detach().numpy().ravel()))
             for i, q in enumerate(handle.quantizers)]

    def run() -> None:
        for frames in windows:
            model.forward_sequence(frames, causal=True)

    calibrated = handle.calibrate(run, rule)
    for hook in hooks:
        hook.remove()
    checked = 0
    for i, quantizer in enumerate(handle.quantizers):
        values = np.concatenate(seen[i]) if seen[i] else np.zeros(1, np.float32)
        low, high = min(float(values.min()), 0.0), max(float(values.max()), 0.0)
        if not high > low:
            assert not bool(quantizer.initialised)
            continue
        if rule == "mse":
            counts = np.histogram(values, bins=HISTOGRAM_BINS, range=(low, high))[0]
            chosen = choose_range(Histogram(counts, low, high))
            low, high = chosen.low, chosen.high
        scale = np.float32((high - low) / 255)
        zero = int(np.clip(round(-low / float(scale)), 0, 255))
        got_scale, got_zero = quantizer.qparams()
        assert got_scale == pytest.approx(float(scale), rel=1e-5) and abs(got_zero - zero) <= 1, (i, handle.groups[i].sites)
        checked += 1
    assert calibrated == checked and checked > 30
    # Calibrated, the quantisers quantise: the next forward pass rounds instead of recording.
    assert all(q.observer is None for q in handle.quantizers)
    out = model.forward_sequence(windows[0], causal=True)["pose"]
    handle.remove()
    assert not torch.allclose(out, model.forward_sequence(windows[0], causal=True)["pose"], atol=1e-4)


def test_full_integer_qat_learns_no_range_where_its_graph_leaves_an_output_float(qat_tiny_full_integer,
                                                                                 tmp_path: Path) -> None:
    """QATConfig(full_integer=True) simulates `quantize --exclude none` as quantize builds it,
    MatMul/Gemm outputs that no quantised op reads in float (--float-outputs matmul). Catches:
    quantisers learned (and rounding simulated) on outputs the graph never rounds."""
    from e3dpsm.training.qat_ranges import quantised_activations
    from e3dpsm.quantize.static import DEFAULT_OP_TYPES, preprocess

    pre = tmp_path / "pre.onnx"
    preprocess(qat_tiny_full_integer["graph"], pre)
    every_pair = set(quantised_activations(pre, [], DEFAULT_OP_TYPES, "none"))
    covered = {t for g in qat_tiny_full_integer["handle"].groups for t in g.tensors}
    producers = {o: n.op_type for n in onnx.load(str(pre)).graph.node for o in n.output}
    dropped = every_pair - covered
    assert covered < every_pair and len(dropped) >= 10, (len(covered), len(every_pair))
    assert {producers[t] for t in dropped} <= {"MatMul", "Gemm"}, {t: producers[t] for t in dropped}
    # ...and no Conv output: Conv outputs keep their pairs under --float-outputs matmul.
    assert not any(producers.get(t) == "Conv" for t in dropped)


def test_coverage_counts_the_written_graphs_8_bit_activations() -> None:
    """Learned and calibrated ranges are counted over the activations the written graph
    quantises to 8 bits; a 16-bit one is counted apart, a weight (an initializer) not at all."""
    from onnx import TensorProto, helper

    from e3dpsm.training.qat_ranges import coverage_in_graph

    def zero_point(name: str, dtype: int) -> onnx.TensorProto:
        return helper.make_tensor(name, dtype, [], [0])

    nodes = [helper.make_node("QuantizeLinear", [x, "s", zp], [f"{x}_q"])
             for x, zp in (("a", "z8"), ("b", "z8"), ("c", "z16"), ("w", "z8"))]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(x, TensorProto.FLOAT, [1]) for x in "abc"],
                              [helper.make_tensor_value_info(f"{x}_q", TensorProto.UINT8, [1]) for x in "abw"],
                              initializer=[helper.make_tensor("s", TensorProto.FLOAT, [], [0.1]),
                                           zero_point("z8", TensorProto.UINT8), zero_point("z16", TensorProto.UINT16),
                                           helper.make_tensor("w", TensorProto.FLOAT, [1], [1.0])])
    model = helper.make_model(graph)
    report: dict = {}
    coverage_in_graph(report, model, {"a": {}, "c": {}, "gone": {}})
    assert report == {"learned_tensors": 1, "calibrated_tensors": 1, "uncovered": ["b"], "sixteen_bit_tensors": 1}
