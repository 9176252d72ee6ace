"""E-3DPSM model, its config and the variant registry."""
from e3dpsm.models import variants as _variants  # noqa: F401  (registers the variants)
from e3dpsm.models.config import E3DPSMConfig
from e3dpsm.models.e3dpsm import OUTPUT_NAMES, E3DPSM
from e3dpsm.models.registry import create_model, list_models, register_model, variant_config

__all__ = ["E3DPSM", "E3DPSMConfig", "OUTPUT_NAMES", "create_model", "list_models", "register_model", "variant_config"]
