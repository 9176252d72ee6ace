"""Accuracy validation of model variants (PyTorch, ONNX fp32 / fp16 / int8) as continuous
streams over held-out sequences: one table of metrics and of differences to fp32 ONNX."""
from e3dpsm.validation.streams import onnx_stream, torch_stream
from e3dpsm.validation.validate import ValidationResult, validate_variants

__all__ = ["ValidationResult", "onnx_stream", "torch_stream", "validate_variants"]
