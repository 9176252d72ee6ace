"""The run behind `e3dpsm distill`: load the teacher, build or load the student, distil, write

    OUT/checkpoint.pt  the student (config inside: rebuilds alone), with the teacher's path and
                       sha256, the distillation config and the data in its extras
    OUT/report.json    report header + config + the distillation summary (timing, loss log)
    OUT/report.md      the same for a person
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import torch

from e3dpsm.checkpoint import load_checkpoint, save_checkpoint
from e3dpsm.compress.distill import DistillConfig, check_pair, distill
from e3dpsm.errors import ConfigError, OutputExistsError
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import check_writable_folder, write_json_atomic, write_text_atomic

CHECKPOINT_NAME = "checkpoint.pt"
REPORT_NAME = "report.json"
MARKDOWN_NAME = "report.md"
_ARTIFACTS = (CHECKPOINT_NAME, REPORT_NAME, MARKDOWN_NAME)


def prepare_out_dir(out: Path, force: bool) -> None:
    """As `train` treats its run folder: refuse one that holds a run unless `force` (then the
    old artifacts go only when the new ones are written, each by an atomic rename), and one it
    could not write to. Nothing is made yet: a run refused later leaves no empty folder."""
    held = [name for name in _ARTIFACTS if (out / name).exists()]
    if held and not force:
        raise OutputExistsError(f"{out} holds a run ({', '.join(held)}); pass --force to replace it or choose another --out")
    check_writable_folder(out)


def sha256_file(path: str | os.PathLike) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def build_student(spec: str, teacher: Any) -> tuple[Any, str]:
    """(model, "variant" | "checkpoint"): a registered variant name builds a fresh variant at
    the teacher's input size and training window; anything else must be a checkpoint file."""
    from e3dpsm.models import create_model, list_models

    if spec in list_models():
        cfg = teacher.config
        return create_model(spec, height=cfg.height, width=cfg.width, in_channels=cfg.in_channels,
                            num_joints=cfg.num_joints, train_window_ms=cfg.train_window_ms), "variant"
    if not Path(spec).is_file():
        raise ConfigError(f"--student {spec!r} is neither a variant ({', '.join(list_models())}) nor a checkpoint file")
    model, _ = load_checkpoint(spec)
    return model, "checkpoint"


def run_distill(teacher_path: str | os.PathLike, student_spec: str, data_dir: str | os.PathLike,
                out: str | os.PathLike, config: DistillConfig, *, split: str | None = None,
                force: bool = False, progress: bool = True, device: str = "cpu") -> dict[str, Any]:
    """Distil and write OUT; returns the report. `config.prior` applies as given (the CLI
    defaults it to "data" for a fresh variant, "keep" for a checkpoint). `device`: where both
    models run ("auto", "cpu", "cuda"); the student is written from the CPU either way."""
    from e3dpsm.models import list_models
    from e3dpsm.training.distributed import resolve_device

    where = resolve_device(device)  # refuse a missing GPU before reading anything

    if config.qat_ranges_only and student_spec in list_models():
        raise ConfigError(f"--qat-ranges-only learns INT8 ranges for a trained model and keeps its weights; "
                          f"--student {student_spec} is a fresh variant: give a checkpoint (e.g. the teacher's)")
    out = Path(out)
    prepare_out_dir(out, force)  # refuse before the long run, not after
    teacher, teacher_payload = load_checkpoint(teacher_path)
    student, student_kind = build_student(student_spec, teacher)
    check_pair(teacher, student)
    summary = distill(teacher.to(where), student.to(where), data_dir, config, split=split, progress=progress)
    student.cpu()
    summary["device"] = str(where) if where.type == "cpu" else f"{where} ({torch.cuda.get_device_name(where)})"
    teacher_info = {"path": str(teacher_path), "sha256": sha256_file(teacher_path),
                    "variant": teacher.config.variant, "train_step": teacher_payload.get("step")}
    student_info = {"source": student_kind, "spec": student_spec, "variant": student.config.variant}
    # train_args: the fields evaluate and `train --init-from` read (window length of non-causal runs).
    train_args = {"variant": student.config.variant, "steps": config.steps, "seq_len": config.seq_len,
                  "batch_size": config.batch_size, "lr": config.lr, "warmup_steps": config.warmup_steps,
                  "min_lr_ratio": config.min_lr_ratio, "clip_norm": config.clip_norm, "seed": config.seed,
                  "split": summary["split"]}
    header = report_header("distill", {"teacher": str(teacher_path), "student": student_spec, "data": str(data_dir),
                                       "split": summary["split"], "distill": config.to_dict()})
    qat = {"qat_ranges": summary["qat_ranges"]} if "qat_ranges" in summary else {}
    report = {**header, **{k: v for k, v in summary.items() if k not in ("teacher", "student", "config", "qat_ranges")},
              "teacher": {**teacher_info, **summary["teacher"]}, "student": {**student_info, **summary["student"]},
              "checkpoint": str(out / CHECKPOINT_NAME),
              **({"qat_ranges_learned": len(qat["qat_ranges"]["quantizers"])} if qat else {})}
    markdown = report_markdown(report)  # everything built before the first write
    save_checkpoint(out / CHECKPOINT_NAME, student.eval(), step=config.steps, window_ms=summary["window_ms"],
                    data=str(data_dir), train_args=train_args, teacher=teacher_info, student_source=student_info,
                    distill_config=config.to_dict(), **qat)
    write_json_atomic(out / REPORT_NAME, report)
    write_text_atomic(out / MARKDOWN_NAME, markdown)
    return report


def report_markdown(report: dict[str, Any]) -> str:
    teacher, student, cfg = report["teacher"], report["student"], report["config"]["distill"]
    terms = [k for k in ("loss", "fused", "direct", "delta", "labels") if k in report["final"]]
    lines = [
        f"# Distillation: {teacher['variant']} -> {student['variant']}", "",
        f"- teacher: `{teacher['path']}` (sha256 `{teacher['sha256'][:16]}...`, "
        f"{teacher['parameters']:,} parameters)",
        f"- student: {student['source']} `{student['spec']}` ({student['parameters']:,} parameters), "
        f"prior `{report['prior']}`",
        f"- data: `{report['data']}` split `{report['split']}`, {report['windows']:,} windows of "
        f"{cfg['seq_len']} frames, {report['window_ms']:g} ms; labels `{cfg['labels']}`, "
        f"{'causal' if cfg['causal'] else 'non-causal'}"
        + (f"; states carried over {cfg['stream_windows']} consecutive windows per lane"
           if cfg.get("stream_windows", 1) > 1 else ""),
        *([_qat_line(cfg, report.get("qat_range_start", {}))] if cfg.get("qat") else []),
        f"- {report['steps']} steps x {cfg['batch_size']} windows in {report['seconds']:.1f} s "
        f"({report['seconds_per_step']:.3f} s/step) on {report.get('device', 'cpu')}; CPU {report['machine'].get('cpu_model', '?')}, "
        f"ISA `{report['machine'].get('isa', {}).get('kind', '?')}`",
        "", "Loss terms (mm, Charbonnier distance per joint; `labels`: the paper's loss):", "",
        "| step | lr | " + " | ".join(terms) + " |", "|---:|---:|" + "---:|" * len(terms),
    ]
    for record in _thin(report["log"], 12):
        lines.append(f"| {record['step']} | {record['lr']:.2e} | " + " | ".join(f"{record[t]:.3f}" for t in terms) + " |")
    return "\n".join(lines) + "\n"


def _qat_line(cfg: dict[str, Any], start: dict[str, Any]) -> str:
    from e3dpsm.compress.distill import DistillConfig

    full = bool(cfg.get("qat_full_integer"))
    outputs = DistillConfig(**cfg).qat_config.simulated_float_outputs
    bits = f", {start['weight_bits']}-bit weights" if "weight_bits" in start else ""
    line = f"- QAT: the {'full-integer' if full else 'default'} INT8 graph simulated (`--float-outputs {outputs}`{bits})"
    if start.get("calibrated"):
        line += (f"; {start['calibrated']} of {start['quantizers']} learned ranges started from `{start['rule']}` "
                 f"calibration on {start['windows']} windows of {start['frames_per_window']} frames")
    else:
        line += "; learned ranges started from the first batch each quantiser saw"
    if cfg.get("qat_ranges_only"):
        line += "; the ranges alone learned, the student's weights and prior kept (its fp32 graph unchanged)"
    return line


def _thin(records: list[dict[str, Any]], keep: int) -> list[dict[str, Any]]:
    """About `keep` records, evenly spaced, first and last included."""
    if len(records) <= keep:
        return records
    stride = -(-len(records) // (keep - 1))
    return records[::stride] + ([records[-1]] if (len(records) - 1) % stride else [])
