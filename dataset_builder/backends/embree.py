"""The ``embree`` backend: Intel Embree through embreex, outside Blender."""

from __future__ import annotations

import numpy as np

from apcg_core.errors import InputError

from .hits import hits_of, is_hit


def _import_embreex():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:
        raise InputError("the embree backend needs embreex: pip install 'apcg[sim]'") from exc
    return rtcore_scene, TriangleMesh


class EmbreeCaster:
    """First-hit distances along rays in the mesh's frame (robust, watertight traversal)."""

    name = "embree"

    def __init__(self, mesh) -> None:
        rtcore_scene, TriangleMesh = _import_embreex()
        if len(mesh.faces) == 0:
            raise InputError("cannot ray-cast a mesh with no faces")
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        TriangleMesh(scene=self._scene, vertices=mesh.vertices.astype(np.float32),
                     indices=mesh.faces.astype(np.int32))

    def cast(self, origin: np.ndarray, direction: np.ndarray, t_max: float) -> np.ndarray:
        """Distance (float64) from each origin to the first surface along its unit direction,
        inf where there is none within ``t_max``."""
        o = np.ascontiguousarray(origin, dtype=np.float32)
        d = np.ascontiguousarray(direction, dtype=np.float32)
        if len(o) == 0:
            return np.zeros(0)
        limit = np.float32(t_max)
        t = self._scene.run(o, d, dists=np.full(len(o), limit, np.float32), query="DISTANCE")
        t = t.astype(np.float64)
        # Embree measures t in units of the float32 direction's length.
        t *= np.sqrt((d.astype(np.float64) ** 2).sum(axis=1))
        t[~is_hit(t, limit)] = np.inf
        return t

    def cast_hits(self, origin: np.ndarray, direction: np.ndarray,
                  t_max: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`cast` for float32 rays, answering only the hits: (ray index, distance).

        The same numbers as ``cast`` gives at its finite entries; misses (three rays in four)
        come back from embree with t = t_max exactly, so they are dropped before the float64
        work instead of after it."""
        return hits_of(self.distances32, origin, direction, t_max)

    def distances32(self, origin: np.ndarray, direction: np.ndarray, limit: np.float32,
                    out: np.ndarray | None = None) -> np.ndarray:
        """embree's own answer for float32 rays (C-contiguous (n, 3)): t in units of each
        direction's length, float32, exactly ``limit`` where nothing is hit before it; written
        to ``out`` (float32, n) when given, which saves an allocation per call."""
        if len(origin) == 0:
            return np.zeros(0, np.float32)
        if out is None:
            out = np.empty(len(origin), np.float32)
        out.fill(limit)
        return self._scene.run(origin, direction, dists=out, query="DISTANCE")

    def surfaces(self, origin: np.ndarray, direction: np.ndarray,
                 t_max: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`cast`'s distances and the triangle each ray hits (-1 where none), from one
        embree intersection query."""
        if len(origin) == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        o = np.ascontiguousarray(origin, dtype=np.float32)
        d = np.ascontiguousarray(direction, dtype=np.float32)
        limit = np.float32(t_max)
        res = self._scene.run(o, d, dists=np.full(len(o), limit, np.float32),
                              query="INTERSECT", output=1)
        tri = np.asarray(res["primID"], dtype=np.int64)
        t = res["tfar"].astype(np.float64) * np.sqrt((d.astype(np.float64) ** 2).sum(axis=1))
        miss = (tri < 0) | ~is_hit(t, limit)
        t[miss] = np.inf
        tri[miss] = -1
        return t, tri

    def triangles(self, origin: np.ndarray, direction: np.ndarray,
                  limit: np.float32) -> np.ndarray:
        """Index of the triangle each float32 ray hits first before ``limit``, -1 where none
        (for :func:`dataset_builder.refine.refine_ranges`)."""
        if len(origin) == 0:
            return np.zeros(0, np.int64)
        o = np.ascontiguousarray(origin, dtype=np.float32)
        d = np.ascontiguousarray(direction, dtype=np.float32)
        prim = self._scene.run(o, d, dists=np.full(len(o), limit, np.float32),
                               query="INTERSECT")
        return np.asarray(prim, dtype=np.int64)
