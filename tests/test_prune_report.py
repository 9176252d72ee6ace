"""`e3dpsm prune`'s report (compress/report.py) from a hand-made two-round result: the front's
rows and the whole markdown, line by line, for both kinds of target."""
from __future__ import annotations

import copy

import pytest

from e3dpsm.compress.report import front_figure, front_rows, plot_front, render_markdown

HEADER = {"machine": {"cpu_model": "Test CPU", "isa": {"kind": "vnni", "flags": ["avx2", "avx512_vnni"]}}}


def _round(k: int, macs: int, fraction: float, mpjpe: float, **extra) -> dict:
    return {"round": k, "macs": macs, "macs_fraction": fraction, "params": 1234567 - 1000 * k,
            "heldout": {"mpjpe_mm": mpjpe, **({"to_teacher_mm": 1.5 * k} if k else {})},
            "macs_per_stage": {"stage0": 3_000_000 - k * 1_000_000, "decoder": 500_000},
            "profile": {"run_ms": 10.0 - k, "kernel_ms": 8.0 - k, "dispatch_ms_per_node": 0.1,
                        "units": {"stages.0.block1": {"kernel_ms": 1.25}, **({"attention.1": {"kernel_ms": 0.5}}
                                                                            if k == 0 else {})}},
            **extra}


RESULT = {
    "config": {"target_macs": 0.6, "target_latency_ms": None, "threads": 2, "steps": 0, "labels": "teacher"},
    "best": 1, "met": True,
    "final_timing_ms": {"r0_ort_fp32": 10.0, "r0_ov_fp32": 9.5, "r1_ort_fp32": 6.25, "r1_ort_int8": 4.0},
    "rounds": [
        _round(0, 12_000_000, 1.0, 40.0, onnx_bytes=2_500_000),
        _round(1, 6_600_000, 0.55, 42.0, cuts={"stages.0.block1": 4, "attention.1": 0},
               predicted_vs_measured={"predicted_ms": 6.0, "measured_ms": 6.4}, speedup_side_by_side=1.6,
               recovery={"seconds": 12.345},
               int8={"split": "test", "frames": 64, "fp32_mpjpe_mm": 42.0, "mpjpe_mm": 42.5, "loss_pct": 1.19}),
    ],
}


def test_front_rows_carry_each_rounds_figures() -> None:
    rows = front_rows(RESULT)
    assert rows[0] == {"round": 0, "macs": 12_000_000, "macs_fraction": 1.0, "params": 1234567,
                       "onnx_bytes": 2_500_000, "mpjpe_mm": 40.0, "mpjpe_change_pct": 0.0, "to_teacher_mm": None,
                       "predicted_ms": None, "measured_in_round_ms": None, "speedup_in_round": None,
                       "recovery_s": None, "ort_fp32": 10.0, "ov_fp32": 9.5, "ort_int8": None, "ov_int8": None}
    assert rows[1] == {"round": 1, "macs": 6_600_000, "macs_fraction": 0.55, "params": 1233567, "onnx_bytes": None,
                       "mpjpe_mm": 42.0, "mpjpe_change_pct": pytest.approx(5.0), "to_teacher_mm": 1.5,
                       "predicted_ms": 6.0, "measured_in_round_ms": 6.4, "speedup_in_round": 1.6,
                       "recovery_s": 12.345, "ort_fp32": 6.25, "ov_fp32": None, "ort_int8": 4.0, "ov_int8": None}
    assert front_rows({**RESULT, "final_timing_ms": {}})[1]["ort_fp32"] is None  # not timed at the end
    untimed = front_rows({key: value for key, value in RESULT.items() if key != "final_timing_ms"})
    assert [row["ort_fp32"] for row in untimed] == [None, None]  # a run with no final timing


def test_the_markdown_of_a_macs_target_line_by_line() -> None:
    assert render_markdown(RESULT, HEADER).splitlines() == [
        "# e3dpsm prune", "",
        "Target: MACs <= 0.6 of unpruned; result: round 1 (met, measured). Threads 2, 0 distillation steps per "
        "round (labels teacher). CPU: Test CPU, ISA vnni (avx2, avx512_vnni).",
        "",
        "Step times: median ms, batch 1, states carried, every graph timed side by side in one final run. "
        "Predicted and measured ms: the latency model's prediction for the round against the round's "
        "measured step, both read against the unpruned graph timed beside it (start-of-run units); "
        "speed-up: unpruned / pruned in that side-by-side run.",
        "",
        "| round | MACs (M) | of unpruned | params | ONNX MB | ORT fp32 | OV fp32 | ORT INT8 | OV INT8 "
        "| held-out MPJPE | vs unpruned | to teacher | predicted ms | measured ms | speed-up | recovery s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        "| 0 | 12.0 | 1.000 | 1,234,567 | 2.50 | 10.00 | 9.50 | - | - | 40.00 | +0.00% | - | - | - | - | - |",
        "| 1 | 6.6 | 0.550 | 1,233,567 | - | 6.25 | - | 4.00 | - | 42.00 | +5.00% | 1.50 | 6.00 | 6.40 | 1.60 | 12.35 |",
        "",
        "## INT8 after pruning (static, recurrences in float, min-max ranges; the quantiser's held-out check)",
        "",
        "| round | split | frames | fp32 MPJPE | INT8 MPJPE | INT8 vs fp32 |",
        "|---:|---|---:|---:|---:|---:|",
        "| 1 | test | 64 | 42.00 | 42.50 | +1.19% |",
        "",
        "## Cuts per round (unit: new width; 0 removes)", "",
        "- round 1: stages.0.block1 4, attention.1 0",
        "",
        "## MACs per stage (M)", "",
        "| round | decoder | stage0 |",
        "|---:|---:|---:|",
        "| 0 | 0.50 | 3.00 |",
        "| 1 | 0.50 | 2.00 |",
        "",
        "## Step time per unit (ORT profile, kernel ms)", "",
        "| round | run ms | kernels | dispatch/node us | attention.1 | stages.0.block1 |",
        "|---:|---:|---:|---:|---:|---:|",
        "| 0 | 10.00 | 8.00 | 100.0 | 0.50 | 1.25 |",
        "| 1 | 9.00 | 7.00 | 100.0 | - | 1.25 |",
    ]


def test_a_latency_target_and_a_missed_one_are_said() -> None:
    result = copy.deepcopy(RESULT)
    result["config"].update(target_macs=None, target_latency_ms=5.0, target_latency_pct=50.0,
                            target_runtime="onnxruntime")
    result["met"] = False
    last = {key: value for key, value in copy.deepcopy(result["rounds"][1]).items() if key != "int8"}
    result["rounds"].append({**last, "round": 2, "cuts": {"stages.0.block1": 2},
                             "target_ms": 4.75})  # the last round's target is the one named
    result["rounds"][1]["target_ms"] = 9.99
    result["rounds"][1]["macs_per_stage"] = {"stage0": 2_000_000}  # the decoder's MACs left out of round 1
    del result["rounds"][1]["int8"]
    lines = render_markdown(result, {}).splitlines()
    assert lines[2] == ("Target: fp32 step <= 4.75 ms (50% of the unpruned step) on onnxruntime, read against the "
                        "unpruned graph timed beside it (load-corrected); result: round 1 (NOT met). Threads 2, 0 "
                        "distillation steps per round (labels teacher). CPU: ?, ISA ? ().")
    assert "## INT8 after pruning" not in "\n".join(lines)
    assert "| 1 | 0.00 | 2.00 |" in lines  # a stage a round lacks reads 0
    del result["rounds"][2]["target_ms"]
    del result["config"]["target_latency_pct"]
    assert render_markdown(result, {}).splitlines()[2].startswith(
        "Target: fp32 step <= 5.00 ms on onnxruntime, read against")


def test_the_front_is_plotted(tmp_path) -> None:
    """One line per runtime timed at the end (MPJPE against its step time), each point labelled
    with its round, the axes named; written as a PNG."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    fig = front_figure(RESULT)
    ax = fig.axes[0]
    lines = {line.get_label(): (list(line.get_xdata()), list(line.get_ydata())) for line in ax.get_lines()}
    assert lines == {"ORT fp32": ([10.0, 6.25], [40.0, 42.0]), "OV fp32": ([9.5], [40.0]), "ORT INT8": ([4.0], [42.0])}
    assert [t.get_text() for t in ax.legend_.get_texts()] == ["ORT fp32", "OV fp32", "ORT INT8"]
    assert [(t.get_text(), t.xy) for t in ax.texts] == [("0", (10.0, 40.0)), ("1", (6.25, 42.0)), ("0", (9.5, 40.0)),
                                                        ("1", (4.0, 42.0))]
    assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_title()) == (
        "step time (ms, median, side by side)", "held-out MPJPE (mm)", "pruning rounds: accuracy vs latency (labels: round)")
    plt.close(fig)
    timed_ov_int8 = copy.deepcopy(RESULT)
    timed_ov_int8["final_timing_ms"] = {"r1_ov_int8": 3.0}
    fig = front_figure(timed_ov_int8)
    assert [line.get_label() for line in fig.axes[0].get_lines()] == ["OV INT8"]
    plt.close(fig)
    path = plot_front(RESULT, tmp_path / "front.png")
    assert path == tmp_path / "front.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
