"""INT8 of the committed trained `small`, judged as its users judge it: the task budget on held-out
frames no quantiser step saw, on ONNX Runtime and OpenVINO, beside size and speed against fp32.

    python benchmarks/bench_int8.py --checkpoint benchmarks/checkpoints/small/checkpoint.pt \\
        --data prep96_s8 --holdout-data prep96_s7x8 [--qat-checkpoint benchmarks/checkpoints/small_qat/checkpoint.pt]

Data (commands in benchmarks/checkpoints/small/recipe.md): calibration and search on --data
(`train`, `val`), the budget on every frame of --holdout-data (`all`). Rows:
- `quantize --mode int8` with its defaults (full integer first, the fewest nodes back to float);
- `--exclude none` (every Conv/MatMul/Gemm 8-bit, the recurrence's too);
- with --qat-checkpoint: its `--exclude none` graph, judged against the *base* fp32 graph (a QAT
  fine-tune moves the fp32 model; what users get is its INT8 against the model it came from).
Per row and runtime: MPJPE, PA-MPJPE and jitter change over fp32 with the upper end of the
budget's interval, the distance to the fp32 poses (fidelity), Conv/MatMul/Gemm out of 8 bits,
size against fp32, speed against fp32 side by side (interleaved, bootstrap interval).
Writes benchmarks/results/int8_small_<isa kind>.json and .md; README's figures come from the JSON.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from e3dpsm.budget import TaskBudget
from e3dpsm.data.prepared import PreparedData
from e3dpsm.quantize import Advanced, QuantizeOptions, quantize_graph
from e3dpsm.quantize.holdout import held_out, judge
from e3dpsm.quantize.verdict import time_beside_fp32
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic
from e3dpsm.utils.isa import detect_isa

RESULTS = Path(__file__).resolve().parent / "results"
RUNTIMES = ("onnxruntime", "openvino")


def export(checkpoint: str, out: Path) -> Path:
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.export import export_step

    model, _ = load_checkpoint(checkpoint)
    return export_step(model, out / "step.onnx")


def row(label: str, graph: Path, report: dict[str, Any], judged: Any | None = None) -> dict:
    """A table row from the quantiser's own report: its held-out check and its timing beside
    fp32 (`judged` replaces the check where the graph must be judged against another fp32)."""
    by_runtime = ({r: c.to_dict() for r, c in judged.by_runtime.items()} if judged is not None
                  else report["check"]["by_runtime"])
    return {"label": label, "artifact": graph.name, "within": all(c["within"] for c in by_runtime.values()),
            "by_runtime": by_runtime, "out_of_8_bits": report["written"]["compute_nodes_out_of_8_bits"],
            "float_nodes": (report.get("placement") or {}).get("float_nodes", []),
            "size_ratio": report["written"]["size_ratio"], "bytes": report["written"]["bytes"],
            "speed": {r: {k: s[k] for k in ("p50_ms", "fp32_p50_ms", "speedup_vs_fp32", "interval")}
                      for r, s in report["verdict"]["timings"].items()},
            "headline": report["verdict"]["headline"]}


def markdown(result: dict) -> str:
    isa = result["machine"]["isa"]
    lines = [f"# INT8 of `small` against its task budget ({isa['kind']}: {' '.join(isa['flags'])})", "",
             f"Held-out: {result['holdout']['frames']} frames of `{result['holdout']['data']}` that neither "
             "calibration nor search saw; change over fp32 in % with the upper end of the 90% interval "
             "(the budget: MPJPE and PA-MPJPE +1%, jitter +5%); speed side by side, "
             f"{result['config']['timing_steps']} steps, {result['config']['threads']} threads.", "",
             "| graph | runtime | dMPJPE % (upper) | dPA-MPJPE % (upper) | d jitter % (upper) | within | distance to "
             "fp32 poses % | nodes out of 8 bits | size vs fp32 | speed vs fp32 (80% interval) |",
             "|---|---|---|---|---|---|---:|---:|---:|---|"]
    if "retimed" in result:
        t = result["retimed"]
        lines[2:2] = [f"Speeds timed again with `--retime` ({t['when']}, {t['steps']} steps, load average "
                      f"{t['load_average'][0]:.2f} -> {t['load_average'][1]:.2f}); the first run's were under load.", ""]
    for r in result["rows"]:
        for runtime, check in r["by_runtime"].items():
            m = check["metrics"]
            s = r["speed"][runtime]
            change = " | ".join(f"{m[k]['change_pct']:+.2f} ({m[k]['upper_pct']:+.2f})" for k in ("mpjpe", "pa_mpjpe", "jitter"))
            lines.append(f"| {r['label']} | {runtime} | {change} | {'yes' if check['within'] else '**no**'} | "
                         f"{check['fidelity_pct']:.2f} | {r['out_of_8_bits']} | {r['size_ratio']:.3f}x | "
                         f"{s['speedup_vs_fp32']:.2f}x ({s['interval']['low']:.2f}-{s['interval']['high']:.2f}) |")
    return "\n".join(lines) + "\n"


def headline(result: dict) -> str:
    """README's INT8 sentence, every figure from `result` (tests/test_docs.py holds README to it)."""
    rows = {r["label"]: r for r in result["rows"]}
    default, full = rows["default"], rows["--exclude none"]
    ort = default["by_runtime"]["onnxruntime"]["metrics"]
    isa = result["machine"]["isa"]["kind"]

    def speeds(row: dict) -> str:
        return " / ".join(f"{row['speed'][r]['speedup_vs_fp32']:.2f}x" for r in RUNTIMES if r in row["speed"])

    def upper(row: dict, metric: str) -> float:
        return max(c["metrics"][metric]["upper_pct"] for c in row["by_runtime"].values())

    return (f"the trained `small` quantises to INT8 (`quantize --mode int8`, defaults) within its task budget on "
            f"{result['holdout']['frames']:,} held-out frames: MPJPE {ort['mpjpe']['change_pct']:+.2f}% "
            f"(upper bound {upper(default, 'mpjpe'):+.2f}% over both runtimes), PA-MPJPE "
            f"{ort['pa_mpjpe']['change_pct']:+.2f}%, jitter {ort['jitter']['change_pct']:+.2f}% against fp32 on "
            f"ONNX Runtime, at {default['size_ratio']:.3f}x fp32's size with {default['out_of_8_bits']} "
            f"Conv/MatMul/Gemm out of 8 bits, {speeds(default)} fp32's speed (ONNX Runtime / OpenVINO, side by "
            f"side, {isa} host); full integer (`--exclude none`) MPJPE "
            f"{full['by_runtime']['onnxruntime']['metrics']['mpjpe']['change_pct']:+.2f}% (upper bound "
            f"{upper(full, 'mpjpe'):+.2f}%), {full['size_ratio']:.3f}x the size, {speeds(full)} the speed")


def _folder(label: str) -> str:
    return label.replace(" ", "_").replace(",", "")


def retime(out: Path, work: Path, args: argparse.Namespace) -> int:
    """Time each kept row's graph beside the kept fp32 graph again and rewrite its speed."""
    result = json.loads(out.read_text(encoding="utf-8"))
    check = held_out(work / "fp32" / "step.onnx", PreparedData.open(args.holdout_data).split("all")[:1], 20.0, 0,
                     "timing", args.threads)
    load = os.getloadavg()[0]
    for r in result["rows"]:
        timed = time_beside_fp32(work / _folder(r["label"]) / r["artifact"], work / "fp32" / "step.onnx", check.lnes[0],
                                 check.window_ms, RUNTIMES, args.threads, args.timing_steps)
        r["speed"] = {rt: {k: t[k] for k in ("p50_ms", "fp32_p50_ms", "speedup_vs_fp32", "interval")}
                      for rt, t in timed.items()}
    result["retimed"] = {"when": report_header("bench_int8 --retime", vars(args))["created"], "steps": args.timing_steps,
                         "load_average": [load, os.getloadavg()[0]]}
    write_json_atomic(out, result)
    write_text_atomic(out.with_suffix(".md"), markdown(result))
    print(markdown(result) + f"\nREADME: {headline(result)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True, help="prepared: calibration (train) and search (val)")
    parser.add_argument("--holdout-data", required=True, help="prepared: the budget's frames (every one)")
    parser.add_argument("--qat-checkpoint", default=None)
    parser.add_argument("--frames", type=int, default=600, help="calibration frames")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timing-steps", type=int, default=400)
    parser.add_argument("--out", default=None, help="results file (default benchmarks/results/int8_small_<isa>.json)")
    parser.add_argument("--keep", default=None, metavar="DIR",
                        help="keep the graphs in DIR (fp32/, <row>/) for --retime; default: a temporary folder")
    parser.add_argument("--retime", default=None, metavar="DIR",
                        help="only time again the graphs a --keep run left in DIR against its fp32 and rewrite the "
                             "speed figures of --out (for a quieter machine: accuracy does not depend on load)")
    args = parser.parse_args(argv)
    isa = detect_isa().kind
    out = Path(args.out) if args.out else RESULTS / f"int8_small_{isa}.json"
    if args.retime:
        return retime(out, Path(args.retime), args)
    result = report_header("bench_int8", {k: v for k, v in vars(args).items()})
    with contextlib.ExitStack() as stack:
        work = Path(args.keep) if args.keep else Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-int8-")))
        fp32 = export(args.checkpoint, work / "fp32")
        common = dict(frames=args.frames, holdout_data=args.holdout_data, holdout_split="all", runtimes=RUNTIMES,
                      threads=args.threads, advanced=Advanced(timing_steps=args.timing_steps))
        rows = []
        for label, graph, options in [("default", fp32, QuantizeOptions(**common)),
                                      ("--exclude none", fp32, QuantizeOptions(exclude="none", **common)),
                                      *([("small_qat, --exclude none", export(args.qat_checkpoint, work / "qat"),
                                          QuantizeOptions(exclude="none", **common))] if args.qat_checkpoint else [])]:
            q = work / _folder(label)
            report = quantize_graph(graph, args.data, q, options)
            judged = None
            if graph != fp32:  # QAT: its INT8 against the base model's fp32, on the same frames
                check = held_out(fp32, PreparedData.open(args.holdout_data).split("all"), 20.0, 0,
                                 Path(args.holdout_data).name, args.threads)
                judged = judge(q / report["artifact"], check, TaskBudget(), RUNTIMES, args.threads)
            rows.append(row(label, q / report["artifact"], report, judged))
            print(markdown({**result, "holdout": report["check"], "rows": rows}))
    result.update(holdout={"frames": report["check"]["frames"], "data": report["check"]["data"]}, rows=rows)
    write_json_atomic(out, result)
    write_text_atomic(out.with_suffix(".md"), markdown(result))
    print(f"wrote {out}\nREADME: {headline(result)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
