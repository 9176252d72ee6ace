"""Benchmark: does `e3dpsm profile` agree with the runtimes' own timers and with bare loops?

    python benchmarks/bench_profile_agreement.py --variants small paper --threads 2 \
        [--steps 150] [--outside-seconds 8] [--outside-turns 4] [--work runs/profile_agreement] \
        [--out benchmarks/results]

Per variant (initial weights, seed 0: latency does not depend on training), in one run:

1. the dynamic-batch and `--static-batch` graphs, exported once with `e3dpsm export`;
2. `e3dpsm profile --model DYN --static-model STATIC` on the CPU targets (its own side-by-side
   medians: whole step, the runtime's call, the Python overhead; and each target's outside
   timer: OpenVINO's benchmark_app, ONNX Runtime's profiler or onnxruntime_perf_test, run in
   turns with the target's own runner);
3. bare stepping loops, a few lines of plain ONNX Runtime / OpenVINO calls each (ONNX
   Runtime's default options but the thread count and threads that stop spinning after a
   run, OpenVINO compiled with the profile's properties; states carried), on both graphs side by side with the profile's own runners
   on the same graphs;
4. a diagnosis on the dynamic graph, side by side: OpenVINO's step right after an ONNX
   Runtime turn with ORT's threads spinning on (its default) and stopped at the end of a run,
   and the profile's OpenVINO runner beside a bare `infer(feeds)` loop.

Checks (reported, not asserted; the machine's load is recorded beside them): each profile
figure within 10% of its outside timer (both timed in turns; each turn against the two bursts
around it, profiles.agreement.turn_paired_agreement; the fastest burst over the fastest turn and the
medians' ratio beside it); the profile's OpenVINO / ONNX
Runtime ratio within 10% of the bare loops' ratio on each graph (the runners timed in turns
with the loops; the `e3dpsm profile` run's own ratio shown beside). Writes OUT/profile_agreement_<isa kind>.json and .md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

TARGETS = ("ort-cpu-fp32", "ort-cpu-fp32-static", "openvino-cpu-fp32", "openvino-cpu-fp32-static",
           "openvino-cpu-stateful-fp32-static", "openvino-cpu-bf16-static")
PAIRS = {"dynamic": ("openvino-cpu-fp32", "ort-cpu-fp32"), "static": ("openvino-cpu-fp32-static", "ort-cpu-fp32-static")}
TOLERANCE = 0.10
RUNS = Path(__file__).resolve().parents[1] / "runs"  # git-ignored scratch of the repository
CHUNK = 25


def e3dpsm(*args: str) -> None:
    print("$ e3dpsm " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "e3dpsm", *args], check=True)


def export_graphs(variant: str, work: Path) -> dict[str, Path]:
    graphs = {"dynamic": work / "dynamic" / "step.onnx", "static": work / "static" / "step.onnx"}
    for kind, path in graphs.items():
        if not path.is_file():
            extra = ["--static-batch"] if kind == "static" else []
            e3dpsm("export", "--variant", variant, "--out", str(path.parent), "--ort-optimized", "none", "--force", *extra)
    return graphs


def run_profile(graphs: dict[str, Path], targets: list[str], args: argparse.Namespace, out: Path) -> dict[str, Any]:
    e3dpsm("profile", "--model", str(graphs["dynamic"]), "--static-model", str(graphs["static"]),
           "--targets", ",".join(targets), "--threads", str(args.threads), "--steps", str(args.steps),
           "--warmup", str(args.warmup), "--outside-seconds", str(args.outside_seconds),
           "--outside-turns", str(args.outside_turns),
           "--profile-steps", str(args.profile_steps), "--out", str(out), "--force", "--no-progress")
    return json.loads((out / "report.json").read_text())


# -- bare loops: plain runtime calls, no project code ----------------------------------------
def _graph_io(path: Path) -> tuple[list[tuple[str, str]], str, str, tuple[int, int]]:
    """(state input -> output name pairs, frame name, window name, frame H x W) from the metadata."""
    import onnx

    props = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    states = json.loads(props["e3dpsm.states"])
    inputs = json.loads(props["e3dpsm.inputs"])
    frame = inputs["frame"]
    return ([(s["input"], s["output"]) for s in states], frame["name"], inputs["window"]["name"],
            (int(frame["shape"][2]), int(frame["shape"][3])))


def _initial_states(path: Path) -> dict[str, np.ndarray]:
    """Batch-1 initial states from the metadata: zeros, or the listed values (Kalman covariance)."""
    import onnx

    props = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    states = {}
    for s in json.loads(props["e3dpsm.states"]):
        shape = (1, *s["shape"][1:])
        states[s["input"]] = (np.zeros(shape, np.float32) if s["init"] == "zeros"
                              else np.asarray(s["init"], np.float32).reshape(shape))
    return states


def bare_ort(path: Path, threads: int, window_ms: float, stop_spinning: bool = False) -> Callable[[np.ndarray], None]:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    if stop_spinning:
        options.add_session_config_entry("session.force_spinning_stop", "1")
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    pairs, frame, window, _ = _graph_io(path)
    state = _initial_states(path)
    fixed = {window: np.array([window_ms], np.float32)}

    def step(lnes: np.ndarray) -> None:
        nonlocal state
        out = dict(zip(names, session.run(names, {frame: lnes, **fixed, **state})))
        state = {i: out[o] for i, o in pairs}
    return step


def profile_openvino_config(threads: int) -> dict[str, Any]:
    """The compile properties of the profile's openvino-cpu-fp32 targets (the bare loop uses
    them too: the check is of the profile's timing, not of its choice of properties)."""
    from e3dpsm.profiles.latency import openvino_target_config
    from e3dpsm.profiles.targets import load_targets, select_targets

    return openvino_target_config(select_targets(load_targets(), "openvino-cpu-fp32", threads)[0])


def bare_openvino(path: Path, threads: int, window_ms: float) -> Callable[[np.ndarray], None]:
    import openvino as ov

    compiled = ov.Core().compile_model(str(path), "CPU", profile_openvino_config(threads))
    request = compiled.create_infer_request()
    pairs, frame, window, _ = _graph_io(path)
    state = _initial_states(path)
    fixed = {window: np.array([window_ms], np.float32)}

    def step(lnes: np.ndarray) -> None:
        nonlocal state
        out = {name: value for port, value in request.infer({frame: lnes, **fixed, **state}).items()
               for name in port.get_names()}
        state = {i: out[o] for i, o in pairs}
    return step


def side_by_side(steppers: dict[str, Callable[[np.ndarray], None]], frames: np.ndarray, steps: int,
                 warmup: int) -> dict[str, np.ndarray]:
    """ms per step, turns of CHUNK steps; [steps] per stepper, in step order."""
    for step in steppers.values():
        for k in range(warmup):
            step(frames[k % len(frames)][None])
    ms = {name: np.empty(steps) for name in steppers}
    for start in range(0, steps, CHUNK):
        for name, step in steppers.items():
            for k in range(start, min(start + CHUNK, steps)):
                frame = frames[(warmup + k) % len(frames)][None]
                t0 = time.perf_counter()
                step(frame)
                ms[name][k] = (time.perf_counter() - t0) * 1e3
    return ms


def profile_stepper(path: Path, target_name: str, threads: int, window_ms: float) -> Callable[[np.ndarray], None]:
    """The profile's own runner for `target_name` on `path` (as `e3dpsm profile` builds it)."""
    from e3dpsm.profiles.profiler import build_runner
    from e3dpsm.profiles.targets import load_targets, select_targets

    target = select_targets(load_targets(), target_name, threads)[0]
    runner = build_runner(target, {target.graph_key: path}, None, window_ms)
    runner.reset()
    return runner.step


def bare_loops(graphs: dict[str, Path], frames: np.ndarray, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """ms per step of the bare loops and, in the same turns, of the profile's own runners on the
    same graphs; each ONNX Runtime loop's turn right before its OpenVINO partner's."""
    steppers = {}
    for kind in ("dynamic", "static"):
        # Threads stop spinning after a run: a spinning ONNX Runtime slows whichever loop runs next
        # (the diagnosis shows by how much), which is the side-by-side measurement's cost, not a runtime's.
        steppers[f"onnxruntime {kind}"] = bare_ort(graphs[kind], args.threads, 20.0, stop_spinning=True)
        steppers[f"openvino {kind}"] = bare_openvino(graphs[kind], args.threads, 20.0)
        ov_target, ort_target = PAIRS[kind]
        steppers[f"profile onnxruntime {kind}"] = profile_stepper(graphs[kind], ort_target, args.threads, 20.0)
        steppers[f"profile openvino {kind}"] = profile_stepper(graphs[kind], ov_target, args.threads, 20.0)
    return side_by_side(steppers, frames, args.bare_steps, args.warmup)


def diagnose(graph: Path, frames: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    """OpenVINO after a spinning / stopped ONNX Runtime turn, and the profile's runner beside bare infer."""
    from e3dpsm.profiles.latency import OpenVinoRunner
    from e3dpsm.profiles.targets import load_targets, select_targets

    runner = OpenVinoRunner(str(graph), select_targets(load_targets(), "openvino-cpu-fp32", args.threads)[0], 20.0)
    runner.reset()

    def profile_step(lnes: np.ndarray) -> None:
        runner.step(lnes)
    steppers = {"ort spinning": bare_ort(graph, args.threads, 20.0),
                "openvino after spinning ort": bare_openvino(graph, args.threads, 20.0),
                "ort stopped": bare_ort(graph, args.threads, 20.0, stop_spinning=True),
                "openvino after stopped ort": bare_openvino(graph, args.threads, 20.0),
                "openvino profile runner": profile_step}
    ms = side_by_side(steppers, frames, args.diagnose_steps, args.warmup)
    first = {name: t[np.arange(len(t)) % CHUNK == 0] for name, t in ms.items()}
    rest = {name: t[np.arange(len(t)) % CHUNK >= 2] for name, t in ms.items()}
    return {"steps": args.diagnose_steps, "chunk": CHUNK,
            "first_step_of_turn_ms": {n: float(np.median(v)) for n, v in first.items()},
            "steady_ms": {n: float(np.median(v)) for n, v in rest.items()}}


# -- checks and report -----------------------------------------------------------------------
def checks(profile: dict[str, Any], loops: dict[str, np.ndarray]) -> dict[str, Any]:
    """Each outside figure's agreement, and the OpenVINO / ONNX Runtime speed of the profile's
    runners beside the bare loops' (both turn-paired: profiles.step_timing.turn_paired_speedup;
    each ONNX Runtime loop's turn runs right before its OpenVINO partner's)."""
    from e3dpsm.profiles.outside import ORT_PROFILER
    from e3dpsm.profiles.step_timing import turn_paired_speedup

    targets = {t["name"]: t for t in profile["targets"] if t.get("latency_ms")}
    outside = {name: t["agreement"] for name, t in targets.items() if t.get("agreement") is not None}
    ratios, in_turns = {}, {}
    for kind, (ov_name, ort_name) in PAIRS.items():
        loop = turn_paired_speedup(loops[f"openvino {kind}"], loops[f"onnxruntime {kind}"], CHUNK)
        if ov_name in targets and ort_name in targets:
            prof = targets[ort_name]["latency_ms"]["p50"] / targets[ov_name]["latency_ms"]["p50"]
            ratios[kind] = {"profile": prof, "bare": loop, "relative": prof / loop}
        runners = turn_paired_speedup(loops[f"profile openvino {kind}"], loops[f"profile onnxruntime {kind}"], CHUNK)
        in_turns[kind] = {"profile": runners, "bare": loop, "relative": runners / loop,
                          "holds": abs(runners / loop - 1) <= TOLERANCE}
    return {"runners_beside_bare": in_turns,
            "outside": {n: {"ratio": r, "holds": abs(r - 1) <= TOLERANCE,
                            "held_to_it": targets[n]["outside"]["tool"] != ORT_PROFILER} for n, r in outside.items()},
            "ov_over_ort": {k: {**v, "holds": abs(v["relative"] - 1) <= TOLERANCE} for k, v in ratios.items()}}


def _holds(check: dict[str, Any] | None) -> str:
    if check is None:
        return "-"
    if not check.get("held_to_it", True):
        return "not held to it: the profiler's own per-node cost"
    return "yes" if check["holds"] else "NO"


def variant_rows(variant: str, result: dict[str, Any]) -> list[str]:
    from e3dpsm.profiles.report import turn_paired_cell

    rows = [f"### `{variant}`", "",
            "| target | profile p50 ms (step, side by side) | runtime p50 ms (side by side) | Python p50 ms | "
            "runtime p50 ms in turns with the tool (each burst) | outside timer | outside p50 ms (each turn) | "
            "runtime / outside, turn-paired | within 10% | fastest burst / fastest turn | medians |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for t in result["profile"]["targets"]:
        if not t.get("latency_ms"):
            rows.append(f"| {t['name']} | - | - | - | - | - | - | - | {t.get('reason') or ''} | - | - |")
            continue
        o = t.get("outside") or {}
        check = result["checks"]["outside"].get(t["name"])
        figure = "-" if o.get("p50_ms") is None else format(o["p50_ms"], ".2f")
        if o.get("round_p50_ms") and len(o["round_p50_ms"]) > 1:
            figure += " (" + ", ".join(format(v, ".2f") for v in o["round_p50_ms"]) + ")"
        if o.get("note"):
            figure += f"; {o['note']}"
        beside = "-" if t.get("beside_ms") is None else format(t["beside_ms"], ".2f")
        if t.get("beside_burst_ms"):
            beside += " (" + ", ".join(format(v, ".2f") for v in t["beside_burst_ms"]) + ")"
        median, fastest = t.get("agreement_median"), t.get("agreement_fastest")
        rows.append(f"| {t['name']} | {t['latency_ms']['p50']:.2f} | {t['runtime_ms']['p50']:.2f} | "
                    f"{t['overhead_ms']['p50']:.3f} | {beside} | {o.get('tool', '-')} | {figure} | "
                    f"{turn_paired_cell(t)} | {_holds(check)} | "
                    f"{'-' if fastest is None else format(fastest, '.3f')} | "
                    f"{'-' if median is None else format(median, '.3f')} |")
    rows += ["", "| graph | OpenVINO / ONNX Runtime speed (turn-paired): the profile's runners | bare loops | runners / bare | "
             "within 10% | the `e3dpsm profile` run's ratio of whole-run p50s (minutes earlier) | its / bare |",
             "|---|---|---|---|---|---|---|"]
    for kind, r in result["checks"]["runners_beside_bare"].items():
        run = result["checks"]["ov_over_ort"].get(kind)
        rows.append(f"| {kind} | {r['profile']:.3f} | {r['bare']:.3f} | {r['relative']:.3f} | "
                    f"{'yes' if r['holds'] else 'NO'} | {'-' if run is None else format(run['profile'], '.3f')} | "
                    f"{'-' if run is None else format(run['relative'], '.3f')} |")
    bare = ", ".join(f"{name} {ms:.2f}" for name, ms in result["bare_ms"].items())
    rows += ["", "The profile's runners and the bare loops (a few lines of plain runtime calls each: ONNX Runtime's "
             "default options but the thread count and spinning stopped after a run, OpenVINO compiled with the profile's properties) run in the same process, taking turns every "
             f"{CHUNK} steps; each speed ratio is the median over turns of the ONNX Runtime loop's turn median over its "
             "OpenVINO partner's, timed right after it; the `e3dpsm profile` run is a separate process minutes before them."]
    diag = result["diagnosis"]
    from e3dpsm.profiles.report import cpu_time_sentence

    cpu = result["profile"].get("cpu_time") or {}
    rows += ["", f"Bare loops side by side (p50 ms): {bare}.", "",
             "CPU time (`e3dpsm profile`):" + (cpu_time_sentence(cpu) or " not recorded (no /proc/stat)")
             + " Bare loops:" + (cpu_time_sentence({"timed_steps": result.get("bare_cpu_time")}) or " -"), "",
             f"Diagnosis on the dynamic graph ({diag['steps']} steps each, turns of {diag['chunk']}), p50 ms "
             "(first step of a turn / steady, from the third step of a turn):", ""]
    rows += [f"- {name}: {diag['first_step_of_turn_ms'][name]:.2f} / {diag['steady_ms'][name]:.2f}"
             for name in diag["steady_ms"]]
    verdict = result["profile"].get("verdict") or {}
    rows += ["", f"Profile's verdict: `{verdict.get('fastest')}`, {verdict.get('p50_ms', float('nan')):.2f} ms = "
             f"{verdict.get('hz', float('nan')):.1f} Hz.", ""]
    return rows


def markdown(report: dict[str, Any]) -> str:
    machine = report["machine"]
    lines = ["# Profile figures against the runtimes' own timers and bare loops", "",
             f"`{report['command_line']}`", "",
             f"{report['created']}, {machine.get('cpu_model', machine['platform'])} ({machine['cpu_count']} CPUs, ISA "
             f"{machine['isa']['kind']}: {' '.join(machine['isa']['flags'])}); onnxruntime "
             f"{report['versions']['onnxruntime']}, openvino {report['versions']['openvino']}; "
             f"{report['config']['threads']} threads. Load average (1 min) {report['load']['before'][0]:.2f} before, "
             f"{report['load']['after'][0]:.2f} after (`uptime`: {report['load']['uptime_after']}).", ""]
    for variant, result in report["variants"].items():
        lines += variant_rows(variant, result)
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", nargs="+", default=["small", "paper"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--outside-seconds", type=float, default=8.0)
    parser.add_argument("--outside-turns", type=int, default=4)
    parser.add_argument("--profile-steps", type=int, default=30)
    parser.add_argument("--diagnose-steps", type=int, default=100)
    parser.add_argument("--bare-steps", type=int, default=250, help="steps of each bare loop and runner beside them")
    parser.add_argument("--targets", default=",".join(TARGETS))
    parser.add_argument("--work", default=str(RUNS / "profile_agreement"),
                        help="folder for the exported graphs (kept and reused by later runs) and the "
                             "profile reports; default: runs/profile_agreement in the repository "
                             "(git-ignored)")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = parser.parse_args()

    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.utils.cpu_time import CpuShareMeter
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic
    from e3dpsm.utils.isa import bf16_unavailable_reason, detect_isa

    targets = [t for t in args.targets.split(",") if "bf16" not in t or bf16_unavailable_reason() is None]
    report = report_header("bench_profile_agreement", {k: v for k, v in vars(args).items()})
    report["command_line"] = "python benchmarks/bench_profile_agreement.py " + " ".join(sys.argv[1:])
    report["load"] = {"before": list(os.getloadavg())}
    report["variants"] = {}
    for variant in args.variants:
        work = Path(args.work) / variant
        graphs = export_graphs(variant, work)
        profile = run_profile(graphs, targets, args, work / "profile")
        height, width = _graph_io(graphs["dynamic"])[3]
        frames = moving_edge_frames(min(args.steps + args.warmup, 200), height, width, 20.0).lnes
        with CpuShareMeter() as bare_cpu:
            loops = bare_loops(graphs, frames, args)
        bare = {name: float(np.median(ms)) for name, ms in loops.items()}
        diagnosis = diagnose(graphs["dynamic"], frames, args)
        report["variants"][variant] = {"profile": {k: profile[k] for k in ("targets", "verdict", "inputs", "ratios",
                                                                           "cpu_time")},
                                       "bare_ms": bare, "bare_cpu_time": bare_cpu.shares, "diagnosis": diagnosis,
                                       "checks": checks(profile, loops)}
    report["load"]["after"] = list(os.getloadavg())
    report["load"]["uptime_after"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    stem = Path(args.out) / f"profile_agreement_{detect_isa().kind}"
    write_json_atomic(stem.with_suffix(".json"), report)
    write_text_atomic(stem.with_suffix(".md"), markdown(report))
    print(markdown(report))
    print(f"wrote {stem}.json and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
