"""The speed verdict of `quantize` (first line of report.md and of the pipeline's index)."""
from __future__ import annotations

import pytest

from e3dpsm.quantize.front_report import markdown_report, speed_verdict


def _candidate(label: str, p50_ms: float, within: bool, chosen: bool = False) -> dict:
    return {"label": label, "float_groups": [], "distance_pct": 0.5, "p50_ms": p50_ms, "speedup_vs_fp32": None,
            "within_budget": within, "on_front": True, "chosen": chosen}


def _report(chosen_ms: float, fp32_ms: float, *, bf16: bool, within: bool = True) -> dict:
    flags = ["avx2", "avx512_vnni"] + (["avx512_bf16"] if bf16 else [])
    return {
        "mode": "int8", "artifact": "step_int8.onnx",
        "machine": {"isa": {"kind": "vnni", "flags": flags, "bf16": bf16, "int8_dot_product": True}},
        "sizes": {"source_bytes": 6_000_000, "output_bytes": 1_800_000},
        "holdout": {"split": "val", "frames": 100, "mpjpe_mm": 100.5, "fp32_mpjpe_mm": 100.0, "bound_pct": 0.8},
        "exclusion_search": {"within_budget": within},
        "search": {"chosen": {"p50_ms": chosen_ms}, "fp32_p50_ms": fp32_ms, "objective": "latency",
                   "budget_pct": 1.0, "front": [], "timer": {},
                   "candidates": [_candidate("base", chosen_ms, within, chosen=True)]},
    }


def test_slower_than_fp32_says_so_and_names_what_would_pay() -> None:
    """The Xeon case of issue 24: 12.08 against 10.34 ms (0.86x) was chosen with nothing said."""
    verdict = speed_verdict(_report(12.08, 10.34, bf16=True))
    assert verdict.startswith("Verdict: the chosen int8 graph (within budget) does not beat fp32 on this vnni host")
    assert "0.86x fp32 (12.08 against 10.34 ms" in verdict and "No timed int8 graph within budget beats fp32" in verdict
    assert "bf16" in verdict and "1.8 MB against 6.0" in verdict
    assert "bf16" not in speed_verdict(_report(12.08, 10.34, bf16=False))
    assert markdown_report(_report(12.08, 10.34, bf16=True)).splitlines()[2] == f"**{verdict}**"


@pytest.mark.parametrize("chosen_ms, pays", [(10.0, False), (10.0 / 1.03, False), (10.0 / 1.031, True), (5.0, True)])
def test_a_speed_up_within_the_timing_tie_does_not_count(chosen_ms, pays) -> None:
    verdict = speed_verdict(_report(chosen_ms, 10.0, bf16=False))
    assert verdict.startswith("Verdict: the chosen int8 graph (within budget) runs") == pays, verdict


def test_objective_accuracy_chose_a_slower_graph_than_a_timed_one_within_budget() -> None:
    """The verdict speaks of the chosen graph, and names a faster one within budget."""
    report = _report(12.0, 10.0, bf16=False)
    report["search"]["candidates"] += [_candidate("top2", 8.0, True), _candidate("top1", 5.0, False)]
    verdict = speed_verdict(report)
    assert "does not beat fp32" in verdict and "within budget runs 1.25x" in verdict


def test_no_timing_no_verdict() -> None:
    report = _report(1.0, 1.0, bf16=False)
    report["search"]["chosen"]["p50_ms"] = None
    assert speed_verdict(report) is None and "Verdict" not in markdown_report(report)


@pytest.mark.parametrize("target, budget, phrase", [
    (0.75, 1.0, "target 0.75%: the 1% budget less a 25% margin for unseen data"),
    (1.0, 1.0, "budget 1%"),
    (0.1, None, "budget 0.1%"),
])
def test_reports_name_the_search_target_and_its_margin(target, budget, phrase) -> None:
    from e3dpsm.quantize.front_report import search_target_phrase

    assert search_target_phrase({"search": {"budget_pct": target}, "config": {"budget_pct": budget}}) == phrase


def test_the_verdict_speaks_of_the_artifact_timed_last_not_the_search_candidate() -> None:
    """A fresh clone's default search on an AVX2 host (2026-12-01): the candidate with 48 nodes in
    float ran 1.08x fp32, the artifact with those 48 at 16 bits 0.61x; the verdict said 1.08x."""
    report = _report(8.0, 10.0, bf16=False)  # the search's candidate: 1.25x
    report["search"]["candidates"][0]["within_budget"] = True
    assert speed_verdict(report).startswith("Verdict: the chosen int8 graph (within budget) runs 1.25x")
    report["artifact_timing"] = {"p50_ms": 16.0, "fp32_p50_ms": 11.0, "speedup_vs_fp32": 11.0 / 16.0}
    verdict = speed_verdict(report)
    assert "does not beat fp32" in verdict and "0.69x fp32 (16.00 against 11.00 ms" in verdict
    # Nothing changed the chosen candidate after the search timed it: the artifact is that graph.
    assert "The search timed this same graph at 1.25x" in verdict  # its own fp32 run: 10.0 / 8.0
    assert "--objective latency" not in verdict
    report["precision_search"] = {"int16_nodes": ["a", "b"], "int16w16_nodes": ["c"], "float_nodes": []}
    verdict = speed_verdict(report)
    assert "Its 3 nodes run at 16 bits in float" in verdict and "--no-int16 --objective latency" in verdict
    report["precision_search"] = {"int16_nodes": ["a"], "float_nodes": []}  # a fresh clone's pipeline had one
    verdict = speed_verdict(report)
    assert "Its 1 node runs at 16 bits in float behind a DequantizeLinear" in verdict
    assert "with it in float runs 1.25x" in verdict



def test_a_faster_chosen_candidate_is_named_by_what_the_precision_stage_changed() -> None:
    """A fresh clone's pipeline on an AVX-512 VNNI host (2026-12-02): the search timed its only
    candidate, the recurrent projections in float, at 1.10x; the artifact, with the precision
    stage's 11 recurrent projections at 8 bits, at 0.85x. The verdict said "--objective latency
    picks it", which ships the same artifact; --no-int16 ships the candidate as timed."""
    report = _report(8.05, 8.85, bf16=True)
    report["artifact_timing"] = {"p50_ms": 10.04, "fp32_p50_ms": 8.55}
    report["precision_search"] = {"int16_nodes": [], "int16w16_nodes": [], "float_nodes": [],
                                  "int8_recurrent_nodes": [f"Gemm_{i}" for i in range(11)]}
    verdict = speed_verdict(report)
    assert "0.85x fp32 (10.04 against 8.55 ms" in verdict
    assert ("Its 11 recurrent projections at 8 bits; a timed candidate within budget with those nodes in float "
            "runs 1.10x (--no-int16 --objective latency ships it") in verdict
    report["precision_search"]["int16_nodes"] = ["a", "b"]
    assert ("Its 2 nodes run at 16 bits in float behind a DequantizeLinear on ONNX Runtime and its 11 recurrent "
            "projections at 8 bits;") in speed_verdict(report)
    report["precision_search"] = {"int16_nodes": [], "int8_recurrent_nodes": ["Gemm_0"]}
    assert "Its 1 recurrent projection at 8 bits; a timed candidate within budget with it in float" in (
        speed_verdict(report))


def test_a_faster_candidate_other_than_the_chosen_one_is_what_latency_picks() -> None:
    report = _report(8.05, 8.85, bf16=False)
    report["artifact_timing"] = {"p50_ms": 10.0, "fp32_p50_ms": 8.5}
    report["search"]["candidates"].append(_candidate("top3", 7.0, True))
    verdict = speed_verdict(report)
    assert "A timed candidate within budget runs 1.26x (--objective latency picks it)." in verdict
    report["search"]["candidates"][-1]["within_budget"] = False  # over budget: not offered
    assert "The search timed this same graph at 1.10x" in speed_verdict(report)


def test_the_verdict_quotes_the_artifact_timings_interval_and_says_when_it_holds_1x() -> None:
    report = _report(8.0, 8.0, bf16=False)
    report["artifact_timing"] = {"p50_ms": 10.0, "fp32_p50_ms": 8.5, "timer": {"steps": 200},
                                 "interval": {"speedup": 0.85, "low": 0.80, "high": 0.91, "coverage": 0.8, "rounds": 20}}
    verdict = speed_verdict(report)
    assert "0.85x fp32 (10.00 against 8.50 ms per step; 200 steps, 80% interval 0.80-0.91x)." in verdict
    report["artifact_timing"]["interval"].update(low=0.83, high=1.02)
    assert ("(10.00 against 8.50 ms per step; 200 steps, 80% interval 0.83-1.02x: level with fp32 within "
            "this host's timing noise)") in speed_verdict(report)
    report["artifact_timing"].update(p50_ms=8.0, fp32_p50_ms=9.0)
    report["artifact_timing"]["interval"].update(low=1.05, high=1.2)
    assert speed_verdict(report).endswith("runs 1.12x fp32 on this vnni host (avx2 avx512_vnni) "
                                          "(200 steps, 80% interval 1.05-1.20x).")
    report["artifact_timing"]["interval"].update(low=1.0)
    assert "80% interval 1.00-1.20x: level with fp32 within this host's timing noise" in speed_verdict(report)
