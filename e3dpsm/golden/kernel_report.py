"""`python -m e3dpsm.golden.kernel_report host|device`: the kernel-parity trace of one QDQ
graph (kernel_trace.py), in two halves.

    host   GRAPH GOLDEN DIR [--steps N]   writes DIR/exposed.onnx, DIR/cut.onnx, DIR/host.npz
                                          (needs onnx; run on the machine the golden is from)
    device DIR                            runs both rollouts here, writes DIR/device-<isa>.json
                                          (numpy and onnxruntime only: the ARM board, the
                                          emulated aarch64 root of benchmarks/arm_emulation.py)
    portable GRAPH OUT                    writes the graph's portable form (kernel_cut.portable_qdq:
                                          the same codes on x86 and ARM), its metadata saying so
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from e3dpsm.errors import DataError, E3DPSMError, InputError
from e3dpsm.golden import kernel_trace as kt

EXPOSED, CUT, HOST_TRACE, ORDER = "exposed.onnx", "cut.onnx", "host.npz", "codes.json"
KERNELS_FOLDER = "kernels"  # a golden folder's traces: kernels/<graph stem>-<sha256[:12]>/


def trace_folder(golden_dir: str | os.PathLike, graph: str | os.PathLike, sha256: str) -> Path:
    return Path(golden_dir) / KERNELS_FOLDER / f"{Path(graph).stem}-{sha256[:12]}"


def find_trace(golden_dir: str | os.PathLike, sha256: str | None, manifest_name: str = ORDER) -> Path | None:
    """The folder of the golden's trace of the graph with this digest, if `golden record
    --kernel-trace` kept one: a kernel trace (its `codes.json`), or an artifact's code trace
    (artifact_trace.HOST_FILE)."""
    if not sha256:
        return None
    for manifest in sorted((Path(golden_dir) / KERNELS_FOLDER).glob(f"*-{sha256[:12]}/{manifest_name}")):
        if json.loads(manifest.read_text(encoding="utf-8")).get("sha256") == sha256:
            return manifest.parent
    return None


def responsible_lines(report: dict[str, Any], limit: int = 6) -> list[str]:
    """The quantised activations that depart on their own, with the ops of their segments."""
    lines = [f"{d['name']} ({' '.join(d['segment']) or 'data movement'}): {d['apart']} codes apart over "
             f"{d['steps_apart']} steps from step {d['first_step']}, at most {d['max_codes']}"
             for d in report["isolated"][:limit]]
    more = len(report["isolated"]) - limit
    return lines + ([f"... and {more} more (check.json)"] if more > 0 else [])


def record_host(graph: str | os.PathLike, golden_dir: str | os.PathLike, out: str | os.PathLike,
                steps: int | None = None, threads: int = 1) -> dict[str, Any]:
    """The host half: the two graphs and the host's trace over the golden's first `steps` frames."""
    import onnx

    from e3dpsm.golden.kernel_cut import cut_at_quantized, expose_quantized, segment_ops
    from e3dpsm.golden.store import load_golden
    from e3dpsm.runtime.session import StepSession
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    if steps is not None and steps < 1:
        raise InputError(f"--steps must be at least 1, got {steps}")
    model = _load_qdq_graph(graph)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    exposed, codes = expose_quantized(model)
    onnx.save(exposed, str(folder / EXPOSED))
    onnx.save(cut_at_quantized(model)[0], str(folder / CUT))
    golden = load_golden(golden_dir)
    steps = min(steps or golden.steps, golden.steps)
    session = StepSession(graph)
    trace = kt.rollout(folder / EXPOSED, _golden_inputs(session, golden, steps), codes, threads)
    with atomic_path(folder / HOST_TRACE, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **trace)
    from e3dpsm.golden.record import sha256_file

    manifest = {"graph": str(graph), "sha256": sha256_file(graph), "codes": codes, "segments": segment_ops(model),
                "steps": steps,
                "state_inputs": [s.input_name for s in session.meta.states]}
    write_json_atomic(folder / ORDER, manifest)
    return manifest


def _golden_inputs(session: Any, golden: Any, steps: int) -> Iterator[dict[str, np.ndarray]]:
    """Each step's feeds from the golden's frames; the initial states at the first step only
    (rollout carries them after)."""
    from e3dpsm.runtime.session import build_feeds

    state = session.init_state(1)
    for step in range(steps):
        feeds = build_feeds(session.meta, golden.frame(step), state, golden.window_ms(step))
        if step:
            feeds = {k: v for k, v in feeds.items() if k not in {s.input_name for s in session.meta.states}}
        yield feeds


def run_device(folder: str | os.PathLike, threads: int = 1, out: str | os.PathLike | None = None) -> dict[str, Any]:
    """The device half: propagated and isolated rollouts against the host's trace; the report
    goes to `out` (default: the trace's folder, device-<isa kind>.json)."""
    from e3dpsm.utils.io import write_json_atomic
    from e3dpsm.utils.isa import detect_isa

    folder = Path(folder)
    manifest = json.loads((folder / ORDER).read_text(encoding="utf-8"))
    codes, segments, steps = manifest["codes"], manifest["segments"], manifest["steps"]
    if not isinstance(steps, int) or steps < 1:
        raise DataError(f"{folder / ORDER}: the host trace holds no steps ({steps!r}); record it again with "
                        "`python -m e3dpsm.golden.kernel_report host`")
    host = kt.load_trace(folder / HOST_TRACE)
    first_inputs = {k[len(kt.IN):]: v[0] for k, v in host.items() if k.startswith(kt.IN)}
    frame_keys = [k for k in first_inputs if k not in set(manifest["state_inputs"])]
    inputs = ({k: host[kt.IN + k][s] for k in (first_inputs if s == 0 else frame_keys)} for s in range(steps))
    propagated = kt.compare_traces(host, kt.rollout(folder / EXPOSED, inputs, codes, threads), codes)
    own = kt.compare_traces(host, kt.isolated(folder / CUT, host, codes, threads), codes)
    isa = detect_isa()
    report = {"graph": manifest["graph"], "steps": steps, "isa": isa.to_dict(),
              "propagated": [d.to_dict() for d in propagated],
              "first_departures": [d.name for d in kt.first_departures(propagated)],
              "isolated": [{**d.to_dict(), "segment": segments[d.name]} for d in own if d.apart],
              "isolated_identical": sum(1 for d in own if not d.apart), "codes": len(codes)}
    write_json_atomic(Path(out) if out else folder / f"device-{isa.kind}.json", report)
    return report


def _load_qdq_graph(graph: str | os.PathLike) -> Any:
    """The ONNX graph at `graph`; DataError unless it reads and quantises a computed tensor."""
    from e3dpsm.golden.kernel_cut import quantized_activations
    from e3dpsm.onnx_graph import read_onnx

    model = read_onnx(graph)
    if not quantized_activations(model):
        raise DataError(f"{graph}: no QuantizeLinear on a computed tensor: not a QDQ graph (write one with "
                        "`e3dpsm quantize --mode int8`)")
    return model


def write_portable(graph: str | os.PathLike, out: str | os.PathLike) -> dict[str, int]:
    """`graph`'s portable form at `out`; its quantisation metadata records what stayed 8-bit.
    DataError, nothing written, unless `graph` is a readable QDQ graph."""
    import onnx

    from e3dpsm.golden.kernel_cut import portable_qdq, quantized_activations
    from e3dpsm.utils.io import atomic_path

    model = _load_qdq_graph(graph)
    portable, removed = portable_qdq(model)
    counts = {"activations_float": len(removed), "activations_int8": len(quantized_activations(portable))}
    for prop in portable.metadata_props:
        if prop.key == "e3dpsm.quantization":
            prop.value = json.dumps({**json.loads(prop.value), "arm_portable": counts})
    with atomic_path(Path(out), suffix=".onnx") as tmp:
        onnx.save(portable, str(tmp))
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m e3dpsm.golden.kernel_report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="half", required=True)
    host = sub.add_parser("host")
    host.add_argument("graph")
    host.add_argument("golden")
    host.add_argument("out")
    host.add_argument("--steps", type=int, default=None)
    device = sub.add_parser("device")
    device.add_argument("folder")
    portable = sub.add_parser("portable")
    portable.add_argument("graph")
    portable.add_argument("out")
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except E3DPSMError as exc:
        print(f"{parser.prog} {args.half}: error: " + " ".join(str(exc).split()), file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    if args.half == "portable":
        counts = write_portable(args.graph, args.out)
        print(f"portable: {counts['activations_int8']} activations kept 8-bit, {counts['activations_float']} back "
              f"to float, weights 8-bit -> {args.out}")
        return 0
    if args.half == "host":
        manifest = record_host(args.graph, args.golden, args.out, args.steps)
        print(f"kernel trace: {len(manifest['codes'])} quantised activations over {manifest['steps']} steps -> {args.out}")
        return 0
    report = run_device(args.folder)
    first = report["first_departures"][:1]
    print(f"kernel trace on {report['isa']['kind']}: first departure {first or 'none'}; "
          f"{len(report['isolated'])} of {report['codes']} segments depart on their own")
    return 0


if __name__ == "__main__":
    sys.exit(main())
