"""The Blender backend's Geometry Nodes caster on its own: its answers against embree's on the
same float32 rays, across calls of changing size (the ray mesh is reused and resized), and its
clean-up. Real bpy, small sizes."""

import numpy as np
import pytest

from apcg_core.catalog.catalog import default_catalog
from apcg_core.condition import Condition
from apcg_core.lidar import LidarParams
from dataset_builder.backends.blender import BlenderCaster
from dataset_builder.backends.embree import EmbreeCaster
from dataset_builder.rays import angular_boxes, bounding_radius, make_rays, sample_frames

LIDAR = LidarParams()


@pytest.fixture(scope="module", autouse=True)
def _blender_empty():
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _rays(name, n_samples, seed=0, far_m=9000.0):
    """float32 rays of ``n_samples`` random Table-1 conditions of a catalog type."""
    cat = default_catalog()
    t = cat.get(name)
    mesh = cat.mesh(t)
    rng = np.random.default_rng(seed)
    table = np.array([Condition.from_degrees(t.index, rng.uniform(3000, far_m),
                                             rng.uniform(3, 4), rng.uniform(1, 5),
                                             rng.uniform(-60, 60), rng.uniform(-5, 5)).as_array()
                      for _ in range(n_samples)])
    radius = bounding_radius(mesh.vertices)
    m, c = sample_frames(table)
    boxes = angular_boxes(mesh.vertices, table, LIDAR, m, c)
    rays = make_rays(table, boxes, LIDAR, m, c, radius)
    o = np.ascontiguousarray(rays.origin, np.float32)
    d = np.ascontiguousarray(rays.direction, np.float32)
    return mesh, o, d, rays.t_max


def test_geometry_nodes_hits_equal_embree_across_call_sizes():
    mesh, o, d, t_max = _rays("A320neo", 8, far_m=4500.0)
    assert len(o) > 20_000
    ref_ray, ref_t = EmbreeCaster(mesh).cast_hits(o, d, t_max)
    assert 0.05 < len(ref_ray) / len(o) < 0.9
    caster = BlenderCaster(mesh)
    try:
        # one call, then calls that grow, shrink below a quarter (the mesh is made again) and
        # shrink a little (the points past the rays must miss), each over all the rays
        for size in (len(o), 1000, 9000, 30_000, 8500, 100):
            rays, ts = [], []
            for start in range(0, len(o), size):
                r, t = caster.cast_hits(o[start:start + size], d[start:start + size], t_max)
                rays.append(r + start)
                ts.append(t)
            ray, t = np.concatenate(rays), np.concatenate(ts)
            assert np.array_equal(ray, ref_ray), size
            assert np.abs(t - ref_t).max() < 1e-3, size
    finally:
        caster.close()


def test_distances32_follows_embree_conventions():
    """float32 t in units of the direction's length, exactly the limit where nothing is hit:
    what the build's compiled loops read (rays.cast_cells)."""
    mesh, o, d, t_max = _rays("172S Skyhawk", 2, seed=3)
    limit = np.float32(t_max)
    d_long = np.ascontiguousarray(d * np.float32(1.0 + 3e-7))  # not exactly unit length
    ref = EmbreeCaster(mesh).distances32(o, d_long, limit)
    for method in ("geometry-nodes", "bvh"):
        caster = BlenderCaster(mesh, method=method)
        try:
            got = caster.distances32(o, d_long, limit).copy()
            out = np.empty(len(o), np.float32)
            assert caster.distances32(o, d_long, limit, out=out) is out
            assert np.array_equal(out, got)
        finally:
            caster.close()
        assert got.dtype == np.float32 and got.shape == ref.shape
        miss = ref == limit
        assert 0 < miss.sum() < len(ref)
        assert np.array_equal(got == limit, miss), method
        assert np.abs(got[~miss].astype(np.float64) - ref[~miss]).max() < 1e-3, method


def test_cast_answers_inf_for_misses_and_float64_rays():
    mesh, o, d, t_max = _rays("A320neo", 1, seed=5)
    caster = BlenderCaster(mesh)
    try:
        t = caster.cast(o.astype(np.float64), d.astype(np.float64), t_max)
        ray, th = caster.cast_hits(o, d, t_max)
        assert caster.cast(o[:0], d[:0], t_max).shape == (0,)
    finally:
        caster.close()
    assert t.dtype == np.float64 and len(t) == len(o)
    assert np.array_equal(np.flatnonzero(np.isfinite(t)), ray)
    assert np.array_equal(t[ray], th)


def test_close_removes_every_data_block():
    import bpy
    mesh = default_catalog().mesh(default_catalog().get("A320neo"))
    before = (len(bpy.data.scenes), len(bpy.data.objects), len(bpy.data.meshes),
              len(bpy.data.node_groups))
    caster = BlenderCaster(mesh)
    o = np.zeros((5, 3), np.float32)
    o[:, 0] = -50.0
    d = np.zeros((5, 3), np.float32)
    d[:, 0] = 1.0
    ray, _ = caster.cast_hits(o, d, 100.0)
    assert len(ray) == 5  # through the centre of mass: every ray hits
    caster.close()
    after = (len(bpy.data.scenes), len(bpy.data.objects), len(bpy.data.meshes),
             len(bpy.data.node_groups))
    assert after == before


def test_a_simulator_keeps_a_few_casters_and_frees_the_rest():
    """A long-lived build worker meets type after type: its Blender data stays bounded, and a
    type met again after its caster was closed gets the same answer from a new one."""
    import bpy

    from dataset_builder.simulate import MAX_CASTERS, Simulator
    cat = default_catalog()
    names = [t.name for t in cat.types[:MAX_CASTERS + 3]]
    table = {n: np.array([Condition.from_degrees(cat.get(n).index, 3500.0 if
                                                 cat.get(n).kind == "aircraft" else 300.0,
                                                 3.5, 2.0, 30.0, 1.0).as_array()])
             for n in names}
    before = len(bpy.data.objects)
    with Simulator("blender", quantize=False) as sim:
        first = sim.simulate_type(cat, names[0], table[names[0]]).cloud
        for n in names[1:]:
            sim.simulate_type(cat, n, table[n])
            assert len(sim._casters) <= MAX_CASTERS
            assert len(bpy.data.objects) - before <= 2 * MAX_CASTERS  # target + rays each
        again = sim.simulate_type(cat, names[0], table[names[0]]).cloud
    assert len(first) > 10
    assert np.array_equal(first.range_m, again.range_m)
    assert np.array_equal(first.cell_w, again.cell_w) and np.array_equal(first.cell_h,
                                                                           again.cell_h)
    assert len(bpy.data.objects) == before
