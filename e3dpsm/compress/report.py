"""`e3dpsm prune`'s report: the accuracy-latency front, one row per round (report.md,
report.json beside it, front.png)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

RUNTIME_COLUMNS: tuple[tuple[str, str], ...] = (
    ("ort_fp32", "ORT fp32"), ("ov_fp32", "OV fp32"), ("ort_int8", "ORT INT8"), ("ov_int8", "OV INT8"))


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def front_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per round (0: unpruned) with the final side-by-side timings."""
    timings = result.get("final_timing_ms", {})
    base_mpjpe = result["rounds"][0]["heldout"]["mpjpe_mm"]
    rows = []
    for r in result["rounds"]:
        k = r["round"]
        row = {
            "round": k, "macs": r["macs"], "macs_fraction": r["macs_fraction"], "params": r["params"],
            "onnx_bytes": r.get("onnx_bytes"), "mpjpe_mm": r["heldout"]["mpjpe_mm"],
            "mpjpe_change_pct": 100.0 * (r["heldout"]["mpjpe_mm"] / base_mpjpe - 1.0),
            "to_teacher_mm": r["heldout"].get("to_teacher_mm"),
            "predicted_ms": r.get("predicted_vs_measured", {}).get("predicted_ms"),
            "measured_in_round_ms": r.get("predicted_vs_measured", {}).get("measured_ms"),
            "speedup_in_round": r.get("speedup_side_by_side"),
            "recovery_s": (r.get("recovery") or {}).get("seconds"),
        }
        for key, _ in RUNTIME_COLUMNS:
            row[key] = timings.get(f"r{k}_{key}")
        rows.append(row)
    return rows


def render_markdown(result: dict[str, Any], header: dict[str, Any]) -> str:
    cfg = result["config"]
    if cfg["target_macs"] is not None:
        target = f"MACs <= {cfg['target_macs']:g} of unpruned"
    else:
        ms = result["rounds"][-1].get("target_ms") or cfg["target_latency_ms"]
        pct = f" ({cfg['target_latency_pct']:g}% of the unpruned step)" if cfg.get("target_latency_pct") else ""
        target = (f"fp32 step <= {ms:.2f} ms{pct} on {cfg['target_runtime']}, read against the unpruned graph "
                  "timed beside it (load-corrected)")
    isa = header.get("machine", {}).get("isa", {})
    lines = [
        "# e3dpsm prune", "",
        f"Target: {target}; result: round {result['best']} ({'met, measured' if result['met'] else 'NOT met'}). "
        f"Threads {cfg['threads']}, {cfg['steps']} distillation steps per round (labels {cfg['labels']}). "
        f"CPU: {header.get('machine', {}).get('cpu_model', '?')}, ISA {isa.get('kind', '?')} ({', '.join(isa.get('flags', []))}).",
        "",
        "Step times: median ms, batch 1, states carried, every graph timed side by side in one final run. "
        "Predicted and measured ms: the latency model's prediction for the round against the round's "
        "measured step, both read against the unpruned graph timed beside it (start-of-run units); "
        "speed-up: unpruned / pruned in that side-by-side run.",
        "",
        "| round | MACs (M) | of unpruned | params | ONNX MB | ORT fp32 | OV fp32 | ORT INT8 | OV INT8 "
        "| held-out MPJPE | vs unpruned | to teacher | predicted ms | measured ms | speed-up | recovery s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in front_rows(result):
        mb = "-" if row["onnx_bytes"] is None else f"{row['onnx_bytes'] / 1e6:.2f}"
        lines.append(
            f"| {row['round']} | {row['macs'] / 1e6:.1f} | {row['macs_fraction']:.3f} | {row['params']:,} | {mb} "
            + "".join(f"| {_ms(row[k])} " for k, _ in RUNTIME_COLUMNS)
            + f"| {row['mpjpe_mm']:.2f} | {row['mpjpe_change_pct']:+.2f}% | {_ms(row['to_teacher_mm'])} "
            f"| {_ms(row['predicted_ms'])} | {_ms(row['measured_in_round_ms'])} | {_ms(row['speedup_in_round'])} "
            f"| {_ms(row['recovery_s'])} |")
    int8 = [(r["round"], r["int8"]) for r in result["rounds"] if r.get("int8")]
    if int8:
        lines += ["", "## INT8 after pruning (static, recurrences in float, min-max ranges; the quantiser's "
                  "held-out check)", "", "| round | split | frames | fp32 MPJPE | INT8 MPJPE | INT8 vs fp32 |",
                  "|---:|---|---:|---:|---:|---:|"]
        for k, q in int8:
            lines.append(f"| {k} | {q['split']} | {q['frames']} | {q['fp32_mpjpe_mm']:.2f} | {q['mpjpe_mm']:.2f} "
                         f"| {q['loss_pct']:+.2f}% |")
    lines += ["", "## Cuts per round (unit: new width; 0 removes)", ""]
    for r in result["rounds"][1:]:
        cuts = ", ".join(f"{u} {w}" for u, w in r["cuts"].items())
        lines.append(f"- round {r['round']}: {cuts}")
    lines += ["", "## MACs per stage (M)", ""]
    stages = sorted({s for r in result["rounds"] for s in r["macs_per_stage"]})
    lines.append("| round | " + " | ".join(stages) + " |")
    lines.append("|---:|" + "---:|" * len(stages))
    for r in result["rounds"]:
        lines.append(f"| {r['round']} | " + " | ".join(f"{r['macs_per_stage'].get(s, 0) / 1e6:.2f}" for s in stages) + " |")
    lines += ["", "## Step time per unit (ORT profile, kernel ms)", ""]
    units = sorted({u for r in result["rounds"] for u in r["profile"]["units"]})
    lines.append("| round | run ms | kernels | dispatch/node us | " + " | ".join(units) + " |")
    lines.append("|---:|---:|---:|---:|" + "---:|" * len(units))
    for r in result["rounds"]:
        p = r["profile"]
        lines.append(f"| {r['round']} | {p['run_ms']:.2f} | {p['kernel_ms']:.2f} | {1e3 * p['dispatch_ms_per_node']:.1f} | "
                     + " | ".join(_ms(p["units"].get(u, {}).get("kernel_ms")) for u in units) + " |")
    return "\n".join(lines) + "\n"


def front_figure(result: dict[str, Any]) -> Any:
    """The front as a matplotlib figure: held-out MPJPE against the final step time, one line
    per runtime timed, each point labelled with its round."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = front_rows(result)
    fig, ax = plt.subplots(figsize=(6, 4))
    for key, label in RUNTIME_COLUMNS:
        pts = [(r[key], r["mpjpe_mm"], r["round"]) for r in rows if r[key] is not None]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=label)
            for x, y, k in pts:
                ax.annotate(str(k), (x, y), textcoords="offset points", xytext=(3, 3), fontsize=8)
    ax.set_xlabel("step time (ms, median, side by side)")
    ax.set_ylabel("held-out MPJPE (mm)")
    ax.set_title("pruning rounds: accuracy vs latency (labels: round)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def plot_front(result: dict[str, Any], path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig = front_figure(result)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
