"""The main job: synth -> prepare -> train -> evaluate -> export -> parity -> quantize ->
validate -> profile -> report, on the embedded default (synthetic data, small model).

Each stage is one CLI command run in-process; a stage whose marker file exists is not
redone on a rerun, so an interrupted pipeline resumes where it stopped.
"""
from __future__ import annotations

import logging
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from e3dpsm.errors import ConfigError, E3DPSMError

log = logging.getLogger(__name__)


class StageFailed(E3DPSMError):
    """A pipeline stage exited non-zero."""


@dataclass(frozen=True)
class PipelineConfig:
    out: Path
    variant: str = "small"
    minutes: float = 10.0
    seed: int = 0
    sequences: int = 5          # 3 train, 1 val (calibration check), 1 test (held out)
    seconds: float = 4.0
    window_ms: float = 20.0
    seq_len: int = 16
    batch_size: int = 4
    threads: int = 2
    parity_steps: int = 300
    golden_steps: int = 200
    profile_steps: int = 300
    checkpoint: Path | None = None  # a trained or imported checkpoint: no training stage

    @property
    def train_budget_s(self) -> float:
        # About half the budget trains; the other stages are sized to fit the rest.
        return max(30.0, 0.5 * self.minutes * 60.0)


@dataclass(frozen=True)
class Stage:
    name: str
    marker: str                                  # relative path that exists once the stage is done
    argv: Callable[[PipelineConfig], list[str]]  # the CLI command of the stage


def _p(cfg: PipelineConfig, rel: str) -> str:
    return str(cfg.out / rel)


def _ckpt(cfg: PipelineConfig) -> str:
    return str(cfg.checkpoint) if cfg.checkpoint else _p(cfg, CHECKPOINT)


def _frame_args(cfg: PipelineConfig) -> list[str]:
    """Prepare the data at the given checkpoint's resolution (the variants' own by default)."""
    if not cfg.checkpoint:
        return []
    from e3dpsm.checkpoint import read_checkpoint

    model_cfg = read_checkpoint(cfg.checkpoint)["config"]
    return ["--height", str(model_cfg["height"]), "--width", str(model_cfg["width"])]


CHECKPOINT = "train/checkpoint.pt"
GRAPH = "export/step.onnx"
INT8 = "quantize/int8/step_int8.onnx"
FP16 = "quantize/fp16/step_fp16.onnx"
INT8_DYNAMIC = "quantize/int8-dynamic/step_int8_dynamic.onnx"


def _held_out_events(cfg: PipelineConfig) -> str:
    """The first test sequence's event file (the split files `synth` writes)."""
    split = cfg.out / "data" / "test.txt"
    names = split.read_text().split() if split.is_file() else []
    if not names:
        raise ConfigError(f"{split} names no test sequence; rerun the synth stage")
    return str(cfg.out / "data" / names[0] / "events.h5")


def _train_argv(cfg: PipelineConfig) -> list[str]:
    steps = estimate_train_steps(cfg)
    return ["train", "--variant", cfg.variant, "--data", _p(cfg, "prepared"), "--out", _p(cfg, "train"),
            "--steps", str(steps), "--seq-len", str(cfg.seq_len), "--batch-size", str(cfg.batch_size),
            "--seed", str(cfg.seed), "--threads", str(cfg.threads), "--force"]


def _quantize(mode: str) -> Callable[[PipelineConfig], list[str]]:
    def argv(cfg: PipelineConfig) -> list[str]:
        extra = ["--frames", "200", "--holdout-frames", "100"] if mode == "int8" else []
        return ["quantize", "--model", _p(cfg, GRAPH), "--data", _p(cfg, "prepared"), "--out",
                _p(cfg, f"quantize/{mode}"), "--mode", mode, "--threads", str(cfg.threads), "--force", *extra]
    return argv


STAGES: tuple[Stage, ...] = (
    Stage("synth", "data/report.json", lambda c: [
        "synth", "--out", _p(c, "data"), "--sequences", str(c.sequences), "--seconds", str(c.seconds),
        "--seed", str(c.seed), "--preview", "--force"]),
    Stage("prepare", "prepared/report.json", lambda c: [
        "prepare", "--data", _p(c, "data"), "--out", _p(c, "prepared"), "--window-ms", f"{c.window_ms:g}",
        *_frame_args(c), "--force"]),
    Stage("train", "train/report.json", _train_argv),  # written when the run ends
    Stage("evaluate", "evaluate/metrics.json", lambda c: [
        "evaluate", "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--out", _p(c, "evaluate"),
        "--split", "test", "--causal", "--threads", str(c.threads), "--force"]),
    Stage("export", GRAPH, lambda c: [
        "export", "--checkpoint", _ckpt(c), "--out", _p(c, "export"), "--force"]),
    Stage("parity", "parity/report.json", lambda c: [
        "parity", "--model", _p(c, GRAPH), "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"),
        "--split", "test", "--steps", str(c.parity_steps), "--window-ms", "20", "25", "50",
        "--threads", str(c.threads), "--report", _p(c, "parity/report.json")]),
    Stage("quantize-int8", INT8, _quantize("int8")),
    Stage("quantize-fp16", FP16, _quantize("fp16")),
    Stage("quantize-int8-dynamic", INT8_DYNAMIC, _quantize("int8-dynamic")),
    Stage("validate", "validate/report.json", lambda c: [
        "validate", "--models", _p(c, GRAPH), _p(c, INT8), _p(c, FP16), _p(c, INT8_DYNAMIC),
        "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--split", "test",
        "--out", _p(c, "validate"), "--threads", str(c.threads), "--force"]),
    Stage("golden-record", "golden/record/golden.json", lambda c: [
        "golden", "record", "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--split", "test",
        "--steps", str(c.golden_steps), "--threads", str(c.threads), "--out", _p(c, "golden/record"), "--force"]),
    # Every graph on both runtimes, torch-free, as a device would check them; verdicts go to
    # the report (a failing compressed graph is a finding of the run, not a crash).
    Stage("golden-check", "golden/checks/summary.json", lambda c: [
        "golden", "check", "--model", _p(c, GRAPH), _p(c, INT8), _p(c, FP16), _p(c, INT8_DYNAMIC),
        "--runtime", "onnxruntime", "openvino", "--golden", _p(c, "golden/record"), "--threads", str(c.threads),
        "--out", _p(c, "golden/checks"), "--exit-zero"]),
    # A clip to watch: the held-out sequence streamed through the fp32 graph, torch-free.
    Stage("clip", "clip/poses.gif", lambda c: [
        "run", "--model", _p(c, GRAPH), "--events", _held_out_events(c), "--out", _p(c, "clip/poses.csv"),
        "--render", _p(c, "clip/poses.gif"), "--render-max-frames", "100", "--threads", str(c.threads),
        "--no-progress", "--force"]),
    Stage("profile", "profile/report.json", lambda c: [
        "profile", "--checkpoint", _ckpt(c), "--targets", "all", "--int8-model", _p(c, INT8),
        "--fp16-model", _p(c, FP16), "--data", _p(c, "prepared"), "--steps", str(c.profile_steps),
        "--threads", str(c.threads), "--out", _p(c, "profile"), "--force"]),
)


def estimate_train_steps(cfg: PipelineConfig, probe_steps: int = 3) -> int:
    """Training steps that fit the time budget, from a short timing probe of the same model,
    batch and window length (forward and backward, the optimizer's cost is negligible)."""
    import torch

    import e3dpsm

    torch.set_num_threads(cfg.threads)
    model = e3dpsm.create_model(cfg.variant).train()
    lnes = (torch.rand(cfg.batch_size, cfg.seq_len, 2, model.config.height, model.config.width) < 0.03).float()
    timings = []
    for _ in range(probe_steps + 1):
        start = time.perf_counter()
        out = model.forward_sequence(lnes, causal=False)
        sum(v.square().mean() for v in out.values()).backward()
        timings.append(time.perf_counter() - start)
    per_step = sorted(timings[1:])[len(timings[1:]) // 2] * 1.15  # + data loading, optimizer, logging
    steps = int(cfg.train_budget_s / per_step)
    log.info("training budget %.0f s at ~%.2f s/step -> %d steps", cfg.train_budget_s, per_step, steps)
    return max(20, steps)


def run_stage(argv: list[str]) -> int:
    """One stage in its own process, as a user would run it: thread pools, environment and
    memory start clean (an OpenMP pool left busy by training would slow the next stage)."""
    return subprocess.run([sys.executable, "-m", "e3dpsm", *argv], check=False).returncode


def run_pipeline(cfg: PipelineConfig, only: list[str] | None = None) -> list[dict]:
    from e3dpsm.pipeline_report import write_index

    if cfg.variant not in ("tiny", "small", "paper"):
        raise ConfigError(f"unknown variant {cfg.variant!r}; use tiny, small or paper")
    if cfg.checkpoint:
        from e3dpsm.checkpoint import read_checkpoint

        read_checkpoint(cfg.checkpoint)  # a clear error now, not at the evaluate stage
    cfg.out.mkdir(parents=True, exist_ok=True)
    done: list[dict] = []
    names = [s.name for s in STAGES]
    unknown = sorted(set(only or []) - set(names))
    if unknown:
        raise ConfigError(f"unknown stages {unknown}; stages: {', '.join(names)}")
    for index, stage in enumerate(STAGES, 1):
        marker = cfg.out / stage.marker
        header = f"[{index}/{len(STAGES)}] {stage.name}"
        if stage.name == "train" and cfg.checkpoint:
            log.info("%s: skipped, --checkpoint %s given", header, cfg.checkpoint)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        if (only and stage.name not in only) or (marker.exists() and not only):
            log.info("%s: done before, skipped (%s exists)", header, stage.marker)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        argv = stage.argv(cfg)
        log.info("%s: e3dpsm %s", header, " ".join(argv))
        start = time.perf_counter()
        code = run_stage(argv)
        seconds = time.perf_counter() - start
        if code != 0:
            raise StageFailed(f"stage {stage.name} failed (exit {code}); fix it and rerun: finished stages are kept")
        done.append({"stage": stage.name, "status": "ran", "seconds": round(seconds, 1)})
        log.info("%s: finished in %.0f s", header, seconds)
    write_index(cfg.out, asdict(cfg), done)
    return done
