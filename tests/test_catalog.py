import collections
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from apcg_core.catalog import Catalog, Mesh, sample_surface
from apcg_core.catalog.builders import build
from apcg_core.catalog.shapes import box
from apcg_core.errors import InputError

CAT = Catalog(include_user=False)
BUILT = {t.index: build(t) for t in CAT}
LOCK = Path(__file__).with_name("data") / "catalog_index.csv"
APCG = str(Path(sys.executable).parent / "apcg")


def test_catalog_size_and_categories():
    kinds = collections.Counter(t.kind for t in CAT)
    assert kinds["aircraft"] >= 76 and kinds["drone"] >= 4
    cats = {t.category for t in CAT if t.kind == "aircraft"}
    for c in ("airliner_narrowbody", "airliner_widebody", "regional_jet", "turboprop",
              "business_jet", "light_GA", "fighter", "military_transport", "helicopter"):
        assert c in cats
    drone_cats = {t.category for t in CAT if t.kind == "drone"}
    assert drone_cats == {"multirotor_drone", "fixed_wing_drone"}


def test_indices_are_stable():
    # every locked (index, name) pair must still hold; new types may only be appended
    for line in LOCK.read_text().splitlines():
        i, name = line.split(",", 1)
        assert CAT.get(int(i)).name == name
    assert [t.index for t in CAT] == list(range(len(CAT)))


@pytest.mark.parametrize("t", list(CAT), ids=lambda t: t.name)
def test_builtin_mesh_is_clean_and_true_to_size(t):
    b = BUILT[t.index]
    m = b.mesh
    r = m.report()
    assert r.watertight and r.winding_consistent
    assert r.n_degenerate == 0 and r.volume > 0
    tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    # listed extents within 3 %; drone dimensions listed without propellers are checked on
    # the airframe alone
    excl = b.fitted_without_rotors
    assert excl == (t.category == "multirotor_drone" and "with prop" not in t.dims_note)
    ref = Mesh(m.vertices, m.faces[~b.rotor_faces]) if excl else m
    ext = ref.vertices[np.unique(ref.faces)].ptp(axis=0)
    np.testing.assert_allclose(ext, [t.length_m, t.span_m, t.height_m], rtol=0.03)
    # the parametric design was already close: the fit never stretches an axis by > 30 %
    assert ((b.fit_scale > 0.7) & (b.fit_scale < 1.3)).all(), b.fit_scale
    # origin at the centre of mass
    assert np.abs(m.centroid).max() < 1e-9 * t.length_m


FIXED_WING = [t for t in CAT if t.category in ("airliner_narrowbody", "airliner_widebody",
                                               "regional_jet", "business_jet",
                                               "military_transport", "turboprop")]


@pytest.mark.parametrize("t", FIXED_WING, ids=lambda t: t.name)
def test_body_frame_nose_forward_fin_up(t):
    v = CAT.mesh(t).vertices
    nose = v[v[:, 0].argmax()]
    assert abs(nose[1]) < 0.05 * t.span_m  # the most forward point is on the centreline
    top = v[v[:, 2] > v[:, 2].max() - 0.02 * t.height_m]
    assert top[:, 0].mean() < -0.25 * t.length_m  # the fin tip is aft and on top
    assert abs(v[:, 1].max() + v[:, 1].min()) < 0.01 * t.span_m  # left/right symmetric


def test_builds_are_deterministic_and_cached():
    t = CAT.get("C-130J Hercules")
    a, b = build(t).mesh, build(t).mesh
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert CAT.mesh(t) is CAT.mesh(t.index)


def test_depth_length():
    assert CAT.depth_length_m("A320neo") == 37.57
    t = CAT.get("Matrice 300 RTK")
    ext = CAT.mesh(t).extents
    assert CAT.depth_length_m(t) == pytest.approx(max(ext[:2]))
    assert CAT.depth_length_m(t) > t.length_m  # propeller discs reach past the listed body


def test_lookup_errors():
    with pytest.raises(InputError, match="did you mean A380-800"):
        CAT.get("A380")
    with pytest.raises(InputError, match="unknown type index 5000"):
        CAT.get(5000)
    assert CAT.get("a320NEO").index == CAT.get(3).index == 3


def test_condition_space_uses_near_band_for_small_drones():
    space = CAT.condition_space()
    assert space.n_types == len(CAT)
    near = {CAT.types[i].name for i in space.drone_types}
    assert "Matrice 300 RTK" in near and "Alta 8" in near
    assert "MQ-9A Reaper" not in near and "A320neo" not in near


def test_fine_cloud_is_seeded_on_surface_and_area_weighted():
    p = CAT.fine_cloud("A320neo", seed=1)
    assert p.shape == (10_000, 3)
    np.testing.assert_array_equal(p, CAT.fine_cloud("A320neo", seed=1))
    assert not np.array_equal(p, CAT.fine_cloud("A320neo", seed=2))
    m = CAT.mesh("A320neo")
    pts, face = sample_surface(m, 2000, seed=3, return_faces=True)
    a, b, c = (m.vertices[m.faces[face, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    # on its triangle's plane, with barycentric coordinates inside [0, 1]
    unit = n / np.linalg.norm(n, axis=1)[:, None]
    assert np.abs(np.einsum("ij,ij->i", pts - a, unit)).max() < 1e-9
    area = np.linalg.norm(n, axis=1)
    w1 = np.linalg.norm(np.cross(pts - a, c - a), axis=1) / area
    w2 = np.linalg.norm(np.cross(b - a, pts - a), axis=1) / area
    assert (w1 >= -1e-9).all() and (w2 >= -1e-9).all() and (w1 + w2 <= 1 + 1e-9).all()
    # a 1 x 1 x 10 box: the four long faces hold 40 of 42 area units
    b = box([0, 0, 0], [1, 1, 10])
    q = sample_surface(b, 42_000, seed=0)
    on_long = (np.abs(np.abs(q[:, 0]) - 0.5) < 1e-9) | (np.abs(np.abs(q[:, 1]) - 0.5) < 1e-9)
    assert on_long.mean() == pytest.approx(40 / 42, abs=0.01)


def test_mesh_checks_detect_defects():
    b = box([0, 0, 0], [1, 2, 3])
    assert b.report().watertight
    holed = Mesh(b.vertices, b.faces[1:])
    assert not holed.report().watertight
    flipped_one = Mesh(b.vertices, np.r_[b.faces[:1, ::-1], b.faces[1:]])
    r = flipped_one.report()
    assert r.watertight and not r.winding_consistent
    assert b.flipped().report().volume < 0
    degen = Mesh(np.r_[b.vertices, [[0, 0, 0]] * 1], np.r_[b.faces, [[8, 8, 0]]])
    assert degen.report().n_degenerate == 1
    two = Mesh.concat([b, box([5, 0, 0], [1, 1, 1])])
    assert two.report().n_bodies == 2
