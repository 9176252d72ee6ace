"""Results of `e3dpsm prune` on the committed trained small (benchmarks/results/prune_small.md
and .json), from the runs that made benchmarks/checkpoints/small_pruned (its recipe.md has
the commands):

    python benchmarks/prune_small_results.py --prune-run RUN --distill-run MORE --final FINAL \\
        --eval-unpruned EVAL_SMALL --eval-pruned EVAL_RUN --eval-final EVAL_MORE

RUN: the `e3dpsm prune` folder (its report.json: the front per round, predicted against
measured step, the recovery time); MORE: the `e3dpsm distill` folder continuing it; FINAL: a
folder with `timing.json` (the committed model's step graph timed side by side with the
unpruned one, fp32, ONNX Runtime and OpenVINO) and `parity.json` (`e3dpsm parity`, 1,000
steps at 20, 25 and 50 ms); EVAL_*: `e3dpsm evaluate --causal` folders.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from e3dpsm.compress.report import render_markdown
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"


def _load(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in ("prune-run", "distill-run", "final", "eval-unpruned", "eval-pruned", "eval-final"):
        p.add_argument(f"--{name}", type=Path, required=True)
    a = p.parse_args()
    prune = _load(a.prune_run / "report.json")
    distill = _load(a.distill_run / "report.json")
    timing = _load(a.final / "timing.json")
    parity = _load(a.final / "parity.json")
    evals = {k: _load(d / "metrics.json") for k, d in (("unpruned", a.eval_unpruned), ("pruned_300", a.eval_pruned),
                                                     ("pruned_800", a.eval_final))}
    mpjpe = {k: v["totals"]["mpjpe"] for k, v in evals.items()}
    int8 = {k: _load(a.prune_run / "graphs" / f"round{k}_int8" / "report.json")["holdout"] for k in (0, prune["best"])}
    summary = {
        **report_header("prune_small_results", {k: str(v) for k, v in vars(a).items()}),
        "mpjpe_causal_mm": mpjpe, "mpjpe_change_pct": 100 * (mpjpe["pruned_800"] / mpjpe["unpruned"] - 1),
        "final_timing_ms": timing, "speedup_ort_fp32": timing["onnxruntime_unpruned"] / timing["onnxruntime_pruned"],
        "speedup_ov_fp32": timing["openvino_unpruned"] / timing["openvino_pruned"],
        "parity": [{"window_ms": r["window_ms"], "steps": r["steps"], "passed": r["passed"],
                    "max_pose_diff_mm": max(t["max_abs"] for t in r["tensors"] if t["kind"] == "output")}
                   for r in parity["runs"]],
        "int8_holdout": int8,
        "recovery_seconds": {"prune_run": prune["recovery_seconds"], "distill_after": distill.get("seconds")},
        "prune_report": {k: v for k, v in prune.items() if k not in ("rounds",)},
        "rounds": [{k: v for k, v in r.items() if k != "candidates"} for r in prune["rounds"]],
        "candidates_round1": prune["rounds"][1]["candidates"],
    }
    write_json_atomic(RESULTS / "prune_small.json", summary)
    lines = [
        "# Pruning the committed trained small (`e3dpsm prune`)", "",
        "The committed result: benchmarks/checkpoints/small_pruned (recipe.md there: commands, seeds, time).",
        "", "## The committed model against the unpruned small", "",
        "| | unpruned small | small_pruned | |", "|---|---:|---:|---:|",
        f"| MACs (Conv + Linear, one step) | {prune['rounds'][0]['macs'] / 1e6:.1f} M | "
        f"{prune['rounds'][prune['best']]['macs'] / 1e6:.1f} M | {prune['rounds'][prune['best']]['macs_fraction']:.3f} |",
        f"| parameters | {prune['rounds'][0]['params']:,} | {prune['rounds'][prune['best']]['params']:,} | |",
        f"| ORT fp32 step, 2 threads, side by side | {timing['onnxruntime_unpruned']:.2f} ms | "
        f"{timing['onnxruntime_pruned']:.2f} ms | {summary['speedup_ort_fp32']:.2f}x faster |",
        f"| OpenVINO fp32 step, 2 threads, side by side | {timing['openvino_unpruned']:.2f} ms | "
        f"{timing['openvino_pruned']:.2f} ms | {summary['speedup_ov_fp32']:.2f}x faster |",
        f"| held-out causal MPJPE (`e3dpsm evaluate`, prep96_test, 3,000 frames) | {mpjpe['unpruned']:.2f} mm | "
        f"{mpjpe['pruned_800']:.2f} mm | {summary['mpjpe_change_pct']:+.2f}% |",
        f"| after the prune run's 300 recovery steps alone | | {mpjpe['pruned_300']:.2f} mm | "
        f"{100 * (mpjpe['pruned_300'] / mpjpe['unpruned'] - 1):+.2f}% |",
        "", "Parity of the committed model's export against its PyTorch step (ONNX Runtime, 1,000 steps):", "",
    ]
    lines += [f"- {r['window_ms']:g} ms: max |pose diff| {r['max_pose_diff_mm']:.2e} mm "
              f"({'passed' if r['passed'] else 'FAILED'}, limit 0.01 mm)" for r in summary["parity"]]
    lines += ["", "## The prune run (its own report.md)", "",
              "Its held-out MPJPE column was computed before the fix that groups the frames by the data's action "
              "names as `e3dpsm evaluate` does (commit 'prune: held-out MPJPE grouped by the data's action names'): "
              "one merged group, 128.48 mm for the unpruned model where `evaluate` gives 120.28 mm. The "
              "frame-weighted figures in report.json (120.70 -> 128.20 mm) and the table above are unaffected.", "",
              render_markdown(prune, prune)]
    write_text_atomic(RESULTS / "prune_small.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
