"""Label-free distillation of the trained `small` into `tiny` against `tiny` trained on labels
for the same steps: the table of benchmarks/results/distill_small_to_tiny.md/.json from runs
made with the CLI (commands in that file), so the figures come from the commands users run.

    python benchmarks/distill_small_to_tiny.py --teacher-eval EVAL_SMALL \\
        --distilled RUN_DISTILLED EVAL_DISTILLED --labelled RUN_LABELLED EVAL_LABELLED \\
        [--distilled RUN EVAL --labelled RUN EVAL ...] [--commands commands.txt]

--distilled and --labelled repeat (one per seed of the window order); each kind gets a mean row.

Each EVAL_* is an `e3dpsm evaluate --causal` folder on the same split of the same held-out
data; the distance of a student to the teacher is the MPJPE between their causal poses,
frame by frame (all joints, every frame equally weighted).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.metrics import mpjpe
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic, write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
NAME = "distill_small_to_tiny"


def _eval(folder: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    metrics = json.loads((folder / "metrics.json").read_text())
    with np.load(folder / "predictions.npz") as archive:
        return metrics, archive["pred_mm"], archive["gt_mm"]


def _row(name: str, run: Path | None, eval_dir: Path, teacher_pred: np.ndarray) -> dict[str, Any]:
    metrics, pred, gt = _eval(eval_dir)
    row = {"model": name, "eval": str(eval_dir), **{k: metrics["totals"][k] for k in ("mpjpe", "pa_mpjpe", "e_smooth")},
           "mpjpe_frames": mpjpe(pred, gt), "to_teacher_mm": mpjpe(pred, teacher_pred),
           "direct_head_mpjpe": metrics.get("direct_head", {}).get("mpjpe")}
    if run is not None:
        report = json.loads((run / "report.json").read_text())
        config = report["config"]
        seed = config["distill"]["seed"] if "distill" in config else config["args"]["seed"]
        row.update({"run": str(run), "seed": seed, "steps": report.get("steps", report.get("step")),
                    "train_seconds": report["seconds"],
                    "parameters": report.get("parameters") or report["student"]["parameters"]})
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--teacher-eval", type=Path, required=True)
    parser.add_argument("--distilled", type=Path, nargs=2, required=True, action="append", metavar=("RUN", "EVAL"))
    parser.add_argument("--labelled", type=Path, nargs=2, required=True, action="append", metavar=("RUN", "EVAL"))
    parser.add_argument("--commands", type=Path, help="text file of the commands that made the runs")
    args = parser.parse_args()

    _, teacher_pred, gt = _eval(args.teacher_eval)
    rows = [_row("small (teacher, trained on labels)", None, args.teacher_eval, teacher_pred)]
    means = []
    for name, runs in (("tiny distilled from small, no labels", args.distilled), ("tiny trained on labels", args.labelled)):
        kind = [_row(name, run, eval_dir, teacher_pred) for run, eval_dir in runs]
        rows += kind
        if len(kind) > 1:
            means.append({"model": f"{name}: mean of {len(kind)} seeds", "steps": kind[0]["steps"],
                          **{k: float(np.mean([r[k] for r in kind]))
                             for k in ("mpjpe", "pa_mpjpe", "e_smooth", "to_teacher_mm", "train_seconds")}})
    for row in rows[1:]:
        _, _, row_gt = _eval(Path(row["eval"]))
        if not np.array_equal(row_gt, gt):
            raise SystemExit(f"{row['eval']} was evaluated on other frames than {args.teacher_eval}")
    commands = args.commands.read_text().strip() if args.commands else ""
    header = report_header("bench_distill_small_to_tiny", {"teacher_eval": str(args.teacher_eval),
                                                           "distilled": [str(p) for p in args.distilled],
                                                           "labelled": [str(p) for p in args.labelled]})
    write_json_atomic(RESULTS / f"{NAME}.json", {**header, "frames": int(gt.shape[0]), "rows": rows, "means": means,
                                                 "commands": commands.splitlines()})
    isa = header["machine"]["isa"]
    lines = ["| model | seed | steps | train time | MPJPE | PA-MPJPE | e_smooth | MPJPE to the teacher |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows + means:
        steps = f"{row['steps']:,}" if "steps" in row else "2,600"
        secs = f"{row['train_seconds'] / 60:.1f} min" if "train_seconds" in row else "(recipe)"
        lines.append(f"| {row['model']} | {row.get('seed', '')} | {steps} | {secs} | {row['mpjpe']:.2f} mm | {row['pa_mpjpe']:.2f} mm | "
                     f"{row['e_smooth']:.2f} mm | {row['to_teacher_mm']:.2f} mm |")
    text = "\n".join([f"# Label-free distillation: trained `small` into `tiny` ({gt.shape[0]:,} held-out frames)", "",
                      f"CPU: {header['machine'].get('cpu_model', '?')}, ISA `{isa['kind']}` "
                      f"(flags {', '.join(isa['flags'])}); torch {header['versions']['torch']}.", "", *lines, ""])
    write_text_atomic(RESULTS / f"{NAME}.md", text + ("\n## Commands\n\n```\n" + commands + "\n```\n" if commands else ""))
    print(text)


if __name__ == "__main__":
    main()
