"""Torch-free runtime: numpy and onnxruntime only (edge devices have nothing more)."""
from e3dpsm.runtime.session import StepSession, make_session
from e3dpsm.runtime.stream import EventWindower, PoseEstimate, StreamingPoseEstimator, StreamStats

__all__ = ["EventWindower", "PoseEstimate", "StepSession", "StreamStats", "StreamingPoseEstimator", "make_session"]
