"""What the photon stage and a shard's depth images accept: a bad argument is a named
InputError, never a silently wrong cloud or image (probe findings 5, 6 and 15, stop 54)."""

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.io import dataset as DS
from apcg_core.lidar import LidarParams
from apcg_core.sensor import SubRayHits, check_sensor, load_sensor, photon_cloud

LIDAR = LidarParams()
SENSOR = load_sensor("1550nm-night")


def _hits(n=40, dw=0, sample=None, r=None, sub_rays=1, n_samples=1, cos=None):
    """``n`` hits of one sample near the window's centre (cells shifted by ``dw``)."""
    rng = np.random.default_rng(0)
    w = rng.integers(-20, 20, n).astype(np.int32) + dw
    h = rng.integers(-5, 5, n).astype(np.int32)
    r = 4500 + rng.uniform(-10, 10, n) if r is None else r
    cos = rng.uniform(0.3, 1, n) if cos is None else cos
    sample = np.zeros(n, np.int64) if sample is None else sample
    return SubRayHits(sample, w, h, r, cos, n_samples, sub_rays)


def _run(hits=None, r0=(4500.0,), rho=0.6, seed=1, **kw):
    return photon_cloud(_hits() if hits is None else hits, np.asarray(r0), rho, SENSOR, LIDAR,
                        seed, **kw)


def test_valid_hits_still_give_a_cloud():
    assert len(_run().w) > 0
    # numpy integer seeds and counts are the integers they hold
    a, b = _run(seed=np.uint32(7)), _run(seed=7)
    assert np.array_equal(a.range_m, b.range_m) and np.array_equal(a.w, b.w)


@pytest.mark.parametrize("r0", [np.nan, np.inf, 1e300, -4500.0, 0.0])
def test_r0_must_be_a_finite_range_above_zero(r0):
    with pytest.raises(InputError, match=r"r0 .*accepted: finite, > 0"):
        _run(r0=[r0])


def test_r0_must_hold_one_range_per_sample():
    with pytest.raises(InputError, match="r0 .*one number per sample"):
        photon_cloud(_hits(), 4500.0, 0.6, SENSOR, LIDAR, 1)
    with pytest.raises(InputError, match="r0 .*one number per sample"):
        _run(r0=[4500.0, 4500.0])


@pytest.mark.parametrize("dw", [1000, -1000])
def test_hits_outside_the_window_are_refused_not_folded(dw):
    with pytest.raises(InputError, match=r"w = .* outside the lidar's 256 x 64 window"):
        _run(_hits(dw=dw))


def test_hit_rows_outside_the_window_are_refused():
    hits = _hits()
    hits.h = hits.h + 40
    with pytest.raises(InputError, match=r"h = .* outside the lidar's 256 x 64 window"):
        _run(hits)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0])
def test_a_hit_range_must_be_finite_and_positive(bad):
    r = 4500 + np.zeros(40)
    r[3] = bad
    with pytest.raises(InputError, match=r"range_m = .* accepted: finite, > 0"):
        _run(_hits(r=r))


def test_a_hit_cosine_must_lie_in_0_1():
    cos = np.full(40, 0.5)
    cos[0] = np.nan
    with pytest.raises(InputError, match=r"cos = nan.*\[0, 1\]"):
        _run(_hits(cos=cos))


def test_sample_indices_must_lie_in_the_table_and_in_order():
    with pytest.raises(InputError, match=r"sample = 5 lies outside the 1 samples"):
        _run(_hits(sample=np.full(40, 5, np.int64)))
    with pytest.raises(InputError, match=r"sample = -1"):
        _run(_hits(sample=np.full(40, -1, np.int64)))
    s = np.r_[np.ones(20, np.int64), np.zeros(20, np.int64)]
    with pytest.raises(InputError, match="grouped by sample"):
        _run(_hits(sample=s, n_samples=2), r0=[4500.0, 4500.0])


def test_hit_columns_must_be_integer_indices_of_one_length():
    hits = _hits()
    hits.w = hits.w.astype(np.float64) + 0.5
    with pytest.raises(InputError, match="SubRayHits w must be a 1-D array of 40 integers"):
        _run(hits)
    hits = _hits()
    hits.cos = hits.cos[:10]
    with pytest.raises(InputError, match="SubRayHits cos must be a 1-D array of 40"):
        _run(hits)


@pytest.mark.parametrize("k", [0, -4, 1.5, True])
def test_sub_rays_must_be_a_whole_count_of_at_least_one(k):
    with pytest.raises(InputError, match="sub_rays must be an integer >= 1"):
        _run(_hits(sub_rays=k))


@pytest.mark.parametrize("seed", [1.5, "3", None, True, -1, 2**32])
def test_seed_must_be_an_integer_in_0_to_2_32(seed):
    with pytest.raises(InputError, match=r"seed must be an integer in 0\.\.4294967295"):
        _run(seed=seed)


def test_reflectivity_of_the_wrong_length_is_named():
    with pytest.raises(InputError, match="reflectivity must be one number, one per sample"):
        _run(rho=[0.5, 0.5, 0.5])


def test_sample_ids_one_integer_per_sample():
    with pytest.raises(InputError, match="sample_ids must be 1 integers >= 0"):
        _run(sample_ids=np.array([0, 1]))
    with pytest.raises(InputError, match="sample_ids must be 1 integers >= 0"):
        _run(sample_ids=np.array([0.5]))


# --- check_sensor: numpy scalars are the numbers they hold (finding 15) -----------------------
@pytest.mark.parametrize("key, value", [("pulses", np.int64(100)), ("threshold", np.int32(3)),
                                        ("wavelength_nm", np.float32(1550.0)),
                                        ("gate_m", np.int64(100))])
def test_check_sensor_takes_numpy_scalars_as_numbers(key, value):
    s = check_sensor({**SENSOR.to_dict(), key: value})
    assert getattr(s, key) == value and type(getattr(s, key)) in (int, float)
    assert s == check_sensor({**SENSOR.to_dict(), key: value.item()})


@pytest.mark.parametrize("key, value, kind", [("pulses", 100.0, "float"),
                                              ("pulses", True, "bool"),
                                              ("wavelength_nm", "1550", "str")])
def test_check_sensor_names_a_wrong_type(key, value, kind):
    with pytest.raises(InputError, match=f"{key} must be .*of type {kind}"):
        check_sensor({**SENSOR.to_dict(), key: value})


# --- Shard.depth_images: only the shard's own H x W (finding 6) --------------------------------
TINY = """description = "tiny"
seed = 1
backend = "embree"
shard_size = 3
test_fraction = 0.2
quantize = true
supersample = 1
sampling = "grid"
types = ["A320neo"]

[counts]
elevation = 1
range_m = 2
yaw = 1
pitch = 1
roll = 1
"""


@pytest.fixture(scope="module")
def shard(tmp_path_factory):
    from dataset_builder.build import build_dataset
    d = tmp_path_factory.mktemp("tiny")
    (d / "tiny.toml").write_text(TINY)
    build_dataset(str(d / "tiny.toml"), d / "ds", progress=False)
    head = DS.read_header(d / "ds")
    idx = DS.read_condition_index(d / "ds", head)
    return DS.load_shard(d / "ds", head["shards"][0], idx, head), head["lidar"]


def test_depth_images_refuse_another_window(shard):
    sh, lidar = shard
    H, W = lidar["height"], lidar["width"]
    assert sh.depth_images(H, W).shape == (len(sh), H, W)
    for h, w in ((W, H), (H, W // 2), (H // 2, W), (H, W + 2)):
        with pytest.raises(InputError, match=rf"its lidar's {H} x {W} window"):
            sh.depth_images(h, w)


def test_depth_images_of_a_shard_read_alone_need_room_for_its_pixels(shard):
    sh, lidar = shard
    alone = DS.Shard(**{k: getattr(sh, k) for k in DS.SHARD_KEYS})
    top = int(sh.pixel.max())
    with pytest.raises(InputError, match=rf"pixel {top}, outside an image"):
        alone.depth_images(1, top)
    with pytest.raises(InputError, match="height must be an integer >= 1"):
        alone.depth_images(0, lidar["width"])
    assert np.array_equal(alone.depth_images(lidar["height"], lidar["width"]),
                          sh.depth_images(lidar["height"], lidar["width"]))
