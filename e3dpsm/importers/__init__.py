"""Importers of weights trained elsewhere into this project's checkpoint format."""
from e3dpsm.importers.released import ImportResult, import_released, read_released_state_dict

__all__ = ["ImportResult", "import_released", "read_released_state_dict"]
