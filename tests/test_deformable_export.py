"""The gather sampler and folded projections of deformable attention (its export form) against
the literal grid_sample form and an explicit-loop bilinear reference; the exported gather
graph, static batch and the ONNX Runtime pre-optimised copy against PyTorch."""
from __future__ import annotations

import copy

import numpy as np
import onnx
import pytest
import torch

import e3dpsm
from e3dpsm.layers.deformable import DeformableAttention, DeformableTransformerBlock, export_attention_form
from e3dpsm.layers.gather_sampling import bilinear_gather
from tests.conftest import sparse_lnes

# float32 round-off of a reordered sum, relative to the output's scale.
RTOL = 2e-5


def _randomise(module: torch.nn.Module, seed: int, offset_scale: float = 3.0) -> None:
    """Trained-looking parameters: fractional offsets reaching well outside the map,
    non-uniform attention weights, a moved 2-D reference grid."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            noise = torch.randn(p.shape, generator=gen)
            if "sampling_offsets" in name:  # offsets of about offset_scale pixels
                p.copy_(noise * (offset_scale / 4 if p.dim() == 2 else offset_scale))
            elif name.endswith("reference"):
                p.add_(noise * 0.2)
            else:
                p.add_(noise * 0.3)


def _max_rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max().detach() / b.abs().max().detach().clamp_min(1e-12))


# Map sizes: wide, odd, a single row, and a single column; the 1-D layout samples an
# (h*w) x 1 column of any of them.
MAPS = [(6, 8), (3, 5), (1, 7), (5, 1)]


@pytest.mark.parametrize("layout", ["2d", "1d"])
@pytest.mark.parametrize("hw", MAPS)
def test_gather_sampler_equals_grid_sample(layout: str, hw: tuple[int, int]) -> None:
    """Forward values and gradients (query, value, every parameter incl. the learned
    reference grid) of the two samplers, with samples inside, across and outside the map."""
    attn = DeformableAttention(16, 2, 4, *hw, layout=layout)
    # The 1-D layout samples a one-pixel-wide column: offsets of a pixel already reach out.
    _randomise(attn, seed=hw[0] * 10 + hw[1], offset_scale=3.0 if layout == "2d" else 1.0)
    gen = torch.Generator().manual_seed(1)
    query = torch.randn(3, hw[0] * hw[1], 16, generator=gen, requires_grad=True)
    value = torch.randn(3, hw[0] * hw[1], 16, generator=gen, requires_grad=True)

    # The test must cover zero padding: some samples fully off the map, some straddling it.
    weight, bias, origin = attn.pixel_offset_projection()
    xy = (torch.nn.functional.linear(query, weight, bias) + origin).detach()
    slots = attn.heads * attn.points
    x, y = xy[..., :slots], xy[..., slots:]
    height, width = attn.map_hw
    outside = (x <= -1) | (x >= width) | (y <= -1) | (y >= height)
    straddle = ~outside & ((x < 0) | (x > width - 1) | (y < 0) | (y > height - 1))
    assert 0.05 < outside.float().mean() < 0.95 and straddle.any()

    inputs = [query, value, *attn.parameters()]
    results = {}
    for sampler in ("grid_sample", "gather", "deform_conv"):
        attn.sampler = sampler
        out = attn(query, value)
        results[sampler] = (out, torch.autograd.grad(out.square().sum(), inputs))
    ref, ref_grads = results["grid_sample"]
    for sampler in ("gather", "deform_conv"):  # deform_conv: its offsets and kernel grid in PyTorch
        got, got_grads = results[sampler]
        assert _max_rel(got, ref) <= RTOL, sampler
        for g, r in zip(got_grads, ref_grads):
            assert _max_rel(g, r) <= 1e-4, sampler  # gradients: longer sums, same round-off scale


def _loop_reference(value: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Bilinear sampling with zero padding, pixel centres at integers (grid_sample's
    align_corners=False), one sample at a time: the definition, not a rewrite of it."""
    n, height, width, heads, dim = value.shape
    out = np.zeros((n, x.shape[1], heads, dim))
    for b, l, h, p in np.ndindex(*x.shape):
        x0, y0 = int(np.floor(x[b, l, h, p])), int(np.floor(y[b, l, h, p]))
        fx, fy = x[b, l, h, p] - x0, y[b, l, h, p] - y0
        for dx, dy, k in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            xi, yi = x0 + dx, y0 + dy
            if 0 <= xi < width and 0 <= yi < height:
                out[b, l, h] += w[b, l, h, p] * k * value[b, yi, xi, h]
    return out


@pytest.mark.parametrize("hw", [(4, 6), (1, 5), (5, 1)])
def test_bilinear_gather_matches_loop_reference(hw: tuple[int, int]) -> None:
    rng = np.random.default_rng(3)
    height, width = hw
    n, tokens, heads, points, dim = 2, 7, 3, 5, 4
    value = rng.normal(size=(n, height, width, heads, dim))
    x = rng.uniform(-2.5, width + 1.5, size=(n, tokens, heads, points))
    y = rng.uniform(-2.5, height + 1.5, size=(n, tokens, heads, points))
    x[0, 0, 0, :3] = [-1.0, width - 1.0, 0.0]  # exact corners and the border lines
    w = rng.uniform(size=(n, tokens, heads, points))
    as_t = lambda a: torch.from_numpy(a).float()  # noqa: E731
    got = bilinear_gather(as_t(value).reshape(n, height * width, heads, dim), hw, as_t(x), as_t(y), as_t(w))
    ref = _loop_reference(value, x, y, w)
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=2e-5 * np.abs(ref).max())


@pytest.mark.parametrize("layout", ["2d", "1d"])
@pytest.mark.parametrize("hw", [(6, 8), (3, 5), (2, 2)])
def test_folded_block_equals_literal_block(layout: str, hw: tuple[int, int]) -> None:
    """The export form of the whole transformer block (folded projections, either sampler),
    including the released short-map rule (2 x 2 = 4 tokens <= 4 points: no sampling)."""
    block = DeformableTransformerBlock(16, 2, 8, 4, *hw, layout=layout)
    _randomise(block, seed=7)
    assert block.uses_sampling == (hw[0] * hw[1] > 4)
    x = torch.randn(2, 16, *hw, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        ref = block(x)
        for sampler in ("gather", "deform_conv", "grid_sample"):
            with export_attention_form(block, sampler=sampler):
                got = block(x)
            assert _max_rel(got - x, ref - x) <= RTOL, sampler  # the block's own contribution
    assert block.attn.sampler == "grid_sample" and not block.fold_projections  # restored


def assert_short_rollout_parity(model: torch.nn.Module, session) -> None:
    """12 carried steps at 25 ms, the project's parity check: every output and state within
    its tolerance, pose within 0.01 mm of poses of metre scale."""
    from e3dpsm.export.parity import Tolerances, run_parity

    frames = [f.numpy() for f in sparse_lnes((12, 2, 192, 256), density=0.05, seed=4)]
    report = run_parity(model, session, frames, 25.0, Tolerances())
    assert report.steps == 12
    for diff in report.diffs:
        assert diff.passed, diff.line()
    pose = next(d for d in report.diffs if d.name == "pose")
    assert pose.max_abs <= 0.01 and pose.reference_scale > 100.0


@pytest.fixture(scope="module")
def gather_static_export(tmp_path_factory):
    """A tiny model with trained-looking attention, exported in the gather form with batch 1,
    and its ONNX Runtime pre-optimised copy."""
    from e3dpsm.export import export_step_with_report
    from e3dpsm.export.ort_optimized import write_ort_optimized

    model = e3dpsm.create_model("tiny").eval()
    model.set_pose_prior(torch.linspace(-800.0, 1200.0, 48).view(16, 3))
    _randomise(model.attention, seed=5, offset_scale=1.0)
    folder = tmp_path_factory.mktemp("deformable_export")
    result = export_step_with_report(model, folder / "step.onnx", attention_form="gather", static_batch=True)
    info = write_ort_optimized(folder / "step.onnx", folder / "step.ort.onnx", "extended")
    return model, folder / "step.onnx", folder / "step.ort.onnx", result, info


def test_gather_static_graph_contract(gather_static_export) -> None:
    model, path, _, result, _ = gather_static_export
    graph = onnx.load(str(path))
    assert result.static_batch and result.attention_form == "gather"
    ops = {n.op_type for n in graph.graph.node}
    assert "GridSample" not in ops and {"Gather", "MatMul"} <= ops
    assert all(n.domain in ("", "ai.onnx") for n in graph.graph.node)
    for value in [*graph.graph.input, *graph.graph.output]:
        first = value.type.tensor_type.shape.dim[0]
        assert first.dim_value == 1 and not first.dim_param, value.name
    from e3dpsm.graph_metadata import GraphMetadata

    meta = GraphMetadata.from_onnx(graph)
    assert meta.frame_input["shape"][0] == 1 and meta.config["static_batch"] == 1
    assert meta.config["attention_form"] == "gather"


@pytest.mark.parametrize("which", ["portable", "ort_optimized"])
def test_gather_static_graphs_match_pytorch(gather_static_export, which: str) -> None:
    """A short carried rollout: the literal PyTorch model vs the gather-form graph (and ONNX
    Runtime's pre-optimised copy of it), pose within 0.01 mm, states within 1e-4 relative."""
    from e3dpsm.runtime import StepSession

    model, path, ort_path, _, info = gather_static_export
    assert info["level"] == "extended" and info["onnxruntime"]
    session = StepSession(path if which == "portable" else ort_path, threads=1, spin=False)
    assert_short_rollout_parity(model, session)


def test_export_form_does_not_change_the_model() -> None:
    model = e3dpsm.create_model("tiny").eval()
    before = copy.deepcopy(model.state_dict())
    with export_attention_form(model):
        assert all(b.fold_projections and b.attn.sampler == "gather" for b in model.attention)
    assert all(not b.fold_projections and b.attn.sampler == "grid_sample" for b in model.attention)
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())
    with pytest.raises(ValueError, match="unknown sampler"):
        with export_attention_form(model, sampler="nearest"):
            pass


def test_gather_export_1d_layout_dynamic_batch(tmp_path) -> None:
    """The released 1-D layout in the gather form, exported with the dynamic batch axis: three
    streams in one call match PyTorch (the batch offsets of the gather indices)."""
    from e3dpsm.export import export_step_with_report
    from e3dpsm.runtime import StepSession

    model = e3dpsm.create_model("tiny", attn_layout="1d").eval()
    _randomise(model.attention, seed=9, offset_scale=1.0)
    result = export_step_with_report(model, tmp_path / "step.onnx", attention_form="gather", simplify=False)
    assert "GridSample" not in result.op_types and not result.static_batch
    session = StepSession(tmp_path / "step.onnx", threads=1, spin=False)
    frames = sparse_lnes((3, 2, 192, 256), density=0.05, seed=6)
    state, ref_state = session.init_state(3), model.init_state(3)
    for _ in range(2):  # carried states, second step fuses
        out, state = session.step(frames.numpy(), state, 20.0)
        with torch.no_grad():
            ref, ref_state = model.step(frames, ref_state, 20.0)
        assert np.abs(out["pose"] - ref["pose"].numpy()).max() <= 0.01
        assert np.abs(out["pose"] - ref["pose"].numpy()).max() < np.abs(np.diff(out["pose"], axis=0)).max()
