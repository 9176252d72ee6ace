"""Passes 1 and 2: the graph the quantiser works on, and its state-aware calibration.

prepare: ONNX Runtime's pre-pass (shapes for every tensor, constant folding); the recurrent
  groups (S5 recurrences, Kalman fusion; e3dpsm/onnx_groups.py), which stay float unless
  `--exclude none`; the Conv/MatMul/Gemm the search may place; a private copy of each state
  a quantised node reads (graph_groups.isolate_state_reads). 16-bit targets get opset 21.
calibrate: feeds recorded from continuous fp32 rollouts (calibration.py), ranges written to a
  cache every later graph reuses, learned ranges read from a checkpoint where asked.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import onnx

from e3dpsm.data.prepared import PreparedSequence
from e3dpsm.errors import ConfigError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.quantize.calibration import record_calibration_set
from e3dpsm.quantize.graph_groups import candidate_groups, isolate_state_reads, recurrent_groups
from e3dpsm.quantize.options import QuantizeOptions
from e3dpsm.quantize.static import DEFAULT_OP_TYPES, StaticConfig, calibrate, ensure_opset, preprocess

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PreparedGraph:
    path: Path                       # the pre-processed graph every trial quantises
    meta: GraphMetadata
    config: StaticConfig
    recurrent_groups: tuple[str, ...]
    recurrent: tuple[str, ...]       # their nodes
    compute: tuple[str, ...]         # Conv/MatMul/Gemm outside them: what the search places
    fixed: tuple[str, ...] | None    # a fixed --exclude: the nodes kept float; None: search
    state_reads: tuple[str, ...]     # nodes given a private copy of a state they read

    def to_dict(self) -> dict[str, Any]:
        return {"config": self.config.to_dict(), "recurrent_groups": list(self.recurrent_groups),
                "recurrent_nodes": len(self.recurrent), "compute_nodes": len(self.compute),
                "state_reads": list(self.state_reads),
                "fixed_float_nodes": None if self.fixed is None else len(self.fixed)}

    def report_lines(self) -> list[str]:
        fixed = ("the search places them" if self.fixed is None else
                 f"`--exclude` keeps {len(self.fixed)} nodes float, recurrent ones included")
        return [f"Graph: {len(self.compute)} Conv/MatMul/Gemm outside the recurrent groups "
                f"({', '.join(self.recurrent_groups)}: {len(self.recurrent)} nodes, float); {fixed}.", ""]


def resolve_exclude(spec: str, model: onnx.ModelProto, recurrent: Sequence[str]) -> tuple[str, ...] | None:
    """The nodes a fixed `--exclude` keeps float; None for "auto" (the search decides)."""
    if spec == "auto":
        return None
    if spec == "none":
        return ()
    chosen = list(recurrent)
    if spec != "recurrent":
        groups = {g.name: list(g.nodes) for g in candidate_groups(model, recurrent)}
        names = {n.name for n in model.graph.node}
        for item in (s.strip() for s in spec.split(",") if s.strip()):
            if item not in groups and item not in names:
                raise ConfigError(f"--exclude: {item!r} is neither a node nor a group; groups: {sorted(groups)}")
            chosen += groups.get(item, [item])
    return tuple(dict.fromkeys(chosen))


def prepare_graph(model_path: str | os.PathLike, options: QuantizeOptions, work: Path) -> PreparedGraph:
    config = StaticConfig.for_target(options.target, options.isa, calibration=options.calibration)
    pre = work / "pre.onnx"
    preprocess(model_path, pre)
    if options.int16:  # before calibrating: every graph and the cache then name the same tensors
        ensure_opset(pre)
    model = onnx.load(str(pre))
    meta = GraphMetadata.from_onnx(model)
    groups = recurrent_groups(model, meta)
    recurrent = tuple(dict.fromkeys(n for g in groups for n in g.nodes))
    fixed = resolve_exclude(options.exclude, model, recurrent)
    floats = set(recurrent if fixed is None else fixed)
    quantisable = [n.name for n in model.graph.node if n.op_type in config.op_types and n.name not in floats]
    state_reads = isolate_state_reads(model, quantisable)
    if state_reads:
        onnx.save(model, str(pre))
    compute = tuple(n.name for n in model.graph.node if n.op_type in DEFAULT_OP_TYPES and n.name not in recurrent)
    return PreparedGraph(pre, meta, config, tuple(g.name for g in groups), recurrent, compute, fixed,
                         tuple(state_reads))


@dataclass(frozen=True)
class Calibration:
    cache: Path                      # ONNX Runtime's range cache, shared by every trial
    feeds: tuple[Mapping[str, Any], ...]
    frames: Mapping[str, int]        # calibration frames per sequence
    state_source: str
    seconds: float
    ranges: Mapping[str, Any] = field(default_factory=dict)    # per-tensor choices under "mse"
    learned: Mapping[str, Any] = field(default_factory=dict)   # --ranges-from-checkpoint overrides
    learned_report: Mapping[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        from e3dpsm.quantize.ranges import summarise

        return {"frames": sum(self.frames.values()), "sequences": dict(self.frames), "state_source": self.state_source,
                "seconds": round(self.seconds, 2), **({"ranges": summarise(self.ranges)} if self.ranges else {}),
                **({"learned_ranges": dict(self.learned_report)} if self.learned_report else {})}

    def report_lines(self, method: str) -> list[str]:
        sequences = ", ".join(f"{name} {n}" for name, n in self.frames.items())
        learned = (f" {len(self.learned)} tensors take the ranges learned in `{self.learned_report['checkpoint']}`."
                   if self.learned_report else "")
        return [f"Calibration: {method} ranges over {sum(self.frames.values())} frames ({sequences}), each paired "
                f"with the states a continuous fp32 rollout carried into it ({self.state_source}).{learned}", ""]


def calibrate_graph(prepared: PreparedGraph, model_path: str | os.PathLike, sequences: Sequence[PreparedSequence],
                    options: QuantizeOptions, work: Path) -> Calibration:
    started = time.perf_counter()
    calib = record_calibration_set(model_path, sequences, options.frames, prepared.meta.train_window_ms,
                                   threads=options.threads)
    cache = work / "calibration.json"
    ranges = calibrate(prepared.path, prepared.config, calib, cache)
    learned, report = {}, None
    if options.advanced.ranges_from_checkpoint:
        from e3dpsm.training.qat_ranges import learned_overrides, quantised_activations

        quantised = quantised_activations(prepared.path, prepared.fixed or (), prepared.config.op_types)
        learned, report = learned_overrides(options.advanced.ranges_from_checkpoint, prepared.path, quantised)
        if report.get("float_outputs") not in (None, options.advanced.float_outputs):
            log.warning("the QAT fine-tune simulated --float-outputs %s, this graph takes %s: it computes close to, "
                        "not exactly, what training simulated", report["float_outputs"], options.advanced.float_outputs)
    return Calibration(cache, tuple(calib.feeds), {k: len(v) for k, v in calib.frames.items()}, calib.state_source,
                       time.perf_counter() - started, ranges, learned, report)

