"""The verdict's first line (quantize/verdict.py) on injected checks and timings: over budget,
surely faster (ship for speed), not faster (ship for size, name what is faster here)."""
from __future__ import annotations

from e3dpsm.budget import BudgetCheck, MetricChange, TaskBudget
from e3dpsm.quantize.verdict import Verdict


def _check(upper_pct: float, name: str = "jitter", limit: float = 5.0) -> BudgetCheck:
    metrics = tuple(MetricChange(n, 100.0, 101.0, upper_pct - 0.5 if n == name else 0.1,
                                 upper_pct - 1.0 if n == name else 0.0, upper_pct if n == name else 0.2, 0.1,
                                 limit if n == "jitter" else 1.0) for n in ("mpjpe", "pa_mpjpe", "jitter"))
    return BudgetCheck(metrics, 3000, 3, 2.5, TaskBudget())


def _timing(speedup: float, low: float, high: float) -> dict:
    return {"p50_ms": 10.0 / speedup, "fp32_p50_ms": 10.0, "speedup_vs_fp32": speedup,
            "interval": {"low": low, "high": high, "coverage": 0.8, "rounds": 20}, "timer": {"steps": 200}}


VNNI = {"kind": "vnni", "bf16": True}
AVX2 = {"kind": "avx2", "bf16": False}


def test_over_budget_says_do_not_ship_and_names_the_metric():
    line = Verdict("int8", _check(5.4), "openvino", 0.29, {"onnxruntime": _timing(1.4, 1.2, 1.6)}, VNNI).headline()
    assert line.startswith("Verdict: over budget, do not ship: jitter +4.90% (upper bound +5.40%, limit +5%)")
    assert "3000 held-out frames (OpenVINO)" in line


def test_surely_faster_ships_for_speed():
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.29,
                      {"onnxruntime": _timing(1.1, 1.02, 1.2), "openvino": _timing(1.35, 1.25, 1.45)}, VNNI)
    assert verdict.headline() == ("Verdict: ship it: int8 within budget on 3000 held-out frames, 0.29x fp32's "
                                  "size, 1.35x fp32's speed on OpenVINO on this vnni host.")
    assert verdict.to_dict()["fastest"] == {"runtime": "openvino", "speedup_vs_fp32": 1.35}


def test_an_interval_that_holds_one_is_not_faster():
    """1.08x with its interval down to 0.97x: level with fp32 within the timing noise."""
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.29, {"onnxruntime": _timing(1.08, 0.97, 1.2)}, AVX2)
    line = verdict.headline()
    assert line.startswith("Verdict: no int8 graph beats fp32 on this avx2 host (ONNX Runtime 1.08x fp32's speed)")
    assert "ship it for size and integer-only accelerators" in line and "structured pruning" in line
    assert "bf16" not in line  # no bf16 units on this host
    assert "bf16 on this CPU's bf16 units" in Verdict("int8", _check(3.0), "onnxruntime", 0.29,
                                                      {"onnxruntime": _timing(0.8, 0.7, 0.9)}, VNNI).headline()


def test_within_budget_at_the_edge_is_within():
    assert Verdict("int8", _check(5.0), "onnxruntime", 0.3, {}, VNNI).within
    assert not Verdict("int8", _check(5.000001), "onnxruntime", 0.3, {}, VNNI).within


def test_a_speed_up_timed_on_an_oversubscribed_host_is_not_trusted():
    """The same interval above 1x: trusted at a load of the core count, not above it."""
    import os

    cores = os.cpu_count() or 1

    def timed(load: float) -> dict:
        t = _timing(1.6, 1.1, 1.9)
        return {**t, "timer": {**t["timer"], "load_average": load}}

    quiet = Verdict("int8", _check(3.0), "onnxruntime", 0.3, {"onnxruntime": timed(cores)}, VNNI)
    assert quiet.headline().startswith("Verdict: ship it:")
    busy = Verdict("int8", _check(3.0), "onnxruntime", 0.3, {"onnxruntime": timed(cores + 0.5)}, VNNI)
    assert busy.headline().startswith("Verdict: no int8 graph beats fp32 on this vnni host (loaded while timed: "
                                      "time it again on a quiet host) (ONNX Runtime 1.60x fp32's speed)")


def test_an_fp16_graph_not_faster_here_is_for_fp16_accelerators():
    line = Verdict("fp16", _check(3.0), "onnxruntime", 0.52, {"onnxruntime": _timing(0.97, 0.9, 1.05)}, VNNI).headline()
    assert "ship it for size and fp16 accelerators (GPUs, NPUs)" in line and "integer-only" not in line


def test_over_budget_names_the_metric_furthest_over_its_own_limit():
    """Each metric's upper end is read against its own limit: jitter's +6% of 5% (1.2x) is
    further over than mpjpe's +1.1% of 1% (1.1x); mpjpe's +1.5% of 1% (1.5x) further than both."""
    metrics = (MetricChange("mpjpe", 100.0, 101.0, 1.0, 0.9, 1.1, 0.1, 1.0),
               MetricChange("pa_mpjpe", 100.0, 101.0, 0.1, 0.0, 0.2, 0.1, 1.0),
               MetricChange("jitter", 100.0, 105.0, 5.5, 5.0, 6.0, 0.1, 5.0))
    line = Verdict("int8", BudgetCheck(metrics, 500, 1, 2.0, TaskBudget()), "onnxruntime", 0.3, {}, AVX2).headline()
    assert line == ("Verdict: over budget, do not ship: jitter +5.50% (upper bound +6.00%, limit +5%) on 500 held-out "
                    "frames (ONNX Runtime); keep more nodes float (`--exclude`) or calibrate on more frames.")
    # mpjpe furthest over (1.5x against jitter's 1.2x): named even though jitter's upper end is the larger number
    worse = (MetricChange("mpjpe", 100.0, 101.0, 1.4, 1.3, 1.5, 0.1, 1.0), *metrics[1:])
    assert "over budget, do not ship: mpjpe +1.40%" in Verdict(
        "int8", BudgetCheck(worse, 500, 1, 2.0, TaskBudget()), "tensorrt", 0.3, {}, AVX2).headline()
    assert "(tensorrt)" in Verdict("int8", BudgetCheck(worse, 500, 1, 2.0, TaskBudget()), "tensorrt", 0.3, {},
                                   AVX2).headline()  # a runtime without a display name keeps its own


def test_an_interval_whose_low_end_is_exactly_one_is_not_surely_faster():
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.29, {"onnxruntime": _timing(1.2, 1.0, 1.4)}, AVX2)
    assert not verdict.surely_faster("onnxruntime") and "no int8 graph beats fp32" in verdict.headline()
    assert Verdict("int8", _check(3.0), "onnxruntime", 0.29, {"onnxruntime": _timing(1.2, 1.0001, 1.4)},
                   AVX2).surely_faster("onnxruntime")
    assert not verdict.surely_faster("openvino")  # not timed there: never surely faster


def test_untimed_runtimes_are_left_out_and_the_full_line_reads_by_hand():
    timings = {"onnxruntime": _timing(0.9, 0.8, 1.0), "openvino": {"p50_ms": 10.0}}  # openvino: no speed-up
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.25, timings, AVX2)
    assert verdict.fastest == ("onnxruntime", 0.9)
    assert verdict.headline() == (
        "Verdict: no int8 graph beats fp32 on this avx2 host (ONNX Runtime 0.90x fp32's speed); this one is within "
        "budget on 3000 held-out frames, 0.25x fp32's size: ship it for size and integer-only accelerators. Faster "
        "here: structured pruning (`e3dpsm prune`: 3.2x on `small`), OpenVINO with the states inside the IR "
        "(`convert openvino --stateful`, fp32).")
    untimed = Verdict("fp16", _check(3.0), "onnxruntime", 0.5, {}, {})
    assert untimed.fastest is None
    assert untimed.headline().startswith("Verdict: no fp16 graph beats fp32 on this unknown host; this one is within")
    assert untimed.to_dict()["fastest"] is None and untimed.to_dict()["surely_faster"] is False


def test_bf16_hosts_are_offered_bf16_second():
    assert Verdict("int8", _check(3.0), "onnxruntime", 0.3, {}, VNNI).faster_alternatives() == [
        "structured pruning (`e3dpsm prune`: 3.2x on `small`)",
        "bf16 on this CPU's bf16 units (profile target openvino-cpu-bf16)",
        "OpenVINO with the states inside the IR (`convert openvino --stateful`, fp32)"]


def test_the_verdict_dict_by_hand():
    timings = {"onnxruntime": _timing(1.1, 1.02, 1.2)}
    verdict = Verdict("int8", _check(3.0), "openvino", 0.29, timings, VNNI)
    assert verdict.to_dict() == {
        "headline": verdict.headline(), "within_budget": True, "check_runtime": "openvino", "size_ratio": 0.29,
        "timings": timings, "fastest": {"runtime": "onnxruntime", "speedup_vs_fp32": 1.1}, "surely_faster": True}
    assert verdict.headline().startswith("Verdict: ship it: int8 within budget")


def test_other_modes_name_what_a_slower_graph_still_serves():
    slow = {"onnxruntime": _timing(0.9, 0.8, 1.0), "openvino": _timing(0.95, 0.85, 1.02)}
    dynamic = Verdict("int8-dynamic", _check(3.0), "onnxruntime", 0.3, slow, AVX2).headline()
    assert "(ONNX Runtime 0.90x, OpenVINO 0.95x fp32's speed)" in dynamic  # every timed runtime, in order
    assert "ship it for size and integer-only accelerators." in dynamic
    other = Verdict("int4", _check(3.0), "onnxruntime", 0.2, slow, AVX2).headline()
    assert "ship it for size and accelerators. Faster here" in other  # a mode without a named accelerator


def test_a_runtime_without_a_display_name_is_named_as_it_is():
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.29, {"tensorrt": _timing(1.5, 1.3, 1.7)}, VNNI)
    assert verdict.headline().endswith("1.50x fp32's speed on tensorrt on this vnni host.")


def test_defaults_and_immutability():
    import dataclasses

    import pytest

    bare = Verdict("int8", _check(3.0), "onnxruntime", 0.3)  # no timings, no ISA: still one line
    assert bare.fastest is None and bare.headline().startswith("Verdict: no int8 graph beats fp32 on this unknown host")
    with pytest.raises(dataclasses.FrozenInstanceError):
        bare.mode = "fp16"


def test_without_a_core_count_one_core_is_assumed(monkeypatch):
    """os.cpu_count() may be None: a load above 1 then counts as oversubscribed."""
    monkeypatch.setattr("os.cpu_count", lambda: None)
    timed = _timing(1.6, 1.1, 1.9)
    verdict = Verdict("int8", _check(3.0), "onnxruntime", 0.3,
                      {"onnxruntime": {**timed, "timer": {**timed["timer"], "load_average": 1.5}}}, VNNI)
    assert verdict.loaded("onnxruntime") and not verdict.surely_faster("onnxruntime")


def test_time_beside_fp32_times_each_runtime_and_records_its_timer(monkeypatch):
    """Fake steppers: which graph opens on which runtime in which order, and each runtime's
    timer record (runtime, threads, the load average rounded to 0.01, the timed steps)."""
    import numpy as np

    import e3dpsm.quantize.holdout as holdout
    from e3dpsm.quantize.verdict import time_beside_fp32

    opened = []

    class FakeStepper:
        def __init__(self, path: str, runtime: str, threads: int | None) -> None:
            opened.append((path, runtime, threads))
            self.path = path

        def init_state(self, batch: int) -> dict:
            return {"s": np.zeros((batch, 1), np.float32)}

        def step(self, lnes, state, window_ms):
            return {}, state

    monkeypatch.setattr(holdout, "open_stepper", FakeStepper)
    monkeypatch.setattr("os.getloadavg", lambda: (1.234, 5.0, 6.0))
    frames = np.zeros((4, 2, 8, 8), np.float32)
    timings = time_beside_fp32("q.onnx", "fp32.onnx", frames, 20.0, ("onnxruntime", "openvino"), 2, steps=10)
    assert list(timings) == ["onnxruntime", "openvino"]
    assert opened == [("q.onnx", "onnxruntime", 2), ("fp32.onnx", "onnxruntime", 2),
                      ("q.onnx", "openvino", 2), ("fp32.onnx", "openvino", 2)]
    for runtime, timed in timings.items():
        assert timed["timer"]["runtime"] == runtime and timed["timer"]["threads"] == 2
        assert timed["timer"]["load_average"] == 1.23 and timed["timer"]["steps"] == 10
        assert timed["speedup_vs_fp32"] > 0 and set(timed["interval"]) >= {"low", "high"}
