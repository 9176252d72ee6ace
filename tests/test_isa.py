"""CPU ISA detection (e3dpsm/utils/isa.py): the flags reports record and tests branch on."""
from __future__ import annotations

import numpy as np
import pytest

from e3dpsm.utils.env import machine_info
from e3dpsm.utils.isa import CpuIsa, detect_isa, parse_cpuinfo

# First lines of /proc/cpuinfo as the hosts of this project print them (flags abridged).
EPYC_AVX2 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx fma avx2 bmi2\nbugs\t: x\n"
EPYC_ZEN4 = "model name\t: AMD EPYC\nflags\t\t: fpu avx2 fma avx512f avx512_vnni avx512_bf16 vaes\n"
XEON_AMX = ("model name\t: Intel Xeon\nflags\t\t: avx2 fma avx512f avx512_vnni avx512_bf16 avx_vnni amx_bf16 "
            "amx_tile amx_int8\n")
NEOVERSE = "processor\t: 0\nFeatures\t: fp asimd crc32 atomics asimddp sve i8mm bf16\nCPU part\t: 0xd40\n"
CORTEX_A72 = "processor\t: 0\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 cpuid\nCPU part\t: 0xd08\n"


@pytest.mark.parametrize("text, kind, int8_dot, bf16, flags", [
    (EPYC_AVX2, "avx2", False, False, ("avx2", "fma")),
    (EPYC_ZEN4, "vnni", True, True, ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16")),
    (XEON_AMX, "vnni", True, True,
     ("avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_int8", "amx_bf16")),
    (NEOVERSE, "dotprod", True, False, ("asimd", "asimddp", "i8mm", "bf16", "sve")),  # OpenVINO ARM: no bf16
    (CORTEX_A72, "neon", False, False, ("asimd",)),
    ("flags\t: fpu sse2\n", "other", False, False, ()),
    ("model name\t: nothing else\n", "unknown", False, False, ()),
])
def test_parse_cpuinfo(text, kind, int8_dot, bf16, flags) -> None:
    isa = parse_cpuinfo(text)
    assert (isa.kind, isa.int8_dot_product, isa.bf16, isa.flags) == (kind, int8_dot, bf16, flags)


def test_flags_are_whole_words() -> None:
    """`avx512_vnni` must not be read out of `avx512_vnni_fake`, nor `avx2` out of `avx256`."""
    assert parse_cpuinfo("flags\t: avx512_vnni_fake avx256\n") == CpuIsa(())  # read, none reported


def test_only_the_first_flags_line_counts() -> None:
    assert parse_cpuinfo(EPYC_AVX2 + "\n" + EPYC_ZEN4).kind == "avx2"


def test_hwcaps_read_like_the_features_line() -> None:
    """aarch64's capability words (what qemu-user reports for its `max` CPU, read in the
    emulated root: AT_HWCAP 0xecfffffb, AT_HWCAP2 0x7f877fff) name the flags the kernel would
    print as Features; bits outside REPORTED_FLAGS do not leak in."""
    from e3dpsm.utils.isa import parse_hwcaps

    qemu_max = parse_hwcaps(0xECFFFFFB, 0x7F877FFF)
    assert qemu_max.flags == ("asimd", "asimddp", "i8mm", "bf16", "sve") and qemu_max.kind == "dotprod"
    a72 = parse_hwcaps(0b11111011, 0)  # fp asimd aes pmull sha1 sha2 crc32: no asimddp (bit 20)
    assert a72.flags == ("asimd",) and a72.kind == "neon" and not a72.int8_dot_product
    assert parse_hwcaps(1 << 20 | 1 << 1, 1 << 13) == parse_cpuinfo("Features\t: fp asimd asimddp i8mm\n")


def test_neon_does_not_saturate_like_avx2() -> None:
    """ARM without dot products sums int8 products in 32 bits: quantize must not narrow its
    weights to 7 bits as it does for AVX2."""
    from e3dpsm.quantize.static import saturates_u8s8

    assert saturates_u8s8("avx2") and not saturates_u8s8("neon") and not saturates_u8s8("dotprod")


def test_unreadable_cpuinfo_gives_unknown(tmp_path) -> None:
    assert detect_isa(tmp_path / "missing").kind == "unknown"


def test_every_report_records_the_isa() -> None:
    isa = machine_info()["isa"]
    assert isa == detect_isa().to_dict() and set(isa) == {"kind", "flags", "int8_dot_product", "bf16"}


def test_golden_check_compares_the_host_with_the_graphs_isa(monkeypatch) -> None:
    from e3dpsm.golden.verify import isa_comparison
    from e3dpsm.utils import isa as isa_module

    monkeypatch.setattr(isa_module, "detect_isa", lambda cpuinfo="/proc/cpuinfo": parse_cpuinfo(EPYC_AVX2))
    vnni = parse_cpuinfo(XEON_AMX).to_dict()
    assert isa_comparison({"mode": "int8", "checked_on_isa": vnni})["same_kind"] is False
    assert isa_comparison({"mode": "int8", "checked_on_isa": parse_cpuinfo(EPYC_AVX2).to_dict()})["same_kind"] is True
    assert isa_comparison(None)["same_kind"] is None  # an fp32 graph has no budget to compare


def test_every_kind_is_a_target_quantize_accepts() -> None:
    """`quantize --target` takes exactly the kinds reports name (one list, ISA_KINDS), plus auto and npu."""
    from e3dpsm.cli import build_parser
    from e3dpsm.utils.isa import ISA_KINDS

    kinds = {parse_cpuinfo(t).kind for t in (EPYC_AVX2, EPYC_ZEN4, XEON_AMX, NEOVERSE, CORTEX_A72, "flags\t: fpu\n", "")}
    assert kinds == set(ISA_KINDS)
    for kind in ISA_KINDS:
        assert build_parser().parse_args(["quantize", "--model", "m", "--data", "d", "--out", "o",
                                          "--target", kind]).target == kind


def _int8_matmul(weight_max: int):
    """A QDQ MatMul (u8 activations, s8 weights) whose every 4 weights along K are
    (w, w, -w, 0): with the activations at 255, a pair (w, w) sums to 510 w, beyond int16 for
    w = 127 (64,770) and inside it for 7-bit weights (32,640 at w = 64)."""
    from onnx import TensorProto, helper, numpy_helper

    k, n = 64, 8
    weights = np.tile(np.array([weight_max, weight_max, -weight_max, 0])[:, None], (k // 4, n)).astype(np.int8)
    consts = {"x.s": np.float32(1.0), "x.z": np.uint8(0), "w.q": weights, "w.s": np.float32(1.0), "w.z": np.int8(0),
              "y.s": np.float32(4096.0), "y.z": np.uint8(0)}
    nodes = [helper.make_node("QuantizeLinear", ["x", "x.s", "x.z"], ["x.q"]),
             helper.make_node("DequantizeLinear", ["x.q", "x.s", "x.z"], ["x.d"]),
             helper.make_node("DequantizeLinear", ["w.q", "w.s", "w.z"], ["w.d"]),
             helper.make_node("MatMul", ["x.d", "w.d"], ["m"]),
             helper.make_node("QuantizeLinear", ["m", "y.s", "y.z"], ["m.q"]),
             helper.make_node("DequantizeLinear", ["m.q", "y.s", "y.z"], ["y"])]
    graph = helper.make_graph(nodes, "int8_matmul", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, k])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, n])],
                              [numpy_helper.from_array(np.asarray(v), name) for name, v in consts.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    x = np.full((1, k), 255.0, np.float32)
    exact = np.clip(np.round(x @ weights.astype(np.float32) / 4096.0), 0, 255) * 4096.0
    return model.SerializeToString(), x, exact


@pytest.mark.parametrize("weight_max", [127, 64])
def test_int8_kernels_saturate_without_dot_product_units_and_7_bit_weights_do_not(weight_max: int) -> None:
    """Why `--target-isa avx2` gives 7-bit weights. The graph's own arithmetic (no fused
    kernel) equals numpy on any host; ONNX Runtime's fused kernel equals it with 7-bit
    weights on any x86 host, and with 8-bit weights only where int8 products accumulate in
    32 bits: on an AVX2-only host the 16-bit pair sums saturate (measured there: 4,096
    against 520,192)."""
    import onnxruntime as ort

    from e3dpsm.runtime.session import exact_arithmetic_options
    from e3dpsm.utils.isa import detect_isa

    model, x, exact = _int8_matmul(weight_max)
    as_defined = ort.InferenceSession(model, exact_arithmetic_options(), providers=["CPUExecutionProvider"])
    np.testing.assert_array_equal(as_defined.run(None, {"x": x})[0], exact)
    fused = ort.InferenceSession(model, providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    kind = detect_isa().kind
    if weight_max == 64 or kind == "vnni":
        np.testing.assert_array_equal(fused, exact)
    elif kind == "avx2":
        assert np.abs(fused - exact).max() > 0.5 * exact.max(), fused
    else:
        pytest.skip(f"8-bit weights on a {kind!r} host: ONNX Runtime's kernels there are not x86's U8S8")
