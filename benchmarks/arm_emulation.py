"""`golden check` on emulated aarch64: does an ARM CPU compute what this x86 host computed for
the same graph? One script, no ARM hardware.

It sets up an arm64 Debian root (debootstrap + qemu-user-static through binfmt_misc; once,
idempotent), installs the aarch64 wheels of this host's onnxruntime and numpy and the project
itself into it, records a golden rollout of the fp32 graph on this host with the host's
rollouts of the other graphs (`golden record --also`), and runs `golden check` of every graph
inside the root under emulation. With --trace, each QDQ graph also gets the kernel-parity
trace (e3dpsm/golden/kernel_report.py): which quantised activations depart, first and on
their own. With --portable, each QDQ graph also gets its portable form
(e3dpsm/golden/kernel_cut.py: activation quantisation kept only where every op before it
computes to the bit on any ISA) and that is checked too.

    sudo apt-get install -y qemu-user-static binfmt-support debootstrap   # once, Debian/Ubuntu
    python benchmarks/arm_emulation.py --graphs step.onnx step_int8.onnx --data PREP --steps 60 \
        --trace --portable                 # -> benchmarks/results/arm_emulation.{json,md}

Needs root (debootstrap, chroot). The host's /proc and /sys are NOT mounted into the root:
ONNX Runtime's cpuinfo reads them and segfaults under emulation when they are the x86
host's; without them it warns once and MLAS reads the emulated CPU's features from the
auxiliary vector (as e3dpsm.utils.isa does). One core: OMP_NUM_THREADS=1, --threads 1.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic, write_text_atomic  # noqa: E402
from e3dpsm.utils.isa import detect_isa  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SUITE, MIRROR = "bookworm", "http://deb.debian.org/debian"
SITE, PROJECT, WORK = "opt/site", "opt/e3dpsm", "work"  # inside the root
WHEEL_PLATFORMS = ("manylinux_2_28_aarch64", "manylinux_2_27_aarch64", "manylinux2014_aarch64")
STAMP = ".e3dpsm-arm-root.json"
NOISE = ("Error in cpuinfo", "cpuinfo_initialize failed", "W:onnxruntime")  # the emulated root's expected warnings


def default_root() -> Path:
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "e3dpsm" / "arm64-root"


def fail(message: str) -> None:
    print(f"arm_emulation: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    print("+ " + " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, **kwargs)


def enable_binfmt() -> None:
    """qemu-aarch64 registered with binfmt_misc (so the root's binaries run through chroot)."""
    entry = Path("/proc/sys/fs/binfmt_misc/qemu-aarch64")
    if not Path("/proc/sys/fs/binfmt_misc/status").exists():
        run(["mount", "binfmt_misc", "-t", "binfmt_misc", "/proc/sys/fs/binfmt_misc"])
    if not entry.exists() or "enabled" not in entry.read_text():
        run(["update-binfmts", "--enable", "qemu-aarch64"])


def setup_root(root: Path) -> dict:
    """An arm64 Debian root with python3 at `root` (kept when its stamp says it is complete)."""
    if os.geteuid() != 0:
        fail("debootstrap and chroot need root; run as root (or in a root container)")
    for tool, package in (("debootstrap", "debootstrap"), ("qemu-aarch64-static", "qemu-user-static"),
                          ("update-binfmts", "binfmt-support")):
        if shutil.which(tool) is None:
            fail(f"{tool} is missing; apt-get install -y {package}")
    enable_binfmt()
    stamp = root / STAMP
    if stamp.exists():
        return json.loads(stamp.read_text())
    if root.exists() and any(root.iterdir()):
        fail(f"{root} holds something other than a finished root (no {STAMP}); remove it or pick another --root")
    run(["debootstrap", "--arch=arm64", "--foreign", "--variant=minbase", "--include=python3", SUITE, root, MIRROR])
    run(["chroot", root, "/debootstrap/debootstrap", "--second-stage"])
    info = {"suite": SUITE, "mirror": MIRROR, "python": emulated(root, ["python3", "--version"]).strip()}
    write_json_atomic(stamp, info)
    return info


def install_packages(root: Path) -> None:
    """The aarch64 wheels of this host's onnxruntime and numpy, and the project from this tree."""
    import numpy
    import onnxruntime

    platforms = [a for p in WHEEL_PLATFORMS for a in ("--platform", p)]
    pins = [f"onnxruntime=={onnxruntime.__version__}", f"numpy=={numpy.__version__}", "tqdm"]
    site = root / SITE
    if not (site / f"onnxruntime-{onnxruntime.__version__}.dist-info").exists():
        run([sys.executable, "-m", "pip", "install", "-q", "--upgrade", "--target", site, *platforms,
             "--python-version", "3.11", "--implementation", "cp", "--only-binary=:all:", *pins])
    wheels = root / "tmp" / "e3dpsm-wheel"
    shutil.rmtree(wheels, ignore_errors=True)
    build = [] if importlib.util.find_spec("setuptools") is None else ["--no-build-isolation"]  # minutes saved
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", *build, ROOT, "-w", wheels])
    shutil.rmtree(root / PROJECT, ignore_errors=True)
    run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", root / PROJECT, *wheels.glob("*.whl")])


def emulated(root: Path, cmd: list[str]) -> str:
    """Run `cmd` inside the root (chroot through binfmt's qemu), one thread; its stdout."""
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": f"/{PROJECT}:/{SITE}", "OMP_NUM_THREADS": "1", "HOME": "/root"}
    done = subprocess.run(["chroot", str(root), "/usr/bin/env", "-i", *(f"{k}={v}" for k, v in env.items()), *cmd],
                          capture_output=True, text=True)
    quiet = "\n".join(line for line in done.stderr.splitlines() if not any(n in line for n in NOISE))
    if done.returncode:
        fail(f"under emulation, {' '.join(cmd[:4])} ... exited {done.returncode}: {quiet[-2000:]}")
    return done.stdout


def emulated_machine(root: Path) -> dict:
    """What the emulated CPU says about itself: ISA flags, versions, qemu."""
    probe = ("import json, platform, numpy, onnxruntime; from e3dpsm.utils.isa import detect_isa; "
             "print(json.dumps({'machine': platform.machine(), 'python': platform.python_version(), "
             "'isa': detect_isa().to_dict(), 'numpy': numpy.__version__, 'onnxruntime': onnxruntime.__version__}))")
    info = json.loads(emulated(root, ["python3", "-c", probe]).strip().splitlines()[-1])
    qemu = subprocess.run(["qemu-aarch64-static", "--version"], capture_output=True, text=True).stdout
    info["qemu"] = qemu.splitlines()[0] if qemu else "unknown"
    return info


def portable_graphs(graphs: list[Path], folder: Path) -> list[Path]:
    """Each QDQ graph's portable form (kernel_cut.portable_qdq), written beside the others."""
    import onnx

    from e3dpsm.golden.kernel_cut import quantized_activations
    from e3dpsm.golden.kernel_report import write_portable

    made = []
    for graph in graphs:
        if not quantized_activations(onnx.load(str(graph))):
            continue
        path = folder / f"{graph.stem}_portable.onnx"
        counts = write_portable(graph, path)
        print(f"{path.name}: {counts['activations_float']} activations back to float, "
              f"{counts['activations_int8']} kept 8-bit")
        made.append(path)
    return made


def stage_graphs(graphs: list[Path], work: Path) -> list[Path]:
    """Copies of the graphs under distinct names (two `step_int8.onnx` from two folders)."""
    work.mkdir(parents=True, exist_ok=True)
    staged = []
    for graph in graphs:
        name = graph.name if sum(g.name == graph.name for g in graphs) == 1 else f"{graph.parent.name}_{graph.name}"
        target = work / name
        if target.resolve() != graph.resolve():
            shutil.copyfile(graph, target)
        staged.append(target)
    return staged


def host_golden(fp32: Path, others: list[Path], data: str, steps: int, work: Path) -> Path:
    """The fp32 graph's golden rollout on this host, with this host's rollouts of `others`."""
    golden = work / "golden"
    run([sys.executable, "-m", "e3dpsm", "golden", "record", "--model", fp32, "--data", data, "--steps", steps,
         "--threads", 1, "--out", golden, "--force", *(["--also", *others] if others else [])],
        stdout=subprocess.DEVNULL)
    return golden


def emulated_checks(root: Path, graphs: list[Path], work: Path) -> list[dict]:
    """`golden check` of every graph inside the root; the verdicts of its summary.json."""
    inside = lambda p: "/" + str(p.relative_to(root))  # noqa: E731
    out = work / "checks"
    shutil.rmtree(out, ignore_errors=True)
    emulated(root, ["python3", "-m", "e3dpsm", "golden", "check", "--model", *map(inside, graphs), "--golden",
                    inside(work / "golden"), "--out", inside(out), "--threads", "1", "--exit-zero"])
    return collect_checks(root, graphs, out)


def collect_checks(root: Path, graphs: list[Path], out: Path) -> list[dict]:
    """The verdicts of the checks in `out` (summary.json, or check.json for one graph)."""
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else None
    if summary is None:  # a single graph writes check.json only
        return [_single_verdict(graphs[0], json.loads((out / "check.json").read_text()))]
    checks = summary["checks"]
    for check in checks:
        report = json.loads(Path(root / check["report"].lstrip("/")).read_text())
        check["host_rollout"] = _host_figures(report)
    return checks


def _single_verdict(graph: Path, report: dict) -> dict:
    return {"model": str(graph), "status": "passed" if report["passed"] else "failed", **report["questions"],
            "profile": report["profile"]["name"], "first_failure": report["first_failure"],
            "ms_per_step": report["ms_per_step"], "host_rollout": _host_figures(report),
            "pose_max": next(t["max"] for t in report["tensors"] if t["name"] == "pose"),
            "pose_mean": next(t["mean"] for t in report["tensors"] if t["name"] == "pose")}


def _host_figures(report: dict) -> dict:
    """Per output: how far the emulated rollout is from the host's (max / mean over the steps
    of the per-step measure): mean joint distance to the host's rollout of an INT8 graph, max
    abs difference to the fp32 golden (itself the host's rollout) of an fp32 one."""
    measure = "host_distance_mm" if report["profile"]["kind"] == "budget" else "max_abs_mm"
    return {t["name"]: {"measure": measure, "max": t["max"], "mean": t["mean"], "passed": t["passed"],
                        "mean_limit": t["mean_limit"], "step_limit": t["step_limit"]}
            for t in report["tensors"] if t["kind"] == "output" and t["measure"] == measure}


def kernel_traces(root: Path, graphs: list[Path], work: Path, steps: int) -> dict:
    """The kernel-parity trace of every QDQ graph: host half here, device half emulated."""
    import onnx

    from e3dpsm.golden.kernel_cut import quantized_activations
    from e3dpsm.golden.kernel_report import record_host

    traces = {}
    for graph in graphs:
        if not quantized_activations(onnx.load(str(graph))):
            continue
        folder = work / "traces" / graph.stem
        shutil.rmtree(folder, ignore_errors=True)
        record_host(graph, work / "golden", folder, steps)
        emulated(root, ["python3", "-m", "e3dpsm.golden.kernel_report", "device", "/" + str(folder.relative_to(root))])
        report = json.loads(next(folder.glob("device-*.json")).read_text())
        (folder / "host.npz").unlink()  # large; the report keeps what it found
        traces[graph.name] = report
    return traces


def arm_ready(check: dict, trace: dict | None) -> dict:
    """An INT8 graph is ARM-ready when the emulated rollout computes what the host computed
    (question (a) of `golden check`); where not, the trace names the quantised activations
    that depart on their own and the ops of their segments."""
    same = check.get("same_as_host")
    ready = {"ready": bool(same) if same is not None else check["status"] == "passed"}
    if trace and not ready["ready"]:
        ready["departs_first"] = trace["first_departures"][:3]
        ready["responsible"] = [{"code": d["name"], "segment": d["segment"], "first_step": d["first_step"],
                                 "codes_apart": d["apart"], "max_codes": d["max_codes"]} for d in trace["isolated"]]
    return ready


def markdown(report: dict) -> str:
    host, device = report["host"], report["emulated"]
    lines = [f"# golden check on emulated aarch64 ({report['steps']} steps)", "",
             f"Host: {host['isa']['kind']} ({' '.join(host['isa']['flags'])}), onnxruntime {host['onnxruntime']}, "
             f"numpy {host['numpy']}. Emulated: {device['qemu']}, {device['machine']}, Python {device['python']}, "
             f"ISA {device['isa']['kind']} ({' '.join(device['isa']['flags'])}), onnxruntime {device['onnxruntime']}, "
             f"numpy {device['numpy']}. One thread each; load average at the start {report['load_average']}.", "",
             "| graph | profile | output | measure | max | mean | limits (mean / step) | verdict | ARM-ready |",
             "|---|---|---|---|---:|---:|---|---|---|"]
    for check in report["checks"]:
        name = Path(check["model"]).name
        ready = check["arm_ready"]
        for output, fig in check["host_rollout"].items():
            limits = f"{fig['mean_limit'] or '-'} / {fig['step_limit']}"
            lines.append(f"| {name} | {check['profile']} | {output} | {fig['measure']} | {fig['max']:.3g} | "
                         f"{fig['mean']:.3g} | {limits} | {'ok' if fig['passed'] else '**over**'} | "
                         f"{'yes' if ready['ready'] else '**no**'} |")
    for name, trace in report["traces"].items():
        lines += ["", f"## {name}: where the codes depart ({trace['codes']} quantised activations)", "",
                  f"Propagated (each side its own rollout): first departures {', '.join(trace['first_departures']) or 'none'}; "
                  f"{sum(1 for d in trace['propagated'] if d['first_step'] is not None)} activations depart by the end. "
                  f"Isolated (each segment fed the host's codes): {trace['isolated_identical']} identical at every step, "
                  f"{len(trace['isolated'])} depart on their own:", "",
                  "| code | segment ops | first step | steps apart | codes apart / elements | max codes |",
                  "|---|---|---:|---:|---:|---:|"]
        for d in trace["isolated"]:
            lines.append(f"| {d['name']} | {' '.join(d['segment']) or '(data movement)'} | {d['first_step']} | "
                         f"{d['steps_apart']} | {d['apart']} / {d['elements']} | {d['max_codes']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--graphs", nargs="+", required=True, help="the fp32 step graph first, then INT8 graphs")
    parser.add_argument("--data", required=True, help="prepared folder the golden frames come from")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--root", type=Path, default=default_root(), help=f"arm64 root (default {default_root()})")
    parser.add_argument("--trace", action="store_true", help="kernel-parity trace of every QDQ graph")
    parser.add_argument("--portable", action="store_true", help="check each QDQ graph's portable form too")
    parser.add_argument("--out", type=Path, default=RESULTS / "arm_emulation", help="report stem (.json, .md)")
    args = parser.parse_args(argv)
    graphs = [Path(g) for g in args.graphs]
    for graph in graphs:
        if not graph.is_file():
            fail(f"--graphs: {graph} does not exist")
    os.environ["OMP_NUM_THREADS"] = "1"
    load = os.getloadavg()[0]
    setup_root(args.root)
    install_packages(args.root)
    work = args.root / WORK / "arm_emulation"
    staged = stage_graphs(graphs, work)
    if args.portable:
        staged += portable_graphs(staged[1:], work)
    host_golden(staged[0], staged[1:], args.data, args.steps, work)
    checks = emulated_checks(args.root, staged, work)
    traces = kernel_traces(args.root, staged[1:], work, args.steps) if args.trace else {}
    for check in checks:
        check["arm_ready"] = arm_ready(check, traces.get(Path(check["model"]).name))
    return write_report(args, checks, traces, load)


def write_report(args: argparse.Namespace, checks: list[dict], traces: dict, load: float) -> int:
    import numpy
    import onnxruntime

    report = report_header("benchmarks/arm_emulation.py", {k: str(v) for k, v in vars(args).items()})
    report.update(steps=args.steps, load_average=round(load, 2), checks=checks, traces=traces,
                  host={"isa": detect_isa().to_dict(), "onnxruntime": onnxruntime.__version__,
                        "numpy": numpy.__version__},
                  emulated=emulated_machine(args.root))
    write_json_atomic(args.out.with_suffix(".json"), report)
    write_text_atomic(args.out.with_suffix(".md"), markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
