import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from apcg_core.depth import (
    BACKGROUND,
    DEPTH_SCALE,
    TARGET_FLOOR,
    denorm,
    denorm_source_inside,
    im2pc,
    norm,
    pc2im,
)
from apcg_core.errors import InputError
from apcg_core.frames import spherical_to_cartesian
from apcg_core.lidar import LidarParams

LIDAR = LidarParams()
H, W = LIDAR.height, LIDAR.width
DEG = math.pi / 180


def point_at(w, h, r, beta0, lidar=LIDAR, frac=(0.0, 0.0)):
    """A point in cell (w, h) at range r, offset inside the cell by frac (in cells)."""
    a = (np.asarray(w) + frac[0]) * lidar.r_alpha
    b = (np.asarray(h) + frac[1]) * lidar.r_beta + beta0
    return spherical_to_cartesian(a, b, r)


def test_lidar_defaults_and_pixel_layout():
    assert LIDAR.to_dict() == pytest.approx(
        {"r_alpha_deg": 0.004, "r_beta_deg": 0.0076, "r_r_m": 0.15, "width": 256, "height": 64})
    assert LIDAR.w_of_col(0) == -128 and LIDAR.w_of_col(255) == 127
    assert LIDAR.h_of_row(0) == 31 and LIDAR.h_of_row(63) == -32
    assert LIDAR.col_of_w(LIDAR.w_of_col(17)) == 17
    assert LIDAR.row_of_h(LIDAR.h_of_row(5)) == 5
    with pytest.raises(InputError, match="width"):
        LidarParams(width=255)
    with pytest.raises(InputError, match="r_r"):
        LidarParams(r_r=float("nan"))


def test_pc2im_places_a_point_in_its_pixel():
    r0, b0, length = 4500.0, 3.4 * DEG, 37.57
    pts = point_at([5, -128, 127], [3, -32, 31], [r0 + 10.0, r0 - 5, r0], b0)
    img, st_ = pc2im(pts, r0, b0, length)
    assert img.shape == (H, W) and img.dtype == np.float32
    assert img[LIDAR.row_of_h(3), LIDAR.col_of_w(5)] == pytest.approx(DEPTH_SCALE * 10 / length)
    corner = img[LIDAR.row_of_h(-32), LIDAR.col_of_w(-128)]
    assert corner == pytest.approx(-DEPTH_SCALE * 5 / length)
    assert img[0, W - 1] == pytest.approx(0.0, abs=1e-6)
    assert (img == BACKGROUND).sum() == H * W - 3
    assert st_.n_pixels == 3 and st_.n_outside == 0 and st_.n_clamped == 0 and st_.n_hidden == 0


def test_pc2im_cell_edges():
    # Cell w covers [(w - .5) Ra, (w + .5) Ra]: just inside either edge stays in cell w.
    b0 = 3.5 * DEG
    pts = np.concatenate([point_at(7, 2, 3000, b0, frac=(0.499, -0.499)),
                          point_at(7, 2, 3000, b0, frac=(0.501, 0.0))])
    img, s = pc2im(pts[None, :3].reshape(-1, 3)[:1], 3000, b0, 40)
    assert img[LIDAR.row_of_h(2), LIDAR.col_of_w(7)] > BACKGROUND
    img, s = pc2im(pts[3:].reshape(-1, 3), 3000, b0, 40)
    assert img[LIDAR.row_of_h(2), LIDAR.col_of_w(8)] > BACKGROUND


def test_pc2im_keeps_the_nearest_return_and_counts_the_rest():
    b0 = 3.5 * DEG
    pts = point_at([0, 0, 0], [0, 0, 0], [3005.0, 3001.0, 3010.0], b0, frac=(0.1, 0.2))
    img, s = pc2im(pts, 3000.0, b0, 45.0)
    assert img[LIDAR.row_of_h(0), LIDAR.col_of_w(0)] == pytest.approx(1.8 * 1.0 / 45.0)
    assert s.n_hidden == 2 and s.n_pixels == 1


def test_pc2im_counts_points_outside_the_window():
    b0 = 3.5 * DEG
    pts = point_at([0, 128, -129, 0], [0, 0, 0, 32], 3000.0, b0)
    img, s = pc2im(pts, 3000.0, b0, 45.0)
    assert s.n_outside == 3 and s.n_pixels == 1 and s.n_points == 4


def test_pc2im_clamps_and_counts_depths_beyond_one():
    b0, length = 3.5 * DEG, 10.0
    pts = point_at([0, 1, 2, 3], [0, 0, 0, 0], [3000 + 6.0, 3000 - 6.0, 3000 - 5.6, 3000 + 1], b0)
    img, s = pc2im(pts, 3000.0, b0, length)
    row = img[LIDAR.row_of_h(0), LIDAR.col_of_w(np.arange(4))]
    assert row[0] == 1.0 and row[1] == TARGET_FLOOR and row[2] == TARGET_FLOOR
    assert (row > BACKGROUND).all()
    assert s.n_clamped == 3
    assert np.float16(TARGET_FLOOR) > np.float16(BACKGROUND)  # survives float16 storage


def test_pc2im_rejects_bad_input():
    with pytest.raises(InputError, match="finite"):
        pc2im(np.array([[np.nan, 0, 3000]]), 3000.0, 0.05, 40)
    with pytest.raises(InputError, match="length_m"):
        pc2im(np.zeros((1, 3)) + [0, 0, 3000], 3000.0, 0.05, 0.0)


def test_empty_cloud_and_all_background_image():
    img, s = pc2im(np.empty((0, 3)), 3000.0, 0.05, 40.0)
    assert (img == BACKGROUND).all() and s.n_pixels == 0
    cloud = im2pc(img, 3000.0, 0.05, 40.0)
    assert cloud.empty and cloud.xyz.shape == (0, 3)
    assert (norm(img, 3.7) == BACKGROUND).all()
    assert (denorm(img, 3.7) == BACKGROUND).all()
    b = im2pc(np.stack([img, img]), [3000.0, 4000.0], 0.05, 40.0)
    assert b.empty and len(b.split(2)) == 2


@st.composite
def target_cloud(draw):
    n = draw(st.integers(1, 200))
    seed = draw(st.integers(0, 2**31))
    r0 = draw(st.floats(100.0, 18000.0))
    b0 = draw(st.floats(-10 * DEG, 10 * DEG))
    length = draw(st.floats(0.3, 80.0))
    rng = np.random.default_rng(seed)
    w = rng.integers(-W // 2, W // 2, n)
    h = rng.integers(-H // 2, H // 2, n)
    r = r0 + rng.uniform(-0.5, 0.5, n) * length / DEPTH_SCALE * 0.99
    frac = rng.uniform(-0.49, 0.49, (2, n))
    return point_at(w, h, r, b0, frac=frac), r0, b0, length


@given(target_cloud())
def test_im2pc_of_pc2im_gives_cell_centres_and_ranges(args):
    pts, r0, b0, length = args
    img, s = pc2im(pts, r0, b0, length)
    assert s.n_clamped == 0 and s.n_outside == 0
    cloud = im2pc(img, r0, b0, length, tau=-1.0 + 1e-6)
    assert len(cloud) == s.n_pixels
    # each output point sits on the centre direction of its cell ...
    a, b = LIDAR.cell_centre_angles(cloud.cell_w, cloud.cell_h, b0)
    np.testing.assert_allclose(cloud.xyz, spherical_to_cartesian(a, b, cloud.range_m), atol=1e-6)
    # ... with the range of the nearest input point of that cell, to within R_r
    from apcg_core.frames import cartesian_to_spherical
    ia, ib, ir = cartesian_to_spherical(pts)
    iw, ih = LIDAR.cell_of_angles(ia, ib, b0)
    for w_, h_, r_ in zip(cloud.cell_w, cloud.cell_h, cloud.range_m, strict=True):
        nearest = ir[(iw == w_) & (ih == h_)].min()
        assert abs(r_ - nearest) < LIDAR.r_r
        assert abs(r_ - nearest) < 1e-5 * max(1.0, length)  # float32 image, not the 15 cm bound


def test_pc2im_batch_equals_single_images():
    rng = np.random.default_rng(3)
    clouds, r0s, b0s, ls = [], [3000.0, 9000.0, 150.0], [0.05, 0.06, 0.07], [40.0, 60.0, 1.5]
    for r0, b0, length in zip(r0s, b0s, ls, strict=True):
        n = 50
        clouds.append(point_at(rng.integers(-20, 20, n), rng.integers(-5, 5, n),
                               r0 + rng.uniform(-0.2, 0.2, n) * length, b0))
    pts = np.concatenate(clouds)
    sample = np.repeat(np.arange(3), 50)
    batch, s = pc2im(pts, r0s, b0s, ls, sample=sample, n_samples=3)
    assert batch.shape == (3, H, W)
    for i in range(3):
        single, _ = pc2im(clouds[i], r0s[i], b0s[i], ls[i])
        np.testing.assert_array_equal(batch[i], single)
    cl = im2pc(batch, r0s, b0s, ls)
    parts = cl.split(3)
    for i in range(3):
        one = im2pc(batch[i], r0s[i], b0s[i], ls[i])
        np.testing.assert_array_equal(parts[i].xyz, one.xyz)


def _random_image(seed, density=0.3):
    rng = np.random.default_rng(seed)
    img = np.where(rng.random((H, W)) < density, rng.uniform(-0.99, 1, (H, W)), -1.0)
    return img.astype(np.float32)


@given(q=st.floats(1.0, 20.0), seed=st.integers(0, 1000))
def test_denorm_inverts_norm_where_the_source_is_inside(q, seed):
    d = _random_image(seed)
    back = denorm(norm(d, q), q)
    inside = denorm_source_inside((H, W), q)
    np.testing.assert_array_equal(back[inside], d[inside])
    assert (back[~inside] == BACKGROUND).all()


@pytest.mark.parametrize("q", [1.0, 1.5, 2.0, 3.0, 4.5, 5.5, 6.0, 1.1, 2.2, 3.3])
def test_denorm_inverts_norm_at_exact_ratios(q):
    # ratios that make w q land exactly on integers stress the float rounding of floor/ceil
    d = _random_image(int(q * 10), 0.9)
    inside = denorm_source_inside((H, W), q)
    np.testing.assert_array_equal(denorm(norm(d, q), q)[inside], d[inside])


@pytest.mark.parametrize("base", [1.0, 1.5, 2.0, 3.0])
def test_denorm_inverts_norm_at_knife_edges_of_the_rounding_tolerance(base):
    """q a hair above an exact ratio, where (q - base) |w| is about the index tolerance: the
    two resamplings used to round with opposite tolerances and disagree (317 pixels of column
    w = 1 at q = 1 + 1e-9; probe finding, stop 53)."""
    d = _random_image(int(base * 7), 0.95)
    qs = base + np.concatenate([np.logspace(-12, -6, 61), [1e-9, 1e-9 / 64, 1e-9 / 3, 2e-9]])
    for q in qs:
        inside = denorm_source_inside((H, W), q)
        assert inside.sum() > 0
        np.testing.assert_array_equal(denorm(norm(d, q), q)[inside], d[inside],
                                      err_msg=f"q = {q!r}")


def test_norm_is_floor_of_w_over_q_away_from_rounding():
    """Norm's source is floor(w / q) wherever w / q is not within rounding of an integer."""
    rng = np.random.default_rng(3)
    w = _centred_indices_for_test(W)
    for q in np.concatenate([rng.uniform(0.2, 20.0, 200), [0.5, 1.0, 2.0, 7.0]]):
        x = w / q
        away = np.abs(x - np.round(x)) > 1e-6
        img = np.tile(np.arange(W, dtype=np.float32) / W, (H, 1))  # each column its own value
        out = norm(img, q)[H // 2 - 1]  # the row h = 0, its own source at every q
        src = np.floor(x[away]).astype(int) + W // 2
        ok = (src >= 0) & (src < W)
        np.testing.assert_array_equal(out[away][ok], img[0, src[ok]])


def _centred_indices_for_test(n):
    return np.arange(n) - n // 2


def test_norm_covers_the_whole_target_when_it_fits_at_the_reference_range():
    # a target of 60 x 10 cells at 9 km (q = 3) fills 180 x 30 cells after Norm and comes back
    d = np.full((H, W), -1.0, np.float32)
    d[LIDAR.row_of_h(np.arange(-5, 5))[:, None], LIDAR.col_of_w(np.arange(-30, 30))[None]] = 0.25
    n = norm(d, 3.0)
    assert (n > -1).sum() == 180 * 30
    np.testing.assert_array_equal(denorm(n, 3.0), d)


def test_norm_with_q_below_one_shrinks_and_pads():
    d = _random_image(5, 1.0)
    n = norm(d, 0.5)  # d_n(w) = d(floor(2 w))
    assert n[LIDAR.row_of_h(0), LIDAR.col_of_w(0)] == d[LIDAR.row_of_h(0), LIDAR.col_of_w(0)]
    assert n[LIDAR.row_of_h(3), LIDAR.col_of_w(-7)] == d[LIDAR.row_of_h(6), LIDAR.col_of_w(-14)]
    assert n[LIDAR.row_of_h(0), LIDAR.col_of_w(64)] == BACKGROUND  # source w = 128 is outside
    assert n[LIDAR.row_of_h(16), LIDAR.col_of_w(0)] == BACKGROUND  # source h = 32 is outside
    assert n[LIDAR.row_of_h(-16), LIDAR.col_of_w(-64)] != BACKGROUND  # source (-128, -32) inside


def test_norm_magnifies_by_floor():
    d = _random_image(7, 1.0)
    n = norm(d, 2.0)
    for w, h in [(0, 0), (1, 1), (-1, -1), (5, -3), (127, 31), (-128, -32)]:
        src = d[LIDAR.row_of_h(math.floor(h / 2)), LIDAR.col_of_w(math.floor(w / 2))]
        assert n[LIDAR.row_of_h(h), LIDAR.col_of_w(w)] == src


def test_norm_denorm_batch_with_per_sample_q():
    ds = np.stack([_random_image(i) for i in range(4)])
    qs = np.array([1.0, 2.5, 4.0, 6.0])
    nb = norm(ds, qs)
    for i in range(4):
        np.testing.assert_array_equal(nb[i], norm(ds[i], qs[i]))
    db = denorm(nb, qs)
    for i in range(4):
        np.testing.assert_array_equal(db[i], denorm(nb[i], qs[i]))
    with pytest.raises(InputError, match="q must be"):
        norm(ds, np.array([1.0, 0.0, 1.0, 1.0]))


def test_im2pc_threshold_and_equations():
    d = np.full((H, W), -1.0, np.float32)
    d[LIDAR.row_of_h(2), LIDAR.col_of_w(-3)] = 0.5
    d[LIDAR.row_of_h(0), LIDAR.col_of_w(0)] = -0.96  # below tau = -0.95: dropped
    r0, b0, length = 9000.0, 3.2 * DEG, 50.0
    c = im2pc(d, r0, b0, length)
    assert len(c) == 1
    assert c.range_m[0] == pytest.approx(0.5 * length / 1.8 + r0)
    expect = spherical_to_cartesian(-3 * LIDAR.r_alpha, 2 * LIDAR.r_beta + b0, c.range_m[0])
    np.testing.assert_allclose(c.xyz[0], expect, rtol=1e-15)
    assert (c.cell_w[0], c.cell_h[0]) == (-3, 2)
    assert len(im2pc(d, r0, b0, length, tau=-0.97)) == 2
    with pytest.raises(InputError, match="does not match"):
        im2pc(np.zeros((10, 10)), r0, b0, length)
