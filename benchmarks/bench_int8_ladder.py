"""The INT8 ladder: full-integer distance to fp32 for each way of choosing activation ranges,
the default search's graph, and bf16, with size and speed side by side on ONNX Runtime and
OpenVINO, on the host's ISA.

    python benchmarks/bench_int8_ladder.py --checkpoint benchmarks/checkpoints/small/checkpoint.pt \\
        --data prep96_test [--split train --holdout-split test --check-split val] [--steps 200] [--threads 2]

Rows (each an `e3dpsm quantize` run, calibrated on --split, its distance measured on
--holdout-split):
- full integer (`--exclude none`: every Conv/MatMul/Gemm reads int8 weights and 8-bit
  activations) with `--calibration minmax`, `percentile`, `mse` (ranges per tensor), and
  `mse` after `--equalize` (GEGLU and LayerNorm scales folded into the weights);
- the default `--exclude auto` graph with `--calibration mse` (AdaRound weights, int16 before
  float, `--objective size`), with `--objective latency`, without int16, with nearest weight
  rounding, and so without the search's margin;
  full integer with AdaRound weights (`--weight-rounding adaround`);
- the fp32 graph run in bf16 on OpenVINO (where the CPU has bf16 units);
- full integer, `mse`, with the other weight width than this host's default target gives
  (`--target-isa`): 8-bit weights on a host without int8 dot-product units (where ONNX
  Runtime's U8S8 kernels saturate), 7-bit on one with them.
- with `--qat-checkpoint CKPT` (a `train --qat` fine-tune of --checkpoint): its export full
  integer with its learned ranges (`--ranges-from-checkpoint`) and, for comparison, with
  calibrated min-max ranges; distances are to that checkpoint's own fp32 graph, and
  `mpjpe_vs_base_pct` compares its INT8 poses' MPJPE with --checkpoint's fp32 one. A
  `distill --qat-ranges-only` checkpoint of --checkpoint (ranges learned, its weights frozen,
  checked tensor by tensor) has --checkpoint's fp32 graph: its rows are labelled "learned
  ranges" and are post-training graphs.
`--rows` keeps only the rows whose label contains one of the given words, `--only` those with
exactly the given labels, and `--append` adds the rows to the existing results (each row keeps the fp32 p50 timed beside it).
Every graph's distance is also measured on --check-split, which no search saw (the gap says
how far a budget chosen on one split carries), and on --holdout-split in the graph's exact
arithmetic (ONNX Runtime with graph optimisations off: every Q/DQ pair computed in float, no
fused integer kernel), which does not depend on the host: its gap to the first column is what
the host's integer kernels add (16-bit sums saturating without VNNI). Latency: all graphs stepped side by side in
rounds (`profiles.latency.measure_side_by_side`), states carried, on real frames.
Writes benchmarks/results/int8_<variant>_ladder_<isa kind>.md/.json (one per kind of host: ratios
compare only within one run on one host).
"""
from __future__ import annotations

import argparse
import importlib.util
import tempfile
from pathlib import Path

import numpy as np

from e3dpsm.data.prepared import PreparedData
from e3dpsm.quantize import QuantizeOptions, quantize_graph
from e3dpsm.quantize.front_report import RUNTIME_NAMES
from e3dpsm.quantize.holdout import accuracy_of, make_holdout
from e3dpsm.quantize.static import saturates_u8s8
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic
from e3dpsm.utils.isa import detect_isa

RESULTS = Path(__file__).resolve().parent / "results"
CALIBRATIONS = ("minmax", "percentile", "mse")


def _runners(graphs: dict[str, Path], fp32: Path, threads: int, window_ms: float) -> dict:
    from e3dpsm.profiles.latency import OpenVinoRunner, OrtRunner
    from e3dpsm.profiles.targets import Target

    def target(name: str, runtime: str, precision: str) -> Target:
        provider = "CPUExecutionProvider" if runtime == "onnxruntime" else "CPU"
        return Target(name=name, runtime=runtime, provider=provider, precision=precision, graph=precision,
                      threads=threads)

    runners = {"ort fp32": OrtRunner(str(fp32), target("ort fp32", "onnxruntime", "fp32"), window_ms),
               "openvino fp32": OpenVinoRunner(str(fp32), target("ov fp32", "openvino", "fp32"), window_ms)}
    if detect_isa().bf16:
        runners["openvino bf16"] = OpenVinoRunner(str(fp32), target("ov bf16", "openvino", "bf16"), window_ms)
    for label, path in graphs.items():
        runners[f"ort {label}"] = OrtRunner(str(path), target(label, "onnxruntime", "int8"), window_ms)
        runners[f"openvino {label}"] = OpenVinoRunner(str(path), target(label, "openvino", "int8"), window_ms)
    return runners


def _bf16_distance(fp32: Path, holdout, threads: int) -> float | None:
    """Distance of the fp32 graph run in bf16 on OpenVINO, the measure quantize budgets on."""
    from e3dpsm.runtime.openvino_session import OpenVINOStepSession
    from e3dpsm.validation.streams import onnx_stream_outputs

    if not detect_isa().bf16:
        return None
    session = OpenVINOStepSession(fp32, threads=threads, precision="bf16")
    outputs = [onnx_stream_outputs(session, x, holdout.window_ms) for x in holdout.lnes]
    from e3dpsm.metrics import joint_errors

    worst = max(float(joint_errors(np.concatenate([o[k] for o in outputs]),
                                   np.concatenate([o[k] for o in holdout.fp32_outputs])).mean())
                for k in holdout.fp32_outputs[0])
    return 100.0 * worst / holdout.fp32_mpjpe


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True, help="prepared folder with the three splits below")
    parser.add_argument("--split", default="train", help="calibration frames")
    parser.add_argument("--holdout-split", default="test", help="quantize's own accuracy check and search")
    parser.add_argument("--check-split", default="val", help="an independent check no search saw")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--holdout-frames", type=int, default=200)
    parser.add_argument("--check-frames", type=int, default=1000,
                        help="frames of the --check-split sequences for the independent check")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per graph")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-search", action="store_true", help="skip the default --exclude auto row")
    parser.add_argument("--qat-checkpoint", default=None, help="a `train --qat` fine-tune of --checkpoint")
    parser.add_argument("--rows", nargs="*", default=None, help="only rows whose label contains one of these")
    parser.add_argument("--only", nargs="*", default=None, help="only the rows with exactly these labels")
    parser.add_argument("--append", action="store_true", help="add the rows to the existing results")
    parser.add_argument("--runtimes", nargs="+", choices=("onnxruntime", "openvino"), default=["onnxruntime"],
                        help="quantize --runtimes for every row: the runtimes the search checks its budget on; "
                        "rows searched on more than one are labelled so")
    args = parser.parse_args(argv)

    import torch

    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export import export_step
    from e3dpsm.training.qat_ranges import learned_with_weights_frozen, simulated_float_outputs
    from e3dpsm.profiles.latency import measure_side_by_side

    model, _ = load_checkpoint(args.checkpoint)
    variant = model.config.variant
    data = PreparedData.open(args.data)
    report = report_header("bench_int8_ladder", vars(args))
    rows = []
    with tempfile.TemporaryDirectory(prefix="e3dpsm-ladder-") as work:
        work = Path(work)
        fp32 = export_step(model, work / "step.onnx")
        window_ms = model.config.train_window_ms
        check = make_holdout(fp32, data.split(args.check_split), window_ms, args.check_frames, args.threads)
        graphs: dict[str, Path] = {}
        runs = [(f"full int8, {c}", QuantizeOptions(mode="int8", exclude="none", calibration=c)) for c in CALIBRATIONS]
        runs.append(("full int8, mse, equalized", QuantizeOptions(mode="int8", exclude="none", calibration="mse",
                                                                   equalize=True)))
        runs.append(("full int8, mse, adaround", QuantizeOptions(mode="int8", exclude="none", calibration="mse",
                                                                  weight_rounding="adaround")))
        # The default leaves MatMul/Gemm outputs no quantised op reads in float (outputs.py).
        runs.append(("full int8, mse, every output pair kept (--float-outputs none)",
                     QuantizeOptions(mode="int8", exclude="none", calibration="mse", float_outputs="none")))
        runs.append(("full int8, mse, Conv outputs float too (--float-outputs all)",
                     QuantizeOptions(mode="int8", exclude="none", calibration="mse", float_outputs="all")))
        other = "vnni" if saturates_u8s8(detect_isa().kind) else "avx2"
        bits = {"vnni": 8, "avx2": 7}[other]
        runs.append((f"full int8, mse, {bits}-bit weights (--target-isa {other})",
                     QuantizeOptions(mode="int8", exclude="none", calibration="mse", target_isa=other)))
        if not args.no_search:
            # "default search, mse, int16" is the INT8 default (AdaRound weights under the search);
            # the nearest rows name their rounding, which the default no longer is.
            runs.append(("default search, mse", QuantizeOptions(mode="int8", calibration="mse", int16=False)))
            runs.append(("default search, mse, int16", QuantizeOptions(mode="int8", calibration="mse")))
            runs.append(("default search, mse, int16, latency objective",
                         QuantizeOptions(mode="int8", calibration="mse", objective="latency")))
            runs.append(("default search, mse, int16, nearest", QuantizeOptions(mode="int8", calibration="mse",
                                                                                 weight_rounding="nearest")))
            runs.append(("default search, mse, int16, nearest, no search margin",
                         QuantizeOptions(mode="int8", calibration="mse", search_margin=0.0, weight_rounding="nearest")))
        sources = {label: fp32 for label, _ in runs}
        base_mpjpe = check.fp32_mpjpe
        if args.qat_checkpoint:
            qat_model, qat_payload = load_checkpoint(args.qat_checkpoint)
            qat_fp32 = export_step(qat_model, work / "qat_step.onnx")
            steps = qat_payload.get("step", "?")
            # Ranges learned with --checkpoint's own weights frozen (`distill --qat-ranges-only` of
            # it): the fp32 graph is --checkpoint's, and its rows are post-training graphs.
            base_state = model.state_dict()
            ranges_only = learned_with_weights_frozen(qat_payload) and all(
                torch.equal(v, base_state[k]) for k, v in qat_model.state_dict().items())
            prefix = f"learned ranges {steps} steps (weights frozen)" if ranges_only else f"QAT {steps} steps"
            if simulated_float_outputs(qat_payload) == "all":  # another graph than the default rows'
                prefix += ", Conv outputs float too"
            qat_runs = [(f"{prefix}, full int8, QAT ranges", QuantizeOptions(
                        mode="int8", exclude="none", ranges_from_checkpoint=args.qat_checkpoint)),
                    (f"{prefix}, default search, QAT ranges, int16", QuantizeOptions(
                        mode="int8", ranges_from_checkpoint=args.qat_checkpoint))]
            if not ranges_only:  # else the same graph as the base checkpoint's minmax row
                qat_runs.insert(1, (f"{prefix}, full int8, minmax", QuantizeOptions(mode="int8", exclude="none")))
            for label, options in qat_runs:
                runs.append((label, options))
                sources[label] = qat_fp32
        if len(args.runtimes) > 1:  # a different experiment from the same row on ONNX Runtime alone
            searched_on = " + ".join(RUNTIME_NAMES[r] for r in args.runtimes)
            relabelled = []
            for label, options in runs:
                new = f"{label}, on {searched_on}" if options.exclude == "auto" else label
                sources[new] = sources[label]
                relabelled.append((new, options))
            runs = relabelled
        if args.rows:
            runs = [(label, o) for label, o in runs if any(word in label for word in args.rows)]
        if args.only:
            unknown = sorted(set(args.only) - {label for label, _ in runs})
            if unknown:
                parser.error(f"no row labelled {unknown}; the rows: {[label for label, _ in runs]}")
            runs = [(label, o) for label, o in runs if label in args.only]
        checks = {fp32: check}
        exact_holdouts: dict[Path, object] = {}
        failed: list[dict] = []
        for label, options in runs:
            options = QuantizeOptions(**{**options.__dict__, "frames": args.frames, "holdout_frames": args.holdout_frames,
                                         "split": args.split, "holdout_split": args.holdout_split,
                                         "threads": args.threads, "runtimes": tuple(args.runtimes)})
            source = sources[label]
            if source not in checks:
                checks[source] = make_holdout(source, data.split(args.check_split), window_ms, args.check_frames,
                                              args.threads)
            folder = work / label.replace(" ", "_").replace(",", "")
            try:
                q = quantize_graph(source, args.data, folder, options)
            except Exception as error:  # noqa: BLE001 - one row's failure must not lose the hour's other rows
                failed.append({"label": label, "error": f"{type(error).__name__}: {error}"})
                print(f"{label}: FAILED ({failed[-1]['error']})", flush=True)
                continue
            path = folder / q["artifact"]
            graphs[label] = path
            measured = accuracy_of(path, checks[source], args.threads)
            independent = measured["bound_pct"]
            # The same frames on OpenVINO, which fuses and rounds a QDQ graph its own way.
            on_openvino = (accuracy_of(path, checks[source], args.threads, runtime="openvino")["bound_pct"]
                           if importlib.util.find_spec("openvino") else None)
            if source not in exact_holdouts:
                exact_holdouts[source] = make_holdout(source, data.split(args.holdout_split), window_ms,
                                                      args.holdout_frames, args.threads)
            exact = accuracy_of(path, exact_holdouts[source], args.threads, exact_arithmetic=True)["bound_pct"]
            ranked = q.get("exclusion_search") or {}
            kept = [n for n in q["excluded_nodes"] if n in {r["node"] for r in ranked.get("sensitivity", [])}]
            rows.append({"label": label, "distance_pct": q["holdout"]["bound_pct"], "check_distance_pct": independent,
                         "exact_distance_pct": exact, "check_distance_openvino_pct": on_openvino,
                         "runtimes": list(args.runtimes), "weight_bits": 7 if q["quantization"].get("reduce_range") else 8,
                         "check_frames": checks[source].frames,
                         "mpjpe_loss_pct": q["holdout"]["loss_pct"], "bytes": path.stat().st_size,
                         "compute_nodes_in_float": len(kept) if ranked else 0,
                         "compute_nodes_int16": len(q["quantization"].get("int16_nodes") or []),
                         "compute_nodes_int16w16": len(q["quantization"].get("int16w16_nodes") or []),
                         # read off the graph, recurrent groups included (quantize/census.py)
                         "compute_precision": q["quantization"].get("compute_precision"),
                         "compute_nodes_out_of_8_bits": q["quantization"].get("compute_nodes_out_of_8_bits"),
                         "mpjpe_vs_base_pct": 100.0 * (measured["mpjpe_mm"] / base_mpjpe - 1.0),
                         "qat_ranges": {k: v for k, v in (q.get("qat_ranges") or {}).items() if k != "uncovered"},
                         "ranges_won_by": (q["calibration"].get("ranges") or {}).get("won_by")})
            print(f"{label}: {rows[-1]['distance_pct']:.3f}% ({args.holdout_split}; exact arithmetic {exact:.3f}%), "
                  f"{independent:.3f}% ({args.check_split}), {rows[-1]['bytes'] / 1e6:.2f} MB", flush=True)
        holdout = exact_holdouts.get(fp32) or make_holdout(fp32, data.split(args.holdout_split), window_ms,
                                                           args.holdout_frames, args.threads)
        bf16 = _bf16_distance(fp32, holdout, args.threads)
        lnes = np.concatenate(holdout.lnes)[: max(args.steps, 50)]
        runners = _runners(graphs, fp32, args.threads, window_ms)
        times = measure_side_by_side(runners, lnes, args.steps, warmup=10)
        p50 = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
        fp32_bytes = fp32.stat().st_size
    for r in rows:  # each row keeps the fp32 timed beside it (rows appended later come from another run)
        r.update(ort_ms=p50[f"ort {r['label']}"], openvino_ms=p50[f"openvino {r['label']}"], fp32_bytes=fp32_bytes,
                 ort_fp32_ms=p50["ort fp32"], openvino_fp32_ms=p50["openvino fp32"], isa=detect_isa().kind)
    report.update(variant=variant, isa=detect_isa().to_dict(), fp32_bytes=fp32_bytes, rows=rows, failed_rows=failed,
                  bf16_distance_pct=bf16, p50_ms=p50, fp32_mpjpe_mm=holdout.fp32_mpjpe)
    name = f"int8_{variant}_ladder_{detect_isa().kind}"
    if args.append and (RESULTS / f"{name}.json").is_file():
        import json

        old = json.loads((RESULTS / f"{name}.json").read_text())
        old.setdefault("appended", []).append({k: report[k] for k in ("created", "config", "machine", "isa")})
        labels = {r["label"] for r in rows}
        old["rows"] = [r for r in old["rows"] if r["label"] not in labels] + rows
        old["failed_rows"] = failed
        report = old
    write_json_atomic(RESULTS / f"{name}.json", report)
    write_text_atomic(RESULTS / f"{name}.md", markdown(report))
    print(markdown(report))
    return 1 if failed else 0


def markdown(report: dict) -> str:
    isa, p50 = report["isa"], report["p50_ms"]
    cfg = report["config"]
    # Runs before 2026-12-01 10:27 did not measure the exact arithmetic: their tables keep
    # the columns they had.
    has_exact = any(r.get("exact_distance_pct") is not None for r in report["rows"])
    lines = [f"# INT8 ladder, `{report['variant']}` ({report['created']})", "",
             f"Host: {report['machine'].get('cpu_model', '?')}, ISA {isa['kind']} ({' '.join(isa['flags'])}), "
             f"{cfg['threads']} threads. Distance to fp32: the largest mean joint distance over the fused, direct "
             f"and delta poses relative to the fp32 MPJPE ({report['fp32_mpjpe_mm']:.1f} mm), on "
             f"`{cfg['holdout_split']}` (quantize's own check) and on `{cfg['check_split']}` (never searched)"
             + (f"; 'exact %': on `{cfg['holdout_split']}` in the graph's exact arithmetic (ONNX Runtime without "
                "graph optimisations: Q/DQ in float, no integer kernel; the same on any host)" if has_exact else "")
             + f". Step p50 side by side, {cfg['steps']} steps each.", "",
             "| graph | distance % | " + ("exact % | " if has_exact else "") + "independent % | compute nodes "
             + ("out of 8 bits (read off the graph)" if any(r.get("compute_precision") for r in report["rows"])
                else "in float (+ 16-bit)") + " | MB (x fp32) | ORT p50 ms (x fp32) | OpenVINO p50 ms (x fp32) |",
             "|---|---:|---:|---:|---:|---:|---:|" + ("---:|" if has_exact else "")]
    exact_cell = (lambda text: f" {text} |") if has_exact else (lambda text: "")
    ort32, ov32 = p50["ort fp32"], p50["openvino fp32"]
    lines.append(f"| fp32 | 0 |{exact_cell('0')} 0 | all | {report['fp32_bytes'] / 1e6:.2f} (1x) | {ort32:.2f} | {ov32:.2f} |")
    if "openvino bf16" in p50:
        lines.append(f"| fp32 in bf16 (OpenVINO) | {report['bf16_distance_pct']:.3f} |{exact_cell('')} | | "
                     f"{report['fp32_bytes'] / 1e6:.2f} | | {p50['openvino bf16']:.2f} ({ov32 / p50['openvino bf16']:.2f}x) |")
    for r in report["rows"]:
        ort, ov = r.get("ort_ms", p50.get(f"ort {r['label']}")), r.get("openvino_ms", p50.get(f"openvino {r['label']}"))
        o32, v32 = r.get("ort_fp32_ms", ort32), r.get("openvino_fp32_ms", ov32)
        sixteen = [f"+{r[key]} {kind}" for key, kind in (("compute_nodes_int16", "int16"),
                                                         ("compute_nodes_int16w16", "int16w16")) if r.get(key)]
        out8 = str(r["compute_nodes_in_float"]) + (f" ({', '.join(sixteen)})" if sixteen else "")
        census = r.get("compute_precision")
        if census:  # the graph's own count, recurrent projections included
            out8 = f"{r['compute_nodes_out_of_8_bits']} of {sum(census.values())}" + "".join(
                f", {n} {label}" for label, n in census.items() if label != "int8" and n)
        # against the fp32 graph of the row's own run (appended rows may come from another export)
        size = f"{r['bytes'] / 1e6:.2f} ({r['bytes'] / r.get('fp32_bytes', report['fp32_bytes']):.3f}x)"
        frames = f" ({r['check_frames']} f)" if r.get("check_frames") else " (200 f)"
        exact = f"{r['exact_distance_pct']:.3f}" if r.get("exact_distance_pct") is not None else ""
        lines.append(f"| {r['label']} | {r['distance_pct']:.3f} |{exact_cell(exact)} {r['check_distance_pct']:.3f}{frames} | "
                     f"{out8} | {size} | {ort:.2f} ({o32 / ort:.2f}x) | {ov:.2f} ({v32 / ov:.2f}x) |")
    if any("mpjpe_vs_base_pct" in r for r in report["rows"]):
        lines += ["", "MPJPE on the independent check's frames against the base checkpoint's fp32 graph (a short "
                  "check; the QAT bar is judged on every held-out frame by benchmarks/bench_qat_mpjpe.py, "
                  f"results/qat_{report['variant']}_mpjpe_{report['isa']['kind']}.md):", ""]
        lines += [f"- {r['label']}: {r['mpjpe_vs_base_pct']:+.2f}%" for r in report["rows"] if "mpjpe_vs_base_pct" in r]
    on_openvino = [r for r in report["rows"] if r.get("check_distance_openvino_pct") is not None]
    if on_openvino:
        lines += ["", "The independent check's frames on OpenVINO (CPU, f32; the same graphs), distance to the fp32 "
                  "graph on ONNX Runtime, % of MPJPE:", ""]
        lines += [f"- {r['label']}: {r['check_distance_openvino_pct']:.3f} (ONNX Runtime {r['check_distance_pct']:.3f})"
                  for r in on_openvino]
    lines += [f"\nNote: {note}" for note in report.get("notes", [])]
    lines += [f"\nFailed in the last run (no row): {f['label']}: {f['error']}" for f in report.get("failed_rows", [])]
    appended = report.get("appended", [])
    if appended:
        runs = ", ".join(f"{extra['created']} (ISA {extra['isa']['kind']})" for extra in appended)
        lines.append(f"\nRows appended by later runs: {runs}; each row's speed is against the fp32 graph timed "
                     "beside it in its own run, and the independent column gives the frames it was checked on.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
