"""The pipeline's one stage table: for each stage its name, the file whose existence means it
is done, its CLI command (argv, built from the PipelineConfig) and its human- and
machine-readable reports. The runner and the report index both read this table.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from e3dpsm.errors import ConfigError
from e3dpsm.runtime.artifact_metadata import CONVERT_RECORD, CONVERTED_NAMES

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineConfig:
    out: Path
    variant: str = "small"
    # The default model trains a fixed number of steps, so every host and every rerun trains
    # the same model (seeded) and the reports of two runs compare. `minutes` instead fits the
    # steps to a time budget from a short timing probe: faster hosts train longer, and the
    # probe's noise moved the count between runs on one host (45 and 110 steps, 2026-12-02).
    train_steps: int | None = None
    minutes: float | None = None
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
    # Optional stages to run (off by default, `--with`): e.g. ("prune",).
    with_stages: tuple[str, ...] = ()
    prune_target_macs: float = 0.5
    prune_steps: int = 100

    def __post_init__(self) -> None:
        if self.train_steps is not None and self.minutes is not None:
            raise ConfigError("give the training either --train-steps or --minutes, not both")
        if self.train_steps is not None and self.train_steps < 1:
            raise ConfigError(f"--train-steps must be positive, got {self.train_steps}")
        if self.minutes is not None and self.minutes <= 0:
            raise ConfigError(f"--minutes must be positive, got {self.minutes}")

    @property
    def train_budget_s(self) -> float:
        # About half the budget trains; the other stages are sized to fit the rest.
        return max(30.0, 0.5 * (self.minutes or 0.0) * 60.0)


@dataclass(frozen=True)
class Stage:
    """Paths are relative to the pipeline's output folder."""
    name: str
    marker: str                                  # exists once the stage is done
    human_report: str                            # what the index links for a reader
    machine_report: str                          # the JSON a tool reads (the same file for some stages)
    argv: Callable[[PipelineConfig], list[str]]  # the CLI command of the stage
    optional: bool = False                       # runs only when named in --with (or --only)


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
# The optional edge stages convert to these formats (`e3dpsm convert`, docs/edge.md), each into
# edge/<format>/: the artifact and its record, under the names the convert command writes.
EDGE_FORMATS = ("executorch", "litert")
EDGE_ARTIFACTS = {fmt: f"edge/{fmt}/{CONVERTED_NAMES[fmt]}" for fmt in EDGE_FORMATS}
EDGE_RECORDS = {fmt: f"edge/{fmt}/{CONVERT_RECORD}" for fmt in EDGE_FORMATS}
# `--with edge` names the three edge stages at once.
STAGE_GROUPS = {"edge": ("executorch", "litert", "edge-check")}


def expand_stage_names(names: tuple[str, ...] | list[str]) -> list[str]:
    """Stage names with each group (STAGE_GROUPS) replaced by its stages, order kept."""
    return list(dict.fromkeys(n for name in names for n in STAGE_GROUPS.get(name, (name,))))


def edge_artifacts(cfg: PipelineConfig) -> list[str]:
    """The edge artifacts the optional stages have written so far, in EDGE_ARTIFACTS' order."""
    return [_p(cfg, rel) for rel in EDGE_ARTIFACTS.values() if (cfg.out / rel).is_file()]


def _edge_convert_stage(fmt: str) -> Stage:
    record = EDGE_RECORDS[fmt]
    return Stage(fmt, record, record, record, lambda c: [
        "convert", fmt, "--checkpoint", _ckpt(c), "--out", _p(c, str(Path(record).parent)), "--force"], optional=True)


def _edge_check_argv(cfg: PipelineConfig) -> list[str]:
    models = edge_artifacts(cfg)
    if not models:
        raise ConfigError("edge-check has no artifact to check: run it with --with executorch and/or litert "
                          "(or --with edge)")
    return ["golden", "check", "--model", *models, "--golden", _p(cfg, "golden/record"), "--threads",
            str(cfg.threads), "--out", _p(cfg, "edge/checks")]


def _held_out_events(cfg: PipelineConfig) -> str:
    """The first test sequence's event file (the split files `synth` writes)."""
    split = cfg.out / "data" / "test.txt"
    names = split.read_text().split() if split.is_file() else []
    if not names:
        raise ConfigError(f"{split} names no test sequence; rerun the synth stage")
    return str(cfg.out / "data" / names[0] / "events.h5")


# About 4 minutes of training for `small` on two cores (1.9 s a step on an AVX-512 VNNI host,
# ~2.5 on an AVX2 one); what `--minutes 10` gave there.
DEFAULT_TRAIN_STEPS = 120


def train_steps(cfg: PipelineConfig) -> int:
    """The training stage's steps: given, fitted to `--minutes`, or the fixed default."""
    if cfg.train_steps is not None:
        return cfg.train_steps
    if cfg.minutes is not None:
        return estimate_train_steps(cfg)
    return DEFAULT_TRAIN_STEPS


def _train_argv(cfg: PipelineConfig) -> list[str]:
    steps = train_steps(cfg)
    return ["train", "--variant", cfg.variant, "--data", _p(cfg, "prepared"), "--out", _p(cfg, "train"),
            "--steps", str(steps), "--seq-len", str(cfg.seq_len), "--batch-size", str(cfg.batch_size),
            "--seed", str(cfg.seed), "--threads", str(cfg.threads), "--force"]


def _quantize(mode: str) -> Callable[[PipelineConfig], list[str]]:
    def argv(cfg: PipelineConfig) -> list[str]:
        # Calibration on `train`, the search on `val`, the budget's final check on `test`,
        # the split the golden check runs on too.
        return ["quantize", "--model", _p(cfg, GRAPH), "--data", _p(cfg, "prepared"), "--out",
                _p(cfg, f"quantize/{mode}"), "--mode", mode, "--threads", str(cfg.threads), "--force",
                "--runtimes", *checked_runtimes()]
    return argv


def checked_runtimes() -> list[str]:
    """The runtimes the golden check runs the graphs on, so the quantised graphs' budgets are
    checked on each (`quantize --runtimes`): an INT8 graph searched on ONNX Runtime alone was
    0.75% from fp32 there and 2.2% on OpenVINO, and failed its golden check there (2026-12-03).
    OpenVINO is an optional extra; where it is not available the golden check skips it, by
    the same test."""
    from e3dpsm.runtime.openvino_session import openvino_available

    return ["onnxruntime", *(["openvino"] if openvino_available()[0] else [])]


STAGES: tuple[Stage, ...] = (
    Stage("synth", "data/report.json", "data/report.json", "data/report.json", lambda c: [
        "synth", "--out", _p(c, "data"), "--sequences", str(c.sequences), "--seconds", str(c.seconds),
        "--seed", str(c.seed), "--preview", "--force"]),
    Stage("prepare", "prepared/report.json", "prepared/report.json", "prepared/report.json", lambda c: [
        "prepare", "--data", _p(c, "data"), "--out", _p(c, "prepared"), "--window-ms", f"{c.window_ms:g}",
        *_frame_args(c), "--force"]),
    # train/report.json is written when the run ends; the log grows while it runs.
    Stage("train", "train/report.json", "train/log.jsonl", "train/report.json", _train_argv),
    Stage("evaluate", "evaluate/metrics.json", "evaluate/metrics.md", "evaluate/metrics.json", lambda c: [
        "evaluate", "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--out", _p(c, "evaluate"),
        "--split", "test", "--causal", "--threads", str(c.threads), "--force"]),
    Stage("export", GRAPH, "export/export.json", "export/export.json", lambda c: [
        "export", "--checkpoint", _ckpt(c), "--out", _p(c, "export"), "--force"]),
    Stage("parity", "parity/report.json", "parity/report.json", "parity/report.json", lambda c: [
        "parity", "--model", _p(c, GRAPH), "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"),
        "--split", "test", "--steps", str(c.parity_steps), "--window-ms", "20", "25", "50",
        "--threads", str(c.threads), "--report", _p(c, "parity/report.json")]),
    Stage("quantize-int8", INT8, "quantize/int8/report.md", "quantize/int8/report.json", _quantize("int8")),
    Stage("quantize-fp16", FP16, "quantize/fp16/report.json", "quantize/fp16/report.json", _quantize("fp16")),
    Stage("quantize-int8-dynamic", INT8_DYNAMIC, "quantize/int8-dynamic/report.json",
          "quantize/int8-dynamic/report.json", _quantize("int8-dynamic")),
    Stage("validate", "validate/report.json", "validate/validation.md", "validate/report.json", lambda c: [
        "validate", "--models", _p(c, GRAPH), _p(c, INT8), _p(c, FP16), _p(c, INT8_DYNAMIC),
        "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--split", "test",
        "--out", _p(c, "validate"), "--threads", str(c.threads), "--force"]),
    Stage("golden-record", "golden/record/golden.json", "golden/record/golden.json",
          "golden/record/golden.json", lambda c: [
        "golden", "record", "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--split", "test",
        "--steps", str(c.golden_steps), "--threads", str(c.threads), "--out", _p(c, "golden/record"), "--force",
        # the host's rollouts of the compressed graphs: a device checks that it computes the same
        "--also", _p(c, INT8), _p(c, FP16), _p(c, INT8_DYNAMIC), "--also-runtime", *checked_runtimes()]),
    # Every graph on both runtimes, torch-free, as a device would check them; verdicts go to
    # the report (a failing compressed graph is a finding of the run, not a crash).
    Stage("golden-check", "golden/checks/summary.json", "golden/checks/summary.md",
          "golden/checks/summary.json", lambda c: [
        "golden", "check", "--model", _p(c, GRAPH), _p(c, INT8), _p(c, FP16), _p(c, INT8_DYNAMIC),
        "--runtime", "onnxruntime", "openvino", "--golden", _p(c, "golden/record"), "--threads", str(c.threads),
        "--out", _p(c, "golden/checks"), "--exit-zero"]),
    # A clip to watch: the held-out sequence streamed through the fp32 graph, torch-free.
    Stage("clip", "clip/poses.gif", "clip/poses.gif", "clip/poses.report.json", lambda c: [
        "run", "--model", _p(c, GRAPH), "--events", _held_out_events(c), "--out", _p(c, "clip/poses.csv"),
        "--render", _p(c, "clip/poses.gif"), "--render-max-frames", "100", "--threads", str(c.threads),
        "--no-progress", "--force"]),
    # Off by default: structured pruning of the checkpoint to half its MACs, recovered by
    # distillation on the training data, judged on the held-out split.
    Stage("prune", "prune/report.json", "prune/report.md", "prune/report.json", lambda c: [
        "prune", "--checkpoint", _ckpt(c), "--data", _p(c, "prepared"), "--eval-data", _p(c, "prepared"),
        "--eval-split", "test", "--out", _p(c, "prune"), "--target-macs", str(c.prune_target_macs),
        "--rounds", "1", "--steps", str(c.prune_steps), "--threads", str(c.threads), "--force", "--no-progress"],
        optional=True),
    # Off by default: the checkpoint as fp32 ExecuTorch and LiteRT artifacts (XNNPACK), each
    # checked against the golden rollout with its own runtime carrying the states, and
    # profiled beside the ONNX graphs (`--with edge`).
    *(_edge_convert_stage(fmt) for fmt in EDGE_FORMATS),
    Stage("edge-check", "edge/checks/summary.json", "edge/checks/summary.md", "edge/checks/summary.json",
          _edge_check_argv, optional=True),
    Stage("profile", "profile/report.json", "profile/report.md", "profile/report.json", lambda c: [
        "profile", "--checkpoint", _ckpt(c), "--targets", "all", "--int8-model", _p(c, INT8),
        "--fp16-model", _p(c, FP16), "--data", _p(c, "prepared"), "--steps", str(c.profile_steps),
        "--threads", str(c.threads), "--out", _p(c, "profile"), "--force",
        *(["--edge-models", *edge] if (edge := edge_artifacts(c)) else [])]),
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
