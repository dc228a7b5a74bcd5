"""Bad arguments to the Python API are refused with an InputError that names the value and what
is accepted, never turned into a silently wrong result or a bare numpy error (probe findings of
stop 54: depth, metrics, lidar, condition, frames, a model's type keys and seed)."""

import math

import numpy as np
import pytest

from apcg_core.condition import Condition, ConditionSpace
from apcg_core.depth import im2pc, norm, pc2im
from apcg_core.errors import InputError
from apcg_core.frames import (
    cartesian_to_spherical,
    pose_from_lidar_local,
    spherical_to_cartesian,
    target_matrix_lidar_local,
)
from apcg_core.lidar import DEG, LidarParams
from apcg_core.metrics import jsd, mmd

L = LidarParams()
R0, B0, LEN = 4500.0, 3.4 * DEG, 37.57


def _points():
    a, b = L.cell_centre_angles(np.array([0, 5]), np.array([0, -7]), B0)
    return spherical_to_cartesian(a, b, np.array([R0, R0 + 1.0]))


def _image():
    return pc2im(_points(), R0, B0, LEN, L)[0]


# --- PC2Im / Im2PC: per-sample scalars are what a Condition takes ---------------------------
@pytest.mark.parametrize("name, value, words", [
    ("elevation", 3.4, "194.806 deg"),  # degrees given as radians: every point "outside"
    ("elevation", -math.pi / 2, "-90 deg"),
    ("elevation", [B0, 2.0], "(sample 1)"),
    ("range_m", -1.0, "range_m = -1.0"),  # every depth clamped to 1
    ("range_m", 0.0, "range_m > 0"),
    ("length_m", 0.0, "length_m must be > 0"),
    ("length_m", -37.0, "-37.0"),
])
@pytest.mark.parametrize("which", ["pc2im", "im2pc"])
def test_depth_scalars_are_a_conditions(which, name, value, words):
    args = {"range_m": R0, "elevation": B0, "length_m": LEN}
    args[name] = value
    n = np.size(value)
    with pytest.raises(InputError, match=f"{which}: .*{words}".replace("(", r"\(")
                       .replace(")", r"\)")):
        if which == "pc2im":
            pts = _points()
            sample = np.arange(len(pts)) % n if n > 1 else None
            pc2im(pts, args["range_m"], args["elevation"], args["length_m"], L,
                  sample=sample, n_samples=n if n > 1 else None)
        else:
            img = np.stack([_image()] * n) if n > 1 else _image()
            im2pc(img, args["range_m"], args["elevation"], args["length_m"], L)


def test_depth_elevation_limit_is_the_conditions():
    below = math.nextafter(math.pi / 2, 0.0)
    Condition(0, R0, below)  # the largest elevation a Condition takes: the depth functions too
    img, _ = pc2im(_points(), R0, below, LEN, L)
    im2pc(img, R0, -below, LEN, L)
    with pytest.raises(InputError):
        Condition(0, R0, math.pi / 2)
    with pytest.raises(InputError, match="Accepted: -90 deg < elevation < 90 deg"):
        pc2im(_points(), R0, math.pi / 2, LEN, L)


@pytest.mark.parametrize("pixel", [np.inf, -np.inf, np.nan])
def test_im2pc_refuses_a_non_finite_image(pixel):
    img = _image()
    img[3, 7] = pixel
    with pytest.raises(InputError, match="finite"):
        im2pc(img, R0, B0, LEN, L)


@pytest.mark.parametrize("tau", [np.nan, np.inf, -1.5, 1.0, "x"])
def test_im2pc_refuses_a_tau_outside_the_depths(tau):
    with pytest.raises(InputError, match="tau"):
        im2pc(_image(), R0, B0, LEN, L, tau=tau)


@pytest.mark.parametrize("points", [[1.0, 2.0, 3.0, 4.0], np.zeros((2, 6)), np.zeros((0, 2))])
def test_pc2im_refuses_points_that_are_not_xyz(points):
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        pc2im(points, R0, B0, LEN, L)


def test_pc2im_takes_one_point_and_nothing_as_before():
    assert pc2im(_points()[0], R0, B0, LEN, L)[1].n_pixels == 1
    assert pc2im([], R0, B0, LEN, L)[1].n_points == 0


@pytest.mark.parametrize("n", [-1, 2.0, "3"])
def test_pc2im_refuses_a_bad_n_samples(n):
    with pytest.raises(InputError, match="n_samples"):
        pc2im(np.zeros((0, 3)), R0, B0, LEN, L, sample=[], n_samples=n)


def test_norm_refuses_a_q_of_another_batch_and_an_empty_image():
    with pytest.raises(InputError, match=r"batch shape \(2,\), got shape \(3,\)"):
        norm(np.zeros((2, 64, 256)), [1.0, 2.0, 3.0])
    for shape in [(0, 0), (64, 0), (2, 0, 256)]:
        with pytest.raises(InputError, match="H, W >= 1"):
            norm(np.zeros(shape), 1.5)
    assert norm(np.zeros((0, 64, 256)), 1.5).shape == (0, 64, 256)  # no image: still fine


# --- metrics --------------------------------------------------------------------------------
def test_jsd_bins_are_bounded_where_the_cell_index_fits_int64():
    a, b = np.zeros((4, 3)), np.ones((4, 3))
    c = 2**21  # the largest: c^3 = 2^63, the flat cell index (x c + y) c + z still fits int64
    assert jsd(a, b, bins=c) == 1.0
    with pytest.raises(InputError, match=r"bins = 2097153 is too many; accepted: "
                                         r"1 \.\. 2097152 .*int64"):
        jsd(a, b, bins=c + 1)  # the index would wrap and cells collide (JSD 0 at 2^22)


@pytest.mark.parametrize("seed", [-1, None, 1.5, True])
@pytest.mark.parametrize("metric", [mmd, jsd])
def test_metric_seed_is_a_whole_number_at_least_0(metric, seed):
    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        metric(np.ones((5, 3)), np.zeros((5, 3)), max_points=2, seed=seed)


# --- LidarParams: what is checked is what is kept --------------------------------------------
@pytest.mark.parametrize("kwargs, words", [
    ({"width": 256.9}, "width .* got 256.9"),  # int() made it 256
    ({"width": 3.7}, "width .* got 3.7"),  # named as 3 before
    ({"height": "64"}, "height .* got '64'"),
    ({"height": True}, "height .* got True"),
    ({"r_alpha_deg": "0.004"}, "r_alpha_deg must be a number"),
])
def test_lidar_from_degrees_takes_whole_numbers_as_given(kwargs, words):
    with pytest.raises(InputError, match=words):
        LidarParams.from_degrees(**kwargs)


def test_lidar_keeps_the_numbers_it_checked():
    with pytest.raises(InputError, match="r_alpha must be a number, got '0.0001'"):
        LidarParams(r_alpha="0.0001")
    lidar = LidarParams(r_alpha=np.float32(1e-4), width=np.int64(128))
    assert type(lidar.r_alpha) is float and type(lidar.width) is int
    assert lidar.r_alpha == float(np.float32(1e-4)) and lidar.width == 128


# --- ConditionSpace: ranges within a Condition's, tables of numbers ---------------------------
@pytest.mark.parametrize("field, pair", [
    ("elevation", (-2.0, 2.0)), ("elevation", (0.0, math.pi / 2)),
    ("pitch", (0.0, math.pi / 2 + 1e-9)), ("yaw", (-4.0, 4.0)), ("roll", (-0.1, 3.2)),
])
def test_condition_space_ranges_lie_within_a_conditions(field, pair):
    with pytest.raises(InputError, match=f"the {field} range .* reaches past what a condition"):
        ConditionSpace(**{field: pair})


def test_condition_space_takes_a_conditions_whole_range():
    s = ConditionSpace(elevation=(-math.nextafter(math.pi / 2, 0), math.nextafter(math.pi / 2, 0)),
                       pitch=(-90 * DEG, 90 * DEG), yaw=(-180 * DEG, 180 * DEG),
                       roll=(-180 * DEG, 180 * DEG))
    row = [[0, 4500.0, 89.99 * DEG, 90 * DEG, 180 * DEG, -180 * DEG]]
    assert s.check(row).shape == (1, 6)
    Condition.from_array(row[0])


@pytest.mark.parametrize("kwargs, words", [
    ({"drone_types": (1.5,)}, "drone_types .* integers"),
    ({"n_types": 2.5}, "n_types must be an integer"),
    ({"n_types": "5"}, "n_types must be an integer"),
])
def test_condition_space_counts_are_integers(kwargs, words):
    with pytest.raises(InputError, match=words):
        ConditionSpace(**kwargs)


def test_condition_space_from_dict_names_an_unknown_key():
    with pytest.raises(InputError, match="unknown condition space key.*'foo'.*accepted: n_types"):
        ConditionSpace.from_dict({"foo": 1})
    s = ConditionSpace()
    assert ConditionSpace.from_dict(s.to_dict()) == s


def test_condition_space_check_and_decode_refuse_by_name():
    s = ConditionSpace()
    with pytest.raises(InputError, match="a condition table holds numbers"):
        s.check(np.array([[0, "x", 1, 1, 1, 1]], object))
    with pytest.raises(InputError, match=r"shape \(N, 6\).*\(2, 1, 6\)"):
        s.decode(np.zeros((2, 1, 6)))
    with pytest.raises(InputError, match="a condition row holds numbers"):
        Condition.from_array([0, "far", 0, 0, 0, 0])


# --- frames -----------------------------------------------------------------------------------
@pytest.mark.parametrize("xyz", [[1.0, 2.0], np.zeros((5, 4)), 1.0])
def test_cartesian_to_spherical_needs_xyz(xyz):
    with pytest.raises(InputError, match="x, y, z"):
        cartesian_to_spherical(xyz)


def test_pose_from_lidar_local_refuses_what_has_no_pose():
    m = np.eye(4)
    m[:3, 3] = [0, 300, 4500]
    m[:3, :3] = 0  # zero scale: NaN pitch, yaw and roll before
    with pytest.raises(InputError, match="zero scale"):
        pose_from_lidar_local(m)
    with pytest.raises(InputError, match="on the lidar"):
        pose_from_lidar_local(np.eye(4))
    with pytest.raises(InputError, match="4 x 4"):
        pose_from_lidar_local(np.eye(3))
    pose = pose_from_lidar_local(target_matrix_lidar_local(4500.0, B0, 0.1, 0.2, 0.3) * 1.0)
    assert pose["yaw"] == pytest.approx(0.2)


# --- a model's type keys and seed -----------------------------------------------------------
@pytest.fixture(scope="module")
def model():
    from apcg_core.families.base import ModelTypes
    return ModelTypes()  # the default model's types and space: no network is loaded


@pytest.mark.parametrize("key", [True, False, "²", "５", "٣", np.bool_(True)])
def test_type_key_is_read_as_the_catalog_reads_it(model, key):
    with pytest.raises(InputError):
        model.type_name(key)


@pytest.mark.parametrize("key", [5, np.int64(5), "5", " 5 ", "+5"])
def test_a_catalog_index_names_the_catalogs_type(model, key):
    from apcg_core.catalog.catalog import default_catalog
    assert model.type_name(key) == default_catalog().get(key).name == default_catalog().get(
        5).name


@pytest.fixture(scope="module")
def cgan():
    pytest.importorskip("onnxruntime")
    from apcg_core.families import load_model
    from apcg_core.families.base import DEFAULT_MODEL_DIR
    return load_model(DEFAULT_MODEL_DIR.parent / "cgan")


@pytest.mark.parametrize("seed", [-1, None, 2.5])
def test_cgan_seed_is_a_whole_number_at_least_0(cgan, seed):
    cond = cgan.condition("A320neo", 4500.0, 3.4 * DEG, 2 * DEG)
    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        cgan.generate(cond, 1, seed)  # None drew unseeded noise: a different cloud each call
    assert len(cgan.generate(cond, 1, np.uint32(2**32 - 1)).table) == 1  # a block's seed


def test_a_range_within_rounding_below_3_km_is_3_kms():
    """The condition space takes 2999.9999999999995 m as within [3000, 18000] (its slack
    absorbs rounding); its reference range must then be 3 km's, not 0.1 km's: the cGAN drew
    1 point for 751 there (q = 30; probe, stop 54). Well below 3 km the paper's rule holds."""
    from apcg_core.condition import ConditionSpace, in_range, scale_ratio
    from apcg_core.families import load_model
    from apcg_core.families.base import DEFAULT_MODEL_DIR
    hair = 2999.9999999999995
    assert in_range(hair, 3000.0, 18000.0) and not in_range(2999.99, 3000.0, 18000.0)
    assert scale_ratio(hair) == pytest.approx(1.0, abs=1e-12)
    assert scale_ratio(2999.0) == pytest.approx(29.99)
    ConditionSpace().check(np.array([[0, hair, 3.5 * DEG, 2 * DEG, 0.0, 0.0]]))
    cgan = load_model(DEFAULT_MODEL_DIR.parent / "cgan")
    n = [len(cgan.generate(cgan.condition("A320neo", r, 3.5 * DEG, 2 * DEG), 1, 0).cloud)
         for r in (3000.0, hair)]
    assert n[0] > 300 and abs(n[0] - n[1]) <= max(3, n[0] // 100), n


def test_the_band_warning_takes_what_the_model_takes():
    """simulate's range-band warning agrees with a model's condition space at the bounds and
    shows a value past them apart from the bound (it said '3000 m lies outside it')."""
    from apcg_core.catalog import default_catalog
    from apcg_core.plausibility import range_band_warning
    t = default_catalog().get("A320neo")
    assert range_band_warning(t, 2999.9999999999995) is None
    assert range_band_warning(t, 18000.000000000004) is None
    said = range_band_warning(t, 2999.99)
    assert said and "2999.99 m lies outside it" in said
