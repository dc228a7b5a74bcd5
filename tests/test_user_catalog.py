"""The user's catalog as a small database: changes from several processes at once are never
lost (a lock and an atomic replace of the registry), names are one name whatever their case,
spaces, dashes or underscores, and a damaged registry is named with the fix."""

import json
import os
import subprocess
import sys
import time
import unicodedata
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog import Catalog, Mesh
from apcg_core.catalog.catalog import LAST_INDEX, REGISTRY, mesh_file_stem, name_key
from apcg_core.errors import InputError

APCG = str(Path(sys.executable).parent / "apcg")


def _box(length=10.0, span=8.0, height=2.0) -> Mesh:
    v = np.array([[x, y, z] for x in (0, length) for y in (0, span) for z in (0, height)], float)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7],
         [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return Mesh(v - v.mean(axis=0), f)


@pytest.fixture
def box_obj(tmp_path) -> Path:
    m = _box()
    p = tmp_path / "box.obj"
    p.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in m.vertices)
                 + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in m.faces))
    return p


def _env(tmp_path) -> dict:
    return {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}


def _apcg(*args, env, timeout=300):
    return subprocess.run([APCG, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


def _user_names(env) -> list[str]:
    out = _apcg("catalog", "list", "--json", env=env)
    assert out.returncode == 0, out.stderr
    return [r["name"] for r in json.loads(out.stdout) if r["index"] >= 1000]


# --- several processes at once ----------------------------------------------------------

WORKER = r"""
import sys, time
from pathlib import Path
import numpy as np
from apcg_core.catalog import Catalog, Mesh
user, me, n, go = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), Path(sys.argv[4])
v = np.array([[x, y, z] for x in (-5, 5) for y in (-4, 4) for z in (-1, 1)], float)
f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
     [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
while not go.exists():  # every process starts its changes at the same moment
    time.sleep(0.005)
for i in range(n):
    Catalog(user_path=user).add_user_type(f"{me}-{i}", Mesh(v * (1 + i / 10), f), "aircraft",
                                          "user", "w")
for i in range(0, n, 2):  # and removes every other one again
    Catalog(user_path=user).remove_user_type(f"{me}-{i}")
"""


def test_concurrent_adds_and_removes_from_several_processes_lose_nothing(tmp_path):
    user, go = tmp_path / "cat", tmp_path / "go"
    n, workers = 6, 5
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(user), f"w{k}", str(n),
                               str(go)], stderr=subprocess.PIPE, text=True)
             for k in range(workers)]
    time.sleep(1.0)  # let them all import and wait at the gate
    go.touch()
    for p in procs:
        assert p.wait(timeout=300) == 0, p.stderr.read()
    cat = Catalog(user_path=user)
    want = {f"w{k}-{i}" for k in range(workers) for i in range(1, n, 2)}
    got = [t.name for t in cat if t.source != "builtin"]
    assert sorted(got) == sorted(want)  # every add kept, every remove done, nothing twice
    assert len({t.index for t in cat}) == len(cat)  # no index given twice
    for name in want:  # each one's own mesh
        i = int(name.split("-")[1])
        assert cat.mesh(name).extents[0] == pytest.approx(10 * (1 + i / 10))
    left = sorted(p.name for p in user.iterdir())
    assert left == sorted([REGISTRY, LAST_INDEX] + [f"{mesh_file_stem(w)}.npz" for w in want])
    # 30 adds, each its own index, none given twice even where the type was removed
    assert int((user / LAST_INDEX).read_text()) == 1000 + n * workers - 1


def test_concurrent_catalog_add_commands_all_stay(tmp_path, box_obj):
    """The issue's case: several `apcg catalog add` at once all print "added", and all are
    listed afterwards."""
    env = _env(tmp_path)
    names = [f"jet {k}" for k in range(4)]
    procs = [subprocess.Popen([APCG, "catalog", "add", str(box_obj), "--name", n],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for n in names]
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0 and "added" in out, err
    assert sorted(_user_names(env)) == names


def test_a_lock_left_by_a_killed_process_does_not_block(tmp_path):
    user = tmp_path / "cat"
    user.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    import socket
    (user / ".lock").write_text(f"{dead} {socket.gethostname()}\n")
    t = Catalog(user_path=user).add_user_type("after a crash", _box(), "aircraft", "user", "x")
    assert t.index == 1000 and not (user / ".lock").exists()


# --- one name, one type, one file ---------------------------------------------------------

@pytest.mark.parametrize("second", ["Jet_A", "jet-a", "JET A", " jet  a ", "Jet\u2013A",
                                    "jet_-a"])
def test_names_differing_in_case_or_separators_are_one_name(tmp_path, second):
    cat = Catalog(user_path=tmp_path)
    first = cat.add_user_type("Jet A", _box(), "aircraft", "user", "x")
    with pytest.raises(InputError, match=r"a type named 'Jet A' already exists.*--force"):
        cat.add_user_type(second, _box(20.0), "aircraft", "user", "y")
    assert Catalog(user_path=tmp_path).mesh("Jet A").extents[0] == pytest.approx(10.0)
    # --force replaces it explicitly: the same index, the new name and mesh, one file
    t = cat.add_user_type(second, _box(20.0), "aircraft", "user", "y", force=True)
    assert t.index == first.index and cat.last_replaced.name == "Jet A"
    again = Catalog(user_path=tmp_path)
    assert [u.name for u in again if u.source != "builtin"] == [second.strip()]
    assert again.mesh("Jet A").extents[0] == pytest.approx(20.0)  # found by either spelling
    assert len(list(tmp_path.glob("*.npz"))) == 1


def test_a_builtin_name_in_another_spelling_is_refused_even_with_force(tmp_path):
    cat = Catalog(user_path=tmp_path)
    for name in ("a320-NEO", "Mavic_3", "mavic3"):
        with pytest.raises(InputError, match="built-in type named"):
            cat.add_user_type(name, _box(), "aircraft", "user", "x", force=True)


def test_names_are_normalised_once_nfc_and_outer_spaces(tmp_path):
    cat = Catalog(user_path=tmp_path)
    decomposed = unicodedata.normalize("NFD", "  Café jet\t")
    t = cat.add_user_type(decomposed, _box(), "aircraft", "user", "x")
    assert t.name == "Café jet" and unicodedata.is_normalized("NFC", t.name)
    again = Catalog(user_path=tmp_path)
    for key in ("Café jet", unicodedata.normalize("NFD", "café JET"), " cafe\u0301_jet "):
        assert again.get(key).index == 1000
    assert json.loads((tmp_path / REGISTRY).read_text())[0]["name"] == "Café jet"
    with pytest.raises(InputError, match="already exists"):
        again.add_user_type("CAFÉ-JET", _box(), "aircraft", "user", "x")


def test_name_keys_and_file_names():
    assert name_key("Jet_A") == name_key("Jet A") == name_key("jet-a") == "jeta"
    assert name_key("A-320") != name_key("A.320")  # a point is not a separator
    assert mesh_file_stem("Jet A") == "jeta"
    odd = [mesh_file_stem(n) for n in ("a?b", "a*b", "a:b", "☃")]
    assert len(set(odd)) == 4 and all("/" not in s and "?" not in s for s in odd)
    for bad in ("", "   ", "-_-", "123", "a/b", "a\\b", "tab\x07"):
        with pytest.raises(InputError, match="not accepted"):
            Catalog(include_user=False).check_new_type(bad, "aircraft")


def test_outer_spaces_on_the_command_line_are_stored_stripped_and_found(tmp_path, box_obj):
    env = _env(tmp_path)
    add = _apcg("catalog", "add", box_obj, "--name", "  Spacey Jet  ", env=env)
    assert add.returncode == 0 and "added 'Spacey Jet'" in add.stdout, add.stderr
    assert _user_names(env) == ["Spacey Jet"]
    for i, key in enumerate(("Spacey Jet", "spacey-jet", "  SPACEY JET ")):
        out = tmp_path / f"c{i}.ply"
        c = _apcg("simulate", "--type", key, "--range-m", "2000", "--elevation-deg", "3",
                  "--pitch-deg", "1", "-o", out, env=env)
        assert c.returncode == 0 and b"Spacey Jet" in out.read_bytes(), c.stderr
    same = _apcg("catalog", "add", box_obj, "--name", "spacey_jet", env=env)
    assert same.returncode == 2 and "'Spacey Jet' already exists" in same.stderr
    assert "Traceback" not in same.stderr
    forced = _apcg("catalog", "add", box_obj, "--name", "spacey_jet", "--force", env=env)
    assert forced.returncode == 0 and "replaced 'Spacey Jet' by 'spacey_jet'" in forced.stdout
    assert _user_names(env) == ["spacey_jet"]
    rm = _apcg("catalog", "remove", "SPACEY JET", env=env)
    assert rm.returncode == 0 and _user_names(env) == []
    assert not list((tmp_path / "data" / "catalog").glob("*.npz"))
    for name, words in (("A320neo", "built-in"), ("nothing", "no user type named")):
        r = _apcg("catalog", "remove", name, env=env)
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr


# --- a damaged registry --------------------------------------------------------------------

def _good_registry(tmp_path) -> Path:
    cat = Catalog(user_path=tmp_path / "data" / "catalog")
    cat.add_user_type("Jet A", _box(), "aircraft", "user", "x")
    cat.add_user_type("Jet B", _box(), "aircraft", "user", "x")
    return tmp_path / "data" / "catalog" / REGISTRY


def _entries(reg: Path) -> list:
    return json.loads(reg.read_text())


DAMAGES = {
    "not JSON": lambda r: b"{broken",
    "cut short": lambda r: r.read_bytes()[: len(r.read_bytes()) // 2],
    "empty": lambda r: b"",
    "binary": lambda r: b"\x00\xff\xfe" * 20,
    "an object": lambda r: b'{"name": "Jet A"}',
    "a field missing": lambda r: json.dumps(
        [{k: v for k, v in e.items() if k != "length_m"} for e in _entries(r)]).encode(),
    "a bad kind": lambda r: json.dumps(
        [{**e, "kind": "blimp"} for e in _entries(r)]).encode(),
    "a length as text": lambda r: json.dumps(
        [{**e, "length_m": "ten"} for e in _entries(r)]).encode(),
    "a negative index": lambda r: json.dumps(
        [{**e, "index": -1} for e in _entries(r)]).encode(),
    "two of one name": lambda r: json.dumps(
        [{**e, "name": "jet a" if i else "Jet_A"} for i, e in enumerate(_entries(r))]).encode(),
    "an index twice": lambda r: json.dumps(
        [{**e, "index": 1000} for e in _entries(r)]).encode(),
    "an unknown field": lambda r: json.dumps(
        [{**e, "colour": "red"} for e in _entries(r)]).encode(),
    "an entry not an object": lambda r: b'[1, 2]',
}


@pytest.mark.parametrize("how", sorted(DAMAGES))
def test_a_damaged_registry_is_named_with_the_fix(tmp_path, how):
    reg = _good_registry(tmp_path)
    reg.write_bytes(DAMAGES[how](reg))
    with pytest.raises(InputError) as exc:
        Catalog(user_path=reg.parent)
    message = str(exc.value)
    assert "\n" not in message and str(reg) in message and "damaged" in message
    assert "mv " in message and "apcg catalog add" in message  # what to do


def test_a_damaged_registry_on_the_command_line_is_one_line_not_a_traceback(tmp_path):
    reg = _good_registry(tmp_path)
    before = [e for e in _entries(reg)]
    reg.write_text(json.dumps([{k: v for k, v in e.items() if k != "kind"} for e in before]))
    damaged = reg.read_bytes()
    env = _env(tmp_path)
    for argv in (["catalog", "list"], ["catalog", "add", reg, "--name", "x", "--dry-run"],
                 ["catalog", "remove", "Jet A"]):
        r = _apcg(*argv, env=env)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "entry 1 ('Jet A') has no kind" in lines[0], r.stderr
    assert reg.read_bytes() == damaged  # the user's file is never rewritten by a refusal


def test_a_missing_or_damaged_mesh_file_is_named(tmp_path):
    reg = _good_registry(tmp_path)
    (reg.parent / "jeta.npz").unlink()
    (reg.parent / "jetb.npz").write_bytes(b"PK\x03\x04 not a zip")
    cat = Catalog(user_path=reg.parent)
    with pytest.raises(InputError, match=r"mesh of user type 'Jet A' .*jeta.npz\) is missing; "
                                         "add the type again"):
        cat.mesh("Jet A")
    with pytest.raises(InputError, match=r"mesh of user type 'Jet B' .*is damaged"):
        cat.mesh("Jet B")


def test_a_catalog_written_before_name_keys_still_reads(tmp_path):
    """Older catalogs kept a mesh under its name made safe ("Jet A" -> Jet_A.npz)."""
    reg = _good_registry(tmp_path)
    os.replace(reg.parent / "jeta.npz", reg.parent / "Jet_A.npz")
    assert Catalog(user_path=reg.parent).mesh("Jet A").extents[0] == pytest.approx(10.0)


@pytest.mark.parametrize("spelling", ["a320 neo", "A320-NEO", " A320_neo ", "a320neo"])
def test_every_command_finds_a_type_by_any_spelling_the_catalog_takes(spelling):
    """The catalog, simulate and teach take "A320-NEO" for A320neo; a model's and a
    dataset's type tables (generate, condition, evaluate) take it too, by one rule
    (typetable.name_key), and an unknown name is answered with the nearest one."""
    from apcg_core.families import ModelTypes
    from apcg_core.typetable import name_key
    model = ModelTypes()
    assert spelling in model.types and model.types.code(spelling) == model.types.code(
        "A320neo")
    assert Catalog().get(spelling).name == "A320neo" == model.type_name(spelling)
    assert name_key(spelling) == name_key("A320neo")
    with pytest.raises(InputError, match=r"did you mean 'A320neo'\?"):
        model.types.code("A320neoo")


# --- names that read as something else, indices never handed out twice ------------------

@pytest.mark.parametrize("name", ["+7", "-5", " 12 ", "٣"])
def test_a_name_that_reads_as_an_index_is_refused(tmp_path, name):
    with pytest.raises(InputError, match="not be a number"):
        Catalog(user_path=tmp_path).add_user_type(name, _box(), "aircraft", "user", "x")


@pytest.mark.parametrize("name", ["A320neo\u200b", "\uff21320neo", "Mavic\u202e 3", "ﬁ-jet\u200d"])
def test_a_lookalike_or_invisible_character_name_is_refused(tmp_path, name):
    with pytest.raises(InputError, match="invisible|built-in type named"):
        Catalog(user_path=tmp_path).add_user_type(name, _box(), "aircraft", "user", "x",
                                                  force=True)
    assert not (tmp_path / REGISTRY).exists()


def test_a_name_of_undecodable_bytes_is_one_line(tmp_path, box_obj):
    name = os.fsdecode(b"Avi\xf3n")  # what argv holds for a Latin-1 name
    out = _apcg("catalog", "add", box_obj, "--name", name, env=_env(tmp_path))
    assert out.returncode == 2 and "not valid UTF-8 text" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr
    weird = tmp_path / os.fsdecode(b"pl\xe9ne.obj")
    weird.write_bytes(box_obj.read_bytes())
    out = _apcg("catalog", "add", weird, "--name", "Plane", env=_env(tmp_path))
    assert out.returncode == 2 and "file name is not UTF-8" in out.stderr, out.stderr


def test_a_removed_types_index_is_never_handed_out_again(tmp_path):
    cat = Catalog(user_path=tmp_path)
    a = cat.add_user_type("Jet A", _box(), "aircraft", "user", "x")
    b = cat.add_user_type("Jet B", _box(), "aircraft", "user", "x")
    cat.remove_user_type("Jet B")
    c = Catalog(user_path=tmp_path).add_user_type("Jet C", _box(), "aircraft", "user", "x")
    assert (a.index, b.index, c.index) == (1000, 1001, 1002)
    for t in ("Jet A", "Jet C"):
        Catalog(user_path=tmp_path).remove_user_type(t)
    assert Catalog(user_path=tmp_path).add_user_type("Jet D", _box(), "aircraft", "user",
                                                     "x").index == 1003
    (tmp_path / "last_index").write_text("lots\n")
    with pytest.raises(InputError, match="last_index is damaged"):
        Catalog(user_path=tmp_path).add_user_type("Jet E", _box(), "aircraft", "user", "x")


def _obj_text(m: Mesh) -> str:
    return ("".join(f"v {a!r} {b!r} {c!r}\n" for a, b, c in m.vertices)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in m.faces))


@pytest.mark.parametrize("offset", [(4.5e5, 5.2e6, 1e3), (-3e6, 2e6, 0.0)])
def test_a_model_stored_far_from_its_files_origin_imports_as_at_the_origin(tmp_path, offset):
    """Georeferenced coordinates (UTM: millions of metres): the origin still lands on the
    volume centroid, no vertex is welded to another, and the mesh is the one at the origin."""
    from apcg_core.catalog import default_catalog
    from apcg_core.catalog.importer import import_model
    plane = default_catalog().mesh("A320neo")
    near, far = tmp_path / "near.obj", tmp_path / "far.obj"
    near.write_text(_obj_text(plane))
    far.write_text(_obj_text(plane.transformed(offset=np.array(offset))))
    m0, r0 = import_model(near)
    m1, r1 = import_model(far)
    assert r1.centre == r0.centre == "volume centroid"
    assert (len(m1.vertices), len(m1.faces)) == (len(m0.vertices), len(m0.faces))
    assert np.abs(m1.vertices - m0.vertices).max() < 1e-6  # metres: no digit lost to the offset
    assert np.abs(m1.centroid).max() < 1e-6


def test_a_closed_body_wound_inward_does_not_move_the_origin(tmp_path):
    from apcg_core.catalog import default_catalog
    from apcg_core.catalog.importer import import_model
    plane = default_catalog().mesh("A320neo")
    pod = _box(6.0, 6.0, 6.0).transformed(offset=np.array([0.0, 14.0, 0.0]))
    good, bad = tmp_path / "good.obj", tmp_path / "bad.obj"
    good.write_text(_obj_text(Mesh.concat([plane, pod])))
    bad.write_text(_obj_text(Mesh.concat([plane, pod.flipped()])))
    m0, r0 = import_model(good)
    m1, r1 = import_model(bad)
    assert f"1 of its {r0.n_bodies} bodies were wound inward" in r1.centre
    assert "inward" not in r0.centre
    assert np.abs(m1.vertices - m0.vertices).max() < 1e-9
    assert m1.volume == pytest.approx(m0.volume, rel=1e-12) and m1.volume > 0


def test_generating_a_user_type_the_model_lacks_points_to_teach(tmp_path, box_obj):
    """A user type in the catalog that the model was not trained on: the refusal says how to
    make a model that knows it, not only the names this one knows (probe finding, stop 54)."""
    env = _env(tmp_path)
    assert _apcg("catalog", "add", box_obj, "--name", "Teach Me", "--length-m", "10",
                 env=env).returncode == 0
    out = _apcg("generate", "--type", "teach me", "--range-m", "5000", "--elevation-deg", "3.5",
                "--pitch-deg", "2", "-o", tmp_path / "x.npz", env=env)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "'Teach Me' is in the catalog but not in this model" in out.stderr
    assert "apcg teach --model" in out.stderr and "--type 'Teach Me'" in out.stderr
    assert not (tmp_path / "x.npz").exists()
    # a name in no catalog gets no such advice
    other = _apcg("generate", "--type", "No Such Jet", "--range-m", "5000", "--elevation-deg",
                  "3.5", "--pitch-deg", "2", "-o", tmp_path / "y.npz", env=env)
    assert other.returncode == 2 and "apcg teach" not in other.stderr
