"""`e3dpsm golden record|check`: a reference rollout recorded once, checked anywhere.

`check` imports no torch: copy `step.onnx` and the golden folder to a device with numpy and
onnxruntime (or OpenVINO) and run it there. Exit codes: 0 pass, 1 fail, 2 bad input.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from e3dpsm.cli._common import add_force, add_threads, positive_float, positive_int


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("golden", help="record a golden rollout, or check a graph against one (torch-free)",
                       description="record: step a checkpoint (or an fp32 graph) over prepared sequences and keep "
                                   "the exact input frames, every output and the states at every step. check: run "
                                   "a graph over the same frames carrying its own states and compare step by step.")
    actions = p.add_subparsers(dest="golden_action", metavar="ACTION")
    rec = actions.add_parser("record", help="record a reference rollout")
    source = rec.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", help="trained checkpoint (PyTorch step is the reference)")
    source.add_argument("--model", help="fp32 step graph (ONNX Runtime is the reference; no torch needed)")
    source.add_argument("--variant", help="registered variant with initial weights (tests and demos)")
    rec.add_argument("--seed", type=int, default=0, help="weight seed with --variant")
    rec.add_argument("--data", required=True, help="prepared folder (`e3dpsm prepare`)")
    rec.add_argument("--split", default="all", help="split of --data (default: all sequences, in order)")
    rec.add_argument("--steps", type=positive_int, default=1000)
    rec.add_argument("--window-ms", type=positive_float, default=None,
                     help="window length fed to the model (default: the data's window)")
    rec.add_argument("--all-states", action="store_true",
                     help="keep every state in full at every step (large); default: sampled elements at every "
                          "step, whole states at steps 0, 1, 2, 5, 10, 20, 50, ... and the last")
    rec.add_argument("--also", nargs="+", default=[], metavar="GRAPH",
                     help="compressed graphs whose host rollouts are kept too, so that `golden check` on a device "
                          "can tell whether it computes what this host computed for them")
    rec.add_argument("--also-runtime", nargs="+", choices=("onnxruntime", "openvino"), default=["onnxruntime"],
                     help="runtimes the --also graphs are rolled out on (default onnxruntime)")
    rec.add_argument("--kernel-trace", type=positive_int, default=None, metavar="STEPS",
                     help="also keep this host's codes of every quantised activation of the --also QDQ graphs over "
                          "the first STEPS steps (about 1 MB per step of `small`), so that `golden check` on a "
                          "device that departs from the host's rollout names the nodes where it departs; of an "
                          "INT8 .tflite its codes' digests, of an INT8 .pte its taps program's (step_taps.pte "
                          "beside it, copied in)")
    add_threads(rec)
    rec.add_argument("--out", required=True, help="golden folder to write")
    add_force(rec)
    rec.set_defaults(func=run_record)

    chk = actions.add_parser("check", help="check a graph against a golden record (torch-free)")
    chk.add_argument("--model", required=True, nargs="+",
                     help="step graph(s) to check (fp32, fp16 or INT8): .onnx, or an edge artifact (.pte, "
                          ".tflite, .engine) on its own runtime; with several graphs or runtimes each "
                          "check goes to OUT/<graph>-<runtime>/ and OUT/summary.json lists the verdicts")
    chk.add_argument("--golden", required=True, help="golden folder written by `golden record`")
    chk.add_argument("--out", required=True, help="folder for check.json and check.png")
    chk.add_argument("--runtime", choices=("onnxruntime", "openvino", "openvino-bf16"), nargs="+", default=["onnxruntime"],
                     help="openvino-bf16: the graph's float parts in bf16 (CPUs with bf16 units; held to the bf16 "
                          "profile unless --profile says otherwise)")
    chk.add_argument("--exit-zero", action="store_true",
                     help="exit 0 even when a check fails (the verdicts are in the reports), e.g. in a pipeline")
    chk.add_argument("--providers", nargs="+", default=None,
                     help="ONNX Runtime execution providers, e.g. CUDAExecutionProvider CPUExecutionProvider")
    chk.add_argument("--profile", choices=("fp32", "fp16", "int8", "bf16"), default=None,
                     help="tolerance profile (default: the graph's precision from its metadata)")
    chk.add_argument("--budget-pct", type=positive_float, default=None,
                     help="allowed rise of MPJPE and PA-MPJPE over the fp32 golden for compressed graphs, %% "
                          "(default: the budget the graph carries, else 1)")
    add_threads(chk)
    chk.set_defaults(func=run_check)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    return p


def run_record(args: argparse.Namespace) -> int:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.golden.record import onnx_reference, record_golden, torch_reference
    from e3dpsm.utils.env import report_header

    data = PreparedData.open(args.data)  # bad data fails before any model loads
    for graph in args.also:
        if not Path(graph).is_file():
            from e3dpsm.errors import DataError

            raise DataError(f"--also: {graph} does not exist")
    if args.model:
        reference = onnx_reference(args.model, threads=args.threads)
    else:
        import torch

        from e3dpsm.cli._common import load_model_from_args

        if args.threads:
            torch.set_num_threads(args.threads)
        model = load_model_from_args(args)
        reference = torch_reference(model, "checkpoint" if args.checkpoint else "variant", args.checkpoint)
    window_ms = args.window_ms or data.window_ms
    header = report_header("golden record", {k: v for k, v in vars(args).items() if k != "func"})
    manifest = record_golden(reference, args.data, args.out, steps=args.steps, window_ms=window_ms, split=args.split,
                             all_states=args.all_states, force=args.force, header=header, progress=True)
    if args.also:
        from e3dpsm.golden.host import record_host_rollouts

        for entry in record_host_rollouts(args.out, args.also, args.also_runtime, threads=args.threads):
            print(f"golden record: host rollout of {entry['graph']} on {entry['runtime']} -> {entry['file']}")
    if args.kernel_trace:
        _record_kernel_traces(args.out, args.also, args.kernel_trace)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"golden record: {manifest['steps']} steps of {reference.variant} ({reference.kind}) at {window_ms:g} ms, "
          f"{size / 1e6:.2f} MB in {args.out} ({manifest['record_seconds']:.1f} s)")
    return 0


def _record_kernel_traces(golden_dir: str, graphs: list[str], steps: int) -> None:
    from e3dpsm.golden import artifact_trace
    from e3dpsm.golden.kernel_report import record_host, trace_folder
    from e3dpsm.golden.record import sha256_file

    for graph in graphs:
        if artifact_trace.trace_module(graph) is not None:
            folder, what = artifact_trace.record_host(golden_dir, graph, steps)
            print(f"golden record: {'code trace of' if folder else 'no code trace of'} {Path(graph).name}: {what}"
                  + (f" -> {folder}" if folder else ""))
            continue
        import onnx

        from e3dpsm.golden.kernel_cut import quantized_activations

        if not quantized_activations(onnx.load(graph)):
            print(f"golden record: {graph} has no quantised activations; no kernel trace")
            continue
        folder = trace_folder(golden_dir, graph, sha256_file(graph))
        manifest = record_host(graph, golden_dir, folder, steps)
        print(f"golden record: kernel trace of {Path(graph).name} ({len(manifest['codes'])} quantised activations, "
              f"{manifest['steps']} steps) -> {folder}")


def _print_check(model: str, runtime: str, result, report: dict, out: Path) -> None:
    from e3dpsm.golden.verify import budget_runtime_note

    print(f"golden check {model} on {runtime}, profile {result.profile.name}: {result.summary()}")
    for tensor in result.tensors:
        if tensor.kind == "output" or not tensor.passed:
            print("  " + tensor.line())
    for line in _question_lines(result):
        print("  " + line)
    states_ok = sum(t.passed for t in result.tensors if t.kind == "state")
    states = sum(t.kind == "state" for t in result.tensors)
    print(f"  states within limits: {states_ok}/{states}; {report['ms_per_step']:.2f} ms per step; "
          f"wrote {out / 'check.json'}")
    isa = report["isa"]
    print(f"  host ISA: {isa['host']['kind']} ({' '.join(isa['host']['flags']) or 'no flags read'})"
          + ("" if isa["same_kind"] is not False else
             f"; the graph's budget was checked on a {isa['budget_checked_on']['kind']} host: INT8 error "
             "differs between AVX2 and VNNI/AMX kernels, so this check is the one that counts here"))
    note = budget_runtime_note(report["budget_runtimes"])
    if note:
        print("  " + note)
    if report.get("code_trace"):
        trace = report["code_trace"]
        print(f"  where this machine departs from the host ({trace['trace']}, {trace['steps']} steps): "
              f"{trace['summary']}")
    trace = report.get("kernel_trace")
    if trace:
        from e3dpsm.golden.kernel_report import responsible_lines

        print(f"  where this machine departs from the host (kernel trace, {trace['steps']} steps): first "
              f"{', '.join(trace['first_departures'][:3]) or 'nowhere'}; {len(trace['isolated'])} of {trace['codes']} "
              "quantised activations depart on their own, fed the host's codes:")
        for line in responsible_lines(trace):
            print("    " + line)


def _question_lines(result) -> list[str]:
    """A compressed graph's two answers, one line each."""
    if result.budget is None:
        return []
    b = result.budget
    changes = ", ".join(f"{m.name} {m.change_pct:+.2f}% (upper {m.upper_pct:+.2f}%, limit +{m.limit_pct:g}%)"
                        for m in b.metrics)
    host = result.questions["same_as_host"]
    same = ("not asked: the golden holds no host rollout of this graph on this runtime (record one with "
            "`golden record --also GRAPH --also-runtime RUNTIME`)" if host is None else
            f"{'yes' if host else 'NO'}, against the host rollout of {result.host['graph']} made on a "
            f"{result.host['isa']['kind']} host")
    said = {"within": "yes", "over": "NO", "undecided": "undecided, too few frames to bound it inside its limit"}
    return [f"within its accuracy budget: {said[b.answer]} ({changes}; {b.frames} frames)",
            f"computes what the host computed: {same}"]


def run_check(args: argparse.Namespace) -> int:
    from e3dpsm.errors import ConfigError, DataError
    from e3dpsm.golden.store import load_golden
    from e3dpsm.golden.verify import artifact_check_runtime, verify_graph
    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    golden = load_golden(args.golden)  # a broken golden is bad input before any graph runs; read once
    for model in args.model:
        if not Path(model).exists():  # a file, or a folder for .mlpackage
            raise DataError(f"model {model} does not exist")
    config = {k: v for k, v in vars(args).items() if k != "func"}
    out = Path(args.out)
    single = len(args.model) == 1 and len(args.runtime) == 1
    verdicts = []
    for model in args.model:
        for runtime in args.runtime:
            # named by the runtime it runs on: a .pte's check is executorch's whatever --runtime says
            folder = out if single else out / f"{Path(model).stem}-{artifact_check_runtime(model, runtime)}"
            try:
                result, report = verify_graph(
                    model, golden, folder, runtime=runtime, providers=args.providers, threads=args.threads,
                    profile=args.profile, budget_pct=args.budget_pct, progress=True,
                    header=report_header("golden check", {**config, "model": model, "runtime": runtime}))
            except ConfigError as exc:  # e.g. OpenVINO not installed: a verdict, not a crash, among several
                if single:
                    raise
                print(f"golden check {model} on {runtime}: skipped ({exc})")
                verdicts.append({"model": model, "runtime": runtime, "status": "skipped", "reason": str(exc)})
                continue
            runtime = report["runtime"]  # a .pte / .tflite runs on its own runtime
            _print_check(model, runtime, result, report, folder)
            pose = next(t for t in result.tensors if t.name == "pose")
            verdicts.append({
                "model": model, "runtime": runtime, "status": "passed" if result.passed else "failed",
                "profile": result.profile.name, "first_failure": result.first_failure, **result.questions,
                "pose_max": float(pose.errors.max()), "pose_mean": pose.mean, "pose_measure": pose.measure,
                "ms_per_step": report["ms_per_step"], "report": str(folder / "check.json"),
            })
    failed = [v for v in verdicts if v["status"] == "failed"]
    if not single:
        summary = report_header("golden check", config)
        summary.update(passed=not failed, checks=verdicts)
        write_json_atomic(out / "summary.json", summary)
        write_text_atomic(out / "summary.md", summary_markdown(verdicts))
        print(f"golden check: {len(verdicts) - len(failed)}/{len(verdicts)} passed or skipped; "
              f"wrote {out / 'summary.json'}")
    return 0 if not failed or args.exit_zero else 1


def summary_markdown(verdicts: list[dict]) -> str:
    lines = ["| graph | runtime | profile | verdict | within budget | same as host | pose error (max / mean) "
             "| first failure | ms/step |", "|---|---|---|---|---|---|---:|---|---:|"]
    answer = {True: "yes", False: "**no**", None: "-", "within": "yes", "over": "**no**",
              "undecided": "undecided (too few frames)"}
    for v in verdicts:
        if v["status"] == "skipped":
            lines.append(f"| {Path(v['model']).name} | {v['runtime']} | - | skipped: {v['reason']} | - | - | - | - | - |")
            continue
        unit = "mm max abs" if v["pose_measure"] == "max_abs_mm" else "mm to the fp32 golden"
        first = v["first_failure"]
        where = f"step {first['step']}, {first['tensor']}" if first else "-"
        lines.append(f"| {Path(v['model']).name} | {v['runtime']} | {v['profile']} | **{v['status']}** | "
                     f"{answer[v.get('within_budget')]} | {answer[v.get('same_as_host')]} | "
                     f"{v['pose_max']:.3g} / {v['pose_mean']:.3g} {unit} | {where} | {v['ms_per_step']:.1f} |")
    return "\n".join(lines) + "\n"
