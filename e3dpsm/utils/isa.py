"""The CPU's instruction-set extensions that decide INT8 and bf16 speed and numerics.

Why it matters: ONNX Runtime's x86 U8S8 kernels without VNNI multiply u8 x s8 pairs with
`vpmaddubsw`, which adds each pair of products in saturating 16-bit arithmetic; with
AVX-512 VNNI / AVX-VNNI (`vpdpbusd`) or AMX the products accumulate in 32 bits. The same
INT8 graph therefore runs at different speeds and gives different poses on the two kinds
of host (measured on the trained tiny: 10.4% of MPJPE from fp32 on AVX2, 2.2% on a Xeon
with AVX-512 VNNI and AMX). Every report records these flags, and INT8 graphs record the
ISA their accuracy budget was checked on. Linux reads them from /proc/cpuinfo; elsewhere
the set is empty and reports say "unknown".
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# Flags that bear on this toolchain's kernels (x86 names as Linux spells them; aarch64 after).
REPORTED_FLAGS: tuple[str, ...] = (
    "avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_int8", "amx_bf16",
    "asimddp", "i8mm", "bf16", "sve",
)
INT8_DOT_PRODUCT_FLAGS: tuple[str, ...] = ("avx512_vnni", "avx_vnni", "amx_int8", "asimddp", "i8mm")
# bf16 units OpenVINO's CPU plugin computes with (INFERENCE_PRECISION_HINT=bf16). Its ARM
# plugin runs f32 / f16, so aarch64's `bf16` flag is reported but does not count here.
BF16_FLAGS: tuple[str, ...] = ("avx512_bf16", "amx_bf16")
# What CpuIsa.kind says: the CPU kinds reports name and INT8 graphs are quantised for.
ISA_KINDS: tuple[str, ...] = ("vnni", "dotprod", "avx2", "other", "unknown")


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
        AMX), 'dotprod' (aarch64 int8 dot products), 'avx2', 'other' or 'unknown' (no flags
        read)."""
        if not self.known:
            return "unknown"
        if self.int8_dot_product:
            return "vnni" if any(f.startswith(("avx", "amx")) for f in self.flags) else "dotprod"
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


def detect_isa(cpuinfo: str | Path = "/proc/cpuinfo") -> CpuIsa:
    """This machine's CpuIsa; empty where /proc/cpuinfo cannot be read (not Linux)."""
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
