"""Quantisation of the E-3DPSM step graph: INT8 static with state-aware calibration (QDQ,
per-channel), FP16, dynamic INT8; recurrent parts kept in float; held-out accuracy check;
`--exclude auto` picks the fastest candidate graph within the accuracy budget (front.py).

Entry point: `quantize_graph(model, data_dir, out_dir, QuantizeOptions(...))`; CLI
`e3dpsm quantize`.
"""
from e3dpsm.quantize.api import MODES, QuantizeOptions, artifact_name, quantize_graph
from e3dpsm.quantize.calibration import (
    MIN_CALIBRATION_FRAMES, CalibrationSet, FeedListReader, record_calibration_set,
)
from e3dpsm.quantize.front import OBJECTIVES
from e3dpsm.quantize.graph_groups import NodeGroup, candidate_groups, recurrent_groups
from e3dpsm.quantize.step_timer import SideBySideTimer, StepTimer

__all__ = [
    "MIN_CALIBRATION_FRAMES", "MODES", "OBJECTIVES", "CalibrationSet", "SideBySideTimer", "StepTimer", "FeedListReader", "NodeGroup", "QuantizeOptions",
    "artifact_name", "candidate_groups", "quantize_graph", "record_calibration_set", "recurrent_groups",
]
