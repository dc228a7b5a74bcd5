"""Sampling backends, swappable by name (SPEC section 4, DESIGN 'Backends').

``embree`` and ``blender`` are ray casters: given rays in a mesh's body frame they return the
distance to the first surface. ``points`` is the paper's approximation: a z-buffer over the
type's fine point cloud, with no rays at all.
"""

from __future__ import annotations

from apcg_core.errors import InputError

from .hits import hits_of, is_hit, surface_hits  # noqa: F401 - the backends' shared arithmetic

BACKENDS = ("embree", "blender", "blender-bvh", "points")
RAY_BACKENDS = ("embree", "blender", "blender-bvh")


def make_caster(backend: str, mesh):
    """A ray caster over ``mesh`` (body frame) for a ray-casting backend."""
    if backend == "embree":
        from .embree import EmbreeCaster
        return EmbreeCaster(mesh)
    if backend in ("blender", "blender-bvh"):
        from .blender import BlenderCaster
        return BlenderCaster(mesh, method="geometry-nodes" if backend == "blender" else "bvh")
    raise InputError(f"unknown ray-casting backend {backend!r}; "
                     f"accepted: {', '.join(RAY_BACKENDS)}")


def check_backend(name: str) -> str:
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; accepted: {', '.join(BACKENDS)}")
    return name
