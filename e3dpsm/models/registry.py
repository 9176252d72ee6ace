"""Variant registry: `@register_model` on a tiny function returning an `E3DPSMConfig`."""
from __future__ import annotations

from typing import Any, Callable

from e3dpsm.errors import ConfigError
from e3dpsm.models.config import E3DPSMConfig

_VARIANTS: dict[str, Callable[[], E3DPSMConfig]] = {}


def register_model(fn: Callable[[], E3DPSMConfig]) -> Callable[[], E3DPSMConfig]:
    _VARIANTS[fn.__name__] = fn
    return fn


def list_models() -> list[str]:
    return sorted(_VARIANTS)


def variant_config(name: str, **overrides: Any) -> E3DPSMConfig:
    if name not in _VARIANTS:
        raise ConfigError(f"unknown variant {name!r}; available variants: {', '.join(list_models())}")
    return _VARIANTS[name]().replace(**overrides) if overrides else _VARIANTS[name]()


def create_model(name: str, **overrides: Any):
    """Build a registered variant; keyword overrides replace config fields (e.g. fusion="naive")."""
    from e3dpsm.models.e3dpsm import E3DPSM

    return E3DPSM(variant_config(name, **overrides))
