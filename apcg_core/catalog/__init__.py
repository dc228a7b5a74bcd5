"""Aircraft catalog: built-in parametric models of real types, and imported user models."""

from .catalog import AircraftType, Catalog, default_catalog, sample_surface
from .mesh import Mesh, MeshReport

__all__ = ["AircraftType", "Catalog", "Mesh", "MeshReport", "default_catalog", "sample_surface"]
