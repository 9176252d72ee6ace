"""ONNX's u8 QuantizeLinear / DequantizeLinear written out in numpy (the operator's definition:
divide in float32, round half to even, add the zero point, saturate to [0, 255]): the reference
the toy QDQ graphs' codes are checked against."""
from __future__ import annotations

import numpy as np


def qdq_u8(value: np.ndarray, scale: float, zero_point: int) -> tuple[np.ndarray, np.ndarray]:
    """(codes, dequantised values) of `value`."""
    codes = np.clip(np.rint(value / np.float32(scale)) + zero_point, 0, 255).astype(np.uint8)
    return codes, ((codes.astype(np.float32) - zero_point) * np.float32(scale)).astype(np.float32)
