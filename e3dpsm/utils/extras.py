"""Optional runtimes and converters, each behind an extra of pyproject.toml: one place that
says which extra brings which module, so a missing one is one error line that names the
install command (`e3dpsm CMD: error: ... pip install -e ".[executorch]"`)."""
from __future__ import annotations

import importlib
import importlib.util
import sys
from types import ModuleType

from e3dpsm.errors import ConfigError

# module -> the extra that installs it
EXTRA_OF_MODULE: dict[str, str] = {
    "executorch": "executorch",
    "litert_torch": "litert",
    "ai_edge_litert": "litert",
    "ai_edge_quantizer": "litert",
    "coremltools": "coreml",
    "tensorrt": "tensorrt",
    "cuda": "tensorrt",
    "openvino": "openvino",
}


def install_hint(extra: str) -> str:
    return f'pip install -e ".[{extra}]"'


def missing_reason(module: str, purpose: str = "") -> str | None:
    """Why `module` cannot be used here (None when it can): not installed, with the install line."""
    top = module.split(".")[0]
    try:  # a module blocked in sys.modules (None) counts as missing, as Python's import does
        found = sys.modules[top] is not None if top in sys.modules else importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        found = False
    if found:
        return None
    extra = EXTRA_OF_MODULE[top]
    what = f" ({purpose})" if purpose else ""
    return f"{module.split('.')[0]} is not installed{what}: {install_hint(extra)}"


def require(module: str, purpose: str = "") -> ModuleType:
    """Import `module`, or raise ConfigError naming the extra that brings it."""
    reason = missing_reason(module, purpose)
    if reason:
        raise ConfigError(reason)
    return importlib.import_module(module)
