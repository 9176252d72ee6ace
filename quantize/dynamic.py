"""Dynamic INT8 (weights int8 offline, activation ranges computed per run): the baseline
static calibration is compared against. ORT quantises only MatMul/Gemm-like ops this way
(convolutions stay float), so it needs no calibration data but speeds up little here."""
from __future__ import annotations

import os
from typing import Iterable

DYNAMIC_OP_TYPES: tuple[str, ...] = ("MatMul", "Gemm")


def quantize_dynamic_int8(src: str | os.PathLike, dst: str | os.PathLike, exclude: Iterable[str] = (),
                          reduce_range: bool = False) -> dict:
    """`reduce_range`: 7-bit weights, for targets without int8 dot-product units, as for static
    INT8 (`StaticConfig.for_target`): the dynamic graph's MatMulInteger runs the same U8S8
    kernels, whose 16-bit pair sums saturate there with 8-bit weights (a fresh clone's
    pipeline on an AVX2-only host: golden check failed from step 0, 6.48 mm mean on ONNX
    Runtime against 0.77 mm on OpenVINO)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    quantize_dynamic(str(src), str(dst), op_types_to_quantize=list(DYNAMIC_OP_TYPES), per_channel=True,
                     reduce_range=reduce_range, weight_type=QuantType.QInt8, nodes_to_exclude=sorted(set(exclude)))
    return {"op_types": list(DYNAMIC_OP_TYPES), "per_channel": True, "weight_type": "QInt8",
            "reduce_range": reduce_range, "activation_type": "dynamic uint8 (per run)"}
