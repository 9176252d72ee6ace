"""benchmarks/bench_pruned_paths.py: from the medians of every (model, target) runner, the
speed-up of each pruned model over the unpruned one per target and each model's fastest path,
checked on injected timings; and a runner per (model, target) is timed in the one interleaved run."""
from __future__ import annotations

import numpy as np
import pytest

from _benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_pruned_paths")


def test_speedups_and_fastest_paths_from_injected_medians(bench) -> None:
    figures = {"unpruned|ort": {"p50": 30.0}, "unpruned|ov": {"p50": 20.0},
               "cut|ort": {"p50": 15.0}, "cut|ov": {"p50": 16.0}}
    summary = bench.summarise(figures, ["unpruned", "cut"], ["ort", "ov"])
    assert summary["p50"]["cut"]["ort"]["speedup_vs_unpruned"] == pytest.approx(2.0)
    assert summary["p50"]["cut"]["ov"]["speedup_vs_unpruned"] == pytest.approx(1.25)
    assert "speedup_vs_unpruned" not in summary["p50"]["unpruned"]["ort"]
    # Each model's own fastest path, not the unpruned model's.
    assert summary["fastest"]["unpruned"]["target"] == "ov" and summary["fastest"]["cut"]["target"] == "ort"
    assert summary["fastest"]["cut"]["hz"] == pytest.approx(1000 / 15.0)


def test_every_model_target_pair_is_timed_in_one_run(bench, tiny_step_graph, monkeypatch) -> None:
    from e3dpsm.profiles.targets import load_targets, select_targets

    targets = select_targets(load_targets(), "ort-cpu-fp32-static", threads=1)
    seen = {}

    def fake_measure(runners, frames, steps, warmup):
        seen.update(runners)
        return {key: np.full(steps, 0.01) for key in runners}

    monkeypatch.setattr("e3dpsm.profiles.latency.measure_side_by_side", fake_measure)
    frames = np.zeros((4, 2, 96, 128), np.float32)
    figures = bench.measure({"unpruned": tiny_step_graph, "cut": tiny_step_graph}, targets, frames, 20.0, 3, 1)
    assert sorted(seen) == ["cut|ort-cpu-fp32-static", "unpruned|ort-cpu-fp32-static"]
    assert figures["cut|ort-cpu-fp32-static"]["p50"] == pytest.approx(10.0)  # ms
