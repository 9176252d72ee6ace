"""`quantize_graph`: one exported step graph + prepared data -> one quantised artifact
folder (`DIR/step_<mode>.onnx`, `DIR/report.json`), built under a temporary name."""
from __future__ import annotations

import logging
import os
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import onnx

from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.graph_metadata import GraphMetadata, MetadataError
from e3dpsm.export.onnx_export import op_histogram
from e3dpsm.quantize.adaround import WEIGHT_ROUNDINGS, AdaRoundConfig, adaround_weights, apply_rounding
from e3dpsm.quantize.artifact import finalize, save_model
from e3dpsm.onnx_constants import retile_constants
from e3dpsm.quantize.compact import compact_qdq, graph_names
from e3dpsm.quantize.calibration import record_calibration_set
from e3dpsm.quantize.dynamic import quantize_dynamic_int8
from e3dpsm.quantize.equalize import equalize
from e3dpsm.quantize.exclusions import (NodeRanking, SearchResult, greedy_exclusions, node_sensitivity,
                                        ranked_prefix_exclusions, scratch_model_path)
from e3dpsm.quantize.fp16 import convert_fp16
from e3dpsm.quantize.front import (FP32_LABEL, OBJECTIVES, Candidate, LatencySearch, candidates_from_search,
                                   latency_aware_choice)
from e3dpsm.quantize.front_report import write_search_outputs
from e3dpsm.quantize.census import compute_precisions, out_of_8_bits, precision_counts
from e3dpsm.quantize.graph_groups import (NodeGroup, candidate_groups, isolate_state_reads, recurrent_groups,
                                         shared_input_units)
from e3dpsm.quantize.holdout import HoldoutSet, accuracy_of, make_holdout
from e3dpsm.quantize.ranges import summarise as summarise_ranges
from e3dpsm.quantize.outputs import FLOAT_OUTPUTS, dequantised_outputs
from e3dpsm.quantize.precision import (SizeProbe, demote_to_int16, promote_to_int16w16, quantise_recurrent_compute,
                                       smallest_int16_plan)
from e3dpsm.quantize.qat_ranges import (coverage_in_graph, learned_overrides, qat_weight_bits, quantised_activations,
                                        read_ranges, simulated_float_outputs)
from e3dpsm.quantize.static import (DEFAULT_OP_TYPES, StaticConfig, calibrate, ensure_opset, int16_tensors,
                                   preprocess, quantize_int8, quantised_node_count, saturates_u8s8)
from e3dpsm.quantize.step_timer import SideBySideTimer, StepTimer
from e3dpsm.utils.env import report_header
from e3dpsm.utils.isa import detect_isa
from e3dpsm.utils.io import atomic_dir, write_json_atomic

log = logging.getLogger(__name__)

MODES: tuple[str, ...] = ("int8", "int8-dynamic", "fp16")
SEARCHES: tuple[str, ...] = ("nodes", "groups")
# Held-out error budgets of `--exclude auto` (bound_pct: mean distance to the fp32 poses over
# the fp32 MPJPE): the accuracy each mode is expected to keep (INT8 +1%, FP16 +0.1%).
DEFAULT_BUDGET_PCT: dict[str, float] = {"int8": 1.0, "int8-dynamic": 1.0, "fp16": 0.1}
# The share of the budget the search leaves unspent (--search-margin). The search sees a few
# hundred frames of one sequence; the budget must hold on sequences it never saw. Measured on
# the committed trained `small` (vnni host): the INT8 search's graph at 0.980% on its 200
# frames of `test` was at 1.080% over all 1,000 frames of `test` and 1.148% / 1.200% over
# 200 / 1,000 frames of the unseen `val` (docs/quantize.md, "A budget that holds on unseen
# data"). FP16 keeps its whole budget: its error sits far below it on every graph measured
# (0.06% of a 0.1% budget on `small`, 0.01% in the default pipeline).
DEFAULT_SEARCH_MARGIN: dict[str, float] = {"int8": 0.25, "int8-dynamic": 0.0, "fp16": 0.0}
# What the budget's relative error is relative to: the FP32 MPJPE pooled over the held-out
# frames, or the lowest FP32 MPJPE of any one held-out or calibration sequence (holdout.py
# `with_lowest_reference`), for models whose error differs widely between sequences.
BUDGET_REFERENCES: tuple[str, ...] = ("holdout", "lowest")
# Runtimes `--runtimes` may check the budget on (the first also ranks the nodes search).
CHECK_RUNTIMES: tuple[str, ...] = ("onnxruntime", "openvino")
REPORT_FILE = "report.json"


@dataclass(frozen=True)
class QuantizeOptions:
    mode: str = "int8"
    calibration: str = "minmax"
    frames: int = 200
    exclude: str = "auto"          # auto | none | recurrent | comma-separated groups / nodes
    budget_pct: float | None = None  # None: the mode's DEFAULT_BUDGET_PCT
    # --exclude auto searches to (1 - margin) x budget (None: DEFAULT_SEARCH_MARGIN); the
    # graph is still held to the whole budget (`golden check`).
    search_margin: float | None = None
    budget_reference: str = "holdout"
    split: str = "train"           # calibration frames
    holdout_split: str = "val"     # accuracy check (never calibration frames)
    holdout_frames: int = 200      # per held-out sequence
    # `nodes` search: held-out frames per sequence for the solo trials that only rank the
    # nodes (0: all of --holdout-frames). The probes, the choice and the report use them all.
    rank_frames: int = 64
    max_rounds: int = 4
    # `--exclude auto` strategy: "nodes" (sensitivity-ranked, int8) or "groups" (greedy over
    # module / op-type groups); None: nodes for int8, groups for fp16 (exclusions.py).
    search: str | None = None
    state_source: str = "rollout"
    threads: int | None = None
    seed: int = 0
    # `--exclude auto`: among the candidates within the budget, the fastest (latency), the
    # search's own choice (accuracy), or under int16 the smallest graph (size: the fewest
    # nodes out of 8 bits whose nodes all fit at int16, precision.smallest_int16_plan).
    # None: size where the search tries int16, latency elsewhere (`search_objective`).
    # Timing costs `timing_steps` steps per candidate; under int16 the candidates are timed
    # with their nodes in float, not as shipped: the artifact is timed again at the end
    # (`artifact_timing`, the verdict's figure).
    objective: str | None = None
    timing_steps: int = 30
    # Steps the written artifact is timed beside fp32 for the verdict (SideBySideTimer.compare),
    # and a latency pick beside the search's own choice before it ships (front.confirm_faster):
    # longer than a candidate's, since 30-step ratios on a shared 2-core host spread 0.56-1.25x.
    artifact_timing_steps: int = 200
    max_timed: int = 6
    # INT8 graph choices; None: StaticConfig's defaults (benchmarks/bench_quantize.py `changes`).
    op_types: tuple[str, ...] | None = None
    batchnorm_as_conv: bool | None = None
    # The CPU kind the INT8 graph is for (utils/isa.py); None: this host's. AVX2 targets get
    # 7-bit weights (StaticConfig.reduce_range).
    target_isa: str | None = None
    # int8: fold SmoothQuant scales into the GEGLU feed-forwards' weights and into the
    # LayerNorms before the projections that read them, before calibrating (equalize.py; the
    # fp32 function is unchanged).
    equalize: bool = False
    # int8: a QAT checkpoint whose learned ranges (`qat_ranges`) the graph takes as they are
    # (qat_ranges.py); the graph must be that checkpoint's export.
    ranges_from_checkpoint: str | None = None
    # int8 `--search nodes`: nodes that must leave 8 bits try 16-bit activations before float
    # (precision.py); the graph goes to opset 21 for it.
    int16: bool = True
    # int8: how 8-bit weights are rounded: to nearest (ONNX Runtime) or by AdaRound against the
    # calibration frames' layer outputs (adaround.py). None: AdaRound where the search may
    # keep activations at 16 bits (`--exclude auto`, nodes, int16), where it pays; nearest
    # elsewhere (with 8-bit activations their error dominates: docs/quantize.md).
    weight_rounding: str | None = None
    # int8: the Conv/MatMul/Gemm whose outputs stay float where no quantised op reads them
    # (outputs.py: "none", "matmul" for MatMul and Gemm, "all"). None: "matmul" for a fixed
    # exclusion (full integer: 6.6% -> 4.9% on the committed `small`, no speed cost on ONNX
    # Runtime); "none" under --exclude auto (the search's 16-bit nodes widen the outputs that
    # matter, and with "matmul" its graph went further over on unseen data: docs/quantize.md)
    # and under --ranges-from-checkpoint the graph its fine-tune simulated (recorded in the
    # checkpoint's `qat_ranges`; "none" for checkpoints that predate the record).
    float_outputs: str | None = None
    # The runtimes the budget is checked on: every trial graph of the search (after its
    # ranking, which only orders nodes) and the artifact are measured on each, and the worst
    # distance counts. OpenVINO fuses and rounds a QDQ graph its own way: a pipeline's INT8
    # graph searched on ONNX Runtime alone was 0.745% from fp32 there and 2.21% on OpenVINO
    # over the same held-out frames (2026-12-03, AVX-512 VNNI host), and failed its golden check.
    runtimes: tuple[str, ...] = ("onnxruntime",)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"unknown mode {self.mode!r}; choose from {list(MODES)}")
        unknown = [r for r in self.runtimes if r not in CHECK_RUNTIMES]
        if not self.runtimes or unknown:
            raise ConfigError(f"unknown runtime(s) {unknown}; choose from {list(CHECK_RUNTIMES)}")
        if "openvino" in self.runtimes:
            from e3dpsm.runtime.openvino_session import openvino_available

            available, reason = openvino_available()
            if not available:
                raise ConfigError(f"--runtimes openvino: {reason}")
        if self.objective not in (None, *OBJECTIVES):
            raise ConfigError(f"unknown objective {self.objective!r}; choose from {list(OBJECTIVES)}")
        if self.objective == "size" and not self.searches_int16:
            raise ConfigError("--objective size picks among 16-bit plans: it needs --mode int8, --exclude auto, "
                              "--search nodes and int16 (drop --no-int16); use latency or accuracy otherwise")
        if self.timing_steps < 1 or self.max_timed < 1 or self.artifact_timing_steps < 1:
            raise ConfigError("timing_steps, artifact_timing_steps and max_timed must be positive")
        if self.rank_frames < 0:
            raise ConfigError(f"--rank-frames must be >= 0, got {self.rank_frames}")
        if self.budget_pct is not None and not self.budget_pct > 0:
            raise ConfigError(f"--budget-pct must be positive, got {self.budget_pct}")
        if self.search_margin is not None and not 0.0 <= self.search_margin < 1.0:
            raise ConfigError(f"--search-margin is a share of the budget in [0, 1), got {self.search_margin}")
        if self.budget_reference not in BUDGET_REFERENCES:
            raise ConfigError(f"unknown budget reference {self.budget_reference!r}; choose from {list(BUDGET_REFERENCES)}")
        if self.search not in (None, *SEARCHES):
            raise ConfigError(f"unknown search {self.search!r}; choose from {list(SEARCHES)}")
        if self.search is not None and self.exclude != "auto":
            raise ConfigError(f"--search picks how --exclude auto searches; drop it with --exclude {self.exclude}")
        if self.ranges_from_checkpoint is not None and self.mode != "int8":
            raise ConfigError(f"--ranges-from-checkpoint gives INT8 ranges; drop it with --mode {self.mode}")
        if self.equalize and self.mode != "int8":
            raise ConfigError(f"--equalize reshapes INT8 activation ranges; drop it with --mode {self.mode}")
        if self.equalize and self.ranges_from_checkpoint is not None:
            # The rescaled tensors keep their names: a range learned for the unscaled tensor
            # would be written onto one 1/s as large.
            raise ConfigError("--equalize rescales tensors whose ranges the QAT checkpoint learned unscaled; "
                              "drop --equalize with --ranges-from-checkpoint")
        if self.weight_rounding not in (None, *WEIGHT_ROUNDINGS):
            raise ConfigError(f"unknown weight rounding {self.weight_rounding!r}; choose from {list(WEIGHT_ROUNDINGS)}")
        if self.weight_rounding == "adaround" and self.mode != "int8":
            raise ConfigError(f"--weight-rounding rounds INT8 weights; drop it with --mode {self.mode}")
        if self.float_outputs not in (None, *FLOAT_OUTPUTS):
            raise ConfigError(f"unknown --float-outputs {self.float_outputs!r}; choose from {list(FLOAT_OUTPUTS)}")
        if self.float_outputs not in (None, "none") and self.mode != "int8":
            raise ConfigError(f"--float-outputs picks INT8 Q/DQ pairs; drop it with --mode {self.mode}")
        if self.search == "nodes" and self.mode != "int8":
            raise ConfigError(f"--search nodes ranks INT8 nodes; {self.mode} searches groups (drop --search)")

    @property
    def target(self) -> str:
        """The CPU kind the INT8 graph is for (`target_isa`, else this host's)."""
        return self.target_isa or detect_isa().kind

    @property
    def strategy(self) -> str:
        return self.search or ("nodes" if self.mode == "int8" else "groups")

    @property
    def searches_int16(self) -> bool:
        """Whether nodes the search keeps out of 8 bits are tried at 16 bits (precision.py)."""
        return self.mode == "int8" and self.exclude == "auto" and self.strategy == "nodes" and self.int16

    @property
    def search_objective(self) -> str:
        """The objective this run uses (`objective`, resolved). Under int16 the candidates'
        timings describe graphs with their nodes in float, not the graph written, and the
        latency objective's pick moved between identical runs (docs/quantize.md): size is
        the default there, and it needs no timing to choose."""
        if self.objective is not None:
            return self.objective
        return "size" if self.searches_int16 else "latency"

    @property
    def rounding(self) -> str:
        """The weight rounding this run uses (`weight_rounding`, resolved)."""
        if self.weight_rounding is not None:
            return self.weight_rounding
        return "adaround" if self.searches_int16 else "nearest"

    @property
    def outputs_in_float(self) -> tuple[str, ...]:
        """The op types whose outputs stay float where no quantised op reads them (outputs.py)."""
        if self.float_outputs is not None:
            return FLOAT_OUTPUTS[self.float_outputs]
        # (quantize_graph sets it from the checkpoint under --ranges-from-checkpoint.)
        return FLOAT_OUTPUTS["none" if self.ranges_from_checkpoint or self.exclude == "auto" else "matmul"]

    @property
    def budget(self) -> float:
        return DEFAULT_BUDGET_PCT[self.mode] if self.budget_pct is None else self.budget_pct

    @property
    def margin(self) -> float:
        return DEFAULT_SEARCH_MARGIN[self.mode] if self.search_margin is None else self.search_margin

    @property
    def search_target(self) -> float:
        """The error the `--exclude auto` search aims at: the budget less its margin."""
        return self.budget * (1.0 - self.margin)


def artifact_name(mode: str) -> str:
    return f"step_{mode.replace('-', '_')}.onnx"


def load_source(path: str | os.PathLike) -> tuple[onnx.ModelProto, GraphMetadata]:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # onnx raises DecodeError and friends on damaged files
        raise DataError(f"{path} is not a readable ONNX file: {str(exc).splitlines()[0][:200]}") from exc
    meta = GraphMetadata.from_onnx(model, source=str(path))
    if meta.quantization is not None:
        raise MetadataError(f"{path} is already quantised ({meta.quantization.get('mode')}); start from the fp32 export")
    return model, meta


def resolve_exclusions(spec: str, recurrent: list[str], groups: Sequence, node_names: set[str]) -> list[str] | None:
    """Nodes kept in float for a fixed `--exclude`; None means "search" (auto)."""
    if spec == "auto":
        return None
    if spec == "none":
        return []
    if spec == "recurrent":
        return list(recurrent)
    by_name = {g.name: list(g.nodes) for g in groups}
    chosen = list(recurrent)
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        if item in by_name:
            chosen += by_name[item]
        elif item in node_names:
            chosen.append(item)
        else:
            raise ConfigError(f"--exclude: {item!r} is neither a node nor a group; groups: {sorted(by_name)}")
    return list(dict.fromkeys(chosen))


def quantize_graph(model_path: str | os.PathLike, data_dir: str | os.PathLike, out_dir: str | os.PathLike,
                   options: QuantizeOptions, *, force: bool = False, timer: StepTimer | None = None) -> dict[str, Any]:
    """`timer` ({label: graph} -> {label: p50 ms}) times the search's candidates; default a
    side-by-side timer on the held-out frames at `options.threads` (tests inject timings)."""
    started = time.perf_counter()
    source, meta = load_source(model_path)
    if options.ranges_from_checkpoint:  # fail before calibrating, not after
        from e3dpsm.checkpoint import read_checkpoint

        payload = read_checkpoint(options.ranges_from_checkpoint)
        read_ranges(payload, options.ranges_from_checkpoint)
        simulated = simulated_float_outputs(payload)
        if options.float_outputs is None:  # the graph the fine-tune simulated
            options = replace(options, float_outputs=simulated)
        elif options.float_outputs != simulated:
            log.warning("--float-outputs %s: %s's fine-tune simulated --float-outputs %s, so the graph computes "
                        "close to, not exactly, what training simulated", options.float_outputs,
                        options.ranges_from_checkpoint, simulated)
    data = PreparedData.open(data_dir)
    height, width = meta.frame_hw
    data.check_compatible(window_ms=meta.train_window_ms, height=height, width=width)
    holdout_seqs = data.split(options.holdout_split)
    calib_seqs = data.split(options.split) if options.mode == "int8" else []
    window_ms = meta.train_window_ms
    report: dict[str, Any] = report_header("quantize", {
        "model": str(model_path), "data": str(data_dir), "out": str(out_dir), **options.__dict__,
        "budget_pct": options.budget, "search_target_pct": options.search_target})

    with atomic_dir(out_dir, force=force) as tmp, tempfile.TemporaryDirectory(prefix="e3dpsm-quant-") as work:
        work = Path(work)
        holdout = make_holdout(model_path, holdout_seqs, window_ms, options.holdout_frames, options.threads)
        if options.budget_reference == "lowest":
            calibration = make_holdout(model_path, data.split(options.split), window_ms, options.holdout_frames,
                                       options.threads)
            holdout = holdout.with_lowest_reference(calibration)
            log.info("budget relative to %.2f mm, the lowest fp32 MPJPE of any %s or %s sequence (held-out "
                     "pooled: %.2f mm)", holdout.budget_mpjpe, options.holdout_split, options.split,
                     holdout.fp32_mpjpe)
        timing = _Timing(timer or SideBySideTimer(holdout.lnes[0], window_ms, options.threads,
                                                  steps=options.timing_steps), Path(model_path))
        info: dict[str, Any] = {"mode": options.mode, "source": Path(model_path).name}
        extra: dict[str, Any] = {}
        if options.mode == "int8":
            model, info, extra = _static(model_path, source, calib_seqs, holdout, window_ms, options, work, timing)
        elif options.mode == "fp16":
            model, info, extra = _fp16(source, meta, holdout, options, work, timing)
        else:
            keep = [n for g in recurrent_groups(source, meta) for n in g.nodes]
            dyn = work / "dynamic.onnx"
            info.update(quantize_dynamic_int8(model_path, dyn, exclude=keep,
                                              saturating_target=saturates_u8s8(options.target)),
                        target_isa=options.target)
            model = onnx.load(str(dyn))
            info["excluded_nodes"] = keep
            info["mode"] = options.mode
        # The graph carries its accuracy budget: `golden check` holds it to that budget. INT8
        # error depends on the CPU's kernels (utils/isa.py), so it also says where it was checked.
        info["budget_pct"] = options.budget
        info["checked_on_isa"] = detect_isa().to_dict()
        # ... and on which runtimes: a budget held on one need not hold on another (--runtimes).
        info["checked_on_runtimes"] = list(options.runtimes)
        info["budget_reference"] = options.budget_reference
        finalize(model, meta, info)
        compaction = compact_qdq(model, keep=graph_names(source))
        # The pre-pass folded the export's Tiles of repeating constants back (onnx_constants.py).
        retiled = retile_constants(model)
        out_path = tmp / artifact_name(options.mode)
        size = save_model(model, out_path)
        accuracy = worst_accuracy(out_path, holdout, options)
        artifact_timing = _time_artifact(timing, out_path, options.artifact_timing_steps)
        report.update({
            "mode": options.mode,
            "artifact": artifact_name(options.mode),
            "quantization": {k: v for k, v in info.items() if k != "excluded_nodes"},
            "excluded_nodes": info.get("excluded_nodes", []),
            "holdout": {"split": options.holdout_split, "frames": holdout.frames,
                        "budget_reference": options.budget_reference, **accuracy},
            "sizes": {"source_bytes": Path(model_path).stat().st_size, "output_bytes": size,
                      "compaction": compaction.to_dict(), "retiled_constants": retiled.to_dict()},
            "nodes": {"source": len(source.graph.node), "output": len(model.graph.node),
                      "source_ops": op_histogram(source), "output_ops": op_histogram(model)},
            **extra,
            **({"artifact_timing": artifact_timing} if artifact_timing else {}),
            "seconds": round(time.perf_counter() - started, 2),
        })
        write_json_atomic(tmp / REPORT_FILE, report)
        write_search_outputs(report, tmp)
    log.info("%s: holdout MPJPE %.2f mm (fp32 %.2f, %+.3f%%) -> %s", options.mode, accuracy["mpjpe_mm"],
             accuracy["fp32_mpjpe_mm"], accuracy["loss_pct"], Path(out_dir) / artifact_name(options.mode))
    return report


@dataclass(frozen=True)
class _Timing:
    timer: StepTimer
    reference: Path  # the fp32 graph, timed beside the candidates

    def describe(self) -> dict:
        """The timer's settings for the report (an injected timer has none)."""
        return getattr(self.timer, "describe", lambda: {"kind": "injected"})()


ARTIFACT_LABEL = "artifact"


def _time_artifact(timing: _Timing, artifact: Path, steps: int) -> dict[str, Any] | None:
    """The written artifact timed beside the fp32 graph: what the verdict speaks of. The
    search's candidates are not the artifact where a later stage changes the graph (its
    16-bit nodes, precision.py, run in float behind a DequantizeLinear on ONNX Runtime).
    The default timer times it over `steps` steps with an interval (SideBySideTimer.compare);
    an injected timer, once as it times candidates."""
    compare = getattr(timing.timer, "compare", None)
    if compare is not None:
        return compare(artifact, timing.reference, steps)
    ms = timing.timer({ARTIFACT_LABEL: artifact, FP32_LABEL: timing.reference})
    p50, fp32 = ms.get(ARTIFACT_LABEL), ms.get(FP32_LABEL)
    if not p50 or not fp32:
        return None
    return {"p50_ms": float(p50), "fp32_p50_ms": float(fp32), "speedup_vs_fp32": float(fp32) / float(p50),
            "timer": timing.describe()}


def _static(model_path, source, calib_seqs, holdout, window_ms, options: QuantizeOptions, work: Path,
            timing: _Timing):
    overrides = {k: v for k, v in (("op_types", options.op_types), ("batchnorm_as_conv", options.batchnorm_as_conv))
                 if v is not None}
    target_isa = options.target
    config = StaticConfig.for_target(target_isa, calibration=options.calibration, **overrides)
    pre = work / "pre.onnx"
    preprocess(model_path, pre, config)
    pre_model = onnx.load(str(pre))
    pre_meta = GraphMetadata.from_onnx(pre_model)
    recurrent = recurrent_groups(pre_model, pre_meta)
    keep = [n for g in recurrent for n in g.nodes]
    groups = candidate_groups(pre_model, keep)
    fixed = resolve_exclusions(options.exclude, keep, [*recurrent, *groups], {n.name for n in pre_model.graph.node})
    # A quantised op that writes a graph output (under --int8-elementwise the Add that writes an
    # S5 state or a pose) would output, and carry to the next step, its 8-bit rounding: ONNX
    # Runtime puts the Q/DQ pair on the output itself. Such writers stay float in every plan.
    outputs = {o.name for o in pre_model.graph.output}
    writers = [n.name for n in pre_model.graph.node
               if n.op_type in config.op_types and n.op_type not in DEFAULT_OP_TYPES and set(n.output) & outputs]
    keep = list(dict.fromkeys([*keep, *writers]))
    if fixed is not None:
        fixed = list(dict.fromkeys([*fixed, *writers]))

    calib = record_calibration_set(model_path, calib_seqs, options.frames, window_ms,
                                   state_source=options.state_source, seed=options.seed, threads=options.threads)
    equalized: list[dict] = []
    if options.equalize:
        pre_model, equalized = equalize(pre_model, calib.feeds)
        onnx.save(pre_model, str(pre))
    kept = set(keep)
    projections = [n.name for n in pre_model.graph.node
                   if n.name in kept and n.op_type in config.op_types and n.op_type in DEFAULT_OP_TYPES]
    searched = options.searches_int16 and fixed is None
    # S5's readouts read the new state, a graph output (under --int8-elementwise the fusion's
    # Mul and Sub read the direct pose too). ONNX Runtime's quantiser puts a quantised tensor's
    # Q/DQ pair on the tensor itself, so a quantised reader would make the graph output the
    # rounded value and carry it to the next step (`--exclude none` did so until 2026-12-01:
    # the error then compounds over a stream). Every node that may be quantised (not in the
    # fixed exclusion; under the search, outside the recurrent groups or one of the projections
    # precision.quantise_recurrent_compute tries) reads a copy instead
    # (graph_groups.isolate_state_reads, which rewires only readers of a graph output).
    # Before calibrating, so every graph and the cache name the copies.
    excluded = set(fixed) if fixed is not None else kept - set(projections if searched else ())
    quantisable = [n.name for n in pre_model.graph.node if n.op_type in config.op_types and n.name not in excluded]
    state_reads = isolate_state_reads(pre_model, quantisable)
    if state_reads:
        onnx.save(pre_model, str(pre))
    recurrent_compute: list[str] = []
    if searched:
        # Any that still reads or writes a graph output (a state) stays float.
        wanted = set(projections)
        recurrent_compute = [n.name for n in pre_model.graph.node
                             if n.name in wanted and not {*n.input, *n.output} & outputs]
    cache = work / "calibration.json"
    out = work / "int8.onnx"
    started = time.perf_counter()
    ranges = calibrate(pre, config, calib, cache)
    calib_seconds = time.perf_counter() - started
    rounded, rounding_report = _adaround(options, config, pre, pre_model, cache, calib, work)
    roundings = [rounded]
    learned, qat_report = {}, None
    if options.ranges_from_checkpoint:
        # Every tensor the graph may quantise: `--exclude none` quantises the recurrent groups
        # too, and a search may; overrides for tensors a graph leaves float are not used.
        quantised = quantised_activations(pre, fixed if fixed is not None else [], config.op_types)
        learned, qat_report = learned_overrides(options.ranges_from_checkpoint, pre, quantised)
        qat_report["weights"] = qat_weight_bits(config, target_isa, qat_report.pop("trained_weight_bits"))
    search = latency = precision = None
    size_probes: list[SizeProbe] = []
    int16_nodes: list[str] = []
    int16w16_nodes: list[str] = []
    pre16 = _opset21_copy(pre, work) if options.int16 and fixed is None and options.strategy == "nodes" else None

    def build(excluded: list[str], int16: Sequence[str] = (), int16w16: Sequence[str] = ()) -> onnx.ModelProto:
        path = scratch_model_path(work, "int8")
        # The cache: no re-calibration per trial. 16-bit nodes need the opset-21 copy.
        quantize_int8(pre16 if int16 or int16w16 else pre, path, config, exclude=excluded, cache=cache,
                      learned=learned, int16_nodes=int16, int16w16_nodes=int16w16)
        model = onnx.load(str(path))
        for chosen in roundings:  # each applies where the graph's weight scale is its own
            apply_rounding(model, chosen)
        dequantised_outputs(model, options.outputs_in_float, config.op_types)
        path.unlink()
        return model

    if fixed is None:
        ranked = None
        if options.strategy == "nodes":
            every = [n.name for n in pre_model.graph.node]
            # The compute nodes only (also under --int8-elementwise): one trial per ranked node.
            targets = [n.name for n in pre_model.graph.node
                       if n.op_type in config.op_types and n.op_type in DEFAULT_OP_TYPES and n.name not in kept]
            ranked = rank_nodes(targets, every, holdout, options.rank_frames,
                                lambda subset: _evaluator(pre_meta, subset, options, work, build,
                                                          runtimes=options.runtimes[:1]))
        search, latency = _latency_search(keep, groups, pre_meta, holdout, options, work, build, timing, ranked)
        fixed = search.excluded_nodes
        if pre16 is not None:
            def ranked_nodes(excluded: Sequence[str]) -> list[str]:
                return [n for n in excluded if n not in kept]

            def measure(int16: Sequence[str], w16: Sequence[str], floats: Sequence[str], label: str,
                        int8: Sequence[str] = ()) -> float:
                """One plan's graph error: the recurrent groups (less their nodes in `int8`) and
                `floats` in float."""
                return _evaluator(pre_meta, holdout, options, work, lambda excl: build(excl, int16, w16))(
                    _kept_float(keep, floats, int8), label)

            sized = options.search_objective == "size"
            probed = [c for c in latency.candidates if c.error_pct <= options.search_target] if sized else []
            # The nodes the 16-bit stages may place: their 8-bit weights take the full range
            # where the config reduces it (static.full_range_weight_overrides), rounded anew.
            placeable = dict.fromkeys(n for excluded in [fixed, *(c.excluded_nodes for c in probed)]
                                      for n in ranked_nodes(excluded))
            roundings.append(_adaround_full_range(options, config, [*placeable, *recurrent_compute],
                                                  pre, pre_model, cache, calib, work, rounding_report))
            all_int16 = None
            if sized:
                index, size_probes = smallest_int16_plan(
                    [(c.label, ranked_nodes(c.excluded_nodes), c.error_pct) for c in probed], options.search_target,
                    lambda int16, label: measure(int16, (), (), label))
                if index is not None:
                    latency.chosen = probed[index]
                    search, all_int16 = _with_choice(search, probed[index]), size_probes[-1].int16_error_pct
                    fixed = search.excluded_nodes
            precision = demote_to_int16(ranked_nodes(fixed), search.error_pct, options.search_target,
                                        lambda int16, floats, label: measure(int16, (), floats, label),
                                        all_int16_error_pct=all_int16)
            precision = promote_to_int16w16(precision, measure)
            # A recurrent node reading a tensor the 16-bit nodes widen reads 16 bits whatever it is given.
            widened = set(int16_tensors(pre_model, precision.int16 + precision.int16w16, cache))
            precision = quantise_recurrent_compute(
                precision, shared_input_units(pre_model, recurrent_compute), measure,
                no_int8=[n.name for n in pre_model.graph.node if n.name in recurrent_compute and widened & {*n.input}])
            int16_nodes, int16w16_nodes = precision.int16, precision.int16w16
            fixed = _kept_float(keep, precision.float_nodes, precision.int8)  # 16-bit nodes leave it (quantize_int8)
    quantize_int8(pre16 if int16_nodes or int16w16_nodes else pre, out, config, exclude=fixed, cache=cache,
                  learned=learned, int16_nodes=int16_nodes, int16w16_nodes=int16w16_nodes)
    model = onnx.load(str(out))
    if rounding_report is not None:
        rounding_report["applied"] = sum(apply_rounding(model, chosen) for chosen in roundings)
    float_outputs = dequantised_outputs(model, options.outputs_in_float, config.op_types)
    if qat_report is not None:
        coverage_in_graph(qat_report, model, learned)
    census = compute_precisions(model)
    info = {
        "mode": "int8", **config.to_dict(), "target_isa": target_isa, "equalized_sites": len(equalized),
        "calibration_frames": len(calib),
        "calibration_split": options.split, "state_source": calib.state_source,
        "exclude": options.exclude, "float_groups": _float_group_names(recurrent, search), "state_reads": state_reads,
        "excluded_nodes": fixed, "int16_nodes": int16_nodes, "int16w16_nodes": int16w16_nodes,
        **quantised_node_count(model),
        # Read off the artifact (census.py): what its Conv/MatMul/Gemm compute in, recurrent groups included.
        "compute_precision": precision_counts(census), "compute_nodes_out_of_8_bits": out_of_8_bits(census),
        "ranges_from_checkpoint": options.ranges_from_checkpoint, "weight_rounding": options.rounding,
        "float_outputs": list(options.outputs_in_float), "float_output_nodes": len(float_outputs),
    }
    extra = {
        "calibration": {"record_seconds": round(calib.seconds, 2), "calibrate_seconds": round(calib_seconds, 2),
                        "frames": len(calib), "sequences": {k: len(v) for k, v in calib.frames.items()},
                        **({"ranges": summarise_ranges(ranges),
                            "range_per_tensor": {n: asdict(c) for n, c in ranges.items()}} if ranges else {})},
        **_search_report(search, [*recurrent, *groups], latency),
        **({"equalization": equalized} if options.equalize else {}),
        **({"precision_search": {**precision.to_dict(), "size_probes": [p.to_dict() for p in size_probes]}}
           if precision else {}),
        "compute_precision": census,
        **({"qat_ranges": qat_report} if qat_report else {}),
        **({"weight_rounding": rounding_report} if rounding_report is not None else {}),
    }
    return model, info, extra


def _kept_float(recurrent: Sequence[str], floats: Sequence[str], int8: Sequence[str]) -> list[str]:
    """The nodes a plan keeps in float: the recurrent groups' and `floats`, less the recurrent
    projections it placed at 8 bits (`int8`)."""
    placed = set(int8)
    return [n for n in dict.fromkeys([*recurrent, *floats]) if n not in placed]


def _adaround(options: QuantizeOptions, config: StaticConfig, pre: Path, pre_model: onnx.ModelProto, cache: Path,
              calib, work: Path) -> tuple[dict, dict | None]:
    """AdaRound's integers for every weight (adaround.py), chosen once at ONNX Runtime's own
    scales (read off a graph with every Conv/MatMul/Gemm quantised) and written into each
    trial graph and the artifact; ({}, None) for nearest rounding."""
    if options.rounding != "adaround":
        return {}, None
    rounded, summary = _adaround_at(config, pre, pre_model, cache, calib, work, options.threads)
    return rounded, {"method": "adaround", **asdict(AdaRoundConfig()), **summary}


def _adaround_full_range(options: QuantizeOptions, config: StaticConfig, nodes: Sequence[str], pre: Path,
                         pre_model: onnx.ModelProto, cache: Path, calib, work: Path, report: dict | None) -> dict:
    """AdaRound's integers for the 8-bit weights of `nodes` at the full 8-bit range, where
    `config` reduces it: the 16-bit stages' candidates get such weights
    (static.full_range_weight_overrides), at scales the first pass never saw. Recorded in
    the first pass's `report` under "full_range"; {} where nothing needs them."""
    if report is None or not config.reduce_range or not nodes:
        return {}
    rounded, report["full_range"] = _adaround_at(replace(config, reduce_range=False), pre, pre_model, cache, calib,
                                                 work, options.threads, nodes)
    return rounded


def _adaround_at(config: StaticConfig, pre: Path, pre_model: onnx.ModelProto, cache: Path, calib, work: Path,
                 threads: int | None, nodes: Sequence[str] | None = None) -> tuple[dict, dict]:
    started = time.perf_counter()
    probe = work / "adaround_probe.onnx"
    quantize_int8(pre, probe, config, exclude=[], cache=cache)
    rounded = adaround_weights(pre_model, onnx.load(str(probe)), calib.feeds, threads=threads, nodes=nodes)
    probe.unlink()
    ratios = [r.output_error_ratio for r in rounded.values()]
    return rounded, {"weights": len(rounded), "median_output_error_ratio": float(np.median(ratios)) if ratios else None,
                     "seconds": round(time.perf_counter() - started, 2)}


def _opset21_copy(pre: Path, work: Path) -> Path | None:
    """`pre` converted to opset 21 (16-bit QuantizeLinear in the default domain), or None
    where the conversion renamed a node or tensor: trials share one calibration cache and
    name nodes to keep in float, so both graphs must use the same names. Graphs without
    16-bit nodes stay at the export's opset."""
    import shutil

    pre16 = work / "pre_opset21.onnx"
    shutil.copyfile(pre, pre16)
    ensure_opset(pre16)

    def names(m: onnx.ModelProto) -> tuple[set[str], set[str]]:
        return {n.name for n in m.graph.node}, {t for n in m.graph.node for t in (*n.input, *n.output)}

    if names(onnx.load(str(pre))) != names(onnx.load(str(pre16))):
        log.warning("converting the graph to opset 21 renamed nodes or tensors; the search skips int16")
        return None
    return pre16


def _fp16(source, meta, holdout, options: QuantizeOptions, work: Path, timing: _Timing):
    """FP16 with the recurrent groups in float32 and, under `--exclude auto`, the smallest set
    of further groups in float32 that keeps the held-out error within the FP16 budget.

    Why a search and not only a fixed list: on a trained `small` the last encoder stage's
    residual stream reaches ~5,000 (pre-activation blocks never normalise it). In fp16 that
    is rounded to steps of 4, and the GroupNorm that follows subtracts a mean of about the
    same size, so the normalised features lose most of their bits: the poses moved 9.5 mm
    from fp32 (9.5% of MPJPE) until `stages.3` stayed in float32 (0.07 mm).
    """
    recurrent = recurrent_groups(source, meta)
    keep = [n for g in recurrent for n in g.nodes]
    groups = candidate_groups(source, keep)
    fixed = resolve_exclusions(options.exclude, keep, [*recurrent, *groups], {n.name for n in source.graph.node})
    search = latency = None
    if fixed is None:
        search, latency = _latency_search(keep, groups, meta, holdout, options, work,
                                          lambda excluded: convert_fp16(source, excluded), timing)
        fixed = search.excluded_nodes
    model = convert_fp16(source, fixed)
    info = {"mode": "fp16", "precision": "float16", "io_types": "float32", "exclude": options.exclude,
            "float_groups": _float_group_names(recurrent, search),
            "kept_float32_nodes": len(fixed), "excluded_nodes": fixed}
    return model, info, _search_report(search, [*recurrent, *groups], latency)


def rank_nodes(
    targets: list[str], every: list[str], holdout: HoldoutSet, rank_frames: int,
    make_evaluator: Callable[[HoldoutSet], Callable[[list[str], str], float]],
) -> NodeRanking:
    """The nodes search's ranking: each target quantised alone (every other node in float),
    measured on the first `rank_frames` of each held-out sequence (0: all). Ranking only
    orders the nodes; the probes that choose how many stay in float run on every held-out
    frame, so a shorter ranking set trades only the order's precision for time (one trial
    per node dominates the search)."""
    subset = holdout.head(rank_frames) if rank_frames else holdout
    alone = make_evaluator(subset)
    rows = node_sensitivity(targets, lambda node: alone([n for n in every if n != node], f"alone_{node}"))
    return NodeRanking(rows, frames=max(len(g) for g in subset.gt))


def worst_accuracy(model: Path, holdout: HoldoutSet, options: QuantizeOptions,
                   runtimes: Sequence[str] | None = None) -> dict[str, Any]:
    """accuracy_of on each of `runtimes` (default `options.runtimes`): the one with the
    largest distance to fp32, with every runtime's distance under `bound_pct_by_runtime`."""
    measured = {runtime: accuracy_of(model, holdout, options.threads, runtime=runtime)
                for runtime in (runtimes or options.runtimes)}
    worst = max(measured, key=lambda runtime: measured[runtime]["bound_pct"])
    return {**measured[worst], "runtime": worst,
            "bound_pct_by_runtime": {runtime: m["bound_pct"] for runtime, m in measured.items()}}


def _evaluator(meta: GraphMetadata, holdout: HoldoutSet, options: QuantizeOptions, work: Path,
               build: Callable[[list[str]], onnx.ModelProto],
               built: list[tuple[list[str], Path]] | None = None,
               runtimes: Sequence[str] | None = None) -> Callable[[list[str], str], float]:
    """`evaluate(nodes kept in float, label) -> held-out error %`: the trial is `build(nodes)`,
    given the source metadata, saved to a scratch file and measured on the held-out streams
    on each of `runtimes` (default `options.runtimes`), the worst counting.
    With `built`, each trial's (excluded nodes, scratch file) is appended there and the file
    kept (the caller times and removes them); otherwise the file is removed at once."""
    def evaluate(excluded: list[str], label: str) -> float:
        candidate = build(excluded)
        finalize(candidate, meta, {"mode": options.mode, "trial": label})
        trial = scratch_model_path(work, label)
        save_model(candidate, trial)
        if built is not None:
            built.append((list(excluded), trial))
            return worst_accuracy(trial, holdout, options, runtimes)["bound_pct"]
        try:
            return worst_accuracy(trial, holdout, options, runtimes)["bound_pct"]
        finally:
            trial.unlink()

    return evaluate


def _search_float_groups(keep: list[str], groups: Sequence[NodeGroup], meta: GraphMetadata, holdout: HoldoutSet,
                         options: QuantizeOptions, work: Path, build: Callable[[list[str]], onnx.ModelProto],
                         built: list[tuple[list[str], Path]] | None = None,
                         ranked: NodeRanking | None = None) -> SearchResult:
    """`--exclude auto` for either mode: the greedy group search, or with `ranked` (the
    nodes search's ranking) the ranked-prefix search."""
    evaluate = _evaluator(meta, holdout, options, work, build, built)
    if ranked is not None:
        return ranked_prefix_exclusions(keep, ranked, options.search_target, evaluate)
    return greedy_exclusions(keep, list(groups), options.search_target, evaluate, options.max_rounds)


def _latency_search(keep: list[str], groups: Sequence[NodeGroup], meta: GraphMetadata, holdout: HoldoutSet,
                    options: QuantizeOptions, work: Path, build: Callable[[list[str]], onnx.ModelProto],
                    timing: _Timing, ranked: NodeRanking | None = None) -> tuple[SearchResult, LatencySearch]:
    """The exclusion search, then a bounded number of its trial graphs timed beside the fp32
    graph and one picked by the objective (front.py). With `ranked` (`--search nodes`, the
    INT8 default) the search keeps the fewest top-ranked Conv/MatMul/Gemm nodes (ranked by
    their solo error) in float; without it (`--search groups`, the FP16 default) it adds
    whole groups greedily. The returned result's `chosen` / `excluded_nodes` / `error_pct`
    are that final choice; its trials are the search's."""
    built: list[tuple[list[str], Path]] = []
    try:
        searched = _search_float_groups(keep, groups, meta, holdout, options, work, build, built, ranked)
        candidates = candidates_from_search(searched, built)
        info = timing.describe()
        compare = getattr(timing.timer, "compare", None)
        confirm = ((lambda graph, reference: compare(graph, reference, options.artifact_timing_steps))
                   if compare is not None else None)
        latency = latency_aware_choice(searched, candidates, timing.timer, options.search_objective, options.search_target,
                                       max_timed=options.max_timed, reference=timing.reference, timer_info=info,
                                       confirm=confirm)
    finally:
        for _, path in built:
            path.unlink(missing_ok=True)
    for cand in latency.candidates:
        cand.path = None
    return _with_choice(searched, latency.chosen), latency


def _with_choice(searched: SearchResult, chosen: Candidate) -> SearchResult:
    """The search's result with `chosen` as its final choice (its trials unchanged)."""
    return SearchResult(list(chosen.groups), list(chosen.excluded_nodes), chosen.error_pct, searched.budget_pct,
                        searched.trials, searched.strategy, searched.sensitivity, searched.rank_frames)


def _float_group_names(recurrent: Sequence[NodeGroup], search: SearchResult | None) -> list[str]:
    return [g.name for g in recurrent] + (search.chosen if search else [])


def _search_report(search: SearchResult | None, groups: Sequence[NodeGroup],
                   latency: LatencySearch | None = None) -> dict[str, Any]:
    # "search" is the stable block the pipeline index reads (front, chosen); None for a fixed --exclude.
    return {"exclusion_search": search.to_dict() if search else None,
            "search": latency.to_dict() if latency else None,
            "groups": {g.name: {"kind": g.kind, "nodes": len(g)} for g in groups}}
