"""`e3dpsm convert litert --quantize int8-weights --data PREP`: a `.tflite` whose weights are
stored in 8 bits and whose arithmetic is float, the INT8 artifact that computes the same poses
on an ARM core as on this host.

Why it exists: a static INT8 `.tflite` (export/litert_int8.py) rounds every activation a
quantised operator reads to an 8-bit code. Float operators in front of those codes (layer
norms, softmax, sigmoid) differ in their last bits between ISAs, a value that lands near a
rounding boundary flips a code, and the recurrence carries the flip on: under emulation the
INT8 `.tflite` of `small` lands 1.3-1.4 mm (mean) from the host's rollout of it on every ARM CPU
model tried (docs/edge.md), outside the 0.5 mm kernel-parity tolerance across ISA kinds.
Weight-only quantisation rounds nothing at run time: each CONV_2D / FULLY_CONNECTED reads its
weights through a DEQUANTIZE of constant 8-bit codes (symmetric, per output channel:
ai-edge-quantizer's weight-only recipe), so a device's float kernels differ from the host's
by what fp32 artifacts differ by (2.4e-4 mm under emulation), and `golden check` holds the
artifact to the same-kind tolerance on any ISA (golden/host.kernel_parity_for).

What it gives up: speed. The size falls to about 0.3x of fp32 (the weights are the file); the
step costs what fp32 costs. Accuracy: the weights' rounding alone, judged with the task budget
`quantize` uses on the held-out split (no calibration: there are no activation ranges).
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from e3dpsm.budget import BudgetCheck
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError
from e3dpsm.export.edge_int8 import EdgeInt8Options, check_artifact, fp32_reference, held_out_set
from e3dpsm.export.litert_export import LiteRTOptions, LiteRTResult, litert_content, write_litert
from e3dpsm.export.litert_int8 import QUANTISED_OPERATORS, mac_op_scopes
from e3dpsm.models import E3DPSM
from e3dpsm.quantize.holdout import HeldOut
from e3dpsm.quantize.weights import MODE  # the artifact's precision and its metadata's quantisation mode
from e3dpsm.utils.extras import require

RECIPE = "ai-edge-quantizer weight-only: int8 weights symmetric per output channel, float activations and arithmetic"


def weight_only_content(float_content: bytes) -> bytes:
    """The flatbuffer with every QUANTISED_OPERATORS operator's weights in 8 bits behind a DEQUANTIZE."""
    from ai_edge_quantizer import qtyping, quantizer

    engine = quantizer.Quantizer(bytearray(float_content))
    for operator in QUANTISED_OPERATORS:
        engine.add_weight_only_config(".*", qtyping.TFLOperationName(operator), num_bits=8,
                                      granularity=qtyping.QuantGranularity.CHANNELWISE)
    try:
        return bytes(engine.quantize(enable_progress_bar=False, enable_progress_report=False).quantized_model)
    except (ValueError, RuntimeError, KeyError) as exc:  # the quantizer's own refusals, one line each
        reason = (str(exc).splitlines() or [type(exc).__name__])[0][:300]
        raise ConfigError(f"ai-edge-quantizer could not quantise this model's weights ({reason}); the fp32 "
                          "`convert litert` or the static `--quantize int8` may still convert it") from exc


def convert_litert_weights8(model: E3DPSM, data: PreparedData, path: str | os.PathLike, options: EdgeInt8Options,
                            work: Path, litert: LiteRTOptions = LiteRTOptions()
                            ) -> tuple[LiteRTResult, BudgetCheck, HeldOut]:
    """Write the weight-only `.tflite` to `path` and judge it on the held-out split: (result,
    budget check, its frames), as convert_litert_int8 returns."""
    require("ai_edge_quantizer", "to write INT8 .tflite models")
    from absl import logging as absl_logging

    absl_logging.set_verbosity(absl_logging.WARNING)  # ai-edge-quantizer's step-by-step INFO lines
    reference = fp32_reference(model, work)
    started = time.perf_counter()
    float_content = litert_content(model, litert)
    converted = time.perf_counter()
    content = weight_only_content(float_content)
    seconds = {"convert": round(converted - started, 2), "quantize": round(time.perf_counter() - converted, 2)}
    record: dict[str, Any] = {"quantizer": RECIPE, "operators": list(QUANTISED_OPERATORS),
                              "int8_operators": len(mac_op_scopes(float_content)), "arithmetic": "float",
                              "budget": options.budget.to_dict()}
    result = write_litert(content, model, path, litert, MODE, seconds, record)
    held = held_out_set(reference, data, options)
    return result, check_artifact(path, "litert", held, options), held


__all__ = ["MODE", "convert_litert_weights8", "weight_only_content"]
