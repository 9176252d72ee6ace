"""What PT2E preparation must leave alone, and what XNNPACK's quantizer may annotate.

- export/pt2e_guards.py: a BatchNorm reading a convolution that also feeds a shortcut is made
  an explicit scale and shift, so torchao's conv-BN fold cannot hand the shortcut the
  normalised tensor (checked against eager PyTorch, and the unguarded fold shown to break it).
- export/executorch_int8.py's quantizer: convolutions and linears inside the quantised scopes
  take 8 bits; no `cat`, no head, no recurrent module does (checked on the trained tiny's step).
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

from _edge_helpers import skip_without


class PreActivationBlock(nn.Module):
    """A stage's `down` convolution feeding a block's BatchNorm and its shortcut, as in the
    model's residual stages; `tail` is a convolution whose BatchNorm is its only reader."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        # eps large enough that a rewrite ignoring it misses the tolerance below
        self.down, self.norm, self.conv = nn.Conv2d(3, 4, 3, padding=1), nn.BatchNorm2d(4, eps=0.5), nn.Conv2d(4, 4, 1)
        self.tail, self.tail_norm = nn.Conv2d(4, 4, 1), nn.BatchNorm2d(4)
        for norm in (self.norm, self.tail_norm):  # statistics far from the identity
            norm.running_mean.uniform_(-2.0, 2.0)
            norm.running_var.uniform_(0.2, 4.0)
            norm.weight.data.uniform_(0.5, 2.0)
            norm.bias.data.uniform_(-1.0, 1.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.down(x)
        y = y + self.conv(torch.relu(self.norm(y)))
        return self.tail_norm(self.tail(y))


def _prepared(guard: bool) -> tuple[nn.Module, torch.nn.Module, int]:
    skip_without("executorch")
    from executorch.backends.xnnpack.quantizer.xnnpack_quantizer import XNNPACKQuantizer
    from torchao.quantization.pt2e.quantize_pt2e import prepare_pt2e

    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms

    block = PreActivationBlock().eval()
    module = torch.export.export(block, (torch.randn(1, 3, 8, 8),), strict=False).module()
    rewritten = explicit_shared_batch_norms(module) if guard else 0
    return block, prepare_pt2e(module, XNNPACKQuantizer()), rewritten  # annotates nothing: float


def test_guarded_preparation_computes_the_float_block() -> None:
    block, prepared, rewritten = _prepared(guard=True)
    assert rewritten == 1  # the shared one; the tail's BatchNorm is left to the (exact) fold
    x = torch.randn(1, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(prepared(x), block(x), atol=1e-5, rtol=1e-5)


def test_unguarded_fold_changes_the_block() -> None:
    """Why the guard exists: torchao's fold alone moves the output by far more than the
    tolerance above (if torchao starts checking the convolution's other readers, this fails
    and the guard can go)."""
    block, prepared, _ = _prepared(guard=False)
    x = torch.randn(1, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert (prepared(x) - block(x)).abs().max() > 0.1


def test_guard_finds_only_shared_convolutions() -> None:
    from e3dpsm.export.pt2e_guards import unfoldable_batch_norms

    module = torch.export.export(PreActivationBlock().eval(), (torch.randn(1, 3, 8, 8),), strict=False).module()
    found = unfoldable_batch_norms(module)
    assert len(found) == 1 and found[0].args[0].target == torch.ops.aten.conv2d.default
    assert len(found[0].args[0].users) == 2


class AffineFreeBlock(PreActivationBlock):
    """The shared BatchNorm without weight and bias (`affine=False`): scale and shift from the
    running statistics alone."""

    def __init__(self) -> None:
        super().__init__()
        self.norm = nn.BatchNorm2d(4, eps=0.5, affine=False)
        self.norm.running_mean.uniform_(-2.0, 2.0)
        self.norm.running_var.uniform_(0.2, 4.0)


def _guarded(block: nn.Module, decompose: bool) -> tuple[torch.fx.GraphModule, int]:
    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms

    exported = torch.export.export(block, (torch.randn(1, 3, 8, 8),), strict=False)
    module = (exported.run_decompositions() if decompose else exported).module()
    return module, explicit_shared_batch_norms(module)


@pytest.mark.parametrize("decompose", [False, True], ids=["aten.batch_norm", "native_batch_norm_legit"])
@pytest.mark.parametrize("block", [PreActivationBlock, AffineFreeBlock])
def test_the_rewrite_computes_the_batch_norm(block, decompose) -> None:
    """Both forms of an eval BatchNorm (the core ATen decomposition reads eps at another
    position and returns a tuple), with and without affine parameters: the rewritten graph
    computes the eager block, and no shared BatchNorm (nor its getitem) is left."""
    eager = block().eval()
    module, rewritten = _guarded(eager, decompose)
    assert rewritten == 1
    x = torch.randn(1, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        torch.testing.assert_close(module(x), eager(x), atol=1e-5, rtol=1e-5)
    norms = [n for n in module.graph.nodes if n.op == "call_function" and "batch_norm" in str(n.target)]
    assert len(norms) == 1 and norms[0].args[0].args[0].name.startswith("add")  # the tail's, left to the fold


def test_the_rewrite_keeps_the_module_path_the_quantizer_filters_on() -> None:
    """The scale and shift nodes carry the BatchNorm's module stack and stack trace (the
    quantizer's scope filter reads them), and none of its other metadata (its `val` is a
    tuple in the decomposed form)."""
    module, _ = _guarded(PreActivationBlock().eval(), decompose=True)
    affine = [n for n in module.graph.nodes if n.target in (torch.ops.aten.mul.Tensor, torch.ops.aten.add.Tensor)
              and any(str(a.target).startswith("_explicit_batch_norm") for a in n.args if isinstance(a, torch.fx.Node))]
    assert len(affine) == 2
    for node in affine:
        assert set(node.meta) == {"nn_module_stack", "stack_trace"}
        assert list(node.meta["nn_module_stack"].values())[-1][0] == "norm"
        assert "self.norm(y)" in node.meta["stack_trace"]


def test_a_statistic_that_is_not_a_constant_is_refused() -> None:
    """Running statistics fed as a graph input (not the eval model's buffers): no constant
    scale to compute, said in one line."""
    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms

    class FedStatistics(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.down = nn.Conv2d(3, 4, 3, padding=1)

        def forward(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
            y = self.down(x)
            return y + nn.functional.batch_norm(y, mean, torch.ones(4), training=False)

    module = torch.export.export(FedStatistics().eval(), (torch.randn(1, 3, 8, 8), torch.zeros(4)),
                                 strict=False).module()
    with pytest.raises(ValueError, match=r"^BatchNorm statistic mean is not a constant of the graph: "
                                         r"is the model in eval mode\?$"):
        explicit_shared_batch_norms(module)


def test_a_reader_of_the_saved_statistics_is_refused() -> None:
    """The decomposed BatchNorm's other outputs (saved mean, inverse std) read by something:
    the rewrite cannot stand in for them."""
    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms

    exported = torch.export.export(PreActivationBlock().eval(), (torch.randn(1, 3, 8, 8),), strict=False)
    module = exported.run_decompositions().module()
    norm = next(n for n in module.graph.nodes if n.target == torch.ops.aten._native_batch_norm_legit_no_training.default)
    (output,) = [n for n in module.graph.nodes if n.op == "output"]
    with module.graph.inserting_before(output):
        saved = module.graph.call_function(__import__("operator").getitem, (norm, 1))
    output.args = ((*output.args[0], saved),) if isinstance(output.args[0], (tuple, list)) else ((output.args[0], saved),)
    module.recompile()
    with pytest.raises(ValueError, match=r"^_native_batch_norm_legit_no_training has a reader of its saved "
                                         r"statistics; cannot rewrite it$"):
        explicit_shared_batch_norms(module)


@pytest.fixture(scope="module")
def annotated_step(edge_model):
    """The trained tiny's step, exported as for the INT8 program and annotated by the quantizer."""
    skip_without("executorch")
    from e3dpsm.export.edge_export import export_ready
    from e3dpsm.export.executorch_int8 import xnnpack_int8_quantizer
    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms
    from e3dpsm.export.wrapper import StepGraph

    with export_ready(edge_model, "grid_sample"):
        wrapper = StepGraph(edge_model)
        module = torch.export.export(wrapper, wrapper.example_inputs(1), strict=False).module()
    explicit_shared_batch_norms(module)
    quantizer = xnnpack_int8_quantizer()
    return quantizer.annotate(quantizer.transform_for_annotation(module))


def _annotated(node: torch.fx.Node) -> bool:
    annotation = node.meta.get("quantization_annotation")
    return bool(annotation is not None and annotation._annotated)


def test_quantizer_annotates_the_feature_extractor(annotated_step) -> None:
    from e3dpsm.export.delegation import module_scope
    from e3dpsm.export.executorch_int8 import in_quantised_scope

    convolutions = [n for n in annotated_step.graph.nodes if n.target == torch.ops.aten.conv2d.default]
    assert convolutions and all(_annotated(n) for n in convolutions if in_quantised_scope(n))
    assert any(_annotated(n) and ".stages." in "." + module_scope(n) + "." for n in convolutions)


def test_quantizer_leaves_heads_cats_and_recurrence_float(annotated_step) -> None:
    from e3dpsm.export.delegation import module_scope

    for node in annotated_step.graph.nodes:
        scope = module_scope(node)
        if node.target == torch.ops.aten.cat.default:
            assert not _annotated(node), scope
        if any(part in scope for part in (".s5", "fusion", "pose_embed", "direct_head", "delta_head")):
            assert not _annotated(node), (node.target, scope)
        if node.target in (torch.ops.aten.add.Tensor, torch.ops.aten.mul.Tensor) and _annotated(node):
            # only as a computed weight or bias (the offset projection's rescaled ones), never as an activation
            assert all(user.target == torch.ops.aten.linear.default and node in user.args[1:3]
                       for user in node.users), (node.target, scope)
