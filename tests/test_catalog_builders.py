"""The catalog builders are driven by data: the tables of apcg_core.catalog.parts and each
type's facts, never a type's name or a search of its free text."""

import ast
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog import Catalog, Mesh, builders, parts
from apcg_core.catalog.builders import build
from apcg_core.errors import InputError

CAT = Catalog(include_user=False)
SOURCE = Path(builders.__file__).read_text(encoding="utf-8")
FIXED_WING = [t for t in CAT if parts.BUILDER.get(t.category) == "fixed_wing"]
# free-text columns of types.csv: builders may use them only as keys into a table
FREE_TEXT = {"name", "manufacturer", "dims_note", "propulsion", "engine_placement",
             "wing_position", "tail_type", "sweep_ref", "confidence"}
# words of type names that are ordinary English and may appear in any comment
GENERIC_WORDS = {"twin", "star", "super", "grand", "black", "king", "dash", "fighting"}


def _name_words():
    """Distinctive words and designations of the built-in type names ("reaper", "f-16c" and
    its stem "f-16")."""
    words = set()
    for t in CAT:
        for w in re.findall(r"[a-z0-9][a-z0-9/-]*[a-z0-9]", t.name.lower()):
            has_digit = any(c.isdigit() for c in w)
            has_letter = any(c.isalpha() for c in w)
            if has_digit and has_letter:
                words.add(w)
                stem = w.rstrip("abcdefghijklmnopqrstuvwxyz")
                if any(c.isalpha() for c in stem) and len(stem) >= 3:
                    words.add(stem)
            elif has_letter and len(w) >= 4 and w not in GENERIC_WORDS:
                words.add(w)
    return words


def test_builders_source_names_no_type():
    src = SOURCE.lower()
    for t in CAT:
        assert t.name.lower() not in src, t.name
    found = sorted(w for w in _name_words()
                   if re.search(r"(?<![a-z0-9-])" + re.escape(w) + r"(?![a-z0-9])", src))
    assert not found, f"builders.py names types: {found}"
    assert not re.search(r"\bin\s+(t\.)?name\b", SOURCE)
    assert not re.search(r"^import re\b|^from re\b", SOURCE, re.M)
    for call in (".lower(", ".upper(", ".startswith(", ".endswith(", ".find(", ".index("):
        assert call not in SOURCE, call


def _free_text_attribute(node) -> bool:
    return isinstance(node, ast.Attribute) and node.attr in FREE_TEXT


def test_builders_never_search_or_compare_free_text():
    """No `"phrase" in text` tests at all, and no comparison involving a free-text field (the
    exact sweep_ref code "c/4" is the one comparison a numeric fact needs)."""
    for node in ast.walk(ast.parse(SOURCE)):
        if not isinstance(node, ast.Compare):
            continue
        line = ast.get_source_segment(SOURCE, node)
        searches = any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops)
        assert not (searches and isinstance(node.left, ast.Constant)
                    and isinstance(node.left.value, str)), line
        operands = [node.left, *node.comparators]
        if any(_free_text_attribute(o) for o in operands):
            assert line == 't.sweep_ref == "c/4"', line


def test_every_category_and_phrase_has_a_table_entry():
    for t in CAT:
        assert t.category in parts.BUILDER, t.category
    assert set(parts.CATEGORY) == {c for c, b in parts.BUILDER.items() if b == "fixed_wing"}
    for t in FIXED_WING:
        assert t.wing_position in parts.WING_POSITIONS, (t.name, t.wing_position)
        assert t.tail_type in parts.TAIL_TYPES, (t.name, t.tail_type)
        assert t.engine_placement in parts.ENGINE_PLACEMENTS, (t.name, t.engine_placement)
        assert t.propulsion in parts.PROPELLER_DRIVEN, (t.name, t.propulsion)
        assert parts.TAIL_TYPES[t.tail_type].style in builders.TAIL_PARTS
    for t in CAT:
        if t.category == "helicopter":
            assert parts.TAIL_TYPES[t.tail_type].style in builders.ANTI_TORQUE, t.name


def test_tables_refer_only_to_known_keys():
    for p in parts.CATEGORY.values():
        assert p.profile in parts.PROFILES
    for pos in parts.WING_POSITIONS.values():
        assert pos.mount in parts.MOUNTS and pos.planform in parts.PLANFORMS
    for plan in parts.PLANFORMS.values():
        assert plan.profile is None or plan.profile in parts.PROFILES
    for tail in parts.TAIL_TYPES.values():
        assert tail.tailplane in builders.TAILPLANE_PLACES
        assert tail.fins in (1, 2)
    for engines in parts.ENGINE_PLACEMENTS.values():
        assert engines.groups <= set(builders.ENGINE_PARTS)
    assert set(parts.TYPE_OVERRIDES) <= set(CAT.names())


def test_overrides_carry_what_the_dims_notes_say():
    for t in CAT:
        override = parts.TYPE_OVERRIDES.get(t.name, {})
        if t.category == "helicopter":
            assert override.get("skids", False) == ("skid" in t.dims_note), t.name
        if t.category == "multirotor_drone":
            assert (override.get("dims_include_rotors", False)
                    == ("with propellers" in t.dims_note)), t.name


@pytest.mark.parametrize("t", list(CAT), ids=lambda t: t.name)
def test_every_type_builds_closed_and_fitted(t):
    b = build(t)
    r = b.mesh.report()
    assert r.watertight and r.winding_consistent and r.n_degenerate == 0 and r.volume > 0
    ref = Mesh(b.mesh.vertices, b.mesh.faces[~b.rotor_faces]) if b.fitted_without_rotors \
        else b.mesh
    ext = np.ptp(ref.vertices[np.unique(ref.faces)], axis=0)
    np.testing.assert_allclose(ext, [t.length_m, t.span_m, t.height_m], rtol=0.03)
    assert ((b.fit_scale > 0.7) & (b.fit_scale < 1.3)).all(), b.fit_scale


def _same_mesh(a, b) -> bool:
    return np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(
        a.mesh.faces, b.mesh.faces)


def test_a_name_matters_only_through_the_override_table(monkeypatch):
    for key in ("A320neo", "C-130J Hercules", "Rafale C", "AW139", "Alta 8"):
        t = CAT.get(key)
        assert _same_mesh(build(t), build(replace(t, name="Renamed")))
    hawk = CAT.get("RQ-4B Global Hawk")
    renamed = replace(hawk, name="Renamed")
    assert not _same_mesh(build(hawk), build(renamed))  # its override no longer applies
    monkeypatch.setitem(parts.TYPE_OVERRIDES, "Renamed", parts.TYPE_OVERRIDES[hawk.name])
    assert _same_mesh(build(hawk), build(renamed))


def test_phrases_and_tables_drive_the_parts(monkeypatch):
    t = CAT.get("A320neo")
    base = build(t)
    # a phrase with the same meaning draws the same; one with another meaning does not
    assert _same_mesh(base, build(replace(t, tail_type="conventional (stabilator)")))
    t_tail = build(replace(t, tail_type="T-tail"))
    assert not _same_mesh(base, t_tail)
    v = t_tail.mesh.vertices
    top = v[v[:, 2] > v[:, 2].max() - 0.02 * t.height_m]
    assert np.ptp(top[:, 1]) > 0.2 * t.span_m  # the tailplane now spans the top of the fin
    # the category table sets the proportions
    wide = replace(parts.CATEGORY[t.category], nacelle=0.08)
    monkeypatch.setitem(parts.CATEGORY, t.category, wide)
    assert not _same_mesh(base, build(t))


@pytest.mark.parametrize("column, value, accepted", [
    ("category", "zeppelin", "'fighter'"),
    ("wing_position", "parasol", "'high (strut-braced)'"),
    ("tail_type", "ring tail", "'T-tail'"),
    ("engine_placement", "wingtip pods", "'underwing pylons'"),
    ("propulsion", "rocket", "'turbofan'"),
])
def test_unknown_category_or_phrase_is_refused_by_name(column, value, accepted):
    t = replace(CAT.get("A320neo"), **{column: value})
    with pytest.raises(InputError, match=re.escape(repr(value))) as err:
        build(t)
    assert "A320neo" in str(err.value) and accepted in str(err.value)


def test_a_layout_the_builder_cannot_draw_is_refused(monkeypatch):
    t = CAT.get("A320neo")
    with pytest.raises(InputError, match="tail style 'fenestron'.*accepted: 'none'"):
        build(replace(t, tail_type="fenestron + horizontal stabiliser"))
    with pytest.raises(InputError, match="helicopter tail style 'fins'"):
        build(replace(CAT.get("H135"), tail_type="T-tail"))
    monkeypatch.setitem(parts.TYPE_OVERRIDES, "A320neo", {"wingspan": 40.0})
    with pytest.raises(InputError, match="sets wingspan.*accepted: .*aspect"):
        build(t)
    monkeypatch.setitem(parts.ENGINE_PLACEMENTS, "rocket pack", parts.Engines(
        frozenset({"ventral_rocket"})))
    monkeypatch.delitem(parts.TYPE_OVERRIDES, "A320neo")
    with pytest.raises(InputError, match="engine group 'ventral_rocket'"):
        build(replace(t, engine_placement="rocket pack"))
