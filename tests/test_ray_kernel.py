"""The compiled ray kernel (dataset_builder/kernels.py) against the numpy code it replaces: the
same float32 rays, the same angular boxes, the same hits and float64 ranges, byte for byte, on
conditions covering every catalog type (Table 1 ranges, 18 km, grazing views, attitudes at
their limits, targets that fill and overflow the window, the lidar just outside the bounding
sphere) and on tiny meshes seen edge-on."""

import re

import numpy as np
import pytest
from sim_helpers import rectangle, uv_sphere

from apcg_core.catalog.catalog import Catalog
from apcg_core.depth import DEFAULT_LIDAR
from dataset_builder import kernels
from dataset_builder.backends.embree import EmbreeCaster
from dataset_builder.rays import (
    angular_boxes,
    bounding_radius,
    cast_cells,
    check_conditions,
    compiled_ray_blocks,
    make_rays,
    ray_blocks,
    sample_frames,
    start_margin_m,
)
from dataset_builder.simulate import Simulator

CATALOG = Catalog(include_user=False)
DEG = np.pi / 180
LIDAR = DEFAULT_LIDAR


def _conditions(t, radius: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Five conditions for catalog type t, [type, r0, beta0, pitch, yaw, roll]: four that the
    boxes' float32 screen takes, and one close enough that every vertex is evaluated."""
    lo, hi = (100.0, 600.0) if t.range_band == "near" else (3000.0, 18000.0)
    need = radius + 2.0 * start_margin_m(radius)
    rows = [
        # a Table 1 draw
        [rng.uniform(lo, hi), rng.uniform(3, 4), rng.uniform(1, 5), rng.uniform(-60, 60),
         rng.uniform(-5, 5)],
        # the far end (18 km for aircraft), any attitude
        [hi, rng.uniform(-60, 60), rng.uniform(-90, 90), rng.uniform(-180, 180),
         rng.uniform(-180, 180)],
        # grazing: the line of sight in the wing plane, edge-on, or along the fuselage
        [rng.uniform(lo, hi), 0.0, 0.0, rng.choice([0.0, 90.0, -90.0, 180.0]), 0.0],
        # attitude limits and a steep elevation (the boxes' exact path near the zenith)
        [rng.uniform(lo, hi), rng.choice([-85.0, 85.0]), rng.choice([-90.0, 90.0]),
         rng.choice([-180.0, 180.0]), rng.choice([-180.0, 180.0])],
        # close: the target overflows the window (clipped boxes, every cell a ray)
        [max(need * 1.001, 4.0 * radius), rng.uniform(-10, 10), rng.uniform(-30, 30),
         rng.uniform(-180, 180), rng.uniform(-30, 30)],
    ]
    table = np.array([[t.index, r0, b * DEG, p * DEG, y * DEG, ro * DEG]
                      for r0, b, p, y, ro in rows])
    table = check_conditions(table, radius)
    return table[:4], table[4:]


def _screened(mesh, c, radius) -> bool:
    """Whether rays._angle_extremes screens these samples (else: every vertex exactly)."""
    return len(mesh.vertices) >= 16 and bool((c[:, 2] - radius > 4.0 * radius).all())


def _both_paths(mesh, table, block_rays):
    """Compare everything; (hits, rays, whether the boxes were screened)."""
    radius = bounding_radius(mesh.vertices)
    m, c = sample_frames(table)
    boxes = angular_boxes(mesh.vertices, table, LIDAR, m, c, compiled=False)
    boxes_k = angular_boxes(mesh.vertices, table, LIDAR, m, c, compiled=True)
    for f in ("w_lo", "w_hi", "h_lo", "h_hi", "clipped"):
        assert np.array_equal(getattr(boxes, f), getattr(boxes_k, f)), f

    # the rays, block by block, and make_rays' float64 rays rounded once to float32
    ref = make_rays(table, boxes, LIDAR, m, c, radius)
    blocks = compiled_ray_blocks(table, boxes, LIDAR, m, c, radius, block_rays)
    plan = next(blocks)
    assert plan.n_rays == ref.n_rays
    first = 0
    for blk, (start, stop, o, d) in zip(ray_blocks(table, boxes, LIDAR, m, c, radius,
                                                   block_rays), blocks, strict=True):
        assert blk.row_sample[0] == start and blk.row_sample[-1] == stop - 1
        assert o.tobytes() == blk.origin.tobytes()
        assert d.tobytes() == blk.direction.tobytes()
        n = len(o)
        assert o.tobytes() == ref.origin[first:first + n].astype(np.float32).tobytes()
        assert d.tobytes() == ref.direction[first:first + n].astype(np.float32).tobytes()
        first += n
    assert first == ref.n_rays

    caster = EmbreeCaster(mesh)
    got = cast_cells(caster, table, boxes, LIDAR, m, c, radius, compiled=True,
                     block_rays=block_rays)
    want = cast_cells(caster, table, boxes, LIDAR, m, c, radius, compiled=False,
                      block_rays=block_rays)
    for name, a, b in zip(("sample", "w", "h", "range"), got, want, strict=True):
        assert a.dtype == b.dtype, name
        assert a.tobytes() == b.tobytes(), name
    # and the general path (float64 rays, caster.cast) finds the same cells and ranges
    t = caster.cast(ref.origin, ref.direction, ref.t_max)
    hit = np.isfinite(t)
    assert np.array_equal(got[0], ref.sample[hit])
    assert np.array_equal(got[1], ref.w[hit]) and np.array_equal(got[2], ref.h[hit])
    assert got[3].tobytes() == (ref.t_start[ref.sample[hit]] + t[hit]).tobytes()
    return len(got[0]), ref.n_rays, _screened(mesh, c, radius)


def test_the_kernels_are_there():
    # CI installs the sim extra, numba included: the comparisons below must not be numpy
    # against numpy.
    assert kernels.enabled()
    kernels.require()
    assert kernels.loaded() and kernels.use_for(1)


@pytest.mark.parametrize("block_rays", [32_768, 700])
def test_compiled_and_numpy_paths_give_the_same_bytes_on_every_type(block_rays):
    rng = np.random.default_rng(22)
    n_conditions = n_hits = n_rays = 0
    kinds, screened = set(), []
    for t in CATALOG:
        mesh = CATALOG.mesh(t)
        for table in _conditions(t, bounding_radius(mesh.vertices), rng):
            hits, rays, scr = _both_paths(mesh, table, block_rays)
            n_conditions += len(table)
            n_hits += hits
            n_rays += rays
            screened.append(scr)
        kinds.add(t.range_band)
    assert kinds == {"far", "near"}
    assert n_conditions >= 400
    assert 0 < n_hits < n_rays
    # both ways of finding the boxes were compared: the screen for Table 1 conditions, every
    # vertex for the close ones
    assert screened[0::2] == [True] * len(CATALOG) and not any(screened[1::2])


def test_tiny_meshes_edge_on_and_nothing_hit():
    # fewer than 16 vertices (no screen), a plate seen exactly edge-on (rays parallel to it),
    # and a sphere whose box is hit in its middle only
    plate = rectangle(5.0, 2.0)
    table = np.array([[0, 5000.0, 0.0, 0.0, 90 * DEG, 0.0],  # edge-on
                      [0, 5000.0, 3 * DEG, 0.0, 0.0, 0.0],  # face-on
                      [0, 50.0, 0.0, 0.0, 89.9 * DEG, 0.0],  # nearly edge-on, close
                      [0, 18000.0, -20 * DEG, 45 * DEG, 30 * DEG, 60 * DEG]])
    _both_paths(plate, check_conditions(table, bounding_radius(plate.vertices)), 32_768)
    ball = uv_sphere(3.0, 24, 12)
    table = np.array([[0, r, b * DEG, 0.0, 0.0, 0.0]
                      for r in (10.0, 400.0, 18000.0) for b in (-40.0, 0.0, 60.0)])
    _both_paths(ball, check_conditions(table, bounding_radius(ball.vertices)), 500)


def test_the_kernels_hold_no_fused_multiply_add():
    # An FMA rounds once where the numpy code rounds twice: the kernels must not hold one.
    # Compile them again with their own options but without the cache (whose machine code
    # cannot be inspected), for the argument types they were called with, and read the code.
    from numba import njit
    t = CATALOG.get("A320neo")
    mesh = CATALOG.mesh(t)
    _both_paths(mesh, _conditions(t, bounding_radius(mesh.vertices),
                                  np.random.default_rng(1))[0], 32_768)
    k = kernels.require()
    fused = re.compile(r"\b(v?fn?m(add|sub)\w*|fml[as]\w*)\b", re.IGNORECASE)
    code = {}
    for name in ("row_elevations", "rays", "hits", "screen"):
        f = getattr(k, name)
        assert f.signatures, name
        options = {o: v for o, v in f.targetoptions.items() if o != "nopython"}
        again = njit(**options)(f.py_func)  # the kernel's own options (fastmath...)
        for sig in f.signatures:
            again.compile(sig)
        code[name] = "\n".join(again.inspect_asm().values())
    for name, asm in code.items():
        assert not fused.search(asm), (name, fused.search(asm).group(0))
    assert re.search(r"\b(v?mul[sp][sd]|fmul)\b", code["rays"])  # the pattern reads this code


def test_simulator_shards_equal_with_and_without_kernels(monkeypatch):
    kernels.require()
    assert kernels.use_for(1)  # loaded: the simulator takes the compiled path for any size
    t = CATALOG.get("A320neo")
    mesh = CATALOG.mesh(t)
    rng = np.random.default_rng(5)
    table = np.concatenate([_conditions(t, bounding_radius(mesh.vertices), rng)[0]
                            for _ in range(20)])
    got = Simulator("embree").simulate_cells(mesh, table)
    monkeypatch.setenv(kernels.ENV, "numpy")
    assert not kernels.enabled()
    want = Simulator("embree").simulate_cells(mesh, table)
    for name in ("sample", "cell_w", "cell_h", "range_m", "clipped", "n_rays"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
