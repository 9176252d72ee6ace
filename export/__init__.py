"""Stateful single-step ONNX export of E-3DPSM and its parity check against PyTorch."""
from e3dpsm.export.onnx_export import DEFAULT_OPSET, ExportError, ExportResult, export_step, export_step_with_report
from e3dpsm.export.spec import FRAME_INPUT, WINDOW_INPUT, StepIOSpec, graph_metadata, step_io_spec
from e3dpsm.export.wrapper import StepGraph

__all__ = [
    "DEFAULT_OPSET", "ExportError", "ExportResult", "FRAME_INPUT", "StepGraph", "StepIOSpec", "WINDOW_INPUT",
    "export_step", "export_step_with_report", "graph_metadata", "step_io_spec",
]
