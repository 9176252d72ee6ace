"""The CPU's instruction-set extensions that decide INT8 and bf16 speed and numerics.

Why it matters: ONNX Runtime's x86 U8S8 kernels without VNNI multiply u8 x s8 pairs with
`vpmaddubsw`, which adds each pair of products in saturating 16-bit arithmetic; with
AVX-512 VNNI / AVX-VNNI (`vpdpbusd`) or AMX the products accumulate in 32 bits. The same
INT8 graph therefore runs at different speeds and gives different poses on the two kinds
of host (measured on the trained tiny: 10.4% of MPJPE from fp32 on AVX2, 2.2% on a Xeon
with AVX-512 VNNI and AMX). Every report records these flags, and INT8 graphs record the
ISA their accuracy budget was checked on. Linux reads them from /proc/cpuinfo; elsewhere
the set is empty and reports say "unknown". On aarch64 Linux they come from the kernel's
hardware capability words (getauxval(AT_HWCAP / AT_HWCAP2)), the source of /proc/cpuinfo's
`Features` line: that also holds under qemu-user emulation, where /proc is the x86 host's or
absent (benchmarks/arm_emulation.py; qemu's default `max` CPU has asimddp, i8mm, bf16, sve).
"""
from __future__ import annotations

import ctypes
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

# Flags that bear on this toolchain's kernels (x86 names as Linux spells them; aarch64 after).
REPORTED_FLAGS: tuple[str, ...] = (
    "avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_int8", "amx_bf16",
    "asimd", "asimddp", "i8mm", "bf16", "sve",
)
# Bits of aarch64 Linux's AT_HWCAP / AT_HWCAP2 words (arch/arm64/include/uapi/asm/hwcap.h).
AARCH64_HWCAP_BITS: dict[str, int] = {"asimd": 1, "asimddp": 20, "sve": 22}
AARCH64_HWCAP2_BITS: dict[str, int] = {"i8mm": 13, "bf16": 14}
_AT_HWCAP, _AT_HWCAP2 = 16, 26
INT8_DOT_PRODUCT_FLAGS: tuple[str, ...] = ("avx512_vnni", "avx_vnni", "amx_int8", "asimddp", "i8mm")
# bf16 units OpenVINO's CPU plugin computes with (INFERENCE_PRECISION_HINT=bf16). Its ARM
# plugin runs f32 / f16, so aarch64's `bf16` flag is reported but does not count here.
BF16_FLAGS: tuple[str, ...] = ("avx512_bf16", "amx_bf16")
# What CpuIsa.kind says: the CPU kinds reports name and INT8 graphs are quantised for.
# "neon": aarch64 without int8 dot products (Cortex-A53/A72 class; products summed in 32 bits
# all the same, so no 16-bit saturation either).
ISA_KINDS: tuple[str, ...] = ("vnni", "dotprod", "neon", "avx2", "other", "unknown")


@dataclass(frozen=True)
class CpuIsa:
    """The reported flags this CPU has, in REPORTED_FLAGS order; `known` False where no
    flags could be read at all."""

    flags: tuple[str, ...]
    known: bool = True

    @property
    def int8_dot_product(self) -> bool:
        """INT8 products accumulate in 32 bits (no 16-bit saturation in ORT's U8S8 kernels)."""
        return any(f in self.flags for f in INT8_DOT_PRODUCT_FLAGS)

    @property
    def bf16(self) -> bool:
        return any(f in self.flags for f in BF16_FLAGS)

    @property
    def kind(self) -> str:
        """One word for reports and test branches: 'vnni' (x86 int8 dot products: VNNI or
        AMX), 'dotprod' (aarch64 int8 dot products, with or without i8mm), 'neon' (aarch64
        without them), 'avx2', 'other' or 'unknown' (no flags read)."""
        if not self.known:
            return "unknown"
        if self.int8_dot_product:
            return "vnni" if any(f.startswith(("avx", "amx")) for f in self.flags) else "dotprod"
        if "asimd" in self.flags:
            return "neon"
        return "avx2" if "avx2" in self.flags else "other"

    def to_dict(self) -> dict[str, object]:
        return {"kind": self.kind, "flags": list(self.flags), "int8_dot_product": self.int8_dot_product,
                "bf16": self.bf16}


def parse_cpuinfo(text: str) -> CpuIsa:
    """The REPORTED_FLAGS named on the first `flags` (x86) or `Features` (aarch64) line."""
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() in ("flags", "Features"):
            present = set(value.split())
            return CpuIsa(tuple(f for f in REPORTED_FLAGS if f in present))
    return CpuIsa((), known=False)


def parse_hwcaps(hwcap: int, hwcap2: int) -> CpuIsa:
    """The REPORTED_FLAGS set in aarch64 Linux's two hardware capability words."""
    present = {name for name, bit in AARCH64_HWCAP_BITS.items() if hwcap >> bit & 1}
    present |= {name for name, bit in AARCH64_HWCAP2_BITS.items() if hwcap2 >> bit & 1}
    return CpuIsa(tuple(f for f in REPORTED_FLAGS if f in present))


def _aarch64_hwcaps() -> CpuIsa | None:
    """This process's aarch64 capabilities from the auxiliary vector (None off aarch64 Linux)."""
    if not sys.platform.startswith("linux") or platform.machine() not in ("aarch64", "arm64"):
        return None
    try:
        getauxval = ctypes.CDLL(None).getauxval
    except (OSError, AttributeError):
        return None
    getauxval.restype, getauxval.argtypes = ctypes.c_ulong, [ctypes.c_ulong]
    return parse_hwcaps(int(getauxval(_AT_HWCAP)), int(getauxval(_AT_HWCAP2)))


def detect_isa(cpuinfo: str | Path = "/proc/cpuinfo") -> CpuIsa:
    """This machine's CpuIsa; empty where /proc/cpuinfo cannot be read (not Linux). On aarch64
    Linux the auxiliary vector answers first (the default path only): under emulation it is
    the emulated CPU's, while /proc/cpuinfo is the host's."""
    hwcaps = _aarch64_hwcaps() if str(cpuinfo) == "/proc/cpuinfo" else None
    if hwcaps is not None:
        return hwcaps
    try:
        return parse_cpuinfo(Path(cpuinfo).read_text(encoding="utf-8", errors="replace"))
    except OSError:
        return CpuIsa((), known=False)


def bf16_unavailable_reason(isa: CpuIsa | None = None) -> str | None:
    """Why bf16 cannot run here (None where it can): without bf16 units OpenVINO would run f32
    under a bf16 label."""
    isa = isa or detect_isa()
    if isa.bf16:
        return None
    return (f"this CPU has no bf16 units ({', '.join(BF16_FLAGS)}; it has "
            f"{' '.join(isa.flags) or 'no flags read'})")
