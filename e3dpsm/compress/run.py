"""`e3dpsm prune` end to end: load, prune in rounds with distillation, time the front side by
side (fp32 and INT8, ONNX Runtime and OpenVINO), write the checkpoint and the report."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Callable

from e3dpsm.compress.prune import PruneConfig, prune_loop, target_met, time_graphs, timing_frames
from e3dpsm.compress.report import front_rows, plot_front, render_markdown
from e3dpsm.models import E3DPSM

Recover = Callable[[E3DPSM, E3DPSM, int], dict[str, Any]]


def distill_recovery(data_dir: str | os.PathLike, config: PruneConfig, progress: bool) -> Recover:
    """Recovery by distillation from the unpruned model (compress/distill.py)."""
    def recover(teacher: E3DPSM, student: E3DPSM, round_index: int) -> dict[str, Any]:
        if config.steps == 0:
            return {"steps": 0, "seconds": 0.0}
        from e3dpsm.compress.distill import DistillConfig, distill

        cfg = DistillConfig(steps=config.steps, labels=config.labels, seed=config.seed + round_index,
                            threads=config.threads, lr=config.lr)
        summary = distill(teacher, student, data_dir, cfg, progress=progress)
        student.eval()
        return {k: v for k, v in summary.items() if k in ("steps", "seconds", "seconds_per_step", "final", "initial")}
    return recover


def _int8_figures(check: dict) -> dict:
    """The INT8 graph's MPJPE beside fp32's on the quantiser's held-out check (ONNX Runtime)."""
    on_ort = check["by_runtime"]["onnxruntime"]
    mpjpe = on_ort["metrics"]["mpjpe"]
    return {"split": check["data"].rsplit("/", 1)[-1], "frames": on_ort["frames"], "mpjpe_mm": mpjpe["value_mm"],
            "fp32_mpjpe_mm": mpjpe["fp32_mm"], "loss_pct": mpjpe["change_pct"], "within_budget": on_ort["within"]}


def _int8(graph: Path, data: str | os.PathLike, out: Path, threads: int) -> Path:
    """A static INT8 graph (recurrences in float, min-max ranges), calibrated on `train` (else
    the first split) and checked on `val` (else the last); the quantiser's own report lands
    beside it."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize import Advanced, QuantizeOptions, artifact_name, quantize_graph

    splits = PreparedData.open(data).splits
    calib = "train" if "train" in splits else splits[0]
    holdout = "val" if "val" in splits else splits[-1]
    options = QuantizeOptions(mode="int8", exclude="recurrent", frames=100, split=calib, holdout_split=holdout,
                              threads=threads, advanced=Advanced(holdout_frames=100, timing_steps=20))
    quantize_graph(graph, data, out, options, force=True)
    return out / artifact_name("int8")


def run_prune(checkpoint: str | os.PathLike, data: str | os.PathLike, out: str | os.PathLike, config: PruneConfig,
              *, eval_data: str | os.PathLike, eval_split: str = "all", int8: bool = True, force: bool = False,
              progress: bool = True, recover: Recover | None = None) -> dict[str, Any]:
    from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic

    started = time.perf_counter()
    teacher, _ = load_checkpoint(checkpoint)
    train_data = PreparedData.open(data)
    train_data.check_compatible(window_ms=teacher.config.train_window_ms, height=teacher.config.height,
                                width=teacher.config.width)
    held_out = PreparedData.open(eval_data)
    held_out.check_compatible(window_ms=teacher.config.train_window_ms, height=teacher.config.height,
                              width=teacher.config.width)
    held_out.split(eval_split)  # a bad split name fails now, in one line
    header = report_header("prune", {"checkpoint": str(checkpoint), "data": str(data), "out": str(out),
                                     "eval_data": str(eval_data), "eval_split": eval_split, "int8": int8,
                                     **config.to_dict()})
    with atomic_dir(out, force=force) as tmp:
        graphs = tmp / "graphs"
        result = prune_loop(teacher, data, held_out, config, graphs,
                            recover or distill_recovery(data, config, progress), eval_split=eval_split)
        rounds, best = result["rounds"], result["best"]
        for r in rounds:
            r["onnx_bytes"] = Path(r["graph"]).stat().st_size
            r["graph"] = os.path.relpath(r["graph"], tmp)
        # The front, every graph side by side in one run: fp32 on both runtimes for every
        # round, INT8 for the unpruned and the chosen model.
        timed: dict[str, tuple[str, Path]] = {}
        for r in rounds:
            timed[f"r{r['round']}_ort_fp32"] = ("onnxruntime", tmp / r["graph"])
            timed[f"r{r['round']}_ov_fp32"] = ("openvino", tmp / r["graph"])
        int8_reports = {}
        if int8:
            for k in sorted({0, best}):
                q = _int8(tmp / rounds[k]["graph"], eval_data, graphs / f"round{k}_int8", config.threads)
                check = json.loads((q.parent / "report.json").read_text(encoding="utf-8"))["check"]
                rounds[k]["int8"] = _int8_figures(check)
                timed[f"r{k}_ort_int8"] = ("onnxruntime", q)
                timed[f"r{k}_ov_int8"] = ("openvino", q)
                int8_reports[k] = os.path.relpath(q, tmp)
        frames = timing_frames(held_out.split(eval_split))
        # One interleaved run per runtime: OpenVINO's and ONNX Runtime's thread pools, alternating
        # in one process every few steps, disturbed each other's figures on a loaded 2-core host.
        final_timing = {}
        for runtime in ("onnxruntime", "openvino"):
            group = {label: g for label, g in timed.items() if g[0] == runtime}
            final_timing.update(time_graphs(group, frames, teacher.config.train_window_ms, config.threads,
                                            2 * config.timing_steps))
        chosen = result["models"][best]
        # `step`: the distillation steps the chosen model took since the source checkpoint.
        steps = sum(int((r.get("recovery") or {}).get("steps", 0)) for r in rounds[1:best + 1])
        save_checkpoint(tmp / "checkpoint.pt", chosen, step=steps, prune={
            "round": best, "source": str(checkpoint), "config": config.to_dict(),
            "cuts": [r["cuts"] for r in rounds[1:best + 1]]})
        summary = {
            **header, "best": best, "met": target_met(result, config),
            "base_macs": result["base_macs"], "rounds": rounds, "final_timing_ms": final_timing,
            "int8_graphs": int8_reports, "seconds": round(time.perf_counter() - started, 1),
            "recovery_seconds": round(sum((r.get("recovery") or {}).get("seconds", 0.0) for r in rounds), 1),
        }
        summary["front"] = front_rows(summary)
        write_json_atomic(tmp / "report.json", summary)
        write_text_atomic(tmp / "report.md", render_markdown(summary, header))
        plot_front(summary, tmp / "front.png")
    return summary
