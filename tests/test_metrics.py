import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from apcg_core.errors import InputError
from apcg_core.metrics import (
    jsd,
    jsd_mean,
    median_cross_distance,
    mmd,
    mmd_mean,
    subsample,
)
from apcg_core.pointflow import chamfer_distance, pointflow_scores

FAR = np.array([0.0, 1000.0, 18000.0])  # an airliner's neighbourhood at 18 km


def cloud(seed, n=200, scale=20.0, offset=FAR):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * scale + offset


clouds = st.builds(lambda s, n: cloud(s, n), st.integers(0, 10**6), st.integers(1, 120))


def test_mmd_hand_computed():
    a, b = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    assert mmd(a, b) == pytest.approx(2 - 2 * math.exp(-0.5), rel=1e-12)  # sigma = 1


def test_mmd_sigma_zero_limit():
    a = np.zeros((1, 3))
    assert mmd(a, a) == 0.0
    # more than half the cross distances are 0 -> sigma = 0: the kernel's limit is used
    b = np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0]])
    v = mmd(a, b)
    assert v is not None and math.isfinite(v) and v > 0


@given(clouds)
def test_mmd_of_a_cloud_with_itself_is_zero(a):
    v = mmd(a, a.copy())
    assert 0.0 <= v <= 1e-9


@given(clouds, clouds)
def test_mmd_and_jsd_are_symmetric(a, b):
    assert mmd(a, b) == pytest.approx(mmd(b, a), abs=1e-12)
    assert jsd(a, b) == pytest.approx(jsd(b, a), abs=1e-12)
    assert mmd(a, b) >= 0.0


@given(clouds, clouds, st.integers(1, 64))
def test_jsd_bounds(a, b, c):
    v = jsd(a, b, bins=c)
    assert 0.0 <= v <= 1.0
    assert jsd(a, a.copy(), bins=c) == 0.0


def test_jsd_hand_computed():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[0.0, 0, 0], [2, 0, 0]])
    assert jsd(a, b, bins=3) == pytest.approx(0.5, abs=1e-15)  # P=(.5,.5,0) Q=(.5,0,.5)
    assert jsd(a[:1], b[1:], bins=3) == pytest.approx(1.0)  # disjoint bins



def test_jsd_of_an_edge_on_cloud_against_a_rounded_copy_is_zero():
    # 8 points of a flat target seen edge-on at 200 m: one axis spans 1e-5 m; a re-simulated
    # copy differs by float rounding only and must land in the same bins
    rng = np.random.default_rng(3)
    a = np.column_stack([rng.uniform(-0.05, 0.05, 8), np.full(8, 200.0),
                         rng.uniform(0, 1e-5, 8)])
    b = a + rng.uniform(-1e-9, 1e-9, a.shape)
    assert jsd(a, b, bins=6) == 0.0
    assert jsd(a, a + [0.0, 0.0, 0.5], bins=6) > 0.5  # a real offset still counts

def test_shifted_cloud_scores_worse():
    a = cloud(1, 400)
    near = cloud(2, 400)  # same distribution, new draw
    far = cloud(2, 400) + [15.0, 0, 0]
    assert mmd(a, near) < mmd(a, far)
    assert jsd(a, near, bins=8) < jsd(a, far, bins=8)
    assert mmd(a, far) < mmd(a, far + [30.0, 0, 0])


def test_far_range_precision():
    # Differences matter, not positions: the score at 18 km equals the score at the origin.
    a, b = cloud(3, 300, 5.0, 0.0), cloud(4, 300, 5.0, 0.0) + [0.3, 0, 0]
    assert mmd(a + FAR, b + FAR) == pytest.approx(mmd(a, b), rel=1e-9)
    assert jsd(a + FAR, b + FAR) == pytest.approx(jsd(a, b), abs=1e-12)
    assert chamfer_distance(a + FAR, b + FAR) == pytest.approx(chamfer_distance(a, b), rel=1e-9)


def test_empty_cloud_is_a_counted_no_score():
    a = cloud(5, 50)
    e = np.empty((0, 3))
    assert mmd(a, e) is None and mmd(e, a) is None and jsd(e, e) is None
    pairs = [(a, cloud(6, 50)), (a, e), (e, cloud(7, 50)), (a, cloud(8, 60))]
    s = mmd_mean(pairs)
    assert s.n_pairs == 4 and s.n_scored == 2 and s.n_no_score == 2
    assert s.mean == pytest.approx(np.mean([mmd(a, cloud(6, 50)), mmd(a, cloud(8, 60))]))
    j = jsd_mean(pairs, bins=16)
    assert j.n_no_score == 2 and math.isfinite(j.mean) and j.params["bins"] == 16
    none = mmd_mean([(e, a)])
    assert none.mean is None and none.n_no_score == 1
    assert none.to_dict()["n_no_score"] == 1


def test_chunked_median_and_mmd_equal_the_direct_ones():
    a, b = cloud(9, 301), cloud(10, 257) + 3.0
    direct = np.median(np.linalg.norm(a[:, None] - b[None], axis=-1))
    assert median_cross_distance(a - FAR, b - FAR, chunk=997) == pytest.approx(direct, rel=1e-12)
    assert median_cross_distance(a - FAR, b - FAR) == pytest.approx(direct, rel=1e-12)
    odd = b[:-1]
    direct_odd = np.median(np.linalg.norm(a[:, None] - odd[None], axis=-1))
    assert median_cross_distance(a - FAR, odd - FAR, chunk=500) == pytest.approx(direct_odd)
    assert mmd(a, b, chunk=1000) == pytest.approx(mmd(a, b), rel=1e-10)


def test_median_with_many_ties():
    a = np.zeros((60, 3))
    b = np.r_[np.zeros((40, 3)), np.ones((30, 3))]
    assert median_cross_distance(a, b, chunk=100) == np.median(
        np.linalg.norm(a[:, None] - b[None], axis=-1))


def test_subsample_is_seeded_and_bounded():
    a = cloud(11, 5000)
    s1, s2 = subsample(a, 2048, seed=4), subsample(a, 2048, seed=4)
    assert len(s1) == 2048
    np.testing.assert_array_equal(s1, s2)
    assert not np.array_equal(s1, subsample(a, 2048, seed=5))
    assert subsample(a[:10], 2048) is not None and len(subsample(a[:10], 2048)) == 10
    v = mmd(a, cloud(12, 5000), max_points=500, seed=1)
    assert v == mmd(a, cloud(12, 5000), max_points=500, seed=1)


def test_bad_clouds_are_refused():
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        mmd(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="NaN"):
        jsd(np.array([[np.nan, 0, 0]]), np.zeros((1, 3)))
    with pytest.raises(InputError, match="bins"):
        jsd(np.zeros((1, 3)), np.zeros((1, 3)), bins=0)


def test_chamfer_hand_computed():
    a = np.array([[0.0, 0, 0]])
    b = np.array([[1.0, 0, 0], [3.0, 0, 0]])
    assert chamfer_distance(a, b) == pytest.approx(1.0 + 5.0)
    assert chamfer_distance(a, np.empty((0, 3))) is None


def test_pointflow_scores_separate_good_from_shifted():
    ref = [cloud(100 + i, 80, 3.0, 0.0) for i in range(12)]
    good = [cloud(200 + i, 80, 3.0, 0.0) for i in range(12)]
    bad = [c + [4.0, 0, 0] for c in good]
    g = pointflow_scores(good, ref)
    b = pointflow_scores(bad, ref + [np.empty((0, 3))])
    assert g.mmd_cd < b.mmd_cd
    assert g.cov_cd >= b.cov_cd
    assert abs(g.nna_cd - 0.5) < abs(b.nna_cd - 0.5)
    assert b.nna_cd == 1.0  # shifted samples are trivially told apart
    assert b.n_empty_reference == 1
