"""`golden check` on emulated aarch64: does an ARM CPU compute what this x86 host computed for
the same graph? One script, no ARM hardware.

It sets up an arm64 Debian root (debootstrap + qemu-user-static through binfmt_misc; once,
idempotent), installs the aarch64 wheels of this host's onnxruntime and numpy (and
ai-edge-litert for .tflite artifacts, torch and ExecuTorch's runtime for .pte programs:
EXECUTORCH_PINS) and the project itself into it, records a golden rollout
of the fp32 graph on this host with the host's rollouts of the other graphs (`golden record
--also`), and runs `golden check` of every graph inside the root under emulation, once per
CPU model of --cpus (qemu's `max`, every feature it implements, by default). With --trace,
each QDQ graph also gets the kernel-parity trace (e3dpsm/golden/kernel_report.py): which
quantised activations depart, first and on their own; each INT8 .tflite the code trace
(e3dpsm/golden/tflite_trace.py): where its 8-bit codes first part from the host's; each
INT8 .pte the instruction trace (e3dpsm/golden/pte_trace.py, from ExecuTorch's ETDump):
which kernel or XNNPACK partition's output first parts from the host's; where the root's
ExecuTorch has no event tracer, the taps trace of the `*_taps.pte` beside it
(e3dpsm/golden/pte_taps.py): which quantised activation's codes first part. With
--portable, each QDQ graph also gets its portable form (e3dpsm/golden/kernel_cut.py:
activation quantisation kept only where every op before it computes to the bit on any ISA)
and that is checked too.

    sudo apt-get install -y qemu-user-static binfmt-support debootstrap   # once, Debian/Ubuntu
    python benchmarks/arm_emulation.py --graphs step.onnx step_int8.onnx lt/step.tflite et/step.pte \
        --data PREP --steps 60 [--cpus max cortex-a72 neoverse-n1] [--qemu qemu-aarch64] [--trace --portable] \
        [--host-python VENV/bin/python]

Needs root (debootstrap, chroot). The host's /proc and /sys are NOT mounted into the root:
ONNX Runtime's cpuinfo reads them and segfaults under emulation when they are the x86
host's; the root gets its own one-core /proc/cpuinfo and CPU lists instead (describe_cpu),
and MLAS and XNNPACK read the emulated CPU's features from the auxiliary vector (as
e3dpsm.utils.isa does). One core: OMP_NUM_THREADS=1, --threads 1. qemu 7.2 (Debian 12's)
emulates SME wrongly for XNNPACK's 8-bit kernels: on its `max` CPU an INT8 .tflite lands
169 mm (mean) from the host; pass a newer qemu-aarch64 with --qemu (10.0 from bookworm-backports
agrees to the bit) or `--cpus max,sme=off`.
"""
from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from e3dpsm.runtime.executorch_session import OTHER_RELEASE_ENV  # noqa: E402
from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic, write_text_atomic  # noqa: E402
from e3dpsm.utils.isa import detect_isa  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SUITE, MIRROR = "bookworm", "http://deb.debian.org/debian"
SITE, PROJECT, WORK = "opt/site", "opt/e3dpsm", "work"  # inside the root
# ExecuTorch's Python runtime links torch's libraries. PyPI's aarch64 torch since 2.11 is a CUDA
# build whose CUDA wheels the registry lacks for aarch64; 2.10.0 is the newest CPU build, and
# ExecuTorch 1.1.0 the release built against it. Its runtime loads the programs this host's
# release writes (checked: ET12 programs of 1.5.1, fp32 and INT8); the checks run them with
# E3DPSM_EXECUTORCH_OTHER_RELEASE=1 and the report names both releases. Kept apart from SITE so
# that nothing else in the root finds torch.
EXECUTORCH_SITE = "opt/site-executorch"
EXECUTORCH_PINS = ("torch==2.10.0", "executorch==1.1.0")
EXECUTORCH_PURE = ("filelock", "typing-extensions", "sympy", "mpmath", "networkx", "jinja2", "markupsafe", "fsspec",
                   "ruamel.yaml", "pyyaml", "tabulate")  # what `import torch` and executorch.runtime import
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


# The emulated CPU as the root's own /proc and /sys describe it: one core (the checks run one
# thread) of no named implementer. cpuinfo (in ONNX Runtime and XNNPACK) parses these files;
# without them it fails, and LiteRT then creates no XNNPACK delegate and runs its builtin
# kernels instead of the ones a device runs. The ISA features still come from the auxiliary
# vector qemu hands over (the `max` CPU's), as on a device; a part number of 0 names no core,
# so XNNPACK picks its generic kernels for those features.
EMULATED_CPU_FILES = {
    "sys/devices/system/cpu/possible": "0\n",
    "sys/devices/system/cpu/present": "0\n",
    "proc/cpuinfo": ("processor\t: 0\nBogoMIPS\t: 2000.00\nFeatures\t: fp asimd\nCPU implementer\t: 0x00\n"
                     "CPU architecture: 8\nCPU variant\t: 0x0\nCPU part\t: 0x000\nCPU revision\t: 0\n\n"),
}


def describe_cpu(root: Path) -> None:
    """Write EMULATED_CPU_FILES into the root (plain files: the host's /proc and /sys are never
    mounted there, see the module doc)."""
    for relative, text in EMULATED_CPU_FILES.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def install_packages(root: Path, litert: bool = False, executorch: bool = False) -> None:
    """The aarch64 wheels of this host's onnxruntime and numpy (ai-edge-litert for .tflite
    graphs, EXECUTORCH_PINS for .pte programs), and the project from this tree."""
    import numpy
    import onnxruntime

    pins = [f"onnxruntime=={onnxruntime.__version__}", f"numpy=={numpy.__version__}", "tqdm"]
    wanted = [f"onnxruntime-{onnxruntime.__version__}"]
    if litert:  # the LiteRT runner imports no torch: the interpreter and numpy are all it needs
        version = importlib.metadata.version("ai-edge-litert")
        pins.append(f"ai-edge-litert=={version}")
        wanted.append(f"ai_edge_litert-{version}")
    site = root / SITE
    if not all((site / f"{name}.dist-info").exists() for name in wanted):
        pip_install_aarch64(site, pins)
    if executorch:
        install_executorch(root)
    wheels = root / "tmp" / "e3dpsm-wheel"
    shutil.rmtree(wheels, ignore_errors=True)
    build = [] if importlib.util.find_spec("setuptools") is None else ["--no-build-isolation"]  # minutes saved
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", *build, ROOT, "-w", wheels])
    shutil.rmtree(root / PROJECT, ignore_errors=True)
    run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", root / PROJECT, *wheels.glob("*.whl")])


@dataclass(frozen=True)
class EmulatedCPU:
    """Which CPU qemu emulates, and which qemu. `model` goes to qemu as QEMU_CPU (None: its
    default, `max`: every feature it implements); `qemu`, a qemu-aarch64 binary inside the root
    (copied there by --qemu) run instead of the one binfmt_misc registered: qemu 7.2's SME
    emulation computes XNNPACK's 8-bit SME kernels wrongly (docs/edge.md), qemu 10's does not."""

    model: str | None = None
    qemu: str | None = None

    @property
    def name(self) -> str:
        return self.model or "max"

    def command(self, cmd: list[str]) -> list[str]:
        if not self.qemu:
            return cmd
        return [self.qemu, cmd[0] if "/" in cmd[0] else f"/usr/bin/{cmd[0]}", *cmd[1:]]

    def version(self, root: Path) -> str:
        binary = str(root / self.qemu.lstrip("/")) if self.qemu else "qemu-aarch64-static"
        out = subprocess.run([binary, "--version"], capture_output=True, text=True).stdout
        return out.splitlines()[0] if out else "unknown"


DEFAULT_CPU = EmulatedCPU()
QEMU_IN_ROOT = "/opt/qemu-aarch64"


def emulated(root: Path, cmd: list[str], cpu: EmulatedCPU = DEFAULT_CPU, executorch: bool = False) -> str:
    """Run `cmd` inside the root (chroot, through binfmt's qemu or `cpu.qemu`) on `cpu`, one
    thread; its stdout. `executorch`: with torch and ExecuTorch's runtime importable."""
    done = _emulated_process(root, cmd, cpu, executorch)
    quiet = "\n".join(line for line in done.stderr.splitlines() if not any(n in line for n in NOISE))
    if done.returncode:
        fail(f"under emulation, {' '.join(cmd[:4])} ... exited {done.returncode}: {quiet[-2000:]}")
    return done.stdout


def _emulated_process(root: Path, cmd: list[str], cpu: EmulatedCPU, executorch: bool) -> subprocess.CompletedProcess:
    path = f"/{PROJECT}:/{SITE}" + (f":/{EXECUTORCH_SITE}" if executorch else "")
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": path, "OMP_NUM_THREADS": "1", "HOME": "/root",
           **({"QEMU_CPU": cpu.model} if cpu.model else {}),
           **({OTHER_RELEASE_ENV: "1"} if executorch else {})}
    return subprocess.run(["chroot", str(root), "/usr/bin/env", "-i", *(f"{k}={v}" for k, v in env.items()),
                           *cpu.command(cmd)], capture_output=True, text=True)


def executorch_refusal(root: Path, cpu: EmulatedCPU) -> str | None:
    """Why .pte programs cannot run on `cpu` in the root (None: they can). PyPI's aarch64 torch
    is built for ARMv8.2 and later: on an ARMv8.0 core (cortex-a72) its import dies of SIGILL.
    That is the Python harness, not ExecuTorch: a device app links the C++ runtime, no torch."""
    done = _emulated_process(root, ["python3", "-c", "import torch, executorch.runtime"], cpu, True)
    if done.returncode == 0:
        return None
    if done.returncode == -4 or "Illegal instruction" in done.stderr:
        return f"torch {EXECUTORCH_PINS[0].split('==')[1]} for aarch64 dies of an illegal instruction on `{cpu.name}`"
    return f"`import torch, executorch.runtime` exited {done.returncode} on `{cpu.name}`"


def emulated_machine(root: Path, cpu: EmulatedCPU = DEFAULT_CPU, executorch: bool = False) -> dict:
    """What the emulated CPU says about itself: ISA flags, versions, qemu."""
    probe = ("import json, platform, importlib.metadata as m, numpy, onnxruntime; "
             "from e3dpsm.utils.isa import detect_isa; "
             "v = {d.metadata['Name']: d.version for d in m.distributions()}; "
             "print(json.dumps({'machine': platform.machine(), 'python': platform.python_version(), "
             "'isa': detect_isa().to_dict(), 'numpy': numpy.__version__, 'onnxruntime': onnxruntime.__version__, "
             "'ai_edge_litert': v.get('ai-edge-litert'), 'executorch': v.get('executorch'), 'torch': v.get('torch')}))")
    info = json.loads(emulated(root, ["python3", "-c", probe], cpu, executorch).strip().splitlines()[-1])
    info.update(qemu=cpu.version(root), cpu=cpu.name)
    return info


def _inside(root: Path, path: Path) -> str:
    """`path` (under the root) as the emulated system sees it."""
    return "/" + str(path.relative_to(root))


def emulated_delegation(root: Path, graphs: list[Path], cpu: EmulatedCPU = DEFAULT_CPU) -> dict[str, int]:
    """How many XNNPACK partitions LiteRT's interpreter makes of each .tflite inside the root
    (0: no delegate, LiteRT's builtin kernels run instead, not what a device runs)."""
    partitions = {}
    for graph in graphs:
        if graph.suffix != ".tflite":
            continue
        probe = ("from ai_edge_litert.interpreter import Interpreter; "
                 f"i = Interpreter(model_path={_inside(root, graph)!r}, num_threads=1); "
                 "i.allocate_tensors(); print(sum(d['op_name'] == 'DELEGATE' for d in i._get_ops_details()))")
        partitions[graph.name] = int(emulated(root, ["python3", "-c", probe], cpu).strip().splitlines()[-1])
    return partitions


def install_executorch(root: Path) -> None:
    """EXECUTORCH_PINS without their dependencies (torch's would pull CUDA wheels), and the pure
    Python packages their imports need, into EXECUTORCH_SITE."""
    site = root / EXECUTORCH_SITE
    if all(any(site.glob(f"{pin.replace('==', '-')}*.dist-info")) for pin in EXECUTORCH_PINS):
        return
    pip_install_aarch64(site, [*EXECUTORCH_PINS, *EXECUTORCH_PURE], deps=False)


def pip_install_aarch64(site: Path, packages: list[str], deps: bool = True) -> None:
    """The aarch64 CPython 3.11 wheels of `packages` into `site` (the root's python3 reads them)."""
    platforms = [a for p in WHEEL_PLATFORMS for a in ("--platform", p)]
    run([sys.executable, "-m", "pip", "install", "-q", "--upgrade", *([] if deps else ["--no-deps"]), "--target",
         site, *platforms, "--python-version", "3.11", "--implementation", "cp", "--only-binary=:all:", *packages])


def portable_graphs(graphs: list[Path], folder: Path) -> list[Path]:
    """Each QDQ graph's portable form (kernel_cut.portable_qdq), written beside the others."""
    import onnx

    from e3dpsm.golden.kernel_cut import quantized_activations
    from e3dpsm.golden.kernel_report import write_portable

    made = []
    for graph in graphs:
        if graph.suffix != ".onnx" or not quantized_activations(onnx.load(str(graph))):
            continue
        path = folder / f"{graph.stem}_portable.onnx"
        counts = write_portable(graph, path)
        print(f"{path.name}: {counts['activations_float']} activations back to float, "
              f"{counts['activations_int8']} kept 8-bit")
        made.append(path)
    return made


def stage_graphs(graphs: list[Path], work: Path) -> list[Path]:
    """Copies of the graphs under distinct names (two `step_int8.onnx` from two folders)."""
    from e3dpsm.export.executorch_taps import taps_path

    work.mkdir(parents=True, exist_ok=True)
    staged = []
    for graph in graphs:
        name = graph.name if sum(g.name == graph.name for g in graphs) == 1 else f"{graph.parent.name}_{graph.name}"
        target = work / name
        if target.resolve() != graph.resolve():
            shutil.copyfile(graph, target)
            if Path(taps_path(graph)).is_file():  # an INT8 .pte's taps program travels with it (pte_traces)
                shutil.copyfile(taps_path(graph), taps_path(target))
        staged.append(target)
    return staged


def has_pte(graphs: list[Path]) -> bool:
    return any(g.suffix == ".pte" for g in graphs)


def host_golden(fp32: Path, others: list[Path], data: str, steps: int, work: Path,
                python: str = sys.executable) -> Path:
    """The fp32 graph's golden rollout on this host, with this host's rollouts of `others`, made
    by `python` (another environment: e.g. one with the root's ExecuTorch release, so that a
    .pte's comparison differs in the ISA alone)."""
    golden = work / "golden"
    env = {**os.environ, OTHER_RELEASE_ENV: "1"} if python != sys.executable else None
    run([python, "-m", "e3dpsm", "golden", "record", "--model", fp32, "--data", data, "--steps", steps,
         "--threads", 1, "--out", golden, "--force", *(["--also", *others] if others else [])],
        stdout=subprocess.DEVNULL, env=env)
    return golden


def host_executorch(python: str) -> str | None:
    """The ExecuTorch release `python` runs (None: not installed)."""
    probe = "import importlib.metadata as m; print(m.version('executorch'))"
    done = subprocess.run([python, "-c", probe], capture_output=True, text=True)
    return done.stdout.strip() or None if done.returncode == 0 else None


def emulated_checks(root: Path, graphs: list[Path], work: Path, cpu: EmulatedCPU = DEFAULT_CPU) -> list[dict]:
    """`golden check` of every graph inside the root on `cpu`; the verdicts of its summary.json."""
    out = work / f"checks-{_slug(cpu.name)}"
    shutil.rmtree(out, ignore_errors=True)
    emulated(root, ["python3", "-m", "e3dpsm", "golden", "check", "--model", *(_inside(root, g) for g in graphs),
                    "--golden", _inside(root, work / "golden"), "--out", _inside(root, out), "--threads", "1",
                    "--exit-zero"], cpu, executorch=has_pte(graphs))
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


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def kernel_traces(root: Path, graphs: list[Path], work: Path, steps: int, cpu: EmulatedCPU = DEFAULT_CPU) -> dict:
    """The kernel-parity trace of every QDQ graph: host half here, device half emulated."""
    import onnx

    from e3dpsm.golden.kernel_cut import quantized_activations
    from e3dpsm.golden.kernel_report import record_host

    traces = {}
    for graph in graphs:
        if graph.suffix != ".onnx" or not quantized_activations(onnx.load(str(graph))):
            continue
        folder = work / "traces" / _slug(cpu.name) / graph.stem
        shutil.rmtree(folder, ignore_errors=True)
        record_host(graph, work / "golden", folder, steps)
        emulated(root, ["python3", "-m", "e3dpsm.golden.kernel_report", "device", _inside(root, folder)], cpu)
        report = json.loads(next(folder.glob("device-*.json")).read_text())
        (folder / "host.npz").unlink()  # large; the report keeps what it found
        traces[graph.name] = report
    return traces


def tflite_traces(root: Path, graphs: list[Path], work: Path, steps: int, cpu: EmulatedCPU = DEFAULT_CPU) -> dict:
    """Where every INT8 .tflite's codes part from the host's (e3dpsm/golden/tflite_trace.py):
    digests of each code tensor at each step recorded here and emulated, compared here."""
    from e3dpsm.golden.tflite_trace import compare, record
    from e3dpsm.runtime.litert_session import read_tflite, tflite_metadata

    traces = {}
    for graph in graphs:
        if graph.suffix != ".tflite" or tflite_metadata(graph, read_tflite(graph))[1].get("precision") != "int8":
            continue
        folder = work / "traces" / _slug(cpu.name) / graph.stem
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        host = record(graph, work / "golden", steps)
        device = folder / "device.json"
        emulated(root, ["python3", "-m", "e3dpsm.golden.tflite_trace", "record", _inside(root, graph),
                        _inside(root, work / "golden"), _inside(root, device), "--steps", str(steps)], cpu)
        traces[graph.name] = compare(host, json.loads(device.read_text()))
    return traces


def pte_traces(root: Path, graphs: list[Path], work: Path, steps: int, cpu: EmulatedCPU = DEFAULT_CPU,
               host_python: str = sys.executable) -> dict:
    """Where every INT8 .pte's computation parts from the host's (e3dpsm/golden/pte_trace.py):
    digests of every instruction output at each step, from ETDump, recorded by `host_python`
    and emulated, compared here."""
    from e3dpsm.export.executorch_taps import taps_path
    from e3dpsm.golden.pte_taps import program_taps
    from e3dpsm.golden.pte_trace import NO_EVENT_TRACER_EXIT, compare, read_trace
    from e3dpsm.runtime.executorch_session import load_program, program_metadata

    traces = {}
    for graph in graphs:
        if graph.suffix != ".pte":
            continue
        program = load_program(graph)
        if program_metadata(graph, program)[1].get("precision") != "int8":
            continue
        if program_taps(program, str(graph)) is not None:  # checked as a program; traced as taps of another
            continue
        folder = work / "pte-traces" / _slug(cpu.name) / graph.stem
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        host, device = folder / "host.json", folder / "device.json"
        done = _emulated_process(root, ["python3", "-m", "e3dpsm.golden.pte_trace", "record", _inside(root, graph),
                                        _inside(root, work / "golden"), _inside(root, device), "--steps", str(steps)],
                                 cpu, True)
        if done.returncode == NO_EVENT_TRACER_EXIT:  # the root's ExecuTorch wheel: no ETDump to trace with
            reason = done.stderr.strip().splitlines()[-1].removeprefix("pte_trace: error: ")
            taps = Path(taps_path(graph))
            traces[graph.name] = (taps_trace(root, taps, folder, work, steps, cpu, host_python) if taps.is_file() else
                                  {"not_traced": f"{reason}; and no {taps.name} beside it to trace instead (e3dpsm "
                                                 "convert executorch --quantize int8 --taps)"})
            continue
        if done.returncode:
            fail(f"under emulation, pte_trace record {graph.name} exited {done.returncode}: {done.stderr[-2000:]}")
        env = {**os.environ, OTHER_RELEASE_ENV: "1"} if host_python != sys.executable else None
        run([host_python, "-m", "e3dpsm.golden.pte_trace", "record", graph, work / "golden", host, "--steps", steps],
            stdout=subprocess.DEVNULL, env=env)  # only where the device side traced: nothing to compare otherwise
        traces[graph.name] = compare(read_trace(host), read_trace(device))
    return traces


def taps_trace(root: Path, taps: Path, folder: Path, work: Path, steps: int, cpu: EmulatedCPU,
               host_python: str) -> dict:
    """Where an INT8 .pte's taps part from the host's (e3dpsm/golden/pte_taps.py): its taps
    program, the same arithmetic returning every quantised activation's codes, recorded by
    `host_python` and emulated (no event tracer needed), compared here."""
    from e3dpsm.golden.pte_taps import compare, read_trace

    host, device = folder / "host_taps.json", folder / "device_taps.json"
    emulated(root, ["python3", "-m", "e3dpsm.golden.pte_taps", "record", _inside(root, taps),
                    _inside(root, work / "golden"), _inside(root, device), "--steps", str(steps)], cpu, executorch=True)
    env = {**os.environ, OTHER_RELEASE_ENV: "1"} if host_python != sys.executable else None
    run([host_python, "-m", "e3dpsm.golden.pte_taps", "record", taps, work / "golden", host, "--steps", steps],
        stdout=subprocess.DEVNULL, env=env)
    return compare(read_trace(host), read_trace(device))


def arm_ready(check: dict, trace: dict | None, code_trace: dict | None = None) -> dict:
    """An INT8 graph is ARM-ready when the emulated rollout computes what the host computed
    (question (a) of `golden check`); where not, the trace names the quantised activations
    that depart on their own and the ops of their segments (an ONNX graph's kernel trace), or
    the code tensors that part first (a .tflite's code trace, tflite_trace.compare)."""
    same = check.get("same_as_host")
    ready = {"ready": bool(same) if same is not None else check["status"] == "passed"}
    if code_trace and not ready["ready"] and "not_traced" in code_trace:
        ready["not_traced"] = code_trace["not_traced"]
    elif code_trace and not ready["ready"]:
        if "codes" in code_trace:  # a .tflite's code trace
            from e3dpsm.golden.tflite_trace import describe
        elif "taps" in code_trace:  # a .pte's taps trace
            from e3dpsm.golden.pte_taps import describe
        else:  # a .pte's instruction trace
            from e3dpsm.golden.pte_trace import describe
        ready["departs_first"] = [describe(c) for c in code_trace["first_departures"][:3]]
        ready["first_step"] = code_trace["first_step"]
    elif trace and not ready["ready"]:
        ready["departs_first"] = trace["first_departures"][:3]
        ready["responsible"] = [{"code": d["name"], "segment": d["segment"], "first_step": d["first_step"],
                                 "codes_apart": d["apart"], "max_codes": d["max_codes"]} for d in trace["isolated"]]
    return ready


def markdown(report: dict) -> str:
    host = report["host"]
    lines = [f"# golden check on emulated aarch64 ({report['steps']} steps)", "",
             f"Host: {host['isa']['kind']} ({' '.join(host['isa']['flags'])}), onnxruntime {host['onnxruntime']}, "
             f"numpy {host['numpy']}. One thread each; load average at the start {report['load_average']}.", ""]
    for run in report["runs"]:
        device = run["emulated"]
        litert = f", ai-edge-litert {device['ai_edge_litert']}" if device.get("ai_edge_litert") else ""
        if device.get("executorch"):
            litert += (f", executorch {device['executorch']} with torch {device['torch']} (the host's rollouts "
                       f"by executorch {host.get('executorch')}; {OTHER_RELEASE_ENV}=1)")
        lines.append(f"- CPU `{run['cpu']}`: {device['qemu']}, {device['machine']}, Python {device['python']}, "
                     f"ISA {device['isa']['kind']} ({' '.join(device['isa']['flags'])}), onnxruntime "
                     f"{device['onnxruntime']}, numpy {device['numpy']}{litert}.")
    lines += ["", "| CPU | graph | profile | output | measure | max | mean | limits (mean / step) | verdict | ARM-ready |",
              "|---|---|---|---|---|---:|---:|---|---|---|"]
    for run in report["runs"]:
        for check in run["checks"]:
            name = Path(check["model"]).name
            ready = check["arm_ready"]
            for output, fig in check["host_rollout"].items():
                limits = f"{fig['mean_limit'] or '-'} / {fig['step_limit']}"
                lines.append(f"| {run['cpu']} | {name} | {check['profile']} | {output} | {fig['measure']} | "
                             f"{fig['max']:.3g} | {fig['mean']:.3g} | {limits} | {'ok' if fig['passed'] else '**over**'} | "
                             f"{'yes' if ready['ready'] else '**no**'} |")
    for run in report["runs"]:
        if run.get("pte_not_run"):
            lines += ["", f"`.pte` programs not run on `{run['cpu']}`: {run['pte_not_run']}."]
    for run in report["runs"]:
        partitions = {Path(c["model"]).name: c["xnnpack_partitions"] for c in run["checks"]
                      if c.get("xnnpack_partitions") is not None}
        if partitions:
            lines += ["", f"XNNPACK partitions LiteRT made on `{run['cpu']}` (0 would mean its builtin kernels ran): "
                      + ", ".join(f"{name} {count}" for name, count in partitions.items()) + "."]
    for run in report["runs"]:
        for name, trace in run.get("code_traces", {}).items():
            if "not_traced" in trace:
                lines += ["", f"## {name} on `{run['cpu']}`: not traced", "", trace["not_traced"] + "."]
            elif "codes" in trace:
                from e3dpsm.golden.tflite_trace import summary

                lines += ["", f"## {name} on `{run['cpu']}`: where the codes part ({trace['codes']} code tensors)", "",
                          summary(trace) + "."]
            elif "taps" in trace:
                from e3dpsm.golden.pte_taps import summary as taps_summary

                lines += ["", f"## {name} on `{run['cpu']}`: where its taps part ({trace['taps']} quantised "
                          "activations, from its taps program)", "", taps_summary(trace) + "."]
            else:
                from e3dpsm.golden.pte_trace import summary as pte_summary

                lines += ["", f"## {name} on `{run['cpu']}`: where the instruction outputs part ({trace['outputs']} "
                          "values ETDump logs per step)", "", pte_summary(trace) + "."]
    for run in report["runs"]:
        for name, trace in run["traces"].items():
            lines += ["", f"## {name} on `{run['cpu']}`: where the codes depart ({trace['codes']} quantised activations)",
                      "", f"Propagated (each side its own rollout): first departures "
                      f"{', '.join(trace['first_departures']) or 'none'}; "
                      f"{sum(1 for d in trace['propagated'] if d['first_step'] is not None)} activations depart by the "
                      f"end. Isolated (each segment fed the host's codes): {trace['isolated_identical']} identical at "
                      f"every step, {len(trace['isolated'])} depart on their own:", "",
                      "| code | segment ops | first step | steps apart | codes apart / elements | max codes |",
                      "|---|---|---:|---:|---:|---:|"]
            for d in trace["isolated"]:
                lines.append(f"| {d['name']} | {' '.join(d['segment']) or '(data movement)'} | {d['first_step']} | "
                             f"{d['steps_apart']} | {d['apart']} / {d['elements']} | {d['max_codes']} |")
    return "\n".join(lines) + "\n"


def install_qemu(root: Path, binary: Path | None) -> str | None:
    """Copy `binary` (a static qemu-aarch64) into the root; its path there (None: binfmt's)."""
    if binary is None:
        return None
    if not binary.is_file():
        fail(f"--qemu: {binary} does not exist")
    target = root / QEMU_IN_ROOT.lstrip("/")
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(binary, target)
    return QEMU_IN_ROOT


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--graphs", nargs="+", required=True,
                        help="the fp32 ONNX step graph first, then INT8 graphs and .tflite artifacts")
    parser.add_argument("--data", required=True, help="prepared folder the golden frames come from")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--root", type=Path, default=default_root(), help=f"arm64 root (default {default_root()})")
    parser.add_argument("--cpus", nargs="+", default=["max"],
                        help="qemu CPU models to check on, each in turn (default max; e.g. cortex-a72 for NEON "
                             "only, neoverse-n1 for dot products, max,sme=off)")
    parser.add_argument("--qemu", type=Path, help="a static qemu-aarch64 to run instead of binfmt's (e.g. qemu 10: "
                                                  "qemu 7.2's SME emulation is wrong, docs/edge.md)")
    parser.add_argument("--trace", action="store_true",
                        help="where the codes part: the kernel-parity trace of every QDQ graph, the code trace of "
                             "every INT8 .tflite, the instruction trace of every INT8 .pte")
    parser.add_argument("--portable", action="store_true", help="check each QDQ graph's portable form too")
    parser.add_argument("--host-python", default=sys.executable,
                        help="the Python that records the host's rollouts (default this one); for .pte programs, "
                             f"one with {' '.join(EXECUTORCH_PINS)} makes the host and the root run the same "
                             "ExecuTorch release, so the comparison differs in the ISA alone (docs/edge.md)")
    parser.add_argument("--out", type=Path, default=RESULTS / "arm_emulation", help="report stem (.json, .md)")
    args = parser.parse_args(argv)
    graphs = [Path(g) for g in args.graphs]
    for graph in graphs:
        if not graph.is_file():
            fail(f"--graphs: {graph} does not exist")
    os.environ["OMP_NUM_THREADS"] = "1"
    load = os.getloadavg()[0]
    if graphs[0].suffix != ".onnx":
        fail(f"--graphs: the first graph is the golden's fp32 ONNX graph, not {graphs[0].name}")
    unsupported = [g.name for g in graphs if g.suffix not in (".onnx", ".tflite", ".pte")]
    if unsupported:
        fail(f"--graphs: {', '.join(unsupported)}: only .onnx, .tflite and .pte run in the emulated root")
    setup_root(args.root)
    describe_cpu(args.root)
    install_packages(args.root, litert=any(g.suffix == ".tflite" for g in graphs),
                     executorch=has_pte(graphs))
    qemu = install_qemu(args.root, args.qemu)
    work = args.root / WORK / "arm_emulation"
    staged = stage_graphs(graphs, work)
    if args.portable:
        staged += portable_graphs(staged[1:], work)
    host_golden(staged[0], staged[1:], args.data, args.steps, work, args.host_python)
    runs = [check_on(args.root, staged, work, args.steps, EmulatedCPU(None if m == "max" else m, qemu), args.trace,
                    args.host_python)
            for m in args.cpus]
    return write_report(args, runs, load)


def check_on(root: Path, staged: list[Path], work: Path, steps: int, cpu: EmulatedCPU, trace: bool,
             host_python: str = sys.executable) -> dict:
    """Every staged graph's golden check on one emulated CPU (with the traces if asked: the
    kernel trace of each QDQ graph, the code trace of each INT8 .tflite, the instruction trace
    of each INT8 .pte)."""
    refusal = executorch_refusal(root, cpu) if has_pte(staged) else None
    if refusal:  # the other graphs are still checked on this CPU
        print(f"{cpu.name}: .pte programs not run: {refusal}")
        staged = [g for g in staged if g.suffix != ".pte"]
    checks = emulated_checks(root, staged, work, cpu)
    partitions = emulated_delegation(root, staged, cpu)
    traces = kernel_traces(root, staged[1:], work, steps, cpu) if trace else {}
    code_traces = tflite_traces(root, staged[1:], work, steps, cpu) if trace else {}
    if trace and has_pte(staged):
        code_traces.update(pte_traces(root, staged[1:], work, steps, cpu, host_python))
    for check in checks:
        name = Path(check["model"]).name
        check["xnnpack_partitions"] = partitions.get(name)
        check["arm_ready"] = arm_ready(check, traces.get(name), code_traces.get(name))
    machine = emulated_machine(root, cpu, executorch=has_pte(staged))
    return {"cpu": cpu.name, "emulated": machine, "checks": checks, "traces": traces,
            "code_traces": code_traces, "pte_not_run": refusal}


def write_report(args: argparse.Namespace, runs: list[dict], load: float) -> int:
    import numpy
    import onnxruntime

    report = report_header("benchmarks/arm_emulation.py", {k: str(v) for k, v in vars(args).items()})
    report.update(steps=args.steps, load_average=round(load, 2), runs=runs,
                  host={"isa": detect_isa().to_dict(), "onnxruntime": onnxruntime.__version__,
                        "numpy": numpy.__version__, "executorch": host_executorch(args.host_python)})
    write_json_atomic(args.out.with_suffix(".json"), report)
    write_text_atomic(args.out.with_suffix(".md"), markdown(report))
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
