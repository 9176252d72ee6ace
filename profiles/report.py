"""report.md and plots from the profile / model-info report dict (report.json is that dict)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.profiles.flops import GROUP_NAMES, PAPER_EFFICIENCY, PAPER_FRAMES

CONVENTION_LINE = (
    "Counting convention: MACs per pose update (one step, batch 1) = Conv/Gemm/MatMul MACs + "
    "GridSample bilinear (4 MACs per sampled value per channel) + S5 and Kalman recurrences by "
    "formula; FLOPs = 2 x MACs. The paper counts FLOPs = 2 x MACs over a 2-frame input, so the "
    f"column compared with it is **2 x MACs x {PAPER_FRAMES} frames** (\"paper convention\")."
)


def _g(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def module_table(counts: Mapping[str, Any], reference: Mapping[str, Any] | None = None) -> list[str]:
    """Markdown rows: per module params, MACs and FLOPs per update, paper-convention G, paper G.

    `counts` is a FlopCount dict; `reference` an optional second one (the other counter)."""
    paper = PAPER_EFFICIENCY["gflops_per_module"]
    header = "| module | params | MACs / update (G) | FLOPs / update (G) | ours, paper convention (G) | paper (G) |"
    if reference is not None:
        header += f" {reference['source']} MACs (G) |"
    rows = [header, "|" + "---|" * (header.count("|") - 1)]
    for group in [*GROUP_NAMES, "total"]:
        entry = counts if group == "total" else counts["modules"][group]
        if group == "other" and entry["macs"] == 0 and not entry.get("params"):
            continue
        macs = entry["macs"]
        paper_g = PAPER_EFFICIENCY["gflops"] if group == "total" else paper.get(group)
        row = (f"| {group} | {_params(entry.get('params'))} | {macs / 1e9:.4g} | {2 * macs / 1e9:.4g} | "
               f"{2 * macs * PAPER_FRAMES / 1e9:.4g} | {_g(paper_g)} |")
        if reference is not None:
            other = reference if group == "total" else reference["modules"][group]
            row += f" {other['macs'] / 1e9:.4g} |"
        rows.append(row)
    return rows


def _params(value: int | None) -> str:
    return "-" if value is None else f"{value / 1e6:.4g} M"


def target_table(targets: Sequence[Mapping[str, Any]]) -> list[str]:
    rows = ["| target | available | p50 ms | p90 ms | p99 ms | Hz (p50) | runtime p50 ms | Python p50 ms | GFLOP/s | "
            "of matmul peak | peak RSS MB | RSS growth MB | model MB | reason |", "|" + "---|" * 14]
    for t in targets:
        lat = t.get("latency_ms") or {}
        share = t.get("peak_fraction")
        rows.append(
            f"| {t['name']} | {'yes' if t['available'] else 'no'} | {_g(lat.get('p50'))} | {_g(lat.get('p90'))} | "
            f"{_g(lat.get('p99'))} | {_g(t.get('hz'))} | {_g((t.get('runtime_ms') or {}).get('p50'))} | "
            f"{_g((t.get('overhead_ms') or {}).get('p50'), 2)} | {_g(t.get('gflops_achieved'))} | "
            f"{'-' if share is None else format(100 * share, '.0f') + '%'} | "
            f"{_g(t.get('peak_rss_mb'), 4)} | {_g(t.get('rss_growth_mb'))} | {_g((t.get('model_bytes') or 0) / 1e6 or None)} | {t.get('reason') or ''} |"
        )
    return rows


def cpu_time_sentence(cpu_time: Mapping[str, Any] | None) -> str:
    """' CPU time during ...: busy x%, idle y%, stolen by the hypervisor z%.' or '' (no /proc/stat)."""
    parts = []
    for phase, label in (("timed_steps", "the timed steps"), ("outside_timers", "the outside timers")):
        shares = (cpu_time or {}).get(phase)
        if shares:
            parts.append(f"{label}: busy {100 * shares['busy']:.0f}%, idle {100 * shares['idle']:.0f}%, "
                         f"stolen by the hypervisor {100 * shares['steal']:.0f}%")
    return f" The machine's CPU time during {'; during '.join(parts)}." if parts else ""


def turn_paired_cell(entry: Mapping[str, Any]) -> str:
    """The turn-paired agreement and the turns it is over ("1.012 (3 of 4 turns)"), or why there is none."""
    steady, turns = entry.get("agreement_steady_turns"), (entry.get("outside") or {}).get("round_p50_ms") or ()
    if steady is None:
        return _g(entry.get("agreement"))
    if entry.get("agreement") is None:
        return f"- (the runner's speed changed across each of the {len(turns)} turns)" if steady == 0 else "-"
    return f"{entry['agreement']:.3f} ({steady} of {len(turns)} turns)"


def agreement_table(targets: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each measured target's runtime figure beside its outside timer's median, both timed in
    turns (profiles.agreement), with the side-by-side figures for reference."""
    rows = ["| target | profile p50 ms (step, side by side) | runtime p50 ms (side by side) | runtime p50 ms "
            "(in turns with the tool; each burst) | outside timer | outside p50 ms (each turn) | runtime / outside, "
            "turn-paired | fastest burst / fastest turn | medians |", "|---|---|---|---|---|---|---|---|---|"]
    for t in targets:
        outside = t.get("outside")
        if not t.get("latency_ms") or outside is None:
            continue
        if outside.get("p50_ms") is None:
            figure = f"- ({outside.get('reason')})"
        else:
            turns = outside.get("round_p50_ms") or ()
            figure = _g(outside["p50_ms"]) + (f" ({', '.join(_g(v) for v in turns)})" if len(turns) > 1 else "")
            figure += f"; {outside['note']}" if outside.get("note") else ""
        bursts = t.get("beside_burst_ms") or ()
        beside = _g(t.get("beside_ms")) + (f" ({', '.join(_g(v) for v in bursts)})" if len(bursts) > 1 else "")
        rows.append(f"| {t['name']} | {_g(t['latency_ms']['p50'])} | {_g((t.get('runtime_ms') or {}).get('p50'))} | "
                    f"{beside} | {outside['tool']} | {figure} | {turn_paired_cell(t)} | "
                    f"{_g(t.get('agreement_fastest'))} | {_g(t.get('agreement_median'))} |")
    return rows if len(rows) > 2 else []


def model_info_markdown(report: Mapping[str, Any]) -> str:
    model = report["model"]
    lines = [f"# E-3DPSM model info: `{model['variant']}`", "",
             f"Parameters: **{model['params'] / 1e6:.4g} M** (paper: {PAPER_EFFICIENCY['params_m']} M).", "",
             CONVENTION_LINE, "", *module_table(report["counting"]["pytorch"]), ""]
    return "\n".join(lines)


def profile_markdown(report: Mapping[str, Any]) -> str:
    from e3dpsm.profiles.verdict import verdict_line

    counting, inputs = report["counting"], report["inputs"]
    lines = [f"# E-3DPSM profile: `{report['model']['variant']}`", "", verdict_line(report.get("verdict")), "",
             f"Created {report['created']} on {report['machine'].get('cpu_model', report['machine']['platform'])} "
             f"({report['machine']['cpu_count']} CPUs); {inputs['threads']} threads per target; "
             f"{inputs['steps']} timed steps after {inputs['warmup']} warm-up steps, states carried, inputs: "
             f"{inputs['source']} ({inputs['window_ms']:g} ms windows). Targets measured side by side in one process, "
             f"taking turns every {inputs['chunk']} steps.{cpu_time_sentence(report.get('cpu_time'))}", "",
             "## Parameters and compute per pose update", "", CONVENTION_LINE, ""]
    primary = counting.get("pytorch") or counting.get("onnx")
    secondary = counting.get("onnx") if counting.get("pytorch") else None
    lines += module_table(primary, secondary)
    if counting.get("relative_difference") is not None:
        lines += ["", f"PyTorch vs ONNX MACs differ by {100 * counting['relative_difference']:.3f}%."]
    lines += ["", "## Latency per target", "", *target_table(report["targets"]), "",
              "Runtime p50 is the runtime's own call alone (ONNX Runtime `run`, OpenVINO `infer`, PyTorch "
              "`model.step`); Python p50 is the rest of the step measured apart: feeds built and checked, states "
              "handed over, outputs copied out. "
              "Peak RSS is the whole process while the target loads and runs its first steps (it includes "
              "Python, torch and the targets loaded before it); RSS growth is the increase during that phase.", ""]
    agreement = agreement_table(report["targets"])
    if agreement:
        lines += ["## Against the runtimes' own timers", "",
                  "Each CPU target's runtime figure beside the runtime's own tool on the same graph, inputs and "
                  "settings (`benchmark_app` with one stream, synchronous requests, the target's threads, precision "
                  "and compile properties; `onnxruntime_perf_test` where installed, else ONNX Runtime's profiler, "
                  "whose median `model_run` includes its own per-node cost; its kernels' sum is noted beside it). "
                  f"Each tool runs {inputs.get('outside_seconds', '?')} s in {inputs.get('outside_turns', 1)} turns, the "
                  "target's own runner timing a burst of steps before each turn and after the last, so the two "
                  "figures compared are taken over the same minutes. The agreement is turn-paired: each turn's "
                  "median against the mean of the two bursts around it, the median over the turns whose two "
                  "bursts are within 10% of each other (the host kept one speed across them); the fastest burst "
                  "over the fastest turn and the ratio of the medians are beside it.", "",
                  *agreement, ""]
    if report.get("ratios"):
        lines += ["Speed-ups over the baselines, round by round (the median over the side-by-side rounds of each "
                  "round's baseline median over the target's: drift slower than a round cancels):", ""]
        lines += [f"- {name}: **{value:.2f}x**" for name, value in report["ratios"].items()]
        lines.append("")
    peak = report.get("machine_peak")
    if peak:
        each = ", ".join(f"{lib} {rate:.0f}" for lib, rate in peak.get("by_library", {}).items())
        lines += [f"Machine matmul peak ({peak['size']}^3 float32, {peak['threads']} threads, best of the libraries "
                  f"present: {each} GFLOP/s): **{peak['gflops']:.1f} GFLOP/s** ({peak['library']}; best of the "
                  f"measurements before and after the timed steps: "
                  f"{', '.join(f'{g:.0f}' for g in peak.get('measured_gflops', [peak['gflops']]))}).", ""]
    for name, prof in (report.get("ort_profiles") or {}).items():
        lines += [f"### Where time goes: {name} (onnxruntime profiling, ms per step)", "",
                  f"Kernel time {prof['kernel_ms_per_step']:.2f} ms / step over {prof['steps']} profiled steps.", "",
                  "| op type | ms | module | ms |", "|---|---|---|---|"]
        ops = list(prof["by_op_type_ms"].items())[:10]
        mods = list((prof.get("by_module_ms") or {}).items())
        for k in range(max(len(ops), len(mods))):
            op = ops[k] if k < len(ops) else ("", None)
            mod = mods[k] if k < len(mods) else ("", None)
            lines.append(f"| {op[0]} | {_g(op[1])} | {mod[0]} | {_g(mod[1])} |")
        lines.append("")
        bound = prof.get("int8_speedup_bound") or {}
        if bound.get("quantisable_ms"):
            lines += [f"Ops that INT8 quantisation replaces (Conv / MatMul / Gemm): {bound['quantisable_ms']:.2f} ms "
                      f"({100 * bound['quantisable_share']:.0f}%); the rest stays float ({bound['float_rest_ms']:.2f} ms), "
                      f"so no INT8 graph of this model can beat this one by more than "
                      f"**{bound['max_speedup']:.2f}x** (Amdahl, quantised ops at zero cost).", ""]
    if report.get("devices"):
        lines += ["## Reference devices: roofline ESTIMATE vs the paper's measured rate", "",
                  "Estimate = min(peak compute / FLOPs, bandwidth / bytes moved per step); an upper bound that "
                  "ignores launch and framework overhead. Peaks from vendor datasheets (profiles/devices.toml).", "",
                  "| device | precision | estimate Hz | bound | paper measured Hz |", "|---|---|---|---|---|"]
        for d in report["devices"]:
            lines.append(f"| {d['device']} | {d['precision']} | {d['hz_estimate']:.0f} | {d['bound']} | "
                         f"{_g(d['paper_measured_hz'])} |")
        lines.append("")
    lines += ["Plots: `latency.png` (latency distribution per target), `macs_per_module.png`.", ""]
    return "\n".join(lines)


def plot_latency(times_ms: Mapping[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 0.6 * len(times_ms) + 1.5))
    names = list(times_ms)
    # matplotlib 3.10 replaced `vert` by `orientation`
    horizontal = {"orientation": "horizontal"} if _version(matplotlib.__version__) >= (3, 10) else {"vert": False}
    ax.boxplot([times_ms[n] for n in names], showfliers=True, whis=(1, 99), **horizontal)
    ax.set_yticks(range(1, len(names) + 1), names)
    ax.set_xlabel("latency per pose update (ms); whiskers p1-p99")
    ax.set_title("Step latency per target")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in text.split(".")[:2] if part.isdigit())


def plot_macs(counts: Mapping[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [g for g in GROUP_NAMES if g in PAPER_EFFICIENCY["gflops_per_module"]]
    ours = [max(2 * counts["modules"][g]["macs"] * PAPER_FRAMES / 1e9, 1e-7) for g in groups]
    paper = [PAPER_EFFICIENCY["gflops_per_module"][g] for g in groups]
    x = np.arange(len(groups))
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.bar(x - 0.2, ours, 0.4, label=f"ours ({counts['source']}), 2 x MACs x {PAPER_FRAMES} frames")
    ax.bar(x + 0.2, paper, 0.4, label="paper")
    ax.set_xticks(x, groups, rotation=20)
    ax.set_yscale("log")
    ax.set_ylabel("GFLOPs (paper convention)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
