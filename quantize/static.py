"""INT8 static quantisation (QDQ, per-channel weights) with ONNX Runtime's tooling.

Calibration runs once: its tensor ranges go to a JSON cache, so the exclusion search can
re-quantise with other float-kept nodes without re-running the calibrator (ranges are
per tensor and do not depend on which nodes end up quantised).
"""
from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping

import numpy as np
import onnx
import onnx.version_converter

from e3dpsm.errors import ConfigError
from e3dpsm.onnx_graph import restore_interface_types
from e3dpsm.quantize.calibration import CalibrationSet, FeedListReader
from e3dpsm.quantize.ranges import with_zero
from e3dpsm.utils.isa import ISA_KINDS

if TYPE_CHECKING:
    from e3dpsm.quantize.ranges import RangeChoice

log = logging.getLogger(__name__)

# "mse": each activation's own range, the one with the lowest expected quantisation error on
# its calibration histogram (ranges.py); the others are ONNX Runtime's rules, one per graph.
CALIBRATION_METHODS: tuple[str, ...] = ("minmax", "entropy", "percentile", "mse")
# The compute-heavy ops only. Quantising the CNN blocks' Add/Mul/Sigmoid too (with BatchNorm
# as a depthwise Conv) made `paper` ~6% faster on an AVX2 host but moved the trained tiny's
# poses further from fp32 (10.4% -> 11.3% of MPJPE): benchmarks/results/quantize.changes.md.
DEFAULT_OP_TYPES: tuple[str, ...] = ("Conv", "MatMul", "Gemm")
# CPU kinds an INT8 graph can be quantised for ("unknown" hosts as for int8 dot-product
# units, ONNX Runtime's default).
TARGET_ISAS: tuple[str, ...] = ISA_KINDS
# ONNX's QuantizeLinear / DequantizeLinear take 16-bit integers from opset 21.
INT16_OPSET = 21
# 16-bit tensors take their min-max calibration range widened this many times about zero.
# Measured on the committed trained `small` (vnni host; calibrated on prep96_test's `train`
# sequence, checked on its unseen `test` sequence): with every activation 16-bit (and 16-bit
# weights, to isolate the activations) the poses moved 0.697% of MPJPE from fp32 at the
# calibration's own ranges, all of it clipping; 0.048% at twice the range, 0.094% at four
# times. 8-bit ranges get no margin: there the step dominates (full int8 on `test`: 9.79% at
# the min-max range, 10.85% at 1.25x, 12.22% at 1.5x).
INT16_RANGE_MARGIN = 2.0


def saturates_u8s8(target_isa: str) -> bool:
    """Whether ONNX Runtime's U8S8 kernels on this kind of target add pairs of u8 x s8
    products in saturating 16-bit sums (x86 without int8 dot-product units: utils/isa.py)."""
    if target_isa not in TARGET_ISAS:
        raise ConfigError(f"unknown --target-isa {target_isa!r}; choose from {list(TARGET_ISAS)}")
    return target_isa in ("avx2", "other")


@dataclass(frozen=True)
class StaticConfig:
    """How the INT8 graph is quantised; recorded in the graph's metadata and the report.

    Activations are unsigned 8-bit (ORT's CPU kernels are fastest with U8 activations and
    S8 weights on x86, with or without VNNI); weights are symmetric per output channel.
    """

    calibration: str = "minmax"
    per_channel: bool = True
    activation_type: str = "QUInt8"
    weight_type: str = "QInt8"
    op_types: tuple[str, ...] = DEFAULT_OP_TYPES
    percentile: float = 99.999
    # 7-bit weights (ONNX Runtime's reduce_range): recommended by ONNX Runtime "for better
    # accuracy on non-VNNI CPUs", whose U8S8 kernels add pairs of u8 x s8 products in
    # saturating 16-bit arithmetic; 7-bit weights keep such a pair inside 16 bits.
    reduce_range: bool = False

    def __post_init__(self) -> None:
        if self.calibration not in CALIBRATION_METHODS:
            raise ConfigError(f"unknown calibration {self.calibration!r}; choose from {list(CALIBRATION_METHODS)}")

    @classmethod
    def for_target(cls, target: str, isa: str, **fields) -> "StaticConfig":
        """The config for a target (`options.TARGETS`) on a CPU kind (`utils.isa.CpuIsa.kind`):
        7-bit weights where a CPU target has no int8 dot-product units (AVX2 and other x86),
        8-bit elsewhere, and always for an NPU, whose integer kernels do not saturate so."""
        return cls(reduce_range=target != "npu" and saturates_u8s8(isa), **fields)

    def to_dict(self) -> dict:
        return {**asdict(self), "format": "QDQ", "op_types": list(self.op_types)}


def preprocess(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """ORT's recommended pre-pass: symbolic shape inference and basic graph optimisation
    (constant folding, redundant nodes), so the quantiser sees shapes for every tensor."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    quant_pre_process(str(src), str(dst), skip_optimization=False, skip_onnx_shape=False,
                      skip_symbolic_shape=False, auto_merge=True)
    model = onnx.load(str(dst))
    # ONNX Runtime's symbolic shape inference (auto_merge) renames a symbolic axis it merges,
    # and which name survives follows Python's string hashing: the same export came out with
    # "batch" under PYTHONHASHSEED 0, 1 and 4 and "unk__0" under 2, 3 and 5 (ORT 1.31), so two
    # runs of `quantize` wrote artifacts whose interface differed.
    restore_interface_types(model, onnx.load(str(src), load_external_data=False))
    onnx.save(model, str(dst))


def _method(name: str):
    from onnxruntime.quantization import CalibrationMethod

    # "mse" starts from min-max ranges and is written to the cache as min-max ranges.
    return {"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
            "percentile": CalibrationMethod.Percentile, "mse": CalibrationMethod.MinMax}[name]


def calibrate(src: str | os.PathLike, config: StaticConfig, calibration: CalibrationSet,
              cache: str | os.PathLike) -> dict[str, "RangeChoice"]:
    """Write ONNX Runtime's calibration cache (tensor ranges) for the graph `src`; return the
    per-tensor range choices under "mse" ({} otherwise).

    minmax, entropy and percentile run ONNX Runtime's calibrators with the options
    `quantize_static` gives them (the percentile; ORT's defaults otherwise: entropy 128 bins,
    percentile 2048 bins on |x|, a symmetric range). A bins setting this project used to pass
    (CalibNumBins) never reached them: ORT 1.31's quantize_static does not forward it."""
    from onnxruntime.quantization.calibrate import create_calibrator, save_tensors_data

    from e3dpsm.quantize.ranges import select_ranges, write_minmax_cache

    options = {"percentile": config.percentile} if config.calibration == "percentile" else {}
    with tempfile.TemporaryDirectory(prefix="e3dpsm-calib-") as work:
        calibrator = create_calibrator(Path(src), list(config.op_types), augmented_model_path=str(Path(work) / "aug.onnx"),
                                       calibrate_method=_method(config.calibration), extra_options=options)
        calibrator.collect_data(FeedListReader(calibration.feeds))
        ranges = calibrator.compute_data()
        del calibrator
    if config.calibration != "mse":
        save_tensors_data(ranges, cache)
        return {}
    # A second pass over the feeds: the histograms need each tensor's range before they are
    # made, and ORT's min-max pass gives the ranges and the very tensors it will quantise.
    minmax = {name: tuple(float(np.ravel(v)[0]) for v in ranges[name].range_value) for name in ranges}
    save_tensors_data(ranges, minmax_cache_path(cache))  # for 16-bit tensors (quantize_int8)
    chosen = select_ranges(src, minmax, calibration.feeds)
    write_minmax_cache(cache, chosen)
    return chosen


def minmax_cache_path(cache: str | os.PathLike) -> Path:
    """Where `calibrate` keeps the plain min-max ranges when the cache holds narrower ones."""
    cache = Path(cache)
    return cache.with_name(cache.stem + "_minmax" + cache.suffix)


def int16_ranges(cache: str | os.PathLike, tensors: Iterable[str],
                 margin: float = INT16_RANGE_MARGIN) -> dict[str, tuple[float, float]]:
    """Ranges for 16-bit tensors: the calibration's min-max range (under "mse" the plain
    min-max cache, not the narrowed 8-bit choice; the other rules' own ranges otherwise),
    widened `margin` times about zero (`widened_range`).

    At 65,536 levels the rounding error is negligible; what is left is clipping, and a range
    seen on the calibration frames clips other sequences (INT16_RANGE_MARGIN)."""
    import json

    path = minmax_cache_path(cache)
    data = json.loads((path if path.is_file() else Path(cache)).read_text())["data"]
    return {t: widened_range(float(data[t]["lowest"]["data"][0]), float(data[t]["highest"]["data"][0]), margin)
            for t in tensors if t in data}


def widened_range(low: float, high: float, margin: float) -> tuple[float, float]:
    """[low, high] with zero included (as every QDQ range is), scaled `margin` times about
    zero: the ends move out in proportion to their own size, so a one-sided range stays
    one-sided."""
    if margin < 1.0:
        raise ValueError(f"a range margin below 1 would clip the calibration frames themselves, got {margin}")
    low, high = with_zero(low, high)
    return low * margin, high * margin


def int16_tensors(model: onnx.ModelProto, nodes: Iterable[str], cache: str | os.PathLike) -> list[str]:
    """The activation tensors 16-bit nodes read or write: those of the calibration cache
    (the tensors the quantiser can give a Q/DQ pair). A tensor shared with an 8-bit node
    goes 16-bit too (the 8-bit node then reads it through a 16-bit DequantizeLinear)."""
    import json

    calibrated = set(json.loads(Path(cache).read_text())["data"])
    wanted = set(nodes)
    found = [t for n in model.graph.node if n.name in wanted for t in (*n.input, *n.output) if t in calibrated]
    return sorted(set(found))


def weight_channel_axis(node: onnx.NodeProto) -> int | None:
    """The output-channel axis of a Conv/MatMul/Gemm weight (input 1), as ONNX Runtime's QDQ
    quantiser chooses it per channel (its operators' default axes); None for other ops.
    AdaRound reads per-channel weights at this axis too (adaround.find_layers)."""
    if node.op_type == "Conv":
        return 0
    if node.op_type == "MatMul":
        return 1
    if node.op_type == "Gemm":
        trans_b = next((a.i for a in node.attribute if a.name == "transB"), 0)
        return 0 if trans_b else 1
    return None


def graph_opset(model: onnx.ModelProto) -> int:
    return next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)


def ensure_opset(path: str | os.PathLike, opset: int = INT16_OPSET) -> bool:
    """Convert the graph at `path` to `opset` in place (16-bit QuantizeLinear needs 21 in the
    default domain; ONNX Runtime would otherwise switch to com.microsoft ops, which DESIGN
    forbids). Returns whether it converted. Done before calibrating, so every trial graph
    and the calibration cache name the same tensors and nodes."""
    model = onnx.load(str(path))
    if graph_opset(model) >= opset:
        return False
    converted = onnx.version_converter.convert_version(model, opset)
    for index, node in enumerate(converted.graph.node):  # the converter may add unnamed nodes
        if not node.name:
            node.name = f"opset{opset}_{node.op_type}_{index}"
    onnx.save(converted, str(path))
    return True


def quantize_int8(
    src: str | os.PathLike, dst: str | os.PathLike, config: StaticConfig, *,
    exclude: Iterable[str] = (), calibration: CalibrationSet | None = None, cache: str | os.PathLike,
    learned: Mapping[str, Mapping[str, Any]] | None = None, int16_nodes: Iterable[str] = (),
) -> None:
    """Quantise the pre-processed graph `src` to `dst` with the ranges of `cache`, calibrating
    first (`calibrate`) if there is no cache yet: `calibration` is needed then only.

    `learned`: {tensor: {"scale", "zero_point"}} written as they are (QAT ranges,
    qat_ranges.py); `int16_nodes`: nodes whose activations are quantised to 16 bits (QUInt16;
    the graph must be at opset 21 already, `ensure_opset`), through ONNX Runtime's
    TensorQuantOverrides. A node named at 16 bits is quantised even where `exclude` names it."""
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static

    cache = Path(cache)
    if not cache.is_file():
        if calibration is None:
            raise ValueError("no calibration cache yet: pass the calibration set")
        calibrate(src, config, calibration, cache)
    int16: list[str] = []
    sixteen_bit = list(int16_nodes)
    if sixteen_bit:
        model = onnx.load(str(src))
        if graph_opset(model) < INT16_OPSET:
            raise ValueError(f"{src} is below opset {INT16_OPSET}: convert it with ensure_opset before calibrating")
        int16 = int16_tensors(model, sixteen_bit, cache)
    overrides = ort_overrides(learned or {}, int16, int16_ranges(cache, int16))
    quantize_static(
        str(src), str(dst),
        calibration_data_reader=None,  # the ranges come from the cache written above
        quant_format=QuantFormat.QDQ,
        op_types_to_quantize=list(config.op_types),
        per_channel=config.per_channel,
        reduce_range=config.reduce_range,
        activation_type=getattr(QuantType, config.activation_type),
        weight_type=getattr(QuantType, config.weight_type),
        nodes_to_exclude=sorted(set(exclude) - set(sixteen_bit)),
        calibrate_method=_method(config.calibration),
        # Weights symmetric around 0 (per channel); activations asymmetric U8.
        extra_options={"WeightSymmetric": True, "ActivationSymmetric": False,
                       **({"TensorQuantOverrides": overrides} if overrides else {})},
        calibration_cache_path=str(cache),
    )
    log.debug("quantised %s -> %s (%d nodes kept float)", src, dst, len(set(exclude)))


def ort_overrides(learned: Mapping[str, Mapping[str, Any]], int16: Sequence[str] = (),
                  int16_ranges: Mapping[str, tuple[float, float]] | None = None) -> dict[str, list[dict]]:
    """ONNX Runtime's TensorQuantOverrides for learned U8 ranges and 16-bit activations
    (with `int16_ranges` (rmin, rmax) where given). A tensor both learned and 16-bit keeps
    16 bits (calibrated): a U8 range has no 16-bit form."""
    from onnxruntime.quantization import QuantType

    out: dict[str, list[dict]] = {}
    for name, q in learned.items():
        if name not in int16:
            out[name] = [{"scale": np.array(q["scale"], np.float32), "zero_point": np.array(q["zero_point"], np.uint8)}]
    for name in int16:
        rng = (int16_ranges or {}).get(name)
        extra = {"rmin": np.array(rng[0], np.float32), "rmax": np.array(rng[1], np.float32)} if rng else {}
        out[name] = [{"quant_type": QuantType.QUInt16, **extra}]
    return out


