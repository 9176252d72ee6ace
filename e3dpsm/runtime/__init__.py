"""Torch-free runtime: numpy and onnxruntime only (edge devices have nothing more)."""
from e3dpsm.runtime.iobinding import DeviceState, IOBindingStepSession
from e3dpsm.runtime.multistream import MultiStreamEstimator, MultiStreamStats
from e3dpsm.runtime.session import StepSession, make_session
from e3dpsm.runtime.stream import EventWindower, PoseEstimate, StreamingPoseEstimator, StreamStats

__all__ = [
    "DeviceState", "EventWindower", "IOBindingStepSession", "MultiStreamEstimator", "MultiStreamStats", "PoseEstimate",
    "StepSession", "StreamStats", "StreamingPoseEstimator", "make_session",
]
