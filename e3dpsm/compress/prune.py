"""Iterative structured pruning to a MACs or latency target (`e3dpsm prune`).

Round k of `rounds`: profile the current model's exported step (compress/latency.py), plan
the cuts that bring it to the round's target (compress/plan.py; the targets shrink
geometrically from the unpruned value to the final one), cut (compress/surgery.py), recover
by distillation from the unpruned model (compress/distill.py: its fused, direct and delta
poses, labels optional), then measure: export, time side by side with the unpruned graph,
held-out MPJPE, distance to the teacher. A latency target is met when *measured*; if the
last planned round misses it, extra rounds (up to `extra_rounds`) aim at the remaining
gap, corrected by how far the latency model's last prediction was off. A step of the schedule
whose target an earlier round already overshot cuts nothing and is skipped; the rounds that
cut are numbered 1, 2, ... in the order they ran (`round_target` says which target each aimed at).
"""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from e3dpsm.compress.latency import LatencyProfile, predict_ms, profile_units
from e3dpsm.compress.plan import choose, macs_per_stage, measure_candidates, total_macs
from e3dpsm.compress.surgery import prune_model
from e3dpsm.compress.importance import keep_lists
from e3dpsm.compress.units import prunable_units
from e3dpsm.errors import ConfigError
from e3dpsm.models import E3DPSM

log = logging.getLogger(__name__)
RUNTIMES: tuple[str, ...] = ("onnxruntime", "openvino")


@dataclass(frozen=True)
class PruneConfig:
    target_macs: float | None = None  # fraction of the unpruned MACs, in (0, 1)
    target_latency_ms: float | None = None  # measured fp32 step on `target_runtime`
    # Or the step as a percentage of the unpruned one, measured at the start ("60%").
    target_latency_pct: float | None = None
    target_runtime: str = "onnxruntime"
    rounds: int = 3  # planned rounds; their targets shrink geometrically to the final one
    extra_rounds: int = 2  # more rounds, only while a latency target is still missed when measured
    shrink: float = 0.5  # a candidate narrows a unit to this fraction of its width
    align: int = 4  # widths kept multiples of this, which vector kernels like (compress/plan.py)
    steps: int = 300  # distillation steps per round
    labels: str = "none"  # "gt": distil with the ground-truth poses beside the teacher's (distill.LABEL_MODES)
    budget_pct: float | None = None  # stop once held-out MPJPE exceeds the unpruned by more
    threads: int = 2  # torch threads for the rounds, and the timed runtime's, as the target device runs it
    seed: int = 0
    # Each candidate cut is judged by the pose damage it does alone, streamed causally over
    # `calib_windows` windows of `calib_frames` frames from the calibration split: enough to rank
    # the cuts, small enough that measuring every candidate of a round takes seconds.
    calib_windows: int = 4
    calib_frames: int = 8
    timing_steps: int = 200  # steps per side of the side-by-side timing that decides a latency target
    eval_frames: int = 1000  # held-out frames per sequence (each from its start)
    lr: float = 5e-4

    def __post_init__(self) -> None:
        given = [t for t in (self.target_macs, self.target_latency_ms, self.target_latency_pct) if t is not None]
        if len(given) != 1:
            raise ConfigError("give exactly one target: --target-macs FRACTION or --target-latency-ms MS (or PCT%)")
        if self.target_latency_pct is not None and not 0 < self.target_latency_pct < 100:
            raise ConfigError(f"--target-latency-ms as a percentage of the unpruned step must be in (0, 100)%, "
                              f"got {self.target_latency_pct:g}%")
        if self.target_macs is not None and not 0 < self.target_macs < 1:
            raise ConfigError(f"--target-macs is a fraction of the unpruned MACs in (0, 1), got {self.target_macs}")
        if self.target_latency_ms is not None and not self.target_latency_ms > 0:
            raise ConfigError(f"--target-latency-ms must be positive, got {self.target_latency_ms}")
        if self.target_runtime not in RUNTIMES:
            raise ConfigError(f"unknown --target-runtime {self.target_runtime!r}; choose from {list(RUNTIMES)}")
        if self.rounds < 1 or self.extra_rounds < 0 or self.steps < 0:
            raise ConfigError("--rounds must be >= 1, --extra-rounds and --steps >= 0")
        if not 0 < self.shrink < 1:
            raise ConfigError(f"--shrink must be in (0, 1), got {self.shrink}")
        if self.budget_pct is not None and not self.budget_pct > 0:
            raise ConfigError(f"--budget-pct must be positive, got {self.budget_pct}")

    @property
    def objective(self) -> str:
        return "macs" if self.target_macs is not None else "latency"

    def latency_target_ms(self, unpruned_ms: float) -> float | None:
        if self.target_latency_pct is not None:
            return self.target_latency_pct / 100.0 * unpruned_ms
        return self.target_latency_ms

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def calibration_windows(sequences, count: int, frames: int, seed: int) -> torch.Tensor:
    """[count, frames, 2, H, W] windows from evenly spaced starts of the given sequences."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        seq = sequences[k % len(sequences)]
        start = int(rng.integers(0, max(seq.frames - frames, 1)))
        out.append(np.asarray(seq.lnes[start:start + frames], dtype=np.float32))
    return torch.from_numpy(np.stack(out))


@torch.no_grad()
def stream_poses(model: E3DPSM, sequences, window_ms: float, max_frames: int, chunk: int = 40) -> list[np.ndarray]:
    """Causal fused poses [F, J, 3] of each sequence's first `max_frames` frames, one stream each."""
    model.eval()
    out = []
    for seq in sequences:
        frames, state, parts = min(seq.frames, max_frames), None, []
        for start in range(0, frames, chunk):
            x = torch.from_numpy(np.asarray(seq.lnes[start:min(start + chunk, frames)], dtype=np.float32))[None]
            pred, state = model.forward_sequence(x, causal=True, state=state, window_ms=window_ms, return_state=True)
            parts.append(pred["pose"][0].numpy())
        out.append(np.concatenate(parts))
    return out


def heldout_figures(poses: list[np.ndarray], sequences, teacher_poses: list[np.ndarray] | None,
                    action_names: tuple[str, ...] = ()) -> dict[str, float]:
    """MPJPE (mm; the evaluate command's frame-weighted and per-action-mean figures) and the
    mean joint distance to the teacher's poses."""
    from e3dpsm.evaluation.core import evaluate_predictions

    pred = np.concatenate(poses)
    n = [len(p) for p in poses]
    gt = np.concatenate([np.asarray(s.j3d_mm[:k], np.float32) for s, k in zip(sequences, n)])
    visible = np.concatenate([np.asarray(s.visible[:k]) for s, k in zip(sequences, n)])
    action = np.concatenate([np.asarray(s.action[:k], np.int64) for s, k in zip(sequences, n)])
    ids = np.concatenate([np.full(k, i) for i, k in enumerate(n)])
    # The action names group the per-action means as `e3dpsm evaluate` does (its MPJPE).
    figures = evaluate_predictions(pred, gt, visible, action, list(action_names), ids)
    out = {"mpjpe_mm": float(figures["totals"]["mpjpe"]), "mpjpe_frame_weighted_mm": float(figures["frame_weighted"]["mpjpe"]),
           "frames": int(len(pred))}
    if teacher_poses is not None:
        out["to_teacher_mm"] = float(np.linalg.norm(pred - np.concatenate(teacher_poses), axis=-1).mean())
    return out


def export_fp32(model: E3DPSM, path: Path) -> Path:
    from e3dpsm.export.onnx_export import export_step_with_report

    model.eval()
    export_step_with_report(model, path)
    return path


def time_graphs(graphs: dict[str, tuple[str, Path]], frames: np.ndarray, window_ms: float, threads: int,
                steps: int) -> dict[str, float]:
    """Median step ms of each (runtime, graph), all side by side in one interleaved run."""
    from e3dpsm.golden.verify import open_runner
    from e3dpsm.profiles.latency import measure_side_by_side
    from e3dpsm.runtime.session import CarriedStateRunner

    runners = {label: CarriedStateRunner(open_runner(path, runtime, threads=threads), window_ms)
               for label, (runtime, path) in graphs.items()}
    seconds = measure_side_by_side(runners, frames, steps, warmup=max(10, steps // 10), chunk=20)
    return {label: 1e3 * float(np.median(t)) for label, t in seconds.items()}


def _profile(graph: Path, model: E3DPSM, frames: np.ndarray, window_ms: float, config: PruneConfig,
             run_ms: float) -> LatencyProfile:
    """Shares of the step (per-unit kernels, dispatch) from ONNX Runtime's profiler, scaled to
    the step of an unprofiled run (`run_ms`, on the target runtime): profiling adds its own
    per-node cost, and on a shared CPU the two runs may see different load."""
    profile = profile_units(graph, prunable_units(model.config), frames, window_ms, config.threads,
                            steps=max(30, config.timing_steps // 4))
    return profile.scaled(run_ms)


TIMING_FRAMES = 200  # the held-out frames every side-by-side timing cycles through


def timing_frames(eval_seqs: list) -> np.ndarray:
    """The frames the rounds and the final front are timed on: the first held-out sequence's
    first TIMING_FRAMES, as float32 (the graphs' input type; the prepared frames are float16)."""
    return np.asarray(eval_seqs[0].lnes[:TIMING_FRAMES], dtype=np.float32)


def prune_loop(teacher: E3DPSM, data_dir: str | Path, eval_data, config: PruneConfig, work: Path,
               recover: Callable[[E3DPSM, E3DPSM, int], dict[str, Any]],
               eval_split: str = "all", calib_split: str = "all") -> dict[str, Any]:
    """Run the rounds; returns {"rounds": [...], "best": index, "models": [...]}.

    `recover(teacher, student, round)` fine-tunes the student in place (distillation by
    default, tests pass a no-op); `eval_data` is a PreparedData for the held-out figures.
    The rounds use `config.threads` torch threads; the caller's count comes back after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        return _prune_rounds(teacher, data_dir, eval_data, config, work, recover, eval_split, calib_split)
    finally:
        torch.set_num_threads(threads)


def _prune_rounds(teacher: E3DPSM, data_dir: str | Path, eval_data, config: PruneConfig, work: Path,
                  recover: Callable[[E3DPSM, E3DPSM, int], dict[str, Any]], eval_split: str,
                  calib_split: str) -> dict[str, Any]:
    from e3dpsm.data.prepared import PreparedData

    teacher = teacher.eval()
    window_ms = teacher.config.train_window_ms
    calib = calibration_windows(PreparedData.open(data_dir).split(calib_split), config.calib_windows,
                                config.calib_frames, config.seed)
    eval_seqs = eval_data.split(eval_split)
    frames = timing_frames(eval_seqs)
    teacher_poses = stream_poses(teacher, eval_seqs, window_ms, config.eval_frames)
    base_macs = total_macs(teacher)
    work.mkdir(parents=True, exist_ok=True)
    base_graph = export_fp32(teacher, work / "round0.onnx")
    base_runtime = "openvino" if config.target_runtime == "openvino" else "onnxruntime"
    base_ms = time_graphs({"unpruned": (base_runtime, base_graph)}, frames, window_ms, config.threads,
                          config.timing_steps)["unpruned"]
    base_profile = _profile(base_graph, teacher, frames, window_ms, config, base_ms)
    base = {"round": 0, "measured_ms": base_ms, "macs": base_macs, "macs_fraction": 1.0, "params": teacher.num_parameters(),
            "macs_per_stage": macs_per_stage(teacher), "heldout": heldout_figures(teacher_poses, eval_seqs, None, eval_data.action_names),
            "profile": base_profile.to_dict(), "graph": str(base_graph)}
    base["heldout"]["to_teacher_mm"] = 0.0
    rounds: list[dict[str, Any]] = [base]
    models: list[E3DPSM] = [teacher]
    final_target = (config.target_macs * base_macs if config.objective == "macs" else config.latency_target_ms(base_ms))
    start_value = base_macs if config.objective == "macs" else base_profile.run_ms
    student, profile, correction = copy.deepcopy(teacher), base_profile, 1.0
    total_rounds = config.rounds + config.extra_rounds
    for k in range(1, total_rounds + 1):
        t0 = time.perf_counter()
        if k <= config.rounds:
            round_target = start_value * (final_target / start_value) ** (k / config.rounds)
        else:
            round_target = final_target
        # The latency model's error last round (measured / predicted) tightens this round's aim.
        aim = round_target / correction if config.objective == "latency" else round_target
        current = total_macs(student) if config.objective == "macs" else profile.run_ms
        if current <= aim:  # an earlier round overshot this step's target: on to the next, lower one
            log.info("step %d of the schedule: already within its target", k)
            continue
        candidates = measure_candidates(student, calib, window_ms, config.shrink, config.align, profile)
        units = prunable_units(student.config)
        widths, predicted = choose(candidates, units, config.objective, current, aim, profile)
        predicted_ms = predict_ms(profile, units, widths)
        if not widths:
            log.info("step %d of the schedule: nothing left to cut", k)
            break
        number = len(rounds)
        student = prune_model(student, keep_lists(student, units, widths))
        t_plan = time.perf_counter() - t0
        recovery = recover(teacher, student, number)
        graph = export_fp32(student, work / f"round{number}.onnx")
        measured = time_graphs({"unpruned": (base_runtime, base_graph), "pruned": (base_runtime, graph)},
                               frames, window_ms, config.threads, config.timing_steps)
        # Load drift on a shared CPU: the unpruned graph, timed beside this round's, is the clock
        # every step is read against, in the units of the unpruned step measured at the start.
        corrected_ms = measured["pruned"] * base_ms / measured["unpruned"]
        profile = _profile(graph, student, frames, window_ms, config, corrected_ms)
        poses = stream_poses(student, eval_seqs, window_ms, config.eval_frames)
        record = {
            "round": number, "round_target": round_target, "aim": aim, "cuts": widths,
            "candidates": [c.to_dict() for c in candidates],
            "macs": total_macs(student), "params": student.num_parameters(), "macs_per_stage": macs_per_stage(student),
            "predicted_ms": predicted_ms,
            "measured_side_by_side_ms": measured, "profile": profile.to_dict(),
            "heldout": heldout_figures(poses, eval_seqs, teacher_poses, eval_data.action_names),
            "recovery": recovery, "seconds_plan": round(t_plan, 2), "seconds": round(time.perf_counter() - t0, 2),
            "graph": str(graph),
        }
        record["macs_fraction"] = record["macs"] / base_macs
        record["measured_load_corrected_ms"] = corrected_ms
        record["target_ms"] = config.latency_target_ms(base_ms)
        record["speedup_side_by_side"] = measured["unpruned"] / measured["pruned"]
        # The latency model's prediction for this round's graph against its measured step (both
        # in the start's units).
        record["predicted_vs_measured"] = {"predicted_ms": predicted_ms, "measured_ms": corrected_ms,
                                           "ratio": corrected_ms / predicted_ms if predicted_ms > 0 else None}
        if config.objective == "latency":
            correction = max(corrected_ms / predicted_ms, 1.0) if predicted_ms > 0 else 1.0
        rounds.append(record)
        models.append(copy.deepcopy(student).eval())
        log.info("round %d: MACs %.3f of unpruned, step %.2f ms (unpruned %.2f ms side by side), held-out MPJPE %.2f mm",
                 number, record["macs_fraction"], measured["pruned"], measured["unpruned"], record["heldout"]["mpjpe_mm"])
        if _over_budget(record, base, config):
            log.info("round %d exceeds the accuracy budget (%.1f%%): stopping", number, config.budget_pct)
            break
        if k >= config.rounds and _met(record, config):
            break
    best = _best_round(rounds, base, config)
    return {"rounds": rounds, "best": best, "models": models, "base_macs": base_macs}


def _over_budget(record: dict[str, Any], base: dict[str, Any], config: PruneConfig) -> bool:
    if config.budget_pct is None:
        return False
    return record["heldout"]["mpjpe_mm"] > base["heldout"]["mpjpe_mm"] * (1 + config.budget_pct / 100)


def _met(record: dict[str, Any], config: PruneConfig) -> bool:
    if config.objective == "macs":
        return record["macs_fraction"] <= config.target_macs + 1e-9
    return record["measured_load_corrected_ms"] <= record["target_ms"]


def _best_round(rounds: list[dict[str, Any]], base: dict[str, Any], config: PruneConfig) -> int:
    """The first round meeting the target within the budget; else the last within the budget
    (the target not met: the report says so); else round 0."""
    pruned = rounds[1:]
    within = [r for r in pruned if not _over_budget(r, base, config)]
    met = [r for r in within if _met(r, config)]
    if met:
        return met[0]["round"]
    return within[-1]["round"] if within else 0


def target_met(result: dict[str, Any], config: PruneConfig) -> bool:
    best = result["best"]
    return best > 0 and _met(result["rounds"][best], config)
