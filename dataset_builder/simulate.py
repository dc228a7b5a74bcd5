"""The SPC-Lidar simulator (SPEC section 4): standard point clouds of a type at many conditions.

One return per resolution cell: the first surface along the ray through the cell centre (or the
nearest of k x k rays per cell), its range quantized to the time bin. The point reported for a
cell lies on the cell's centre direction at that range: it is what the lidar records (cell and
time bin), whichever backend found it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from apcg_core.cloud import PointCloud
from apcg_core.depth import DEFAULT_LIDAR, pc2im
from apcg_core.errors import InputError
from apcg_core.frames import cartesian_to_spherical, spherical_to_cartesian
from apcg_core.lidar import LidarParams

from .backends import check_backend, make_caster, surface_hits
from .rays import (
    angular_boxes,
    bounding_radius,
    cast_cells,
    check_conditions,
    make_rays,
    sample_frames,
)
from .refine import refine_ranges

# Rays per ray-casting call: large enough that per-call overhead vanishes, small enough that
# the (rays x 3 x 3) temporaries stay around 100 MB.
RAYS_PER_CALL = 1_000_000
POINTS_SAMPLES_PER_CHUNK = 64
# Rays per chunk of the photon stage: its arrays (sub-ray hits, signal bins) stay ~0.5 GB.
PHOTON_RAYS = 2_000_000
# Ray casters (one per mesh) a simulator keeps; the least recently used is closed beyond this.
MAX_CASTERS = 4


@dataclass
class SimResult:
    """The standard point clouds of N samples, stacked (``cloud.sample`` says whose)."""

    cloud: PointCloud
    n_samples: int
    clipped: np.ndarray  # (N,) bool: the target's angular box reached beyond the window
    n_rays: np.ndarray  # (N,) rays cast (cells x k x k); 0 for the points backend
    backend: str = ""

    def clouds(self) -> list[PointCloud]:
        return self.cloud.split(self.n_samples)

    def depth_images(self, table: np.ndarray, length_m: float, lidar: LidarParams,
                     image: bool = True):
        """PC2Im of every sample (N, H, W) and its statistics (``image`` False: the
        statistics alone, no dense image)."""
        return pc2im(self.cloud.xyz, table[:, 1], table[:, 2], length_m, lidar,
                     sample=self.cloud.sample, n_samples=self.n_samples, image=image)


@dataclass
class SimCells:
    """The standard clouds of N samples as the lidar records them: cell and range per point,
    no Cartesian points (what a dataset shard stores). Points are grouped by sample."""

    sample: np.ndarray  # (P,) int64
    cell_w: np.ndarray  # (P,) centred cell indices
    cell_h: np.ndarray
    range_m: np.ndarray  # (P,) float64, quantized when the simulator quantizes
    n_samples: int
    clipped: np.ndarray
    n_rays: np.ndarray


def _empty_cloud() -> PointCloud:
    z = np.zeros(0)
    return PointCloud(np.zeros((0, 3)), z, z.astype(np.int32), z.astype(np.int32),
                      z.astype(np.int64))


class Simulator:
    """Standard point clouds of meshes (body frame) under conditions, with one backend.

    ``quantize`` rounds ranges to the centre of their time bin; ``supersample`` = k casts k x k
    rays per cell and keeps the nearest hit. Casters are built once per mesh and kept.
    """

    def __init__(self, backend: str = "embree", lidar: LidarParams = DEFAULT_LIDAR,
                 quantize: bool = True, supersample: int = 1,
                 fine_cloud_points: int = 10_000, fine_cloud_seed: int = 0) -> None:
        self.backend = check_backend(backend)
        self.lidar = lidar
        self.quantize = bool(quantize)
        if not isinstance(supersample, (int, np.integer)) or supersample < 1:
            raise InputError(f"supersample must be an integer >= 1, got {supersample!r}")
        if backend == "points" and supersample != 1:
            raise InputError("supersample applies to ray-casting backends, not to 'points'")
        self.supersample = int(supersample)
        self.fine_cloud_points = int(fine_cloud_points)
        self.fine_cloud_seed = int(fine_cloud_seed)
        self._casters: OrderedDict = OrderedDict()  # most recently used last
        self._fine: dict = {}
        self._normal_cache: dict = {}
        self.last_boxes = (np.zeros(0, bool), np.zeros(0, np.int64))

    # --- public ------------------------------------------------------------------------------
    def simulate(self, mesh, conditions, key=None) -> SimResult:
        """Standard clouds of ``mesh`` at each row of ``conditions`` (N, 6): [type, r0 (m),
        beta0, pitch, yaw, roll (rad)]; the type column is carried, not used. ``key`` names the
        mesh for the caster cache (defaults to the object's id)."""
        radius = bounding_radius(mesh.vertices)
        table = check_conditions(conditions, radius)
        if len(table) == 0:
            return SimResult(_empty_cloud(), 0, np.zeros(0, bool), np.zeros(0, np.int64),
                             self.backend)
        key = id(mesh) if key is None else key
        if self.backend == "points":
            return self._simulate_points(mesh, table, key)
        return self._simulate_rays(mesh, table, key, radius)

    def simulate_type(self, catalog, type_key, conditions) -> SimResult:
        """Like :meth:`simulate` for a catalog type (the mesh is cached by the catalog)."""
        t = catalog.get(type_key)
        return self.simulate(catalog.mesh(t), conditions, key=("type", t.index))

    def simulate_cells(self, mesh, conditions, key=None) -> SimCells:
        """:meth:`simulate` without the Cartesian points: the same cells and ranges."""
        radius = bounding_radius(mesh.vertices)
        table = check_conditions(conditions, radius)
        key = id(mesh) if key is None else key
        if len(table) and self.backend != "points":
            s, w, h, r, clipped, n_rays = self._ray_cells(mesh, table, key, radius)
            if self.quantize:
                r = self.lidar.quantize_range(r)
            return SimCells(s, w, h, r, len(table), clipped, n_rays)
        res = self.simulate(mesh, table, key)
        cl = res.cloud
        return SimCells(cl.sample, cl.cell_w, cl.cell_h, cl.range_m, res.n_samples, res.clipped,
                        res.n_rays)

    def simulate_cells_type(self, catalog, type_key, conditions) -> SimCells:
        t = catalog.get(type_key)
        return self.simulate_cells(catalog.mesh(t), conditions, key=("type", t.index))

    def sub_ray_hits(self, mesh, conditions, key=None, geometry=None, sub_index=False):
        """Every sub-ray (k x k per cell of each sample's box) that meets the target: sample,
        cell, unquantized float64 range and the cosine of its incidence, for the photon stage
        (``apcg_core.sensor``). Ray-casting backends only. ``geometry``: see
        :meth:`posed_cells`; ``sub_index`` also returns each hit's sub-ray (0 .. k*k - 1)."""
        from apcg_core.sensor import SubRayHits
        if self.backend == "points":
            raise InputError("a sensor needs a ray-casting backend (the photon stage takes "
                             "every sub-ray's range and incidence); accepted: "
                             "embree, blender, blender-bvh")
        radius = bounding_radius(mesh.vertices)
        table = check_conditions(conditions, radius)
        key = id(mesh) if key is None else key
        caster = self._caster(mesh, key)
        normals = self._normals(mesh, key)
        lidar = self.lidar
        if geometry is None:
            m, c = sample_frames(table)
            boxes = angular_boxes(mesh.vertices, table, lidar, m, c)
        else:
            m, c, boxes = geometry
        rays_per_sample = boxes.n_cells * self.supersample**2
        parts = []
        start, n = 0, len(table)
        while start < n:  # chunks of whole samples, about RAYS_PER_CALL rays each
            stop = min(n, start + max(1, int(np.searchsorted(
                np.cumsum(rays_per_sample[start:]), RAYS_PER_CALL, side="right"))))
            sl = slice(start, stop)
            rays = make_rays(table[sl], boxes[sl], lidar, m[sl], c[sl], radius, self.supersample)
            t, tri = surface_hits(caster, rays.origin, rays.direction, rays.t_max)
            hit = np.flatnonzero(np.isfinite(t))
            cell = hit // rays.k
            s = rays.sample[cell]
            # A hit whose triangle the caster could not name (float32 disagreement between two
            # queries, rare) is taken as facing the lidar.
            cos = np.ones(len(hit))
            named = tri[hit] >= 0
            cos[named] = np.abs((normals[tri[hit][named]] * rays.direction[hit][named]).sum(1))
            parts.append((s + start, rays.w[cell], rays.h[cell], rays.t_start[s] + t[hit], cos,
                          hit % rays.k))
            start = stop
        cols = [np.concatenate([p[i] for p in parts]) if parts else np.zeros(0)
                for i in range(6)]
        hits = SubRayHits(cols[0].astype(np.int64), cols[1].astype(np.int32),
                          cols[2].astype(np.int32), cols[3].astype(np.float64),
                          np.clip(cols[4], 0.0, 1.0), n, self.supersample**2)
        self.last_boxes = (boxes.clipped, rays_per_sample.astype(np.int64))
        if sub_index:
            return hits, cols[5].astype(np.int64)
        return hits

    def photon_cells(self, mesh, conditions, sensor, reflectivity: float, seed: int,
                     sample_ids=None, key=None):
        """The photon stage (``apcg_core.sensor``) on the sub-ray hits of ``conditions``: what
        ``sensor`` records, each sample's draws seeded by (``seed``, its id in
        ``sample_ids``, default 0..N-1). Returns the photon cells, and per sample whether the
        target's box was clipped by the window and how many rays were cast."""
        from apcg_core.sensor import PhotonCells, photon_cloud
        radius = bounding_radius(mesh.vertices)
        table = check_conditions(conditions, radius)
        ids = np.arange(len(table)) if sample_ids is None else np.asarray(sample_ids, np.int64)
        m, c = sample_frames(table)
        rays = angular_boxes(mesh.vertices, table, self.lidar, m, c).n_cells * \
            self.supersample**2
        # chunks of whole samples of about PHOTON_RAYS rays: memory stays bounded whatever the
        # batch (a sample's photons do not depend on its chunk)
        bounds, acc = [0], 0
        for i, r in enumerate(rays.tolist()):
            if acc + r > PHOTON_RAYS and i > bounds[-1]:
                bounds.append(i)
                acc = 0
            acc += r
        bounds.append(len(table))
        parts, clipped, n_rays = [], [], []
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            if hi == lo and len(table):
                continue
            hits = self.sub_ray_hits(mesh, table[lo:hi], key)
            part = photon_cloud(hits, table[lo:hi, 1], np.full(hi - lo, float(reflectivity)),
                                sensor, self.lidar, seed, ids[lo:hi])
            part.sample = part.sample + lo
            part.target_sample = part.target_sample + lo
            parts.append(part)
            clipped.append(self.last_boxes[0])
            n_rays.append(self.last_boxes[1])
        cells = PhotonCells.concatenate(parts, len(table))
        return cells, np.concatenate(clipped), np.concatenate(n_rays)

    def photon_cells_type(self, catalog, type_key, conditions, sensor, seed: int,
                          sample_ids=None):
        """:meth:`photon_cells` of a catalog type, at its reflectivity."""
        from apcg_core.sensor import reflectivity_of
        t = catalog.get(type_key)
        return self.photon_cells(catalog.mesh(t), conditions, sensor, reflectivity_of(t), seed,
                                 sample_ids, key=("type", t.index))

    def _normals(self, mesh, key) -> np.ndarray:
        """Unit face normals (float64) of a mesh, cached with its caster (zero for a
        degenerate triangle)."""
        cache = self._normal_cache
        if key not in cache:
            v = np.asarray(mesh.vertices, np.float64)
            f = np.asarray(mesh.faces, np.int64)
            n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            length = np.sqrt((n**2).sum(axis=1))
            with np.errstate(invalid="ignore", divide="ignore"):
                cache[key] = np.where(length[:, None] > 0, n / length[:, None], 0.0)
            while len(cache) > MAX_CASTERS:
                cache.pop(next(iter(cache)))
        return cache[key]

    def close(self) -> None:
        """Release the backends' resources (Blender objects and scenes) now."""
        for caster in self._casters.values():
            if hasattr(caster, "close"):
                caster.close()
        self._casters.clear()

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- ray casting ---------------------------------------------------------------------------
    def _caster(self, mesh, key):
        casters = self._casters
        if key in casters:
            casters.move_to_end(key)
            return casters[key]
        # A long-lived worker meets type after type (a build's shards come type by type):
        # keep the few it is using, so that its memory does not grow with the catalog.
        while len(casters) >= MAX_CASTERS:
            _, old = casters.popitem(last=False)
            if hasattr(old, "close"):
                old.close()
        casters[key] = make_caster(self.backend, mesh)
        return casters[key]

    def _simulate_rays(self, mesh, table, key, radius) -> SimResult:
        s, w, h, r, clipped, n_rays = self._ray_cells(mesh, table, key, radius)
        cloud = self._cell_cloud(table, s, w, h, r)
        return SimResult(cloud, len(table), clipped, n_rays, self.backend)

    def posed_cells(self, mesh, table, geometry, key=None):
        """(sample, w, h, range) of every hit cell of samples whose frames and cell boxes the
        caller gives: ``geometry`` = (m (N, 3, 3), c (N, 3), boxes), the body -> observation
        maps, centres and :class:`rays.AngularBoxes` (a scene's targets, each turned in azimuth
        and scanned a group of cells at a time: ``dataset_builder/scene.py``). ``table``'s
        range column must be |c| and its elevation column the window's; ranges are float64,
        bins decided in float64 (``refine.py``), not quantized."""
        radius = bounding_radius(mesh.vertices)
        key = id(mesh) if key is None else key
        if self.backend == "points":
            raise InputError("a scene needs a ray-casting backend; accepted: embree, blender, "
                             "blender-bvh")
        s, w, h, r, _, _ = self._ray_cells(mesh, table, key, radius, geometry)
        return s, w, h, r

    def _ray_cells(self, mesh, table, key, radius, geometry=None):
        """(sample, w, h, unquantized range) of every hit cell, clipped, rays per sample."""
        caster = self._caster(mesh, key)
        lidar = self.lidar
        if geometry is None:
            m, c = sample_frames(table)
            boxes = angular_boxes(mesh.vertices, table, lidar, m, c)
        else:
            m, c, boxes = geometry
        rays_per_sample = boxes.n_cells * self.supersample**2
        if self.supersample == 1 and hasattr(caster, "cast_hits"):
            # float32 rays made block by block and only the hits carried on, in compiled loops
            # where numba is installed (docs/SCALE.md)
            s, w, h, r = cast_cells(caster, table, boxes, lidar, m, c, radius)
            if self.quantize:  # a bin decided by float32 rounding: decide it in float64
                r = refine_ranges(caster, mesh.vertices, mesh.faces, table, lidar, m, c,
                                  radius, s, w, h, r)
            return s, w, h, r, boxes.clipped, rays_per_sample.astype(np.int64)
        parts = []
        start = 0
        n = len(table)
        while start < n:  # chunks of whole samples, about RAYS_PER_CALL rays each
            stop = start + max(1, int(np.searchsorted(
                np.cumsum(rays_per_sample[start:]), RAYS_PER_CALL, side="right")))
            stop = min(stop, n)
            sl = slice(start, stop)
            rays = make_rays(table[sl], boxes[sl], lidar, m[sl], c[sl], radius, self.supersample)
            t = caster.cast(rays.origin, rays.direction, rays.t_max)
            t = t.reshape(-1, rays.k).min(axis=1)  # nearest of the k x k rays of each cell
            hit = np.isfinite(t)
            s = rays.sample[hit]
            r = rays.t_start[s] + t[hit]
            parts.append((s + start, rays.w[hit], rays.h[hit], r))
            start = stop
        if parts:
            s, w, h, r = (np.concatenate([p[i] for p in parts]) for i in range(4))
        else:
            s, w, h, r = (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int32),
                          np.zeros(0))
        return s, w, h, r, boxes.clipped, rays_per_sample.astype(np.int64)

    def _cell_cloud(self, table, s, w, h, r) -> PointCloud:
        if self.quantize:
            r = self.lidar.quantize_range(r)
        alpha, beta = self.lidar.cell_centre_angles(w, h, table[s, 2])
        return PointCloud(spherical_to_cartesian(alpha, beta, r), r, w, h, s)

    # --- the paper's z-buffer over a fine point cloud --------------------------------------------
    def _fine_cloud(self, mesh, key) -> np.ndarray:
        if key not in self._fine:
            from apcg_core.catalog.catalog import sample_surface
            self._fine[key] = sample_surface(mesh, self.fine_cloud_points, self.fine_cloud_seed)
        return self._fine[key]

    def _simulate_points(self, mesh, table, key) -> SimResult:
        fine = self._fine_cloud(mesh, key)
        lidar = self.lidar
        m, c = sample_frames(table)
        boxes = angular_boxes(mesh.vertices, table, lidar, m, c)
        parts = []
        for start in range(0, len(table), POINTS_SAMPLES_PER_CHUNK):
            sl = slice(start, start + POINTS_SAMPLES_PER_CHUNK)
            obs = np.einsum("nij,vj->nvi", m[sl], fine) + c[sl, None, :]
            n_chunk = obs.shape[0]
            s = np.repeat(np.arange(start, start + n_chunk), len(fine))
            alpha, beta, r = cartesian_to_spherical(obs.reshape(-1, 3))
            w, h = lidar.cell_of_angles(alpha, beta, table[s, 2])
            inside = lidar.inside(w, h)
            s, w, h, r = s[inside], w[inside], h[inside], r[inside]
            cell = (s * lidar.height + (h - lidar.h_min)) * lidar.width + (w - lidar.w_min)
            order = np.lexsort((r, cell))  # per cell, nearest point first: the z-buffer
            first = np.ones(len(order), bool)
            first[1:] = cell[order][1:] != cell[order][:-1]
            keep = order[first]
            keep = keep[np.argsort(cell[keep], kind="stable")]
            parts.append((s[keep], w[keep], h[keep], r[keep]))
        s, w, h, r = (np.concatenate([p[i] for p in parts]) for i in range(4))
        cloud = self._cell_cloud(table, s, w, h, r)
        return SimResult(cloud, len(table), boxes.clipped, np.zeros(len(table), np.int64),
                         self.backend)
