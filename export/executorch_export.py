"""`e3dpsm convert executorch`: the step graph as an ExecuTorch program (`step.pte`) for
the XNNPACK backend: `torch.export` of the ONNX exporter's step wrapper ->
`to_edge_transform_and_lower(XnnpackPartitioner)` -> `.pte`, the state layout inside it as
the constant method `e3dpsm_metadata` (runtime/artifact_metadata.py).

Two choices put more of the step into XNNPACK (measured in docs/edge.md):
- parameter-only subgraphs (transposed S5 matrices, the rescaled offset projection, the
  folded attention projections) are folded into constants first (ExecuTorch's
  `constant_prop_pass`); otherwise XNNPACK sees a computed weight and leaves the mm /
  addmm to portable kernels ("Expected weight to be a static param");
- LayerNorm and GroupNorm go in as matmuls (export/norm_decompositions.py), which XNNPACK
  takes; it has no rule for the norms themselves.
Grid sampling stays on portable kernels (XNNPACK has no such op); the gather form
replaces it by index_select plus a batched matmul.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import torch

from e3dpsm.export.edge_export import artifact_contract, export_ready
from e3dpsm.export.norm_decompositions import norm_decompositions
from e3dpsm.export.wrapper import StepGraph
from e3dpsm.models import E3DPSM
from e3dpsm.runtime.artifact_metadata import PTE_METHOD, encode
from e3dpsm.utils.extras import require
from e3dpsm.utils.io import atomic_path

FORMAT = "executorch"


@dataclass(frozen=True)
class ExecuTorchOptions:
    attention_form: str = "grid_sample"
    decompose_norms: bool = True  # LayerNorm / GroupNorm as matmuls XNNPACK runs
    fold_constants: bool = True  # parameter-only subgraphs folded before partitioning


@dataclass
class ExecuTorchResult:
    path: str
    bytes: int
    seconds: dict[str, float]
    delegation: dict[str, Any]
    options: dict[str, Any]
    artifact: dict[str, Any] = field(default_factory=dict)
    taps: dict[str, Any] = field(default_factory=dict)  # a taps program: its tap count; an INT8 one: its taps program

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in vars(self).items() if k != "taps" or v}


def export_step_program(model: E3DPSM, options: ExecuTorchOptions, quantizer: Any = None,
                        calibrate: Any = None, transform: Any = None) -> torch.export.ExportedProgram:
    """The step wrapper as an ExportedProgram ready to lower; with a PT2E `quantizer`,
    `calibrate(prepared_module)` feeds it before conversion (export/executorch_int8.py), and
    `transform(converted_module)` rewrites the converted module before it is exported again
    (export/executorch_taps.with_taps)."""
    from executorch.exir.passes.constant_prop_pass import constant_prop_pass

    example = StepGraph(model).example_inputs(1)
    program = step_program(model, options)
    if quantizer is not None:
        module = quantized_module(program, quantizer, calibrate)
        program = torch.export.export(transform(module) if transform else module, example, strict=False)
    if options.fold_constants:
        program = constant_prop_pass(program, custom_skip_targets=fold_skip_targets(quantized=quantizer is not None))
    return program


def step_program(model: E3DPSM, options: ExecuTorchOptions) -> torch.export.ExportedProgram:
    """The step wrapper exported, norms decomposed as `options` say: what PT2E quantises."""
    wrapper = StepGraph(model)
    program = torch.export.export(wrapper, wrapper.example_inputs(1), strict=False)
    return program.run_decompositions(norm_decompositions()) if options.decompose_norms else program


def quantized_module(program: torch.export.ExportedProgram, quantizer: Any,
                     calibrate: Any) -> torch.fx.GraphModule:
    """PT2E on a copy of `program`'s module: prepared, calibrated, converted. The result runs in
    PyTorch, quantize / dequantize pairs and all, which is what the INT8 search judges
    (export/executorch_int8.py) before anything is lowered."""
    from torchao.quantization.pt2e.quantize_pt2e import convert_pt2e, prepare_pt2e

    from e3dpsm.export.pt2e_guards import explicit_shared_batch_norms

    module = program.module()  # a fresh GraphModule each call: trials never share observers
    explicit_shared_batch_norms(module)  # else prepare_pt2e's conv-BN fold feeds shortcuts normalised tensors
    prepared = prepare_pt2e(module, quantizer)
    calibrate(prepared)
    return convert_pt2e(prepared)


def fold_skip_targets(quantized: bool) -> set[Any] | None:
    """What constant folding leaves alone: ExecuTorch's default; in a quantised program also
    the ATen-dialect quantize / dequantize ops (the pass's own list holds their edge-dialect
    forms only, and folded, an 8-bit weight and its dequantize become one float weight)."""
    if not quantized:
        return None
    from executorch.exir.passes.constant_prop_pass import get_default_skip_targets_no_quant

    ops = torch.ops.quantized_decomposed
    primitives = {getattr(getattr(ops, name), overload)
                  for name in ("quantize_per_tensor", "dequantize_per_tensor", "quantize_per_channel",
                               "dequantize_per_channel")
                  for overload in getattr(ops, name).overloads()}
    return set(get_default_skip_targets_no_quant()) | primitives


def convert_executorch(model: E3DPSM, path: str | os.PathLike, options: ExecuTorchOptions = ExecuTorchOptions(),
                       precision: str = "fp32", quantizer: Any = None, calibrate: Any = None,
                       extra_record: dict[str, Any] | None = None, taps: bool = False) -> ExecuTorchResult:
    """Write `path` (.pte); returns sizes, timings and what runs in XNNPACK. `taps` (with a
    `quantizer`): the program also returns every quantised activation's codes, their names and
    segments in its TAPS_METHOD (export/executorch_taps.py)."""
    require("executorch", "to write .pte programs")
    from executorch.backends.xnnpack.partition.xnnpack_partitioner import XnnpackPartitioner
    from executorch.exir import to_edge_transform_and_lower

    from e3dpsm.export.delegation import delegation_summary

    meta, record = artifact_contract(model, FORMAT, precision, options.attention_form, ("executorch",),
                                     {"decompose_norms": options.decompose_norms, **(extra_record or {})})
    if taps and quantizer is None:
        raise ValueError("taps are the codes of quantised activations: an fp32 program has none")
    taps_made: list[dict[str, Any]] = []

    def tapped(module: torch.fx.GraphModule) -> torch.fx.GraphModule:
        from e3dpsm.export.executorch_taps import with_taps

        module, made = with_taps(module)
        taps_made.extend(made)
        return module
    started = time.perf_counter()
    with export_ready(model, options.attention_form):  # frozen parameters until serialised
        program = export_step_program(model, options, quantizer, calibrate, tapped if taps else None)
        exported = time.perf_counter()
        methods = {PTE_METHOD: encode(meta, record)}
        if taps:
            from e3dpsm.runtime.artifact_metadata import TAPS_METHOD, encode_taps

            methods[TAPS_METHOD] = encode_taps(taps_made)
        edge = to_edge_transform_and_lower(program, partitioner=[XnnpackPartitioner()], constant_methods=methods)
        delegation = delegation_summary(edge)
        if quantizer is not None:
            from e3dpsm.export.executorch_int8 import int8_coverage

            delegation["int8"] = int8_coverage(edge)
        lowered = time.perf_counter()
        if quantizer is not None:
            # the quantize / dequantize ops a partition leaves outside XNNPACK (the gather form's
            # computed weights) need their out-variant kernels registered to serialise
            import executorch.kernels.quantized  # noqa: F401
        buffer = edge.to_executorch().buffer
    with atomic_path(path, suffix=".pte") as tmp:
        tmp.write_bytes(buffer)
    done = time.perf_counter()
    return ExecuTorchResult(
        path=str(path), bytes=len(buffer),
        seconds={"export": round(exported - started, 2), "lower": round(lowered - exported, 2),
                 "serialize": round(done - lowered, 2), "total": round(done - started, 2)},
        delegation=delegation, options=vars(options).copy(), artifact=record,
        taps={"count": len(taps_made)} if taps else {},
    )
