"""The pieces of `e3dpsm prune` (compress/prune.py, compress/run.py) on the trained tiny, fast.

The rounds run for real (candidates measured, planned, cut), but on a simulated host: a
graph's step costs a fixed time per MAC, each side-by-side run has its own load, and the
per-unit profile is a fixed share of the step. Every figure a round records is then known in
closed form: the geometric schedule of targets, the load-corrected step, the latency model's
correction of the next aim, the stopping rules and the round chosen.
"""
from __future__ import annotations

import json
import re
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from e3dpsm.compress import prune as prune_module
from e3dpsm.compress import run as run_module
from e3dpsm.compress.latency import LatencyProfile, UnitLatency
from e3dpsm.compress.plan import total_macs
from e3dpsm.compress.prune import (PruneConfig, _best_round, _met, _over_budget, calibration_windows,
                                   heldout_figures, prune_loop, stream_poses, target_met)
from e3dpsm.compress.units import prunable_units
from e3dpsm.errors import ConfigError
from tests._quantize_helpers import TRAINED_TINY

MS_PER_MMAC = 0.01  # the simulated host: 0.01 ms per million MACs (a sub-millisecond tiny, as fast hosts run it)
KERNEL_SHARE = 0.9  # of the step, spread evenly over the prunable units


class SimulatedHost:
    """Stands in for export, side-by-side timing and ONNX Runtime's per-unit profile."""

    def __init__(self, loads: list[float]) -> None:
        self.loads = list(loads)  # one per side-by-side run, in call order; 1.0 after
        self.timed: list[dict[str, float]] = []
        self.runtimes: set[str] = set()
        self.frames: list[tuple[int, np.dtype]] = []  # (rows, dtype) of each timing's frames

    @staticmethod
    def step_ms(graph: Path) -> float:
        return json.loads(Path(graph).read_text())["macs"] / 1e6 * MS_PER_MMAC

    def export(self, model, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"macs": total_macs(model)}))
        return path

    def time(self, graphs, frames, window_ms, threads, steps) -> dict[str, float]:
        load = self.loads.pop(0) if self.loads else 1.0
        out = {label: load * self.step_ms(path) for label, (_, path) in graphs.items()}
        self.timed.append(out)
        self.runtimes |= {runtime for runtime, _ in graphs.values()}
        self.frames.append((frames.shape[0], frames.dtype))
        return out

    @staticmethod
    def profile(graph, model, frames, window_ms, config, run_ms) -> LatencyProfile:
        units = prunable_units(model.config)
        share = KERNEL_SHARE * run_ms / len(units)
        return LatencyProfile(run_ms, KERNEL_SHARE * run_ms, 4 * len(units),
                              {u.name: UnitLatency(share, 3) for u in units})


def _simulated(monkeypatch, loads: list[float] = (), front: bool = False) -> SimulatedHost:
    """A SimulatedHost standing in for the rounds' export, timing and profile (and, with
    `front`, for run_prune's final side-by-side timing too)."""
    host = SimulatedHost(list(loads))
    monkeypatch.setattr(prune_module, "export_fp32", host.export)
    monkeypatch.setattr(prune_module, "time_graphs", host.time)
    monkeypatch.setattr(prune_module, "_profile", host.profile)
    if front:
        monkeypatch.setattr(run_module, "time_graphs", host.time)
    return host


@pytest.fixture(scope="module")
def teacher():
    from e3dpsm.checkpoint import load_checkpoint

    model, _ = load_checkpoint(TRAINED_TINY, variant="tiny")
    return model.eval()


@pytest.fixture(scope="module")
def held_out(quant_data):
    from e3dpsm.data.prepared import PreparedData

    return PreparedData.open(quant_data)


def _run_loop(monkeypatch, teacher, quant_data, held_out, config, loads, tmp_path, heldout=None,
              work: Path | None = None):
    host = _simulated(monkeypatch, loads)
    if heldout is not None:
        monkeypatch.setattr(prune_module, "heldout_figures", heldout)
    recovered: list[int] = []

    def recover(teacher_model, student, round_index):
        assert teacher_model is teacher and student is not teacher
        recovered.append(round_index)
        return {"steps": 10 * round_index, "seconds": 0.5}

    started = time.perf_counter()
    result = prune_loop(teacher, quant_data, held_out, config, work or tmp_path / "graphs", recover, eval_split="test")
    # The rounds' own seconds add up to no more than the loop took, on the same clock.
    assert sum(r["seconds"] for r in result["rounds"][1:]) <= time.perf_counter() - started + 0.01 * len(result["rounds"])
    return result, host, recovered


def _fast(**fields) -> PruneConfig:
    fields = {"threads": 1, "calib_windows": 1, "calib_frames": 2, "eval_frames": 6, "timing_steps": 10, **fields}
    return PruneConfig(**fields)


def _record(k: int, mpjpe: float, fraction: float = 1.0, corrected: float = 10.0, target: float = 8.0) -> dict:
    return {"round": k, "heldout": {"mpjpe_mm": mpjpe}, "macs_fraction": fraction,
            "measured_load_corrected_ms": corrected, "target_ms": target}


def test_the_budget_the_target_and_the_chosen_round_by_hand() -> None:
    base = _record(0, 100.0)
    budget = PruneConfig(target_macs=0.5, budget_pct=2.0)
    assert not _over_budget(_record(1, 102.0), base, budget)
    assert _over_budget(_record(1, 102.001), base, budget)
    assert not _over_budget(_record(1, 1e9), base, PruneConfig(target_macs=0.5))
    assert _met(_record(1, 0, fraction=0.5), budget) and _met(_record(1, 0, fraction=0.5 + 5e-10), budget)
    assert not _met(_record(1, 0, fraction=0.5001), budget)
    assert _met(_record(1, 0, fraction=0.5 + 1e-9), budget) and not _met(_record(1, 0, fraction=0.5 + 1.5e-9), budget)
    latency = PruneConfig(target_latency_ms=8.0, budget_pct=2.0)
    assert _met(_record(1, 0, corrected=8.0), latency) and not _met(_record(1, 0, corrected=8.01), latency)
    # The first round that meets the target within the budget...
    rounds = [base, _record(1, 101.0, 0.8), _record(2, 101.5, 0.5), _record(3, 101.9, 0.4)]
    assert _best_round(rounds, base, budget) == 2
    # ...a met round over the budget does not count, the last within it is chosen...
    rounds = [base, _record(1, 101.0, 0.8), _record(2, 103.0, 0.5), _record(3, 101.9, 0.6)]
    assert _best_round(rounds, base, budget) == 3
    assert _best_round([base, _record(1, 100.5, 0.5), _record(2, 101.0, 0.4)], base, budget) == 1
    # ...the last of several within it when none meets the target...
    rounds = [base, _record(1, 101.0, 0.8), _record(2, 101.5, 0.7), _record(3, 101.9, 0.6)]
    assert _best_round(rounds, base, budget) == 3
    # ...and with none within it, the unpruned model.
    assert _best_round([base, _record(1, 105.0, 0.4)], base, budget) == 0
    assert not target_met({"rounds": [base], "best": 0}, budget)
    assert not target_met({"rounds": [_record(0, 100.0, 0.4)], "best": 0}, budget)  # round 0 is never a cut
    assert target_met({"rounds": [base, _record(1, 100.0, 0.5)], "best": 1}, budget)


ONE_TARGET = "give exactly one target: --target-macs FRACTION or --target-latency-ms MS (or PCT%)"
PCT = "--target-latency-ms as a percentage of the unpruned step must be in (0, 100)%, got "
STEPS = "--rounds must be >= 1, --extra-rounds and --steps >= 0"


@pytest.mark.parametrize("fields, message", [
    ({"target_latency_pct": 100.0}, PCT + "100%"),
    ({"target_latency_pct": 0.0}, PCT + "0%"),
    ({"target_macs": 1.0}, "--target-macs is a fraction of the unpruned MACs in (0, 1), got 1.0"),
    ({"target_macs": 0.0}, "--target-macs is a fraction of the unpruned MACs in (0, 1), got 0.0"),
    ({"target_latency_ms": 0.0}, "--target-latency-ms must be positive, got 0.0"),
    ({"target_macs": 0.5, "target_runtime": "tensorrt"},
     "unknown --target-runtime 'tensorrt'; choose from ['onnxruntime', 'openvino']"),
    ({"target_macs": 0.5, "rounds": 0}, STEPS),
    ({"target_macs": 0.5, "extra_rounds": -1}, STEPS),
    ({"target_macs": 0.5, "steps": -1}, STEPS),
    ({"target_macs": 0.5, "shrink": 1.0}, "--shrink must be in (0, 1), got 1.0"),
    ({"target_macs": 0.5, "shrink": 0.0}, "--shrink must be in (0, 1), got 0.0"),
    ({"target_macs": 0.5, "budget_pct": 0.0}, "--budget-pct must be positive, got 0.0"),
    ({"target_macs": 0.5, "target_latency_pct": 50.0}, ONE_TARGET),
    ({"target_macs": 0.5, "target_latency_ms": 5.0}, ONE_TARGET),
    ({"target_latency_ms": 5.0, "target_latency_pct": 50.0}, ONE_TARGET),
    ({}, ONE_TARGET),
])
def test_a_bad_config_is_one_clear_error(fields, message) -> None:
    with pytest.raises(ConfigError) as err:
        PruneConfig(**fields)
    assert str(err.value) == message


def test_the_edges_of_a_good_config_are_accepted() -> None:
    for fields in ({"target_latency_pct": 99.9}, {"target_latency_pct": 0.1}, {"target_latency_ms": 0.5},
                   {"target_macs": 0.5, "rounds": 1,
                   "extra_rounds": 0, "steps": 0, "shrink": 0.01, "budget_pct": 0.01, "target_runtime": "openvino"}):
        PruneConfig(**fields)
    assert PruneConfig(target_latency_pct=60.0).latency_target_ms(20.0) == pytest.approx(12.0)
    assert PruneConfig(target_latency_ms=7.5).latency_target_ms(20.0) == 7.5
    assert PruneConfig(target_macs=0.5).latency_target_ms(20.0) is None
    assert PruneConfig(target_macs=0.5).objective == "macs"
    assert PruneConfig(target_latency_pct=60.0).objective == "latency"
    assert PruneConfig(target_macs=0.5).to_dict()["target_macs"] == 0.5


def test_the_commands_defaults_are_the_configs_and_the_config_is_frozen() -> None:
    """The command writes its defaults again (its module must not import torch): they agree."""
    import argparse
    import dataclasses

    from e3dpsm.cli.prune import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["prune", "--checkpoint", "c.pt", "--out", "o", "--target-macs", "0.5"])
    config = PruneConfig(target_macs=0.5)
    for name in ("target_runtime", "rounds", "extra_rounds", "shrink", "steps", "labels", "budget_pct", "seed",
                 "timing_steps", "eval_frames", "lr", "target_latency_ms"):
        assert getattr(args, name) == getattr(config, name), name
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.rounds = 5


def test_calibration_windows_cycle_the_sequences_from_seeded_starts() -> None:
    sequences = [SimpleNamespace(frames=n, lnes=np.arange(n * 2 * 3 * 4, dtype=np.float64).reshape(n, 2, 3, 4) + 1000 * i)
                 for i, n in enumerate((10, 6))]
    windows = calibration_windows(sequences, count=5, frames=4, seed=3)
    assert windows.dtype == torch.float32 and windows.shape == (5, 4, 2, 3, 4)
    rng = np.random.default_rng(3)
    for k in range(5):
        seq = sequences[k % 2]
        start = int(rng.integers(0, seq.frames - 4))
        np.testing.assert_array_equal(windows[k].numpy(), seq.lnes[start:start + 4])
    # A sequence no longer than the window starts at 0 (never an empty draw).
    short = [SimpleNamespace(frames=3, lnes=np.ones((3, 2, 3, 4)))]
    assert calibration_windows(short, count=2, frames=4, seed=0).shape == (2, 3, 2, 3, 4)


def test_heldout_figures_against_numpy() -> None:
    rng = np.random.default_rng(0)
    joints = 16
    gts = [rng.normal(0, 300, (n, joints, 3)) for n in (7, 5)]
    actions = [np.array([0, 0, 0, 1, 1, 1, 1]), np.array([1, 1, 1, 1, 1])]
    sequences = [SimpleNamespace(j3d_mm=g.astype(np.float32), visible=np.ones((len(g), joints)), action=a)
                 for g, a in zip(gts, actions)]
    poses = [(g + rng.normal(0, 20, g.shape)).astype(np.float32) for g in gts]
    teacher = [(p + rng.normal(0, 5, p.shape)).astype(np.float32) for p in poses]
    figures = heldout_figures([p[:k] for p, k in zip(poses, (6, 5))], sequences, [t[:k] for t, k in zip(teacher, (6, 5))],
                              ("walk", "run"))
    pred = np.concatenate([poses[0][:6], poses[1]]).astype(np.float64)
    gt = np.concatenate([gts[0][:6], gts[1]]).astype(np.float32).astype(np.float64)
    err = np.linalg.norm(pred - gt, axis=-1).mean(axis=1)
    action = np.concatenate([actions[0][:6], actions[1]])
    assert figures["frames"] == 11
    assert figures["mpjpe_frame_weighted_mm"] == pytest.approx(err.mean(), rel=1e-6)
    # The per-action mean, as `e3dpsm evaluate` gives it: 3 frames of action 0, 8 of action 1.
    assert figures["mpjpe_mm"] == pytest.approx((err[action == 0].mean() + err[action == 1].mean()) / 2, rel=1e-6)
    to_teacher = np.linalg.norm(pred - np.concatenate([teacher[0][:6], teacher[1]]), axis=-1).mean()
    assert figures["to_teacher_mm"] == pytest.approx(to_teacher, rel=1e-5)
    assert "to_teacher_mm" not in heldout_figures(poses, sequences, None, ("walk", "run"))


def test_streamed_poses_do_not_depend_on_the_chunk(teacher, held_out) -> None:
    sequences = held_out.split("test")
    window_ms = teacher.config.train_window_ms
    whole = stream_poses(teacher, sequences, window_ms, max_frames=11, chunk=1000)
    chunked = stream_poses(teacher, sequences, window_ms, max_frames=11, chunk=3)
    assert [p.shape for p in whole] == [(min(11, s.frames), 16, 3) for s in sequences]
    for a, b in zip(whole, chunked):
        np.testing.assert_allclose(b, a, atol=1e-3)
    # The state is carried across chunks: restarting it each chunk moves the poses.
    restarted = np.concatenate([stream_poses(teacher, [SimpleNamespace(frames=3, lnes=sequences[0].lnes[s:s + 3])],
                                             window_ms, max_frames=3)[0] for s in range(0, 9, 3)])
    assert np.abs(restarted - whole[0][:9]).max() > 1e-2


def test_the_int8_figures_and_a_recovery_without_steps() -> None:
    check = {"data": "runs/prep/val", "by_runtime": {"onnxruntime": {
        "frames": 100, "within": True, "metrics": {"mpjpe": {"value_mm": 101.0, "fp32_mm": 100.0, "change_pct": 1.0}}}}}
    assert run_module._int8_figures(check) == {"split": "val", "frames": 100, "mpjpe_mm": 101.0, "fp32_mpjpe_mm": 100.0,
                                              "loss_pct": 1.0, "within_budget": True}
    bare = {**check, "data": "val"}  # a split given by its bare name
    assert run_module._int8_figures(bare)["split"] == "val"
    recover = run_module.distill_recovery("no/such/data", _fast(target_macs=0.5, steps=0), progress=False)
    assert recover(None, None, 1) == {"steps": 0, "seconds": 0.0}



def test_run_prune_writes_the_chosen_model_its_report_and_provenance(monkeypatch, teacher, quant_data, tmp_path) -> None:
    from e3dpsm.checkpoint import load_checkpoint

    _simulated(monkeypatch, front=True)
    config = _fast(target_macs=0.6, rounds=2, extra_rounds=0)
    out = tmp_path / "pruned"
    summary = run_module.run_prune(TRAINED_TINY, quant_data, out, config, eval_data=quant_data, eval_split="test",
                                   int8=False, progress=False,
                                   recover=lambda t, s, k: {"steps": 7 * k, "seconds": 0.25, "ignored": 1})
    report = json.loads((out / "report.json").read_text())
    assert report["best"] == summary["best"] == 2 and report["met"] is True
    assert report["recovery_seconds"] == 0.5
    for r in report["rounds"]:
        graph = out / r["graph"]
        assert not Path(r["graph"]).is_absolute() and graph.is_file()
        assert r["onnx_bytes"] == graph.stat().st_size and r["graph"] == f"graphs/round{r['round']}.onnx"
    assert set(report["final_timing_ms"]) == {f"r{k}_{rt}_fp32" for k in range(3) for rt in ("ort", "ov")}
    model, extras = load_checkpoint(out / "checkpoint.pt")
    assert total_macs(model) == report["rounds"][2]["macs"]
    assert extras["step"] == 7 * 1 + 7 * 2  # the distillation steps of rounds 1 and 2
    assert extras["prune"]["round"] == 2 and extras["prune"]["source"] == str(TRAINED_TINY)
    assert extras["prune"]["cuts"] == [report["rounds"][1]["cuts"], report["rounds"][2]["cuts"]]
    assert (out / "report.md").is_file() and (out / "front.png").is_file()

def test_time_graphs_opens_each_graph_on_its_runtime_and_gives_median_ms(monkeypatch) -> None:
    from e3dpsm.golden import verify
    from e3dpsm.profiles import latency as latency_module
    from e3dpsm.runtime import session as session_module

    opened, timed = [], {}
    monkeypatch.setattr(verify, "open_runner", lambda path, runtime, threads: opened.append((path, runtime, threads))
                        or (path, runtime))
    monkeypatch.setattr(session_module, "CarriedStateRunner", lambda runner, window_ms: (runner, window_ms))

    def side_by_side(runners, frames, steps, warmup, chunk):
        timed.update(runners=runners, steps=steps, warmup=warmup, chunk=chunk)
        return {"a": np.array([0.003, 0.001, 0.002]), "b": np.array([0.010, 0.030, 0.020, 0.040])}

    monkeypatch.setattr(latency_module, "measure_side_by_side", side_by_side)
    frames = np.zeros((5, 2, 4, 4), np.float32)
    got = prune_module.time_graphs({"a": ("onnxruntime", Path("a.onnx")), "b": ("openvino", Path("b.onnx"))},
                                   frames, 20.0, threads=3, steps=255)
    assert got == pytest.approx({"a": 2.0, "b": 25.0})
    assert opened == [(Path("a.onnx"), "onnxruntime", 3), (Path("b.onnx"), "openvino", 3)]
    assert timed["runners"] == {"a": ((Path("a.onnx"), "onnxruntime"), 20.0), "b": ((Path("b.onnx"), "openvino"), 20.0)}
    # A tenth of the steps warm up, ten at least; the runners take turns every 20 steps.
    assert (timed["steps"], timed["warmup"], timed["chunk"]) == (255, 25, 20) and isinstance(timed["warmup"], int)
    prune_module.time_graphs({"a": ("onnxruntime", Path("a.onnx"))}, frames, 20.0, threads=1, steps=50)
    assert timed["warmup"] == 10


def test_the_profile_is_of_a_quarter_of_the_timed_steps_scaled_to_the_unprofiled_run(monkeypatch, teacher) -> None:
    calls = {}

    def profile_units(graph, units, frames, window_ms, threads, steps):
        calls.update(graph=graph, units=[u.name for u in units], window_ms=window_ms, threads=threads, steps=steps)
        return LatencyProfile(10.0, 8.0, 40, {"u": UnitLatency(2.0, 4)})

    monkeypatch.setattr(prune_module, "profile_units", profile_units)
    frames = np.zeros((3, 2, 4, 4), np.float32)
    profile = prune_module._profile(Path("g.onnx"), teacher, frames, 20.0, _fast(target_macs=0.5, timing_steps=402,
                                                                               threads=2), run_ms=15.0)
    assert calls == {"graph": Path("g.onnx"), "units": [u.name for u in prunable_units(teacher.config)],
                     "window_ms": 20.0, "threads": 2, "steps": 100}
    assert isinstance(calls["steps"], int)  # a whole number of steps
    assert (profile.run_ms, profile.kernel_ms, profile.units["u"].kernel_ms) == pytest.approx((15.0, 12.0, 3.0))
    prune_module._profile(Path("g.onnx"), teacher, frames, 20.0, _fast(target_macs=0.5, timing_steps=40), run_ms=15.0)
    assert calls["steps"] == 30  # thirty at least



def test_a_macs_target_follows_the_geometric_schedule_and_stops_when_met(monkeypatch, teacher, quant_data,
                                                                          held_out, tmp_path, caplog) -> None:
    config = _fast(target_macs=0.6, rounds=2, extra_rounds=2)
    work = tmp_path / "run" / "graphs"  # its parent made too
    with caplog.at_level("INFO", logger=prune_module.__name__):
        result, host, recovered = _run_loop(monkeypatch, teacher, quant_data, held_out, config, [], tmp_path,
                                            work=work)
    # Met at the last planned step: the loop ends there, no later step is even considered.
    assert [r.getMessage().split(":")[0] for r in caplog.records] == ["round 1", "round 2"]
    assert [Path(r["graph"]) for r in result["rounds"]] == [work / f"round{k}.onnx" for k in range(3)]
    assert host.runtimes == {"onnxruntime"}
    frames = min(200, held_out.split("test")[0].frames)
    assert host.frames == [(frames, np.float32)] * 3  # the held-out split's first frames, every timing
    rounds, base_macs = result["rounds"], total_macs(teacher)
    assert result["base_macs"] == base_macs == rounds[0]["macs"]
    assert rounds[0]["macs_fraction"] == 1.0 and rounds[0]["heldout"]["to_teacher_mm"] == 0.0
    assert rounds[0]["measured_ms"] == pytest.approx(base_macs / 1e6 * MS_PER_MMAC, rel=1e-12)
    # Met at the last planned round: no extra round, and each round was recovered once.
    assert len(rounds) == 3 and recovered == [1, 2]
    for k in (1, 2):
        record = rounds[k]
        assert record["round_target"] == pytest.approx(base_macs * 0.6 ** (k / 2), rel=1e-12)
        assert record["aim"] == record["round_target"]
        assert record["macs"] == total_macs(result["models"][k])
        assert record["macs_fraction"] == pytest.approx(record["macs"] / base_macs, rel=1e-12)
        assert record["cuts"] and record["recovery"] == {"steps": 10 * k, "seconds": 0.5}
        assert 0 <= record["seconds_plan"] <= record["seconds"]
        assert all(record[k] == round(record[k], 2) for k in ("seconds_plan", "seconds"))  # hundredths, as reported
        sim = host.step_ms(Path(record["graph"]))
        assert record["measured_side_by_side_ms"] == pytest.approx({"unpruned": rounds[0]["measured_ms"], "pruned": sim})
        assert record["speedup_side_by_side"] == pytest.approx(rounds[0]["measured_ms"] / sim, rel=1e-12)
        assert record["target_ms"] is None
    assert rounds[1]["macs"] < base_macs and rounds[2]["macs"] < rounds[1]["macs"]
    # Every narrowing candidate keeps half its width, in multiples of 4 channels (plan._aligned).
    narrowed = [c for r in rounds[1:] for c in r["candidates"] if c["width"]]
    assert narrowed
    for c in narrowed:
        old = c["old_width"]
        assert c["width"] == (max(4, old // 8 * 4) if old > 4 else max(1, old // 2)), c
    assert rounds[2]["macs_fraction"] <= 0.6
    assert result["best"] == 2 and target_met(result, config)


def test_a_latency_target_is_read_against_the_unpruned_step_timed_beside_it(monkeypatch, teacher, quant_data,
                                                                           held_out, tmp_path) -> None:
    # The host runs twice as slow in round 1's timing and 1.5x in round 2's: the pruned step
    # is read against the unpruned one timed beside it, in the units of the first timing.
    loads = [1.0, 2.0, 1.5, 1.25]
    config = _fast(target_latency_pct=70.0, rounds=2, extra_rounds=2, target_runtime="openvino")
    (tmp_path / "graphs").mkdir()  # a folder that is there already is used as it is
    result, host, _ = _run_loop(monkeypatch, teacher, quant_data, held_out, config, loads, tmp_path)
    assert host.runtimes == {"openvino"}
    rounds = result["rounds"]
    base_ms = rounds[0]["measured_ms"]
    final = 0.7 * base_ms
    correction = 1.0
    for k, record in enumerate(rounds[1:], start=1):
        sim = host.step_ms(Path(record["graph"]))
        load = loads[k]
        assert record["measured_side_by_side_ms"]["pruned"] == pytest.approx(load * sim, rel=1e-12)
        assert record["measured_load_corrected_ms"] == pytest.approx(sim * base_ms / host.step_ms(Path(rounds[0]["graph"])),
                                                                     rel=1e-12)
        assert record["target_ms"] == pytest.approx(final, rel=1e-12)
        target = base_ms * 0.7 ** (k / 2) if k <= 2 else final
        assert record["round_target"] == pytest.approx(target, rel=1e-12)
        # The latency model's error last round tightens this round's aim, never loosens it.
        assert record["aim"] == pytest.approx(target / correction, rel=1e-12)
        predicted = record["predicted_ms"]
        corrected = record["measured_load_corrected_ms"]
        assert record["predicted_vs_measured"] == pytest.approx(
            {"predicted_ms": predicted, "measured_ms": corrected, "ratio": corrected / predicted}, rel=1e-12)
        correction = max(record["measured_load_corrected_ms"] / predicted, 1.0)
    met = [r["round"] for r in rounds[1:] if r["measured_load_corrected_ms"] <= r["target_ms"]]
    assert met and result["best"] == met[0] and target_met(result, config)
    # The loop stops at the first round at or after the last planned one that meets the target.
    assert rounds[-1]["round"] == max(met[0], config.rounds)
    # Corrected by more than 1 somewhere: the simulated host's step is not the profile's model.
    assert any(r["aim"] < r["round_target"] for r in rounds[2:])


def test_a_round_over_the_accuracy_budget_ends_the_loop_and_is_never_chosen(monkeypatch, teacher, quant_data,
                                                                            held_out, tmp_path) -> None:
    real = prune_module.heldout_figures

    def worse_when_pruned(poses, sequences, teacher_poses, action_names=()):
        figures = real(poses, sequences, teacher_poses, action_names)
        if teacher_poses is not None:  # a pruned round: 10% worse than the unpruned
            figures["mpjpe_mm"] *= 1.10
        return figures

    config = _fast(target_macs=0.5, rounds=2, extra_rounds=0, budget_pct=9.9)
    result, _, recovered = _run_loop(monkeypatch, teacher, quant_data, held_out, config, [], tmp_path,
                                     heldout=worse_when_pruned)
    assert recovered == [1] and len(result["rounds"]) == 2
    assert result["best"] == 0 and not target_met(result, config)


def test_an_unmet_target_chooses_the_last_round_within_the_budget(monkeypatch, teacher, quant_data, held_out,
                                                                  tmp_path) -> None:
    config = _fast(target_macs=0.05, rounds=1, extra_rounds=1)
    result, _, recovered = _run_loop(monkeypatch, teacher, quant_data, held_out, config, [], tmp_path)
    assert recovered == [1, 2]
    assert result["rounds"][2]["round_target"] == pytest.approx(0.05 * result["base_macs"])
    assert result["rounds"][2]["macs_fraction"] > 0.05
    assert result["best"] == 2 and not target_met(result, config)


def test_a_step_whose_target_an_earlier_round_overshot_is_skipped_not_the_end(monkeypatch, teacher, quant_data,
                                                                              held_out, tmp_path) -> None:
    # Targets 0.88, 0.775, 0.68, 0.6 of the unpruned MACs; round 1's cuts land at about 0.77,
    # within the second step's target already: that step cuts nothing, the third and fourth do.
    config = _fast(target_macs=0.6, rounds=4, extra_rounds=0)
    result, host, recovered = _run_loop(monkeypatch, teacher, quant_data, held_out, config, [], tmp_path)
    rounds, base_macs = result["rounds"], result["base_macs"]
    assert rounds[1]["macs_fraction"] <= 0.6 ** (2 / 4)  # the overshoot this test is about
    targets = [r["round_target"] / base_macs for r in rounds[1:]]
    assert targets == pytest.approx([0.6 ** (1 / 4), 0.6 ** (3 / 4), 0.6])
    assert [r["round"] for r in rounds] == [0, 1, 2, 3] and recovered == [1, 2, 3]
    assert [Path(r["graph"]).name for r in rounds] == [f"round{k}.onnx" for k in range(4)]
    assert len(host.timed) == 4  # the unpruned step, then one side-by-side timing per round that cut
    assert result["best"] == 3 and rounds[3]["macs_fraction"] <= 0.6 and target_met(result, config)


def test_the_timing_frames_are_the_first_held_out_sequences_first_200_as_float32() -> None:
    long, other = (SimpleNamespace(lnes=np.arange(n * 2 * 3, dtype=np.float16).reshape(n, 2, 3) + n) for n in (250, 9))
    frames = prune_module.timing_frames([long, other])
    assert frames.dtype == np.float32 and frames.shape == (200, 2, 3)
    np.testing.assert_array_equal(frames, long.lnes[:200].astype(np.float32))
    np.testing.assert_array_equal(prune_module.timing_frames([other, long]), other.lnes.astype(np.float32))


def test_distillation_recovers_each_round_with_its_own_seed(monkeypatch) -> None:
    from e3dpsm.compress import distill as distill_module

    calls = []

    def fake_distill(teacher, student, data_dir, cfg, progress):
        calls.append((teacher, student, data_dir, cfg, progress))
        student.train()
        return {"steps": cfg.steps, "seconds": 1.5, "seconds_per_step": 0.01, "final": {"loss": 1.0},
                "initial": {"loss": 2.0}, "history": [1, 2], "lr": 9.0}

    monkeypatch.setattr(distill_module, "distill", fake_distill)
    config = _fast(target_macs=0.5, steps=150, labels="gt", seed=11, threads=3, lr=1e-3)
    recover = run_module.distill_recovery("prep", config, progress=True)
    teacher, student = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
    assert recover(teacher, student, 2) == {"steps": 150, "seconds": 1.5, "seconds_per_step": 0.01,
                                            "final": {"loss": 1.0}, "initial": {"loss": 2.0}}
    assert not student.training  # left in eval mode for the round's export and figures
    (t, s, data_dir, cfg, progress), = calls
    assert (t, s, data_dir, progress) == (teacher, student, "prep", True)
    assert (cfg.steps, cfg.labels, cfg.seed, cfg.threads, cfg.lr) == (150, "gt", 13, 3, 1e-3)


def _renamed_splits(quant_data: Path, tmp_path: Path, names: dict[str, str]) -> Path:
    import shutil

    copy = tmp_path / "renamed"
    shutil.copytree(quant_data, copy)
    meta = json.loads((copy / "meta.json").read_text())
    for entry in meta["sequences"]:
        entry["split"] = names[entry["split"]]
    (copy / "meta.json").write_text(json.dumps(meta))
    return copy


@pytest.mark.parametrize("names, calib, holdout", [
    ({"train": "train", "val": "val", "test": "test"}, "train", "val"),
    ({"train": "a", "val": "b", "test": "c"}, "a", "c"),  # no train, no val: the first and the last split
    ({"train": "a", "val": "train", "test": "val"}, "train", "val"),  # train found where it is, not first
])
def test_the_int8_graph_is_calibrated_on_train_and_checked_on_val(monkeypatch, quant_data, tmp_path, names, calib,
                                                                    holdout) -> None:
    import e3dpsm.quantize as quantize_package

    calls = []
    monkeypatch.setattr(quantize_package, "quantize_graph", lambda *a, **k: calls.append((a, k)))
    data = _renamed_splits(quant_data, tmp_path, names)
    q = run_module._int8(Path("g.onnx"), data, tmp_path / "q", 3)
    assert q == tmp_path / "q" / "step_int8.onnx"
    ((graph, data_arg, out, options), kwargs), = calls
    assert (graph, data_arg, out, kwargs) == (Path("g.onnx"), data, tmp_path / "q", {"force": True})
    assert (options.mode, options.exclude, options.frames, options.split, options.holdout_split, options.threads) == (
        "int8", "recurrent", 100, calib, holdout, 3)
    assert (options.advanced.holdout_frames, options.advanced.timing_steps) == (100, 20)


def test_run_prune_times_every_round_and_the_int8_graphs_side_by_side(monkeypatch, teacher, quant_data,
                                                                      tmp_path) -> None:
    host = _simulated(monkeypatch)
    timings = []

    def time_front(graphs, frames, window_ms, threads, steps):
        timings.append((dict(graphs), frames, window_ms, threads, steps))
        return host.time({k: v for k, v in graphs.items() if "int8" not in k}, frames, window_ms, threads, steps)

    monkeypatch.setattr(run_module, "time_graphs", time_front)
    quantised = []

    def fake_int8(graph, data, out, threads):
        quantised.append((graph, data, out, threads))
        out.mkdir(parents=True)
        mpjpe = {"value_mm": 50.0 + len(quantised), "fp32_mm": 50.0, "change_pct": 2.0 * len(quantised)}
        check = {"data": f"{data}/val", "by_runtime": {"onnxruntime": {"frames": 40, "within": len(quantised) == 1,
                                                                        "metrics": {"mpjpe": mpjpe}}}}
        (out / "report.json").write_text(json.dumps({"check": check}))
        (out / "step_int8.onnx").write_text("q")
        return out / "step_int8.onnx"

    monkeypatch.setattr(run_module, "_int8", fake_int8)
    config = _fast(target_macs=0.6, rounds=2, extra_rounds=0, threads=2, timing_steps=12)
    out = tmp_path / "pruned"
    summary = run_module.run_prune(TRAINED_TINY, quant_data, out, config, eval_data=quant_data, eval_split="test",
                                   progress=False, recover=lambda t, s, k: {"steps": 1, "seconds": 0.26})
    report = json.loads((out / "report.json").read_text())
    assert report == json.loads(json.dumps(summary))
    assert report["best"] == 2 and report["recovery_seconds"] == 0.5  # 0.52 to a tenth
    work = out / "graphs"
    # The unpruned and the chosen model are quantised (their fp32 graphs, the held-out data).
    assert [(Path(g).name, d, Path(o).name, t) for g, d, o, t in quantised] == [
        ("round0.onnx", quant_data, "round0_int8", 2), ("round2.onnx", quant_data, "round2_int8", 2)]
    assert report["int8_graphs"] == {"0": "graphs/round0_int8/step_int8.onnx", "2": "graphs/round2_int8/step_int8.onnx"}
    assert (work / "round2_int8" / "step_int8.onnx").is_file()
    assert report["rounds"][0]["int8"] == {"split": "val", "frames": 40, "mpjpe_mm": 51.0, "fp32_mpjpe_mm": 50.0,
                                           "loss_pct": 2.0, "within_budget": True}
    assert report["rounds"][2]["int8"]["mpjpe_mm"] == 52.0 and "int8" not in report["rounds"][1]
    # One run per runtime, each with every graph of its runtime, on the eval split's timing
    # frames, twice the rounds' steps.
    expected_frames = prune_module.timing_frames(PreparedData_split(quant_data, "test"))
    assert [sorted(graphs) for graphs, *_ in timings] == [
        ["r0_ort_fp32", "r0_ort_int8", "r1_ort_fp32", "r2_ort_fp32", "r2_ort_int8"],
        ["r0_ov_fp32", "r0_ov_int8", "r1_ov_fp32", "r2_ov_fp32", "r2_ov_int8"]]
    for graphs, frames, window_ms, threads, steps in timings:
        assert {runtime for runtime, _ in graphs.values()} in ({"onnxruntime"}, {"openvino"})
        for label, (_, graph) in graphs.items():  # under the run's temporary folder, renamed at the end
            k, kind = label[1], label.rsplit("_", 1)[1]
            expected = ("graphs", f"round{k}_int8", "step_int8.onnx") if kind == "int8" else ("graphs", f"round{k}.onnx")
            assert graph.parts[-len(expected):] == expected
        np.testing.assert_array_equal(frames, expected_frames)
        assert (window_ms, threads, steps) == (20.0, 2, 24)
    # The report records what ran: the command's own options beside the pruning config.
    assert report["command"] == "prune" and report["config"] == {
        "checkpoint": str(TRAINED_TINY), "data": str(quant_data), "out": str(out), "eval_data": str(quant_data),
        "eval_split": "test", "int8": True, **config.to_dict()}
    assert set(report["final_timing_ms"]) == {f"r{k}_{rt}_fp32" for k in range(3) for rt in ("ort", "ov")}
    assert 0 <= report["seconds"] < 600 and report["front"]


def PreparedData_split(root: Path, split: str):
    from e3dpsm.data.prepared import PreparedData

    return PreparedData.open(root).split(split)


@pytest.mark.parametrize("which, message", [
    ("data", "was prepared with 40 ms windows, but the model/graph expects 20 ms"),
    ("eval_data", "was prepared with 40 ms windows, but the model/graph expects 20 ms"),
    ("eval_split", "has no sequences in split 'nope'"),
])
def test_run_prune_refuses_data_that_does_not_fit_before_writing(quant_data, tmp_path, which, message) -> None:
    from e3dpsm.errors import DataError

    other = _renamed_splits(quant_data, tmp_path, {"train": "train", "val": "val", "test": "test"})
    meta = json.loads((other / "meta.json").read_text())
    meta["window_us"] = 40_000
    (other / "meta.json").write_text(json.dumps(meta))
    paths = {"data": quant_data, "eval_data": quant_data, "eval_split": "test", which: "nope" if which == "eval_split" else other}
    out = tmp_path / "pruned"

    def never(*_):
        raise AssertionError("pruned before the data was checked")

    with pytest.raises(DataError, match=re.escape(message)):
        run_module.run_prune(TRAINED_TINY, paths["data"], out, _fast(target_macs=0.6), eval_data=paths["eval_data"],
                             eval_split=paths["eval_split"], progress=False, recover=never)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["renamed"]


def test_run_prunes_library_defaults_all_splits_int8_on_and_distillation_with_a_bar(monkeypatch, teacher, quant_data,
                                                                                   tmp_path) -> None:
    """Called as a library with the fewest arguments: held-out figures and timing on every split,
    the INT8 front on, recovery by distillation with its progress bar."""
    _simulated(monkeypatch)
    frames_timed, quantised, recoveries = [], [], []
    monkeypatch.setattr(run_module, "time_graphs",
                        lambda graphs, frames, *a: frames_timed.append(frames) or {k: 1.0 for k in graphs})

    def fake_int8(graph, data, out, threads):
        quantised.append(graph)
        out.mkdir(parents=True)
        mpjpe = {"value_mm": 1.0, "fp32_mm": 1.0, "change_pct": 0.0}
        (out / "report.json").write_text(json.dumps({"check": {"data": "d/val", "by_runtime": {"onnxruntime": {
            "frames": 1, "within": True, "metrics": {"mpjpe": mpjpe}}}}}))
        return out / "step_int8.onnx"

    def fake_recovery(data_dir, config, progress):
        recoveries.append((data_dir, progress))
        return lambda t, s, k: {"seconds": 0.0}  # a recovery that reports no steps took none

    monkeypatch.setattr(run_module, "_int8", fake_int8)
    monkeypatch.setattr(run_module, "distill_recovery", fake_recovery)
    out = tmp_path / "pruned"
    config = _fast(target_macs=0.6, rounds=1, extra_rounds=0)
    summary = run_module.run_prune(TRAINED_TINY, quant_data, out, config, eval_data=quant_data)
    assert recoveries == [(quant_data, True)] and len(quantised) == 2
    from e3dpsm.checkpoint import read_checkpoint

    extras = read_checkpoint(out / "checkpoint.pt")
    assert extras["step"] == 0 and extras["prune"]["config"] == config.to_dict()
    assert summary["base_macs"] == summary["rounds"][0]["macs"]
    assert summary["seconds"] == round(summary["seconds"], 1) and summary["seconds"] >= 0
    first_of_all = PreparedData_split(quant_data, "all")
    assert summary["config"]["eval_split"] == "all" and summary["config"]["int8"] is True
    for frames in frames_timed:
        np.testing.assert_array_equal(frames, prune_module.timing_frames(first_of_all))
    from e3dpsm.errors import OutputExistsError

    with pytest.raises(OutputExistsError, match="--force"):  # force off by default: the folder is there now
        run_module.run_prune(TRAINED_TINY, quant_data, out, _fast(target_macs=0.6, rounds=1, extra_rounds=0),
                             eval_data=quant_data)


def test_the_loop_runs_on_its_threads_and_gives_the_callers_back(monkeypatch, teacher, quant_data, held_out,
                                                                 tmp_path) -> None:
    _simulated(monkeypatch)
    seen = []

    def recover(teacher_model, student, round_index):
        seen.append(torch.get_num_threads())
        if round_index == 2:
            raise KeyError("a failed recovery")
        return {"steps": 0, "seconds": 0.0}

    before = torch.get_num_threads()
    other = 3 if before != 3 else 2
    torch.set_num_threads(other)
    try:
        prune_loop(teacher, quant_data, held_out, _fast(target_macs=0.6, rounds=1, extra_rounds=0, threads=1),
                   tmp_path / "a", recover, eval_split="test")
        assert seen == [1] and torch.get_num_threads() == other
        with pytest.raises(KeyError):
            prune_loop(teacher, quant_data, held_out, _fast(target_macs=0.3, rounds=2, extra_rounds=0, threads=1),
                       tmp_path / "b", recover, eval_split="test")
        assert seen == [1, 1, 1] and torch.get_num_threads() == other  # given back on an error too
    finally:
        torch.set_num_threads(before)


def test_the_chosen_models_steps_and_cuts_stop_at_its_round(monkeypatch, teacher, quant_data, tmp_path) -> None:
    """Round 2 goes over the accuracy budget: round 1 is chosen, and the checkpoint counts its
    distillation steps and cuts alone, not round 2's."""
    from e3dpsm.checkpoint import read_checkpoint

    _simulated(monkeypatch, front=True)
    real = prune_module.heldout_figures
    calls = []

    def worse_from_round_two(poses, sequences, teacher_poses, action_names=()):
        figures = real(poses, sequences, teacher_poses, action_names)
        calls.append(1)
        # The unpruned model's figure set high, so that round 1 is within the budget whatever it
        # measures; round 2 then far over it.
        figures["mpjpe_mm"] *= {1: 100.0, 2: 1.0}.get(len(calls), 1000.0)
        return figures

    monkeypatch.setattr(prune_module, "heldout_figures", worse_from_round_two)
    out = tmp_path / "pruned"
    summary = run_module.run_prune(TRAINED_TINY, quant_data, out, _fast(target_macs=0.3, rounds=2, extra_rounds=0,
                                                                        budget_pct=9.9),
                                   eval_data=quant_data, eval_split="test", int8=False, progress=False,
                                   recover=lambda t, s, k: {"steps": 10 ** k, "seconds": 0.0})
    assert summary["best"] == 1 and len(summary["rounds"]) == 3
    extras = read_checkpoint(out / "checkpoint.pt")
    assert extras["step"] == 10 and extras["prune"]["round"] == 1
    assert extras["prune"]["cuts"] == [summary["rounds"][1]["cuts"]]
