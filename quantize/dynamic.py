"""Dynamic INT8 (weights int8 offline, activation ranges computed per run): the baseline
static calibration is compared against. ORT quantises only MatMul/Gemm-like ops this way
(convolutions stay float), so it needs no calibration data but speeds up little here."""
from __future__ import annotations

import os
from typing import Iterable

DYNAMIC_OP_TYPES: tuple[str, ...] = ("MatMul", "Gemm")


def quantize_dynamic_int8(src: str | os.PathLike, dst: str | os.PathLike, exclude: Iterable[str] = ()) -> dict:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    quantize_dynamic(str(src), str(dst), op_types_to_quantize=list(DYNAMIC_OP_TYPES), per_channel=True,
                     weight_type=QuantType.QInt8, nodes_to_exclude=sorted(set(exclude)))
    return {"op_types": list(DYNAMIC_OP_TYPES), "per_channel": True, "weight_type": "QInt8",
            "activation_type": "dynamic uint8 (per run)"}
