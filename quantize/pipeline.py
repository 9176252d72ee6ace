"""`quantize_graph`: one exported step graph + prepared data -> one artifact folder
(`DIR/step_<mode>.onnx`, `DIR/report.json`, `DIR/report.md`), built under a temporary name.

INT8 runs the passes in order, each a function returning a frozen result with its own
report section: prepare -> calibrate (state-aware) -> place precisions (full integer first,
then the fewest nodes back to float; prepare.py, place.py) -> round weights -> write
(write.py) -> check (holdout.py: the task budget on frames neither calibration nor search
saw) -> verdict (verdict.py). FP16 searches whole groups; dynamic INT8 and weight-only INT8
(weights.py: float arithmetic, the same poses on any ISA) have nothing to search.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import onnx

from e3dpsm.data.prepared import PreparedData
from e3dpsm.export.onnx_export import op_histogram
from e3dpsm.graph_metadata import GraphMetadata, MetadataError
from e3dpsm.onnx_graph import read_onnx
from e3dpsm.quantize.adaround import apply_rounding
from e3dpsm.quantize.artifact import finalize, save_model
from e3dpsm.quantize.dynamic import quantize_dynamic_int8
from e3dpsm.quantize.fp16 import convert_fp16
from e3dpsm.quantize.graph_groups import candidate_groups, recurrent_groups
from e3dpsm.quantize.holdout import HeldOut, Judgement, distance_pct, graph_outputs, held_out, judge
from e3dpsm.quantize.options import QuantizeOptions, artifact_name
from e3dpsm.quantize.place import Placement, greedy_groups, place_precisions
from e3dpsm.quantize.prepare import calibrate_graph, prepare_graph
from e3dpsm.quantize.static import saturates_u8s8
from e3dpsm.quantize.verdict import Verdict, time_beside_fp32
from e3dpsm.quantize.weights import MODE as WEIGHTS_MODE, weight_only_int8
from e3dpsm.quantize.write import Written, build_int8, round_weights, scratch_path, write_artifact
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic
from e3dpsm.utils.isa import detect_isa

REPORT_FILE = "report.json"


def load_source(path: str | os.PathLike) -> tuple[onnx.ModelProto, GraphMetadata]:
    path = Path(path)
    model = read_onnx(path)
    meta = GraphMetadata.from_onnx(model, source=str(path))
    if meta.quantization is not None:
        raise MetadataError(f"{path} is already quantised ({meta.quantization.get('mode')}); start from the fp32 export")
    return model, meta


def _open_data(path: str | os.PathLike, meta: GraphMetadata) -> PreparedData:
    data = PreparedData.open(path)
    height, width = meta.frame_hw
    data.check_compatible(window_ms=meta.train_window_ms, height=height, width=width)
    return data


def quantize_graph(model_path: str | os.PathLike, data_dir: str | os.PathLike, out_dir: str | os.PathLike,
                   options: QuantizeOptions, *, force: bool = False) -> dict[str, Any]:
    started = time.perf_counter()
    source, meta = load_source(model_path)
    data = _open_data(data_dir, meta)
    check_data = _open_data(options.holdout_data, meta) if options.holdout_data else data
    window_ms, threads = meta.train_window_ms, options.threads
    report = report_header("quantize", {"model": str(model_path), "data": str(data_dir), "out": str(out_dir),
                                        **options.to_dict()})
    with atomic_dir(out_dir, force=force) as tmp, tempfile.TemporaryDirectory(prefix="e3dpsm-quant-") as work:
        work = Path(work)
        check = held_out(model_path, check_data.split(options.holdout_split), window_ms,
                         options.advanced.holdout_frames, f"{Path(check_data.root).name}/{options.holdout_split}", threads)
        build = {"int8": _int8, "fp16": _fp16, "int8-dynamic": _dynamic, WEIGHTS_MODE: _weights}[options.mode]
        model, info, blocks, sections = build(model_path, source, meta, data, options, work)
        info = {**info, "budget": options.advanced.budget.to_dict(), "checked_on_isa": detect_isa().to_dict(),
                "checked_on_runtimes": list(options.runtimes)}
        written = write_artifact(model, source, meta, info, tmp / artifact_name(options.mode),
                                 Path(model_path).stat().st_size)
        final = judge(written.path, check, options.advanced.budget, options.runtimes, threads)
        worst_runtime = max(final.by_runtime, key=lambda r: final.by_runtime[r].worst_share)
        timings = time_beside_fp32(written.path, model_path, check.lnes[0], window_ms, options.runtimes, threads,
                                   options.advanced.timing_steps)
        verdict = Verdict(options.mode, final.worst, worst_runtime, written.size_ratio, timings, detect_isa().to_dict())
        report.update({"mode": options.mode, "artifact": written.path.name, "verdict": verdict.to_dict(),
                       "check": {"data": check.name, "frames": check.frames, **final.to_dict()},
                       "written": written.to_dict(), "quantization": info, **blocks,
                       "nodes": {"source_ops": op_histogram(source), "output_ops": op_histogram(model)},
                       "seconds": round(time.perf_counter() - started, 2)})
        write_json_atomic(tmp / REPORT_FILE, report)
        write_text_atomic(tmp / "report.md", markdown_report(report, verdict, final, written, sections))
    return report


def markdown_report(report: dict[str, Any], verdict: Verdict, final: Judgement, written: Written,
                    sections: Sequence[list[str]]) -> str:
    lines = [f"# e3dpsm quantize: {report['mode']}", "", f"**{verdict.headline()}**", "",
             f"## Budget on {report['check']['frames']} held-out frames ({report['check']['data']}), never seen by "
             "calibration or search", ""]
    for runtime, check in final.by_runtime.items():
        lines += [f"{runtime}: distance to the fp32 poses {check.fidelity_mm:.3f} mm "
                  f"({check.fidelity_pct:.2f}% of fp32's MPJPE; fidelity, not budgeted).", "", *check.table(), ""]
    timings = report["verdict"]["timings"]
    for runtime, t in timings.items():
        interval = t.get("interval") or {}
        lines.append(f"Speed on {runtime}: {t['p50_ms']:.2f} ms per step against fp32's {t['fp32_p50_ms']:.2f} "
                     f"({t['speedup_vs_fp32']:.2f}x, 80% interval {interval.get('low', 0):.2f}-"
                     f"{interval.get('high', 0):.2f}x, {t['timer']['steps']} steps side by side).")
    lines += ["", *written.report_lines()]
    for section in sections:
        lines += section
    return "\n".join(lines) + "\n"


def _int8(model_path, source, meta, data, options: QuantizeOptions, work: Path):
    prepared = prepare_graph(model_path, options, work)
    calibration = calibrate_graph(prepared, model_path, data.split(options.split), options, work)
    placement = None
    if prepared.fixed is None:
        search = held_out(model_path, data.split(options.search_split), meta.train_window_ms,
                          options.advanced.search_frames, f"{Path(data.root).name}/{options.search_split}",
                          options.threads)
        placement = _search(prepared, calibration, search, options, work)
    rounding = round_weights(prepared, calibration, options.advanced.weight_rounding, options.threads)
    plan = placement or Placement((), (), True, ())
    model = build_int8(prepared, calibration, plan.float_nodes, plan.int16_nodes,
                       float_outputs=options.advanced.float_outputs, rounding=rounding)
    learned = _learned_coverage(calibration, model)
    info = {"mode": "int8", **prepared.config.to_dict(), "target": options.target, "isa": options.isa,
            "exclude": options.exclude, "float_nodes": list(plan.float_nodes), "int16_nodes": list(plan.int16_nodes),
            "float_outputs": options.advanced.float_outputs, "weight_rounding": rounding.method}
    sections = [prepared.report_lines(), calibration.report_lines(options.calibration)]
    if learned:
        sections.append([f"Learned ranges: {learned['learned_tensors']} of the {learned['learned_tensors'] + learned['calibrated_tensors']} "
                         f"8-bit activations take those of `{learned['checkpoint']}`"
                         + (f" ({len(learned['unknown_sites'])} of its sites name modules this model lacks: repeat the "
                            "QAT fine-tune with this version)" if learned["unknown_sites"] else "") + ".", ""])
    if placement is not None:
        sections.append(placement.report_lines(f"{len(search.lnes)} sequence(s) of {options.search_split}"))
    return model, info, {"graph": prepared.to_dict(), "calibration": calibration.to_dict(),
                         "placement": placement.to_dict() if placement else None,
                         "rounding": {**rounding.to_dict(), "applied": apply_rounding(model, rounding.rounded)},
                         "learned_ranges": learned}, sections


def _learned_coverage(calibration, model: onnx.ModelProto) -> dict[str, Any] | None:
    """How many of the written graph's 8-bit activations took learned ranges (--ranges-from-checkpoint)."""
    if calibration.learned_report is None:
        return None
    from e3dpsm.training.qat_ranges import coverage_in_graph

    report = dict(calibration.learned_report)
    coverage_in_graph(report, model, calibration.learned)
    return report


def _search(prepared, calibration, search: HeldOut, options: QuantizeOptions, work: Path) -> Placement:
    """place_precisions with real trials: each plan's graph built, run on the search frames and
    judged; each node ranked on the first `rank_frames` of them, alone at 8 bits."""
    advanced = options.advanced
    ranking_set = search.head(advanced.rank_frames)

    def trial(floats: Sequence[str], int16: Sequence[str], label: str) -> Path:
        model = build_int8(prepared, calibration, floats, int16, float_outputs=advanced.float_outputs)
        finalize(model, prepared.meta, {"mode": "int8", "trial": label})
        path = scratch_path(work, label)
        save_model(model, path)
        return path

    def evaluate(floats, int16, label):
        path = trial(floats, int16, label)
        try:
            return judge(path, search, advanced.budget, options.runtimes, options.threads)
        finally:
            path.unlink()

    def rank(node: str) -> float:
        path = trial([n for n in prepared.compute if n != node], (), f"alone_{node}")
        try:
            return distance_pct(graph_outputs(path, ranking_set, "onnxruntime", options.threads), ranking_set)
        finally:
            path.unlink()

    return place_precisions(prepared.compute, evaluate, rank, int16=options.int16, max_trials=advanced.max_trials)


def _fp16(model_path, source, meta, data, options: QuantizeOptions, work: Path):
    recurrent = [n for g in recurrent_groups(source, meta) for n in g.nodes]
    placement = None
    if options.exclude == "auto":
        search = held_out(model_path, data.split(options.search_split), meta.train_window_ms,
                          options.advanced.search_frames, options.search_split, options.threads)

        def evaluate(floats, _int16, label):
            path = scratch_path(work, label)
            save_model(finalize(convert_fp16(source, [*recurrent, *floats]), meta, {"mode": "fp16", "trial": label}),
                       path)
            try:
                return judge(path, search, options.advanced.budget, options.runtimes, options.threads)
            finally:
                path.unlink()

        groups = [(g.name, g.nodes) for g in candidate_groups(source, recurrent)]
        placement = greedy_groups(groups, evaluate)
    floats = [*recurrent, *(placement.float_nodes if placement else ())]
    info = {"mode": "fp16", "precision": "float16", "io_types": "float32", "exclude": options.exclude,
            "float32_nodes": len(floats)}
    sections = [placement.report_lines(options.search_split)] if placement else []
    return convert_fp16(source, floats), info, {"placement": placement.to_dict() if placement else None}, sections


def _dynamic(model_path, source, meta, data, options: QuantizeOptions, work: Path):
    keep = [n for g in recurrent_groups(source, meta) for n in g.nodes]
    path = work / "dynamic.onnx"
    info = quantize_dynamic_int8(model_path, path, exclude=keep, saturating_target=saturates_u8s8(options.isa))
    return onnx.load(str(path)), {"mode": "int8-dynamic", **info, "float_nodes": len(keep)}, {}, []


def _weights(model_path, source, meta, data, options: QuantizeOptions, work: Path):
    model, info = weight_only_int8(source)
    lines = [f"Weights: {info['weights_int8']} Conv / Gemm / MatMul weights in 8 bits, "
             f"{info['weight_bytes_float'] / 1e6:.2f} MB of float weights stored in {info['weight_bytes_stored'] / 1e6:.2f} MB; "
             "activations and arithmetic float.", ""]
    return model, {"mode": WEIGHTS_MODE, **info}, {}, [lines]
