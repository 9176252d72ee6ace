"""e3dpsm: export and compression toolchain for the E-3DPSM event-based egocentric pose model.

`import e3dpsm` imports neither torch nor onnxruntime: the streaming runtime
(`e3dpsm.runtime`) must run on devices that have numpy and onnxruntime only, so the model
API below is loaded on first use.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["create_model", "list_models", "E3DPSM", "E3DPSMConfig", "__version__"]

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.models import E3DPSM, E3DPSMConfig, create_model, list_models


def __getattr__(name: str) -> Any:
    if name in ("create_model", "list_models", "E3DPSM", "E3DPSMConfig"):
        from e3dpsm import models

        return getattr(models, name)
    raise AttributeError(f"module 'e3dpsm' has no attribute {name!r}")
