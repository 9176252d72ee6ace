"""CPU ISA detection (e3dpsm/utils/isa.py): the flags reports record and tests branch on."""
from __future__ import annotations

import pytest

from e3dpsm.utils.env import machine_info
from e3dpsm.utils.isa import CpuIsa, detect_isa, parse_cpuinfo

# First lines of /proc/cpuinfo as the hosts of this project print them (flags abridged).
EPYC_AVX2 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx fma avx2 bmi2\nbugs\t: x\n"
EPYC_ZEN4 = "model name\t: AMD EPYC\nflags\t\t: fpu avx2 fma avx512f avx512_vnni avx512_bf16 vaes\n"
XEON_AMX = ("model name\t: Intel Xeon\nflags\t\t: avx2 fma avx512f avx512_vnni avx512_bf16 avx_vnni amx_bf16 "
            "amx_tile amx_int8\n")
NEOVERSE = "processor\t: 0\nFeatures\t: fp asimd crc32 atomics asimddp sve i8mm bf16\nCPU part\t: 0xd40\n"


@pytest.mark.parametrize("text, kind, int8_dot, bf16, flags", [
    (EPYC_AVX2, "avx2", False, False, ("avx2", "fma")),
    (EPYC_ZEN4, "vnni", True, True, ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16")),
    (XEON_AMX, "vnni", True, True,
     ("avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_int8", "amx_bf16")),
    (NEOVERSE, "dotprod", True, False, ("asimddp", "i8mm", "bf16", "sve")),  # OpenVINO ARM: no bf16
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
    """`quantize --target-isa` takes exactly the kinds reports name (one list, ISA_KINDS)."""
    from e3dpsm.cli import build_parser
    from e3dpsm.utils.isa import ISA_KINDS

    kinds = {parse_cpuinfo(t).kind for t in (EPYC_AVX2, EPYC_ZEN4, XEON_AMX, NEOVERSE, "flags\t: fpu\n", "")}
    assert kinds == set(ISA_KINDS)
    for kind in ISA_KINDS:
        assert build_parser().parse_args(["quantize", "--model", "m", "--data", "d", "--out", "o",
                                          "--target-isa", kind]).target_isa == kind
