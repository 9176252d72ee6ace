"""`e3dpsm convert tensorrt --model step.onnx --out DIR [--fp16 | --int8]`: placeholder until
export/tensorrt_build.py lands."""
from __future__ import annotations

import argparse


def register(formats: argparse._SubParsersAction) -> None:
    return None
