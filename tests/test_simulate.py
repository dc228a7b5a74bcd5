"""The simulator against closed-form geometry, across backends, and on the hard cases."""

import numpy as np
import pytest
from sim_helpers import grid_mesh, rectangle, uv_sphere

from apcg_core.catalog.catalog import default_catalog
from apcg_core.condition import Condition
from apcg_core.errors import InputError
from apcg_core.frames import body_to_observation_matrix, target_centre
from apcg_core.lidar import LidarParams
from dataset_builder.simulate import Simulator

LIDAR = LidarParams()
RAY_BACKENDS = ["embree", "blender", "blender-bvh"]


@pytest.fixture(scope="module", autouse=True)
def _blender_empty():
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _all_cell_dirs(beta0):
    w, h = np.meshgrid(np.arange(LIDAR.w_min, -LIDAR.w_min),
                       np.arange(LIDAR.h_min, -LIDAR.h_min))
    w, h = w.ravel(), h.ravel()
    a, b = LIDAR.cell_centre_angles(w, h, beta0)
    d = np.stack([np.cos(b) * np.sin(a), np.sin(b), np.cos(b) * np.cos(a)], 1)
    return w, h, d


def _as_dict(cloud):
    cells = zip(cloud.cell_w, cloud.cell_h, cloud.range_m, strict=True)
    return {(int(w), int(h)): r for w, h, r in cells}


@pytest.mark.parametrize("backend", RAY_BACKENDS)
def test_tilted_plane_at_18_km_within_1_mm(backend):
    mesh = rectangle(20.0, 5.0)
    cond = Condition.from_degrees(0, 18000.0, 3.5, pitch_deg=3, yaw_deg=20, roll_deg=4)
    res = Simulator(backend, quantize=False).simulate(mesh, [cond.as_array()])
    m = body_to_observation_matrix(cond.pitch, cond.yaw, cond.roll)
    c = target_centre(cond.range_m, cond.elevation)
    n = m @ np.array([1.0, 0, 0])
    w, h, d = _all_cell_dirs(cond.elevation)
    t = (n @ c) / (d @ n)
    p = (t[:, None] * d - c) @ m  # body coordinates of the analytic hit
    inside = (np.abs(p[:, 1]) < 20) & (np.abs(p[:, 2]) < 5)
    border = (np.abs(np.abs(p[:, 1]) - 20) < 1e-3) | (np.abs(np.abs(p[:, 2]) - 5) < 1e-3)
    got = _as_dict(res.cloud)
    keep = inside & ~border
    expect = {(int(a), int(b)): r for a, b, r, ok in zip(w, h, t, keep, strict=True) if ok}
    assert len(expect) > 100
    assert set(expect) <= set(got)
    maybe = inside | border
    extra = set(got) - {(int(a), int(b)) for a, b, ok in zip(w, h, maybe, strict=True) if ok}
    assert not extra
    err = np.array([got[k] - expect[k] for k in expect])
    assert np.abs(err).max() < 1e-3, np.abs(err).max()


@pytest.mark.parametrize("backend", ["embree", "blender"])
def test_sphere_at_18_km_within_1_mm(backend):
    radius = 10.0
    mesh = uv_sphere(radius, 512, 256)
    cond = Condition.from_degrees(0, 18000.0, 3.2, pitch_deg=2, yaw_deg=-35, roll_deg=1)
    res = Simulator(backend, quantize=False).simulate(mesh, [cond.as_array()])
    c = target_centre(cond.range_m, cond.elevation)
    w, h, d = _all_cell_dirs(cond.elevation)
    dc = d @ c
    disc = dc**2 - c @ c + radius**2
    impact = np.sqrt(np.maximum(c @ c - dc**2, 0))
    core = impact < 0.9 * radius
    t = dc - np.sqrt(np.maximum(disc, 0))
    got = _as_dict(res.cloud)
    expect = {(int(a), int(b)): r for a, b, r, ok in zip(w, h, t, core, strict=True) if ok}
    assert len(expect) > 80
    assert set(expect) <= set(got)
    near = impact < 1.001 * radius
    hit_any = {(int(a), int(b)) for a, b, ok in zip(w, h, near, strict=True) if ok}
    assert set(got) <= hit_any
    err = np.array([got[k] - expect[k] for k in expect])
    assert np.abs(err).max() < 1e-3, np.abs(err).max()


def test_quantization_puts_ranges_at_bin_centres():
    cat = default_catalog()
    cond = Condition.from_degrees(cat.get("A320neo").index, 9000.0, 3.5, 2, 30, -3)
    exact = Simulator("embree", quantize=False).simulate_type(cat, "A320neo", [cond.as_array()])
    quant = Simulator("embree", quantize=True).simulate_type(cat, "A320neo", [cond.as_array()])
    assert np.array_equal(exact.cloud.cell_w, quant.cloud.cell_w)
    bins = quant.cloud.range_m / LIDAR.r_r - 0.5
    assert np.allclose(bins, np.round(bins), atol=1e-6)
    assert np.abs(quant.cloud.range_m - exact.cloud.range_m).max() <= LIDAR.r_r / 2 + 1e-9
    assert np.abs(quant.cloud.range_m - exact.cloud.range_m).max() > LIDAR.r_r / 4
    # points sit on their cell's centre direction at the recorded range
    assert np.allclose(np.linalg.norm(quant.cloud.xyz, axis=1), quant.cloud.range_m, rtol=1e-12)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)])
@pytest.mark.parametrize("backend", ["embree", "blender"])
def test_rays_through_shared_vertices_and_edges_leave_no_holes(backend, offset):
    """A surface whose vertices (offset 0) or edges (offset 0.5) lie on the cell-centre rays."""
    cond = Condition.from_degrees(0, 3000.0, 3.5)
    r_plane = 3000.0
    c = target_centre(cond.range_m, cond.elevation)
    m = body_to_observation_matrix(0, 0, 0)
    du, dv = offset
    uu, vv = np.meshgrid(np.arange(-20, 21) + du, np.arange(-10, 11) + dv, indexing="ij")
    a, b = LIDAR.cell_centre_angles(uu, vv, cond.elevation)
    # vertices on a sphere of radius r_plane about the lidar, on the cell-centre directions
    d = np.stack([np.cos(b) * np.sin(a), np.sin(b), np.cos(b) * np.cos(a)], -1)
    body = (r_plane * d - c) @ m
    mesh = grid_mesh(body)
    res = Simulator(backend, quantize=False).simulate(mesh, [cond.as_array()])
    got = _as_dict(res.cloud)
    interior = {(i, j) for i in range(-19, 20) for j in range(-9, 10)}
    assert interior <= set(got), sorted(interior - set(got))[:5]
    cells = set(zip(res.cloud.cell_w, res.cloud.cell_h, strict=True))
    assert len(res.cloud) == len(cells)  # one return per cell
    err = np.array([got[k] - r_plane for k in interior])
    assert np.abs(err).max() < 1e-3


@pytest.mark.parametrize("backend", ["embree", "blender"])
def test_grazing_plane(backend):
    """A plane seen at 88 deg incidence: long thin returns, ranges still exact."""
    mesh = rectangle(30.0, 10.0)
    cond = Condition.from_degrees(0, 3000.0, 3.5, yaw_deg=88.0)
    res = Simulator(backend, quantize=False).simulate(mesh, [cond.as_array()])
    m = body_to_observation_matrix(cond.pitch, cond.yaw, cond.roll)
    c = target_centre(cond.range_m, cond.elevation)
    n = m @ np.array([1.0, 0, 0])
    a, b = LIDAR.cell_centre_angles(res.cloud.cell_w, res.cloud.cell_h, cond.elevation)
    d = np.stack([np.cos(b) * np.sin(a), np.sin(b), np.cos(b) * np.cos(a)], 1)
    t = (n @ c) / (d @ n)
    assert len(res.cloud) > 50
    incidence = np.degrees(np.arccos(np.abs(d @ n)))
    assert incidence.min() > 85
    assert np.abs(res.cloud.range_m - t).max() < 1e-3


def test_target_larger_than_window_is_clipped_and_reported():
    cat = default_catalog()
    cond = Condition.from_degrees(cat.get("A380-800").index, 400.0, 3.5, yaw_deg=40)
    res = Simulator("embree").simulate_type(cat, "A380-800", [cond.as_array()])
    assert res.clipped.tolist() == [True]
    assert res.n_rays[0] <= LIDAR.width * LIDAR.height
    cl = res.cloud
    assert LIDAR.inside(cl.cell_w, cl.cell_h).all()
    assert cl.cell_w.min() == LIDAR.w_min and cl.cell_w.max() == -LIDAR.w_min - 1
    far = Simulator("embree").simulate_type(
        cat, "A380-800", [Condition.from_degrees(cond.type_index, 9000.0, 3.5).as_array()])
    assert far.clipped.tolist() == [False]


def test_lidar_inside_bounding_sphere_and_overhead_are_clear_errors():
    cat = default_catalog()
    sim = Simulator("embree")
    t = cat.get("A320neo")
    with pytest.raises(InputError, match="inside the target's bounding sphere"):
        sim.simulate_type(cat, t, [[t.index, 20.0, 0.05, 0, 0, 0]])
    with pytest.raises(InputError, match="overhead"):
        sim.simulate_type(cat, t, [[t.index, 3000.0, np.pi / 2, 0, 0, 0]])
    with pytest.raises(InputError, match="finite"):
        sim.simulate_type(cat, t, [[t.index, np.nan, 0.05, 0, 0, 0]])
    with pytest.raises(InputError, match="unknown backend"):
        Simulator("optix")


def test_drone_at_600_m_and_supersampling():
    cat = default_catalog()
    drones = [t for t in cat if t.range_band == "near"]
    t = drones[0]
    cond = Condition.from_degrees(t.index, 600.0, 3.3, 2, 25, -4)
    one = Simulator("embree").simulate_type(cat, t, [cond.as_array()])
    three = Simulator("embree", supersample=3).simulate_type(cat, t, [cond.as_array()])
    assert len(one.cloud) >= 5
    # 3 x 3 rays per cell (the centre ray among them) see at least the cells one ray sees,
    # never a farther surface there
    k1, k3 = _as_dict(one.cloud), _as_dict(three.cloud)
    assert set(k1) <= set(k3) and len(k3) > len(k1)
    assert all(k3[k] <= k1[k] + 1e-9 for k in k1)
    assert any(k3[k] < k1[k] - 0.1 for k in k1)
    assert three.n_rays[0] == 9 * one.n_rays[0]


def test_far_tiny_target_gives_a_small_or_empty_cloud_not_an_error():
    cat = default_catalog()
    t = [t for t in cat if t.range_band == "near"][0]
    res = Simulator("embree").simulate_type(
        cat, t, [Condition.from_degrees(t.index, 18000.0, 3.5, 0, 90, 0).as_array()])
    assert res.n_samples == 1 and len(res.cloud) <= 2
    empty = Simulator("embree").simulate_type(cat, t, np.zeros((0, 6)))
    assert empty.n_samples == 0 and len(empty.cloud) == 0


def _parity_conditions(cat, rng):
    aircraft = ["A320neo", "777-300ER", "C-130J Hercules", "F-16C Fighting Falcon",
                "UH-60 Black Hawk", "CH-47F Chinook"]
    drones = [t.name for t in cat if t.range_band == "near"][:3]
    jobs = []
    for names, ranges in ((aircraft, (3000.0, 9000.0, 18000.0)), (drones, (100.0, 600.0))):
        for name in names:
            t = cat.get(name)
            rows = [Condition.from_degrees(t.index, r, rng.uniform(3, 4), rng.uniform(-5, 5),
                                           rng.uniform(-60, 60), rng.uniform(-5, 5)).as_array()
                    for r in ranges for _ in range(3)]
            jobs.append((name, np.array(rows)))
    return jobs


def _compare(a, b):
    ka = {(int(s), int(w), int(h)): r for s, w, h, r in
          zip(a.sample, a.cell_w, a.cell_h, a.range_m, strict=True)}
    kb = {(int(s), int(w), int(h)): r for s, w, h, r in
          zip(b.sample, b.cell_w, b.cell_h, b.range_m, strict=True)}
    common = set(ka) & set(kb)
    same = len(common) / max(1, len(set(ka) | set(kb)))
    dr = np.array([abs(ka[k] - kb[k]) for k in common])
    return same, dr


@pytest.mark.parametrize("other", ["blender", "blender-bvh"])
def test_blender_and_embree_agree_on_catalog_types(other):
    cat = default_catalog()
    jobs = _parity_conditions(cat, np.random.default_rng(7))
    emb, oth = Simulator("embree", quantize=False), Simulator(other, quantize=False)
    n_cells = 0
    for name, table in jobs:
        a = emb.simulate_type(cat, name, table).cloud
        b = oth.simulate_type(cat, name, table).cloud
        same, dr = _compare(a, b)
        n_cells += len(a)
        assert same >= 0.995, (name, same)
        assert dr.max() < 2e-3, (name, dr.max())
    assert n_cells > 20_000


def test_points_backend_is_close_but_not_exact():
    """The paper's z-buffer approximation, reported against exact ray casting."""
    cat = default_catalog()
    jobs = _parity_conditions(cat, np.random.default_rng(8))
    exact, approx = Simulator("embree"), Simulator("points")
    overlaps = []
    for name, table in jobs:
        a = exact.simulate_type(cat, name, table).cloud
        b = approx.simulate_type(cat, name, table).cloud
        same, dr = _compare(a, b)
        overlaps.append(same)
        assert np.median(dr) < 1.0, name  # same surface, to within metres
    assert 0.2 < np.mean(overlaps) < 0.995


@pytest.mark.parametrize("elevation_deg", [-89.999, 89.999])
def test_rows_past_the_zenith_or_nadir_are_cast(elevation_deg):
    """A drone straight overhead or below: the window's rows beyond +-90 deg (rays over the
    pole) meet it too, though no vertex has such an elevation; every row a brute-force
    float64 cast (Moller-Trumbore on every face) finds a hit in is in the cloud (they were
    dropped: rows -2, -6..-15 at -89.999 deg)."""
    from apcg_core.frames import body_to_observation, spherical_to_cartesian
    from apcg_core.lidar import DEG
    cat = default_catalog()
    mesh = cat.mesh("Phantom 4 Pro")
    cond = Condition.from_degrees(0, 100.0, elevation_deg, 0.0, 33.0, 70.0)
    got = Simulator("embree", quantize=False).simulate(mesh, [cond.as_array()]).cloud
    v = body_to_observation(mesh.vertices, 100.0, elevation_deg * DEG, 0.0, 33.0 * DEG,
                            70.0 * DEG)
    v0, v1, v2 = (v[mesh.faces[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    lidar = LidarParams()
    hit_rows = set()
    for h in range(-lidar.height // 2, lidar.height // 2):
        for w in range(-lidar.width // 2, lidar.width // 2, 8):
            d = spherical_to_cartesian(w * lidar.r_alpha, cond.elevation + h * lidar.r_beta,
                                       1.0)
            p = np.cross(d, e2)
            det = (p * e1).sum(axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / det
                u = (p * -v0).sum(axis=1) * inv
                q = np.cross(-v0, e1)
                s = (q @ d) * inv
                t = (e2 * q).sum(axis=1) * inv
            if ((u >= 0) & (s >= 0) & (u + s <= 1) & (t > 0)).any():
                hit_rows.add(h)
    assert len(hit_rows) > 10
    assert hit_rows <= set(got.cell_h.tolist()), sorted(hit_rows - set(got.cell_h.tolist()))
