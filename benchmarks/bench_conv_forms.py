"""Benchmark: can an exact, MAC-reducing form of the CNN's 3x3 convolutions beat ONNX
Runtime's own Conv on this CPU? (The fp32 step's convolutions already run near
the machine's dense peak, so a faster fp32 step needs fewer multiplications.)

    python benchmarks/bench_conv_forms.py [--variant paper] [--steps 200] [--threads 2] \
        [--out benchmarks/results/conv_forms_paper]

Winograd minimal filtering F(m x m, 3 x 3) (Lavin & Gray, "Fast Algorithms for Convolutional
Neural Networks", CVPR 2016) computes an m x m output tile from an (m+2)^2 input tile with
(m+2)^2 multiplications per input/output channel pair instead of 9 m^2: 2.25x fewer for
m = 2, 4x fewer for m = 4. It is exact in real arithmetic; in float32 it adds round-off
(measured below against the direct convolution).

Each distinct 3x3 stride-1 convolution of the variant's CNN (shapes read from one step of
the PyTorch model) is built three ways as a standalone ONNX graph from default-domain ops:
the plain `Conv`, and Winograd F(2x2,3x3) and F(4x4,3x3) laid out for ONNX Runtime:
  * input transform: one `Conv` over the channels folded into the batch (kernel B^T (x) B^T,
    stride m), so tiles overlap without any gather;
  * the products: one batched `MatMul` [tile-pos, out, in] x [tile-pos, in, tiles] (ONNX
    Runtime folds the preceding transpose into it);
  * output transform: one `MatMul` with A^T (x) A^T, then `DepthToSpace` (DCR) scatters the
    m x m outputs; crop and bias `Add`.
Every form is checked against the plain Conv before it is timed; timing is interleaved
(rounds of `--chunk` runs per form, worker spinning off), medians per form. Writes OUT.json
and OUT.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

# Interpolation points 0, +-1 (m = 2) and 0, +-1, +-2 (m = 4), each with the point at
# infinity: the standard matrices of Lavin & Gray (2016), written as B^T, G, A^T.
_WINOGRAD = {
    2: ([[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]],
        [[1, 0, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0, 0, 1]],
        [[1, 1, 1, 0], [0, 1, -1, -1]]),
    4: ([[4, 0, -5, 0, 1, 0], [0, -4, -4, 1, 1, 0], [0, 4, -4, -1, 1, 0], [0, -2, -1, 2, 1, 0],
         [0, 2, -1, -2, 1, 0], [0, 4, 0, -5, 0, 1]],
        [[1 / 4, 0, 0], [-1 / 6, -1 / 6, -1 / 6], [-1 / 6, 1 / 6, -1 / 6], [1 / 24, 1 / 12, 1 / 6],
         [1 / 24, -1 / 12, 1 / 6], [0, 0, 1]],
        [[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0], [0, 1, 1, 4, 4, 0], [0, 1, -1, 8, -8, 1]]),
}


@dataclass(frozen=True)
class ConvShape:
    in_channels: int
    out_channels: int
    height: int
    width: int
    count: int = 1  # how many convolutions of the step have this shape

    @property
    def macs(self) -> int:
        return self.in_channels * self.out_channels * 9 * self.height * self.width


def winograd_matrices(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B^T, G, A^T) of F(m, 3) in float64."""
    if m not in _WINOGRAD:
        raise ValueError(f"F({m},3) is not tabulated; choose one of {sorted(_WINOGRAD)}")
    return tuple(np.asarray(t, dtype=np.float64) for t in _WINOGRAD[m])


def _graph(nodes, inits, shape: ConvShape):
    import onnx
    from onnx import TensorProto, helper

    c, o, h, w = shape.in_channels, shape.out_channels, shape.height, shape.width
    graph = helper.make_graph(nodes, "conv_form", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, c, h, w])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, o, h, w])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def direct_conv_graph(shape: ConvShape, weight: np.ndarray, bias: np.ndarray):
    from onnx import helper, numpy_helper

    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], kernel_shape=[3, 3], pads=[1, 1, 1, 1])
    return _graph([node], [numpy_helper.from_array(weight, "w"), numpy_helper.from_array(bias, "b")], shape)


def winograd_conv_graph(shape: ConvShape, weight: np.ndarray, bias: np.ndarray, m: int):
    """`Conv(x, weight, bias, pads=1)` as Winograd F(m x m, 3 x 3), batch 1 (see module doc)."""
    from onnx import helper, numpy_helper

    bt, g, at = winograd_matrices(m)
    a = m + 2
    c, o, h, w = shape.in_channels, shape.out_channels, shape.height, shape.width
    tiles_h, tiles_w = -(-h // m), -(-w // m)
    tiles = tiles_h * tiles_w
    # U[(i, j), o, c] = (G w[o, c] G^T)[i, j]; input kernel [(i, j), 1, r, s] = B^T[i, r] B^T[j, s];
    # output [(p, q), (i, j)] = A^T[p, i] A^T[q, j].
    u = np.einsum("ik,ockl,jl->ijoc", g, weight.astype(np.float64), g).reshape(a * a, o, c)
    b_kernel = np.einsum("ir,js->ijrs", bt, bt).reshape(a * a, 1, a, a)
    a_full = np.einsum("pi,qj->pqij", at, at).reshape(m * m, a * a)
    inits = [numpy_helper.from_array(u.astype(np.float32), "U"),
             numpy_helper.from_array(b_kernel.astype(np.float32), "B"),
             numpy_helper.from_array(a_full.astype(np.float32), "A"),
             numpy_helper.from_array(bias.reshape(1, o, 1, 1).astype(np.float32), "bias")]

    def shape_const(name: str, values) -> str:
        inits.append(numpy_helper.from_array(np.asarray(values, dtype=np.int64), name))
        return name

    pad_bottom, pad_right = 1 + m * tiles_h - h, 1 + m * tiles_w - w
    nodes = [
        helper.make_node("Reshape", ["x", shape_const("channels_as_batch", [c, 1, h, w])], ["xb"]),
        helper.make_node("Conv", ["xb", "B"], ["v_tiles"], kernel_shape=[a, a], strides=[m, m],
                         pads=[1, 1, pad_bottom, pad_right]),
        helper.make_node("Reshape", ["v_tiles", shape_const("v_shape", [c, a * a, tiles])], ["v_cit"]),
        helper.make_node("Transpose", ["v_cit"], ["v"], perm=[1, 0, 2]),
        helper.make_node("MatMul", ["U", "v"], ["products"]),
        helper.make_node("Reshape", ["products", shape_const("p_shape", [a * a, o * tiles])], ["products_flat"]),
        helper.make_node("MatMul", ["A", "products_flat"], ["y_tiles"]),
        helper.make_node("Reshape", ["y_tiles", shape_const("y_shape", [1, m * m * o, tiles_h, tiles_w])],
                         ["y_blocks"]),
        helper.make_node("DepthToSpace", ["y_blocks"], ["y_full"], blocksize=m, mode="DCR"),
    ]
    last = "y_full"
    if (m * tiles_h, m * tiles_w) != (h, w):
        nodes.append(helper.make_node("Slice", ["y_full", shape_const("crop_start", [0, 0]),
                                                shape_const("crop_end", [h, w]), shape_const("crop_axes", [2, 3])],
                                      ["y_crop"]))
        last = "y_crop"
    nodes.append(helper.make_node("Add", [last, "bias"], ["y"]))
    return _graph(nodes, inits, shape)


def step_conv_shapes(variant: str) -> list[ConvShape]:
    """The distinct 3x3 stride-1 convolutions of one `step` of the variant, with counts."""
    import torch

    from e3dpsm.models import create_model

    model = create_model(variant).eval()
    seen: dict[tuple[int, int, int, int], int] = {}

    def record(module, inputs, _output) -> None:
        if module.kernel_size == (3, 3) and module.stride == (1, 1) and module.groups == 1:
            _, c, h, w = inputs[0].shape
            key = (c, module.out_channels, h, w)
            seen[key] = seen.get(key, 0) + 1

    hooks = [mod.register_forward_hook(record) for mod in model.modules() if isinstance(mod, torch.nn.Conv2d)]
    cfg = model.config
    with torch.no_grad():
        model.step(torch.zeros(1, cfg.in_channels, cfg.height, cfg.width), model.init_state(1), 20.0)
    for hook in hooks:
        hook.remove()
    return [ConvShape(*key, count=n) for key, n in sorted(seen.items(), key=lambda kv: -kv[0][2] * kv[0][3])]


def _session(model, threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    # Interleaved millisecond runs: a session's idle workers would spin into the next form's
    # run (measured on 2 cores: Conv 1.75 ms with spinning off, 5.65 ms with it on).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])


def measure(shape: ConvShape, steps: int, threads: int, chunk: int, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    c, o = shape.in_channels, shape.out_channels
    weight = (rng.standard_normal((o, c, 3, 3)) / np.sqrt(9 * c)).astype(np.float32)
    bias = rng.standard_normal(o).astype(np.float32)
    x = rng.standard_normal((1, c, shape.height, shape.width)).astype(np.float32)
    forms = {"conv": direct_conv_graph(shape, weight, bias),
             "winograd_f2": winograd_conv_graph(shape, weight, bias, 2),
             "winograd_f4": winograd_conv_graph(shape, weight, bias, 4)}
    sessions = {name: _session(model, threads) for name, model in forms.items()}
    reference = sessions["conv"].run(None, {"x": x})[0]
    scale = float(np.abs(reference).max())
    row: dict[str, Any] = {**asdict(shape), "gmacs_direct": shape.macs / 1e9}
    for name, sess in sessions.items():
        err = float(np.abs(sess.run(None, {"x": x})[0] - reference).max()) / scale
        if err > 1e-4:  # refuse to time a wrong graph
            raise SystemExit(f"bench_conv_forms: error: {name} differs from Conv by {err:.2e} of the output scale "
                             f"at {shape}")
        row[f"{name}_max_rel_err"] = err
    times: dict[str, list[float]] = {name: [] for name in sessions}
    for _ in range(3):
        for sess in sessions.values():
            sess.run(None, {"x": x})
    for _ in range(max(1, steps // chunk)):
        for name, sess in sessions.items():
            for _ in range(chunk):
                start = time.perf_counter()
                sess.run(None, {"x": x})
                times[name].append(time.perf_counter() - start)
    for name, values in times.items():
        row[f"{name}_p50_ms"] = float(np.median(values) * 1e3)
    base = row["conv_p50_ms"]
    row["conv_gflops"] = 2 * shape.macs / (base * 1e6)
    for name in forms:
        row[f"{name}_speedup"] = base / row[f"{name}_p50_ms"]
    return row


def markdown(report: dict[str, Any]) -> str:
    rows = report["rows"]
    lines = [f"# 3x3 convolutions of `{report['config']['variant']}`: ONNX Runtime Conv vs Winograd",
             "", f"Created {report['created']}; {report['config']['threads']} threads, "
             f"{report['config']['steps']} timed runs per form (interleaved), medians; batch 1.", "",
             "| in -> out, H x W | count | direct GMAC | Conv ms | Conv GFLOP/s | F(2,3) ms | F(4,3) ms | "
             "best Winograd vs Conv | F(4,3) max rel. error |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        best = max(r["winograd_f2_speedup"], r["winograd_f4_speedup"])
        lines.append(f"| {r['in_channels']} -> {r['out_channels']}, {r['height']} x {r['width']} | {r['count']} | "
                     f"{r['gmacs_direct']:.3f} | {r['conv_p50_ms']:.3f} | {r['conv_gflops']:.0f} | "
                     f"{r['winograd_f2_p50_ms']:.3f} | {r['winograd_f4_p50_ms']:.3f} | {best:.2f}x | "
                     f"{r['winograd_f4_max_rel_err']:.1e} |")
    total = report["totals"]
    lines += ["", f"Per step (each shape times its count): Conv {total['conv_ms']:.2f} ms; the faster form per shape "
              f"{total['best_ms']:.2f} ms ({total['conv_ms'] / total['best_ms']:.2f}x)."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", default="paper")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--chunk", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/results/conv_forms_paper")
    args = parser.parse_args(argv)

    from e3dpsm.utils.env import report_header
    from e3dpsm.utils.io import write_json_atomic, write_text_atomic

    rows = [measure(shape, args.steps, args.threads, args.chunk, args.seed + i)
            for i, shape in enumerate(step_conv_shapes(args.variant))]
    for r in rows:
        print(f"{r['in_channels']:>4}->{r['out_channels']:<4} {r['height']:>3}x{r['width']:<3} x{r['count']}: "
              f"Conv {r['conv_p50_ms']:.3f} ms, F2 {r['winograd_f2_p50_ms']:.3f}, F4 {r['winograd_f4_p50_ms']:.3f}",
              file=sys.stderr)
    conv_ms = sum(r["conv_p50_ms"] * r["count"] for r in rows)
    best_ms = sum(min(r["conv_p50_ms"], r["winograd_f2_p50_ms"], r["winograd_f4_p50_ms"]) * r["count"] for r in rows)
    report = {**report_header("bench_conv_forms", vars(args)), "rows": rows,
              "totals": {"conv_ms": conv_ms, "best_ms": best_ms}}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out.with_suffix(".json"), report)
    write_text_atomic(out.with_suffix(".md"), markdown(report))
    print(f"wrote {out.with_suffix('.md')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
