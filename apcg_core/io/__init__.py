"""Point cloud and depth image files (numpy only; LAS through laspy, imported when used)."""

from .clouds import read_cloud, read_cloud_attributes, write_cloud
from .images import write_depth_image

__all__ = ["read_cloud", "read_cloud_attributes", "write_cloud", "write_depth_image"]
