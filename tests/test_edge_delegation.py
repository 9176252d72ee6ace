"""The MAC count convert.json's `delegation` rests on (export/delegation.py), on a small module
exported with torch.export: each operator's multiply-accumulates against the formulas in the
module's docstring, written out here from the shapes."""
from __future__ import annotations

import pytest
import torch

from e3dpsm.export.delegation import DELEGATE_CALL, _compute_nodes, node_macs, op_name


class Mix(torch.nn.Module):
    """One of each operator the count knows, and some it gives 0."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(4, 6, kernel_size=3, padding=1, groups=2)
        self.linear = torch.nn.Linear(5, 7)

    def forward(self, image: torch.Tensor, rows: torch.Tensor, grid: torch.Tensor, a: torch.Tensor,
                b: torch.Tensor, bias: torch.Tensor) -> tuple[torch.Tensor, ...]:
        conv = self.conv(image)  # [1, 6, 8, 8]
        linear = self.linear(rows)  # [3, 5] -> [3, 7]
        mm = torch.mm(rows, a)  # [3, 5] x [5, 2] -> [3, 2]
        bmm = torch.bmm(b, b.transpose(1, 2))  # [2, 3, 4] x [2, 4, 3] -> [2, 3, 3]
        addmm = torch.addmm(bias, rows, a)  # [3, 2]
        sampled = torch.nn.functional.grid_sample(image, grid, align_corners=False)  # [1, 4, 5, 6]
        return conv.relu() + 1.0, linear, mm, bmm, addmm, sampled


def _graph() -> torch.fx.Graph:
    inputs = (torch.randn(1, 4, 8, 8), torch.randn(3, 5), torch.rand(1, 5, 6, 2) * 2 - 1, torch.randn(5, 2),
              torch.randn(2, 3, 4), torch.randn(3, 2))
    # the core ATen operators ExecuTorch's edge dialect is made of (conv2d -> convolution, ...)
    return torch.export.export(Mix().eval(), inputs).run_decompositions().graph


def test_each_operator_counts_its_multiply_accumulates() -> None:
    macs = {}
    for node in _graph().nodes:
        if node.op == "call_function":
            macs.setdefault(op_name(node), []).append(node_macs(node))
    assert macs["aten.convolution.default"] == [1 * 6 * 8 * 8 * (4 // 2) * 3 * 3]  # outputs x in/groups x kernel
    assert macs["aten.mm.default"] == [3 * 2 * 5]
    assert macs["aten.bmm.default"] == [2 * 3 * 3 * 4]
    assert sorted(macs["aten.addmm.default"]) == sorted([3 * 7 * 5, 3 * 2 * 5])  # the linear's and the explicit one
    assert macs["aten.grid_sampler_2d.default"] == [4 * 1 * 4 * 5 * 6]  # the four bilinear corners
    assert macs["aten.relu.default"] == [0] and macs["aten.add.Tensor"] == [0]
    placeholders = [n for n in _graph().nodes if n.op != "call_function"]
    assert placeholders and all(node_macs(n) == 0 for n in placeholders)


def test_operator_names_drop_the_namespace_prefix() -> None:
    names = {op_name(n) for n in _graph().nodes if n.op == "call_function"}
    assert {"aten.convolution.default", "aten.mm.default", "aten.relu.default"} <= names
    assert not any(name.startswith("torch.ops.") for name in names)


def test_getitems_and_delegate_calls_are_not_compute() -> None:
    graph = torch.fx.Graph()
    x = graph.placeholder("x")
    pair = graph.call_function(torch.ops.aten.var_mean.correction, (x,))
    first = graph.call_function(getattr(__import__("operator"), "getitem"), (pair, 0))
    relu = graph.call_function(torch.ops.aten.relu.default, (first,))
    graph.output(relu)
    assert [op_name(n) for n in _compute_nodes(graph)] == ["aten.var_mean.correction", "aten.relu.default"]
    assert DELEGATE_CALL == "executorch_call_delegate"


def test_a_linear_reduces_over_its_weights_last_axis() -> None:
    """aten.linear (before decomposition): outputs x the weight's input features."""
    exported = torch.export.export(torch.nn.Linear(5, 7).eval(), (torch.randn(3, 5),))
    (linear,) = [n for n in exported.graph.nodes if n.op == "call_function"]
    assert op_name(linear) == "aten.linear.default" and node_macs(linear) == 3 * 7 * 5
    no_meta = torch.fx.Graph().call_function(torch.ops.aten.mm.default, ())
    with pytest.raises(IndexError):  # a node without shapes has no reduced length to read
        node_macs(no_meta)


def test_the_delegated_share_of_a_lowered_program() -> None:
    """Mix lowered with XNNPACK's partitioner: whatever XNNPACK takes, the delegated and the
    portable MACs add up to the module's (the formulas above), the portable ones are those of
    the operators left outside, and the share is their ratio."""
    pytest.importorskip("executorch")
    from executorch.backends.xnnpack.partition.xnnpack_partitioner import XnnpackPartitioner
    from executorch.exir import to_edge_transform_and_lower

    from e3dpsm.export.delegation import delegation_summary

    inputs = (torch.randn(1, 4, 8, 8), torch.randn(3, 5), torch.rand(1, 5, 6, 2) * 2 - 1, torch.randn(5, 2),
              torch.randn(2, 3, 4), torch.randn(3, 2))
    lowered = to_edge_transform_and_lower(torch.export.export(Mix().eval(), inputs),
                                          partitioner=[XnnpackPartitioner()])
    summary = delegation_summary(lowered)
    # each operator's MACs in Mix (the edge dialect keeps the Linear as aten.linear)
    by_op = {"aten.convolution.default": 6912, "aten.linear.default": 105, "aten.mm.default": 30,
             "aten.bmm.default": 72, "aten.addmm.default": 30, "aten.grid_sampler_2d.default": 480}
    total = sum(by_op.values())
    portable = summary["portable_ops"]
    assert "aten.grid_sampler_2d.default" in portable  # XNNPACK has no grid sampling
    assert not any(name in portable for name in ("getitem", DELEGATE_CALL))
    assert summary["portable_macs"] == sum(by_op.get(name, 0) * count for name, count in portable.items())
    assert summary["delegated_macs"] + summary["portable_macs"] == total
    assert summary["delegates"] >= 1 and summary["delegated_macs"] > 0
    assert summary["delegated_share"] == summary["delegated_macs"] / total
    assert list(portable.values()) == sorted(portable.values(), reverse=True)  # most common first


def test_callables_other_than_operators_go_by_their_bare_name() -> None:
    """portable_ops lists `getitem`, not `<built-in function getitem>`."""
    import operator

    graph = torch.fx.Graph()
    pair = graph.call_function(torch.ops.aten.var_mean.correction, (graph.placeholder("x"),))
    item = graph.call_function(operator.getitem, (pair, 0))
    assert op_name(item) == "getitem"


@pytest.mark.parametrize("target", [torch.ops.aten.grid_sampler_2d.default, torch.ops.aten.convolution.default])
def test_a_node_without_shapes_counts_nothing(target) -> None:
    """A node whose tensors carry no `val` metadata (a hand-built graph) has no output count."""
    graph = torch.fx.Graph()
    x, w = graph.placeholder("x"), graph.placeholder("w")
    assert node_macs(graph.call_function(target, (x, w))) == 0


def test_a_convolution_whose_weight_has_no_shape_counts_nothing() -> None:
    graph = torch.export.export(torch.nn.Conv2d(2, 3, 3).eval(), (torch.randn(1, 2, 5, 5),)).run_decompositions().graph
    (conv,) = [n for n in graph.nodes if n.op == "call_function"]
    conv.args[1].meta.pop("val")
    assert node_macs(conv) == 0


class Chain(torch.nn.Module):
    """conv -> grid sampling (portable) -> conv: XNNPACK makes two delegates around the sampler."""

    def __init__(self) -> None:
        super().__init__()
        self.first = torch.nn.Conv2d(2, 4, kernel_size=3, padding=1)
        self.second = torch.nn.Conv2d(4, 3, kernel_size=1)

    def forward(self, image: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
        sampled = torch.nn.functional.grid_sample(self.first(image), grid, align_corners=False)
        return self.second(sampled)


def test_every_delegate_of_a_program_is_counted() -> None:
    """Two delegates: the count is the program's delegate calls, and the delegated MACs the sum of
    both convolutions' (outputs x in/groups x kernel), not the last delegate's alone."""
    pytest.importorskip("executorch")
    from executorch.backends.xnnpack.partition.xnnpack_partitioner import XnnpackPartitioner
    from executorch.exir import to_edge_transform_and_lower

    from e3dpsm.export.delegation import delegation_summary

    inputs = (torch.randn(1, 2, 6, 6), torch.rand(1, 5, 4, 2) * 2 - 1)
    lowered = to_edge_transform_and_lower(torch.export.export(Chain().eval(), inputs),
                                          partitioner=[XnnpackPartitioner()])
    calls = [n for n in lowered.exported_program().graph.nodes if op_name(n) == DELEGATE_CALL]
    summary = delegation_summary(lowered)
    assert len(calls) == 2 and summary["delegates"] == 2
    assert summary["delegated_macs"] == (1 * 4 * 6 * 6) * 2 * 3 * 3 + (1 * 3 * 5 * 4) * 4
    assert summary["portable_macs"] == 4 * (1 * 4 * 5 * 4)
