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
