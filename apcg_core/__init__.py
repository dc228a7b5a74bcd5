"""APCG core: lidar parameters, frames, conditions, depth images, metrics. Imports numpy only."""
__version__ = "0.1.0"
