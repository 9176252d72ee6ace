"""Drive an exported step graph with OpenVINO (optional extra: `pip install e3dpsm[openvino]`).

Same interface as `StepSession`, so parity and profiling treat both runtimes alike. The
state stays explicit here; `openvino.passes.MakeStateful` could move it inside the
runtime, but explicit state keeps one graph and one contract for every runtime.
"""
from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from e3dpsm.errors import ConfigError, DataError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.session import MetadataStepper, StateArrays


def openvino_available() -> tuple[bool, str]:
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False, "openvino is not installed (pip install 'e3dpsm[openvino]')"
    return True, ""


def _deform_conv_to_openvino(node: Any) -> list[Any]:
    """ONNX DeformConv (opset 19) -> OpenVINO DeformableConvolution-8 (+ bias Add).

    OpenVINO 2026.4's ONNX frontend has no rule for DeformConv. `bilinear_interpolation_pad`
    must be true: with it, a sample within one pixel outside the map blends the border values
    with zeros, as ONNX (and grid_sample with zero padding) define it; without it such samples
    read zero (measured: up to 3.1 against values of 4.6; with it, 5e-7)."""
    import openvino.opset8 as ops

    spatial = 2
    pads = list(node.get_attribute("pads", [0] * 2 * spatial))
    inputs = node.get_input_size()
    mask = node.get_input(4) if inputs > 4 else None
    out = ops.deformable_convolution(
        node.get_input(0), node.get_input(2), node.get_input(1),
        strides=list(node.get_attribute("strides", [1] * spatial)), pads_begin=pads[:spatial], pads_end=pads[spatial:],
        dilations=list(node.get_attribute("dilations", [1] * spatial)), mask=mask,
        group=node.get_attribute("group", 1), deformable_group=node.get_attribute("offset_group", 1),
        bilinear_interpolation_pad=True,
    )
    if inputs > 3:
        bias = ops.unsqueeze(node.get_input(3), ops.constant([0, 2, 3]))  # [C] -> [1, C, 1, 1]
        out = ops.add(out, bias)
    return [out.output(0)]


def openvino_core() -> Any:
    """An openvino.Core that reads every operator our ONNX graphs may hold (DeformConv included)."""
    import openvino as ov
    from openvino.frontend.onnx import ConversionExtension

    core = ov.Core()
    core.add_extension(ConversionExtension("DeformConv", _deform_conv_to_openvino))
    return core


def read_openvino_model(path: str | os.PathLike) -> tuple[Any, Any]:
    """(openvino.Core, openvino.Model) for an ONNX graph or an IR, each failure one clear error."""
    ok, reason = openvino_available()
    if not ok:
        raise ConfigError(reason)
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    core = openvino_core()
    try:
        model = core.read_model(str(path))
    except RuntimeError as exc:
        raise DataError(f"OpenVINO cannot read {path}: {str(exc).splitlines()[0][:300]}") from exc
    if path.suffix == ".onnx":
        protect_dequantization(model)
    return core, model


def protect_dequantization(model: Any) -> None:
    """OpenVINO's common transformations without constant folding, as its own converter (ovc,
    `openvino.convert_model`) runs them on every model it reads: among them, they mark an
    INT8 QDQ graph's dequantisation so that no later constant folding takes it apart.

    Why: read with `read_model` alone, any constant folding before the CPU plugin compiles
    the graph folds parts of the dequantisation, and the plugin then runs its convolutions in
    f32. `fix_batch`'s reshape does so (measured on `small`'s default INT8 graph, OpenVINO
    2026.4: the stateful IR ran none of the 37 convolutions the graph otherwise runs in u8,
    1.3-1.5x slower side by side; benchmarks/results/openvino_int8_kernels_vnni.md), and so
    does an application's PrePostProcessor on a saved IR (benchmark_app: 12.7 against the
    runner's 9.5 ms). Numerics: the INT8 poses move 0.185 mm mean over 80 held-out steps, as
    far as OpenVINO and ONNX Runtime are apart on the same graph (docs/runtimes.md)."""
    from openvino._offline_transformations import apply_moc_transformations

    apply_moc_transformations(model, cf=False)


OPENVINO_PRECISIONS = ("f32", "bf16")

# OpenVINO's CPU plugin quantises, by default in groups of 32, the float activations of every
# MatMul / Gemm whose weights are int8 behind a DequantizeLinear, to 8 bits at run time
# ("dynamic quantization" of weight-compressed layers). In a graph of `quantize`, those layers
# are the 16-bit-activation nodes: OpenVINO strips their 16-bit Q/DQ pairs and the layer then
# reads 8-bit activations after all, which the budget was never checked on. Measured on the
# committed `small`'s default INT8 graph (61 of 117 nodes at 16 bits; AMD EPYC, OpenVINO
# 2026.4): 0.954% of MPJPE from fp32 on 1,000 unseen frames with it, 0.596% without (ONNX
# Runtime: 0.599%), for 4% of OpenVINO's speed. 0 turns it off (OpenVINO >= 2024.5); the IR
# carries the same option (`export.openvino_ir.RT_RUNTIME_OPTIONS`), so an application that
# compiles it with no options of its own runs these numbers too.
DYNAMIC_QUANTIZATION_OFF: dict[str, Any] = {"DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}


def compile_config(threads: int | None, extra: Mapping[str, Any] | None = None,
                   precision: str = "f32") -> dict[str, Any]:
    """The graph's own arithmetic: float parts in f32 (parity checks and int8 graphs alike), no
    silent bf16 / fp16 on CPUs that have them, and no run-time 8-bit quantisation of the
    activations a graph keeps in 16 bits or float (`DYNAMIC_QUANTIZATION_OFF`); `threads`
    intra-op threads when given. `precision="bf16"` asks for bf16 instead, which needs bf16
    units (checked: without them OpenVINO would quietly run f32). `extra` is applied last."""
    if precision not in OPENVINO_PRECISIONS:
        raise ConfigError(f"unknown OpenVINO precision {precision!r}; choose one of {', '.join(OPENVINO_PRECISIONS)}")
    if precision == "bf16":
        from e3dpsm.utils.isa import bf16_unavailable_reason

        reason = bf16_unavailable_reason()
        if reason:
            raise ConfigError(f"bf16 needs a CPU with bf16 units: {reason}; run f32 (or int8) here")
    config: dict[str, Any] = {"INFERENCE_PRECISION_HINT": precision, **DYNAMIC_QUANTIZATION_OFF, **(extra or {})}
    if threads:
        config["INFERENCE_NUM_THREADS"] = int(threads)
    return config


# The layers that carry a step's arithmetic; their run-time precisions say which graph ran
# (an INT8 graph whose convolutions run in f32 has lost its quantisation on the way).
HEAVY_LAYER_TYPES = ("Convolution", "Deconvolution", "FullyConnected", "MatMul")


def count_heavy_layers(layers: Iterable[tuple[str | None, str]]) -> dict[str, int]:
    """{"<layer type> <run-time precision>": count} over (type, precision) pairs of an
    executed graph, heavy layers only (`HEAVY_LAYER_TYPES`)."""
    counts = Counter(f"{kind} {precision}" for kind, precision in layers if kind in HEAVY_LAYER_TYPES)
    return dict(sorted(counts.items()))


def executed_layers(compiled: Any) -> dict[str, int]:
    """The heavy layers of a compiled model by the precision OpenVINO runs them in (its
    run-time graph's `layerType` / `runtimePrecision`), as `count_heavy_layers` counts them.

    Why: applying `PrePostProcessor.build()` or `ConstantFolding` to the INT8 QDQ graph before
    compiling folds parts of its dequantisation, and the CPU plugin then runs every
    convolution in f32 (`small`, OpenVINO 2026.4: 37 u8 convolutions become 0;
    `protect_dequantization` prevents it). Compare an application's compiled model with this
    to see it."""
    def text(value: Any) -> str:
        return value.astype(str) if hasattr(value, "astype") else str(value)

    ops = compiled.get_runtime_model().get_ops()
    return count_heavy_layers((text(op.get_rt_info()["layerType"]), text(op.get_rt_info()["runtimePrecision"]))
                              for op in ops)


def _contract_name(port, contract: set[str]) -> str:
    """The port's name from the graph's contract: a port can carry several tensor names (an
    FP16 graph's outputs pass through a Cast, and OpenVINO may list the Cast's name first)."""
    names = sorted(port.get_names() & contract)
    return names[0] if names else port.get_any_name()


class OpenVINOStepSession(MetadataStepper):
    """The explicit-state step graph on OpenVINO: `step(lnes, state, window_ms) -> (outputs,
    state)`, or its parts `feeds` -> `run_raw` (the runtime's own call) -> `collect`, as
    `StepSession` has them.

    Inputs are handed to OpenVINO as tensors sharing the numpy arrays' memory (no copy in;
    they must stay untouched until `run_raw` returns, as they do in a step); outputs are
    copied out of the request once, since the next inference overwrites its buffers."""

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None, device: str = "CPU",
                 precision: str = "f32", config: Mapping[str, Any] | None = None) -> None:
        """`config`: OpenVINO properties over `compile_config`'s (applied last)."""
        core, self._model = read_openvino_model(path)
        import onnx

        self.path = Path(path)
        self.meta = GraphMetadata.from_onnx(onnx.load(str(self.path), load_external_data=False), source=str(self.path))
        self._compiled = core.compile_model(self._model, device, compile_config(threads, config, precision=precision))
        self._request = self._compiled.create_infer_request()
        inputs = {self.meta.frame_input["name"], self.meta.window_input["name"], *(s.input_name for s in self.meta.states)}
        outputs = {*self.meta.output_names, *(s.output_name for s in self.meta.states)}
        self._inputs = [_contract_name(p, inputs) for p in self._compiled.inputs]
        self._outputs = [_contract_name(p, outputs) for p in self._compiled.outputs]
        self._input_ports = dict(zip(self._inputs, self._compiled.inputs))
        # A port can carry several names (fusion_pose_out is an Identity of pose): index them all.
        self._output_ports = {name: port for port in self._compiled.outputs for name in port.get_names()}

    @property
    def compiled(self) -> Any:
        """The openvino.CompiledModel (its properties say how it runs)."""
        return self._compiled

    def run_raw(self, feeds: Mapping[str, np.ndarray]) -> None:
        """Bind the feeds (shared memory) and infer; the results stay in the request."""
        import openvino as ov

        for name, value in feeds.items():
            self._request.set_tensor(self._input_ports[name], ov.Tensor(np.ascontiguousarray(value), shared_memory=True))
        self._request.infer()

    def collect(self, _: Any = None) -> tuple[dict[str, np.ndarray], StateArrays]:
        """The last inference's (outputs, next state), copied out of the request."""
        outputs = {name: self._copy_out(name) for name in self.meta.output_names}
        return outputs, {s.name: self._copy_out(s.output_name) for s in self.meta.states}

    def _copy_out(self, name: str) -> np.ndarray:
        return self._request.get_tensor(self._output_ports[name]).data.copy()

    def run_feeds(self, feeds: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]:
        return self.collect(self.run_raw(feeds))
