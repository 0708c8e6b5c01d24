"""The DVC engine: pure numpy and numba, no Qt and no napari."""

from .fields.field import DisplacementField, Provenance, Status, grid_for_volume

__all__ = ["DisplacementField", "Provenance", "Status", "grid_for_volume"]
