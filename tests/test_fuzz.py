"""The fuzz suite: the command line driven with generated bad values, corrupt files, full disks
and interrupted runs, the way a new user (or a cluster) would hit it.

Every case runs the real ``apcg`` (``apcg_core.cli.main`` in this process, or the installed
script in a subprocess where a signal or a resource limit is part of the case) and gets one of
the outcomes below. A clear error is exit 2 (a refused input) or 1 (the file system said no)
with an ``apcg CMD: error:`` line that names the value or file; handled is exit 0 with a correct
result (warnings allowed), or exit 130 after an interrupt with a resume that finishes the same
result. Anything else fails the test: a traceback (an exception escaping ``main``), a silently
wrong result (exit 0 with a wrong or missing output), data lost (a user's file changed).

``APCG_FUZZ_REPORT=FILE pytest tests/test_fuzz.py`` also writes each case's class and outcome
to FILE (JSON); ``tools/fuzz_table.py FILE`` turns it into the table of docs/ERRORS.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from apcg_core.cli import build_parser, main
from apcg_core.options import RULES

APCG = str(Path(sys.executable).parent / "apcg")
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "apcg_core/models/default"
CGAN_MODEL = Path(__file__).resolve().parents[1] / "apcg_core/models/cgan"
POSE = ["--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3", "--pitch-deg", "2"]


def fuzz(examples: int):
    """Each fuzz test's own number of examples (the CI profile stays derandomized)."""
    return settings(max_examples=examples, deadline=None,
                    suppress_health_check=list(HealthCheck))

TALLY: list[dict] = []


def _own_mesh() -> Path:
    """A real aircraft mesh file to import (the catalog's A320neo as PLY, in metres), made
    once per session: the suite needs nothing outside the repository."""
    import atexit
    import shutil
    import tempfile

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.catalog.importer import export_mesh
    folder = tempfile.mkdtemp(prefix="apcg-fuzz-")
    atexit.register(shutil.rmtree, folder, ignore_errors=True)  # nothing left behind
    path = Path(folder) / "a320neo.ply"
    export_mesh(default_catalog().mesh("A320neo"), path)
    return path


MESH = _own_mesh()


@pytest.fixture(scope="module", autouse=True)
def _report():
    yield
    path = os.environ.get("APCG_FUZZ_REPORT")
    if path:
        Path(path).write_text(json.dumps(TALLY, indent=1))


def _record(kind: str, case: str, outcome: str) -> None:
    TALLY.append({"class": kind, "case": case[:160], "outcome": outcome})


def run(argv: list[str], capsys, cwd: Path | None = None) -> tuple[int, str, str]:
    """``apcg ARGV`` in this process: (exit code, stdout, stderr). An exception escaping
    ``main`` is a traceback: the test fails on it."""
    old = Path.cwd()
    if cwd:
        os.chdir(cwd)
    try:
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's own refusals
            rc = exc.code if isinstance(exc.code, int) else 2
    finally:
        os.chdir(old)
    out = capsys.readouterr()
    return rc, out.out, out.err


def clear_error(kind: str, case: str, rc: int, err: str, *names: str) -> None:
    """A clear refusal: exit 1 or 2, an error line, every one of ``names`` in it."""
    assert "Traceback" not in err, f"{case}: traceback\n{err}"
    assert rc in (1, 2), f"{case}: exit {rc}, expected a refusal\n{err}"
    assert "error:" in err, f"{case}: no error line\n{err}"
    for name in names:
        assert str(name) in err, f"{case}: the message does not name {name!r}\n{err}"
    _record(kind, case, "clear error")


def tree_digest(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


# --- 1. every numeric option of every command --------------------------------------------

def _commands():
    """(command words, parser) for every leaf command."""
    out = []

    def walk(parser, words):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for a in subs:
            for name, sub in a.choices.items():
                walk(sub, words + [name])
        if not subs and words:
            out.append((words, parser))
    walk(build_parser(), [])
    return out


def _placeholder(action, tmp: Path) -> list[str]:
    """A value that passes a required argument's own check, so the fuzzed one is reached."""
    if action.choices:
        return [str(next(iter(action.choices)))]
    if action.type in (int, float):
        return ["3000" if "range" in action.dest else "3"]
    value = {"type": "A320neo", "name": "fuzz-type", "file": str(MESH),
             "names": "A320neo"}.get(action.dest, str(tmp / "nowhere"))
    return [value]


def _required_args(parser, tmp: Path, skip: str) -> list[str]:
    argv, positionals = [], []
    for a in parser._actions:
        if a.dest in (skip, "help") or not (a.required or not a.option_strings):
            continue
        if not a.option_strings:
            positionals += _placeholder(a, tmp)
        else:
            value = _placeholder(a, tmp)
            if a.dest in (parser.get_default("_file_outputs") or ()):
                accepted = (parser.get_default("_output_suffixes") or {}).get(a.dest, (".x",))
                value = [str(tmp / f"out{accepted[0]}")]
            argv += [a.option_strings[-1], *value]
    return positionals + argv


NUMERIC = [(words, parser, a) for words, parser in _commands() for a in parser._actions
           if a.type in (int, float)]


def _bad_values(action):
    rule = RULES[action.dest]
    values = ["nan", "inf", "-inf", "abc", ""]
    if action.type is int:
        values += ["2.5", "1e3"]
    if rule.lo != float("-inf"):
        values += [repr(rule.lo - 1) if action.type is float else str(int(rule.lo) - 1),
                   repr(rule.lo) if rule.lo_open else "nan"]
    if rule.hi != float("inf"):
        values += [repr(rule.hi * 10 + 1) if action.type is float else str(int(rule.hi) + 1)]
    if action.choices:
        values += ["999"]
    return values


@fuzz(200)
@given(st.data())
def test_every_numeric_option_refuses_bad_values_by_name(tmp_path_factory, capsys, data):
    words, parser, action = data.draw(st.sampled_from(NUMERIC), label="option")
    value = data.draw(st.sampled_from(_bad_values(action)), label="value")
    tmp = tmp_path_factory.mktemp("num")
    flag = action.option_strings[-1] if action.option_strings else None
    bad = [f"{flag}={value}"] if flag else [value]
    argv = [*words, *_required_args(parser, tmp, action.dest), *bad]
    if not flag:  # a positional: put it first, where argparse reads it
        argv = [*words, value, *_required_args(parser, tmp, action.dest)]
    rc, _, err = run(argv, capsys, cwd=tmp)
    clear_error("numeric option", " ".join(argv), rc, err, flag or action.dest)
    assert not [p for p in tmp.rglob("*")], f"{argv}: something was written"


# --- 2. names ----------------------------------------------------------------------------

TYPE_TEXT = st.one_of(
    st.text(st.characters(codec="utf-8", exclude_characters="\0"), max_size=12),
    st.integers(0, 200).map(str),  # indices, in range and past the catalog's end
    st.sampled_from(["", " ", "A320neo", " a320NEO ", "Mavic 3", "a/b", "-X", "5.0"]))


@fuzz(40)
@given(name=TYPE_TEXT, command=st.sampled_from(["simulate", "generate", "condition"]))
def test_a_type_name_is_found_or_refused_by_name(tmp_path_factory, capsys, name, command):
    """Every command reads a type the same way: a catalog name (any case, outer spaces
    ignored) or an index; anything else is refused, naming what was given."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.errors import APCGError
    try:
        taken = default_catalog().get(int(name) if name.strip().isdigit() else name)
    except APCGError:
        taken = None
    tmp = tmp_path_factory.mktemp("name")
    in_band = "300" if taken is not None and taken.range_band == "near" else "5000"
    argv = [command, f"--type={name}", "--range-m", in_band, "--elevation-deg", "3",
            "--pitch-deg", "2"]
    if command != "condition":
        argv += ["-o", tmp / "c.ply"]
    rc, out, err = run(argv, capsys, cwd=tmp)
    case = f"{command} --type {name!r}"
    if taken is not None:  # the type the catalog names: the output says it took that one
        assert rc == 0, f"{case}: the catalog knows {taken.name!r}\n{err}"
        assert taken.name in (out if command == "condition" else
                              (tmp / "c.ply").read_bytes().decode("latin-1")), case
        _record("type name", case, "handled")
        return
    assert repr(name) in err or repr(name.strip()) in err or name.strip() in err, err
    clear_error("type name", case, rc, err)
    assert not (tmp / "c.ply").exists()


@fuzz(25)
@given(name=TYPE_TEXT)
def test_a_new_type_name_that_could_be_misread_is_refused(tmp_path_factory, capsys, name):
    """Names a later `--type NAME` could not find as themselves, or that read as another
    (empty, a number in any sign, which `--type` reads as an index, a path separator, a
    control, invisible, unassigned or undecodable character, a taken name in any case or
    spelling of its spaces, dashes and underscores, or once compatibility forms fold: NFKC)
    are refused up front."""
    import re
    import unicodedata

    def key(s):  # the catalog's rule, written out again: NFC, case, separators
        s = unicodedata.normalize("NFC", s).strip().casefold()
        return "".join(c for c in s if not c.isspace()
                       and unicodedata.category(c) not in ("Pd", "Pc"))
    from apcg_core.catalog.catalog import default_catalog
    taken = {key(n) for n in default_catalog().names()}
    clean = unicodedata.normalize("NFC", name).strip()
    misread = (not key(name) or clean.isdigit() or re.fullmatch(r"[+-]?[0-9]+", clean)
               or "/" in name or "\\" in name
               or any(unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn") for c in clean)
               or key(name) in taken or key(unicodedata.normalize("NFKC", clean)) in taken)
    tmp = tmp_path_factory.mktemp("newname")
    rc, out, err = run(["catalog", "add", MESH, f"--name={name}",
                        "--dry-run"], capsys, cwd=tmp)
    if misread:
        clear_error("new type name", f"catalog add --name {name!r}", rc, err, repr(name))
    else:
        assert rc == 0 and "dry run: nothing added" in out, err
        _record("new type name", f"catalog add --name {name!r}", "handled")


def test_a_folder_named_like_a_config_does_not_shadow_it(tmp_path, capsys):
    (tmp_path / "demo").mkdir()
    rc, out, err = run(["dataset", "build", "--config", "demo", "-o", tmp_path / "ds",
                        "--no-progress"], capsys, cwd=tmp_path)
    assert rc == 0 and json.loads(out.splitlines()[-1])["complete"], err
    _record("names", "dataset build --config demo beside a folder demo/", "handled")


# --- 3. configs --------------------------------------------------------------------------

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float) and v != v:
        return "nan"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def toml_text(cfg: dict) -> str:
    top = [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in cfg.items()
           if not isinstance(v, dict)]
    tables = [f"[{json.dumps(k)}]\n" + "\n".join(f"{json.dumps(kk)} = {_toml_value(vv)}"
                                                  for kk, vv in v.items())
              for k, v in cfg.items() if isinstance(v, dict)]
    return "\n".join(top + tables) + "\n"


SCALARS = st.one_of(st.integers(-10**12, 10**12), st.floats(allow_infinity=True),
                    st.booleans(), st.text(max_size=8), st.sampled_from(["all", "grid",
                                                                        "random", "embree"]))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=3))
KEYS = st.sampled_from(["seed", "types", "sampling", "shard_size", "test_fraction", "quantize",
                        "supersample", "samples_per_type", "backend", "name", "sead",
                        "fine_cloud_points", "Types"])
TABLES = st.sampled_from(["lidar", "ranges", "counts", "extra"])
TABLE_KEYS = st.sampled_from(["width", "height", "r_r_m", "yaw_deg", "aircraft_range_m", "yaw",
                              "range_m", "bogus"])
CONFIGS = st.fixed_dictionaries({}, optional={"types": st.sampled_from(
    [["A320neo"], [], "A320neo", ["Nope"], 3, "all"])}).flatmap(
    lambda base: st.tuples(st.just(base), st.dictionaries(KEYS, VALUES, max_size=4),
                           st.dictionaries(TABLES, st.dictionaries(TABLE_KEYS, VALUES,
                                                                   max_size=3), max_size=2)))


@fuzz(60)
@given(CONFIGS)
def test_a_config_is_refused_by_key_or_plans(tmp_path_factory, capsys, parts):
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.errors import InputError
    from dataset_builder.plan import config_path, load_config, make_plan
    base, top, tables = parts
    cfg = {**base, **top, **tables}
    tmp = tmp_path_factory.mktemp("cfg")
    path = tmp / "c.toml"
    path.write_text(toml_text(cfg))
    try:  # as `apcg dataset build` plans it (its messages name the config)
        plan = make_plan(load_config(str(path)), default_catalog(),
                         source=f"dataset config {config_path(str(path))}")
    except InputError as exc:
        message = str(exc)
        rc, _, err = run(["dataset", "build", "--config", path, "-o", tmp / "ds"], capsys)
        clear_error("config", json.dumps(cfg, default=str), rc, err, message[:60])
        assert not (tmp / "ds").exists()
        return
    # accepted: every key was one the schema knows, and the plan is a real one
    assert plan.n_samples >= 1 and set(cfg) <= {"types", "seed", "sampling", "shard_size",
                                                "test_fraction", "quantize", "supersample",
                                                "samples_per_type", "backend", "name",
                                                "fine_cloud_points", "lidar", "ranges",
                                                "counts"}
    _record("config", json.dumps(cfg, default=str), "handled")


@pytest.mark.parametrize("text,key", [
    ('types = "all"\nsampling = "random"\nsamples_per_type = 3\n[counts]\nyaw = 2\n', "counts"),
    ('types = "all"\nsamples_per_type = 3\n', "samples_per_type")])
def test_a_key_the_sampling_would_ignore_is_refused(tmp_path, capsys, text, key):
    (tmp_path / "c.toml").write_text(text)
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "c.toml", "-o",
                      tmp_path / "ds"], capsys)
    clear_error("config", f"{key} with the other sampling", rc, err, key, "only")
    assert not (tmp_path / "ds").exists()


def test_an_empty_config_is_refused_not_built(tmp_path, capsys):
    (tmp_path / "empty.toml").write_text("")
    rc, _, err = run(["dataset", "build", "--config", tmp_path / "empty.toml", "-o",
                      tmp_path / "ds"], capsys)
    clear_error("config", "empty TOML", rc, err, "empty", "types")
    assert not (tmp_path / "ds").exists()


# --- 4. corrupt files --------------------------------------------------------------------

@pytest.fixture(scope="module")
def demo_dataset(tmp_path_factory) -> Path:
    from dataset_builder.build import build_dataset
    out = tmp_path_factory.mktemp("fuzz_demo") / "demo"
    build_dataset("demo", out, progress=False)
    return out


def _damage(data: bytes, how: str, at: float, junk: bytes) -> bytes:
    cut = int(len(data) * at)
    if how == "truncate":
        return data[:cut]
    if how == "garbage":
        return junk
    if how == "empty":
        return b""
    flipped = bytearray(data)  # "flip": one byte changed
    flipped[min(cut, len(data) - 1)] ^= 0xFF
    return bytes(flipped)


DAMAGE = st.tuples(st.sampled_from(["truncate", "garbage", "empty", "flip"]),
                   st.floats(0, 0.999), st.binary(min_size=1, max_size=400))


@fuzz(40)
@given(damage=DAMAGE, which=st.integers(0, 17))
def test_a_damaged_shard_is_named_by_verify(demo_dataset, tmp_path_factory, capsys, damage,
                                            which):
    out = tmp_path_factory.mktemp("shard") / "ds"
    shutil.copytree(demo_dataset, out)
    victim = sorted((out / "shards").glob("*.npz"))[which]
    before = victim.read_bytes()
    victim.write_bytes(_damage(before, *damage))
    assume(victim.read_bytes() != before)
    rc, _, err = run(["dataset", "info", out, "--verify"], capsys)
    clear_error("corrupt file", f"shard {damage[0]}", rc, err, victim.name)


MODEL_FILES = [(DEFAULT_MODEL, "model.json"), (DEFAULT_MODEL, "sheets.onnx"),
               (CGAN_MODEL, "model.json"), (CGAN_MODEL, "generator.onnx")]


@fuzz(30)
@given(damage=DAMAGE, target=st.sampled_from(MODEL_FILES))
def test_a_damaged_model_file_is_named(tmp_path_factory, capsys, damage, target):
    model, name = target
    tmp = tmp_path_factory.mktemp("model")
    shutil.copytree(model, tmp / "m")
    f = tmp / "m" / name
    before = f.read_bytes()
    f.write_bytes(_damage(before, *damage))
    assume(f.read_bytes() != before)
    pose = POSE if model == DEFAULT_MODEL else [*POSE[:-1], "2"]
    rc, out, err = run(["generate", "--model", tmp / "m", *pose, "--runtime", "onnx", "-o",
                        tmp / "g.ply"], capsys)
    if rc == 0:
        # Still a valid file: a flipped byte inside an ONNX weight is a valid, different model
        # (ONNX has no checksum), a JSON cut after its closing brace is the same JSON.
        assert (tmp / "g.ply").exists()
        assert (name.endswith(".onnx") and damage[0] == "flip") or (
            name.endswith(".json") and json.loads(f.read_bytes()) == json.loads(before)), err
        _record("corrupt file", f"{model.name}/{name} {damage[0]}", "handled")
        return
    clear_error("corrupt file", f"{model.name}/{name} {damage[0]}", rc, err, name)
    assert not (tmp / "g.ply").exists() and not list(tmp.glob("*.part"))


@fuzz(30)
@given(text=st.text(max_size=200), binary=st.binary(max_size=200), use_binary=st.booleans())
def test_a_conditions_csv_of_anything_is_read_or_refused(tmp_path_factory, capsys, text,
                                                          binary, use_binary):
    tmp = tmp_path_factory.mktemp("csv")
    f = tmp / "c.csv"
    f.write_bytes(binary) if use_binary else f.write_text(
        "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n" + text)
    rc, out, err = run(["generate", "--conditions", f, "-o", tmp / "g.ply"], capsys)
    if rc == 0:  # the text happened to hold valid conditions: the clouds are all there
        n = json.loads(out.splitlines()[-1])["clouds"]
        assert n >= 1 and (tmp / "g.ply").exists()
        _record("corrupt file", "conditions CSV", "handled")
    else:
        clear_error("corrupt file", "conditions CSV", rc, err, "c.csv")


MESH_SUFFIXES = [".ply", ".obj", ".stl", ".off", ".glb", ".dae"]


@fuzz(30)
@given(junk=st.binary(max_size=300), suffix=st.sampled_from(MESH_SUFFIXES),
       damage=DAMAGE)
def test_a_broken_mesh_file_is_named(tmp_path_factory, capsys, junk, suffix, damage):
    tmp = tmp_path_factory.mktemp("mesh")
    f = tmp / f"broken{suffix}"
    f.write_bytes(_damage(MESH.read_bytes(), *damage) if suffix == ".ply" else junk)
    rc, out, err = run(["catalog", "add", f, "--name", "fuzzed", "--dry-run"], capsys)
    if rc == 0:  # a flipped byte in a vertex is still a mesh: it is read as one
        assert "dry run" in out
        _record("corrupt file", f"mesh {suffix} {damage[0]}", "handled")
    else:
        clear_error("corrupt file", f"mesh {suffix} {damage[0]}", rc, err, f.name)


@pytest.mark.parametrize("name,damage", [("dataset.json", b"[]"), ("dataset.json", b"{"),
                                         ("manifest.json", b"{"), ("conditions.csv", b"")])
def test_a_damaged_dataset_header_is_named(demo_dataset, tmp_path, capsys, name, damage):
    shutil.copytree(demo_dataset, tmp_path / "ds")
    (tmp_path / "ds" / name).write_bytes(damage)
    rc, _, err = run(["dataset", "info", tmp_path / "ds", "--verify"], capsys)
    clear_error("corrupt file", f"dataset {name}", rc, err, name)


# --- 5. nothing a user made is overwritten ---------------------------------------------

FILE_WRITERS = {
    "simulate": [["simulate", *POSE, "-o", "{out}.ply"]],
    "generate": [["generate", *POSE, "-o", "{out}.npz"]],
    "catalog export": [["catalog", "export", "Mavic 3", "-o", "{out}.obj"]],
    "catalog show": [["catalog", "show", "Mavic 3", "-o", "{out}.png", "--dpi", "20"]],
}


@pytest.mark.parametrize("command", sorted(FILE_WRITERS))
def test_an_existing_output_file_is_kept_without_force(tmp_path, capsys, command):
    argv = [a.replace("{out}", str(tmp_path / "mine")) for a in FILE_WRITERS[command][0]]
    target = Path(next(a for a in argv if a.startswith(str(tmp_path / "mine"))))
    target.write_bytes(b"the user's own file")
    rc, _, err = run(argv, capsys)
    clear_error("overwrite", command, rc, err, target.name, "--force")
    assert target.read_bytes() == b"the user's own file"
    rc, _, err = run([*argv, "--force"], capsys)
    assert rc == 0 and target.read_bytes() != b"the user's own file", err
    _record("overwrite", f"{command} --force", "handled")


# --- 6. full disk, read-only places, interrupted runs -----------------------------------

def _limited(argv: list[str], file_bytes: int, cwd: Path):
    """``apcg ARGV`` with files limited to ``file_bytes``: a write past it fails with EFBIG,
    as a full disk fails with ENOSPC (SIGXFSZ ignored, so the write reports it)."""
    code = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({file_bytes}, {file_bytes})); "
            "from apcg_core.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


def test_a_full_disk_while_generating_leaves_no_file(tmp_path):
    r = _limited(["generate", *POSE, "--count", "3000", "-o", tmp_path / "g.ply"], 200_000,
                 tmp_path)
    clear_error("full disk", "generate", r.returncode, r.stderr, "g.ply")
    assert "Traceback" not in r.stderr and ".part" not in r.stderr
    assert list(tmp_path.iterdir()) == []  # no g.ply, no g.ply.part


def test_a_full_disk_during_a_build_resumes_to_the_same_dataset(demo_dataset, tmp_path):
    out = tmp_path / "ds"
    r = _limited(["dataset", "build", "--config", "demo", "-o", out, "--no-progress"],
                 60_000, tmp_path)
    clear_error("full disk", "dataset build", r.returncode, r.stderr, str(out.name))
    assert not list(out.rglob("*.part*"))  # the failed write left nothing
    r = subprocess.run([APCG, "dataset", "build", "--config", "demo", "-o", out,
                        "--no-progress"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert tree_digest(out) == tree_digest(demo_dataset)
    _record("full disk", "dataset build, then resumed", "handled")


def test_ctrl_c_while_generating_leaves_nothing_and_exits_130(tmp_path, hold):
    # held after the first of three blocks is written to g.ply's temporary file
    p = subprocess.Popen([APCG, "generate", *POSE, "--count", "20000", "-o",
                          tmp_path / "g.ply"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True, env=hold.env("generate.block-written"))
    try:
        hold.wait("generate.block-written", p)
        p.send_signal(signal.SIGINT)
        hold.release("generate.block-written")
        err = p.communicate(timeout=300)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []
    _record("interrupt", "generate Ctrl-C", "handled")


@fuzz(5)
@given(delay=st.floats(0.0, 2.0),
       sig=st.sampled_from([signal.SIGKILL, signal.SIGINT, signal.SIGTERM]))
def test_a_build_killed_at_any_moment_resumes_byte_for_byte(demo_dataset, tmp_path_factory,
                                                            delay, sig):
    out = tmp_path_factory.mktemp("killed") / "ds"
    cmd = [APCG, "dataset", "build", "--config", "demo", "-o", out, "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # the moment is counted from when the build holds its lock (its handlers are set), not
    # from the start: a loaded machine may take seconds just to start Python and import
    lock, deadline = out / ".build-0-of-1.lock", time.monotonic() + 120
    while not lock.exists() and p.poll() is None:
        assert time.monotonic() < deadline, "the build took no lock in 120 s"
        time.sleep(0.005)
    time.sleep(delay)
    p.send_signal(sig)
    err = p.communicate(timeout=120)[1]
    assert "Traceback" not in err, err
    assert p.returncode in (0, 130, -signal.SIGKILL), (p.returncode, err)
    if out.exists():  # whatever was left is complete files or hidden parts, never a torn one
        for f in (out / "shards").glob("*.npz") if (out / "shards").exists() else []:
            assert f.stat().st_size > 0
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert tree_digest(out) == tree_digest(demo_dataset)
    _record("interrupt", f"dataset build signal {int(sig)} {delay:.1f} s into the build",
            "handled")


# --- 7. the output guard: every declared output, one file under two names, inputs ----------
# (tests/output_helpers.py finds the outputs from the parsers; tests/test_outputs.py checks
# that nothing writes without a declaration)

from output_helpers import (  # noqa: E402
    argv_for,
    inputs_of,
    named_files,
    outputs,
    parse,
    planned_files,
    sample_value,
)

GUARDED = outputs()


def _spelled(path: Path, how: str, cwd: Path) -> str:
    """``path`` (in ``cwd``) written another way that names the same file."""
    if how == "relative":
        return os.path.relpath(path, cwd)
    if how == "dot":
        return f"./{os.path.relpath(path, cwd)}"
    if how == "updown":
        return str(path.parent / ".." / path.parent.name / path.name)
    if how == "link":
        link = path.parent / f"link-{path.name}"
        if not os.path.lexists(link):
            link.symlink_to(path)
        return str(link)
    return str(path)


SPELLINGS = ["absolute", "relative", "dot", "updown", "link"]


@fuzz(40)
@given(data=st.data(), how=st.sampled_from(SPELLINGS), content=st.binary(min_size=0,
                                                                           max_size=64))
def test_an_existing_file_of_any_output_is_kept(tmp_path_factory, capsys, data, how, content):
    cmd, parser, _, spec = data.draw(st.sampled_from(GUARDED), label="output")
    tmp = tmp_path_factory.mktemp("kept")
    target = Path(sample_value(spec, tmp))
    args = parse(argv_for(cmd, parser, tmp, {spec.dest: str(target)}))
    files = ([p for p in planned_files(spec, args) if p.name not in spec.record]
             if named_files(spec, args) else [target / "notes.txt"])
    assume(files)
    mine = data.draw(st.sampled_from(files), label="file")
    mine.parent.mkdir(parents=True, exist_ok=True)
    mine.write_bytes(content)
    value = _spelled(target, how, tmp) if spec.kind == "file" or how != "link" else str(target)
    if how == "link" and spec.kind == "file":
        assume(mine == target)
    rc, _, err = run(argv_for(cmd, parser, tmp, {spec.dest: value}), capsys, cwd=tmp)
    clear_error("overwrite", f"{cmd} {spec.flag} {how}: {mine.name} exists", rc, err,
                mine.name if named_files(spec, args) else target.name, "--force")
    assert mine.read_bytes() == content


SAME_PAIRS = [(cmd, parser, a, b) for cmd, parser, a, _ in GUARDED
              for c2, _, b, _ in GUARDED
              if c2 == cmd and a.dest < b.dest and a.apcg_output.kind == "file"
              and b.apcg_output.kind == "file"
              and set(a.apcg_output.suffixes) & set(b.apcg_output.suffixes)]


@fuzz(15)
@given(data=st.data(), first=st.sampled_from(SPELLINGS), second=st.sampled_from(SPELLINGS),
       exists=st.booleans())
def test_two_outputs_named_as_one_file_are_refused(tmp_path_factory, capsys, data, first,
                                                   second, exists):
    cmd, parser, a, b = data.draw(st.sampled_from(SAME_PAIRS), label="pair")
    tmp = tmp_path_factory.mktemp("same")
    suffix = data.draw(st.sampled_from(sorted(set(a.apcg_output.suffixes)
                                              & set(b.apcg_output.suffixes))))
    target = tmp / f"one{suffix}"
    if exists:
        target.write_bytes(b"the user's own file")
    argv = argv_for(cmd, parser, tmp, {a.dest: _spelled(target, first, tmp),
                                       b.dest: _spelled(target, second, tmp)})
    rc, _, err = run([*argv, "--force"], capsys, cwd=tmp)
    clear_error("same file", f"{cmd} {a.option_strings[-1]} {first} = "
                f"{b.option_strings[-1]} {second}", rc, err, "same file")
    assert not exists or target.read_bytes() == b"the user's own file"
    assert sorted(p.name for p in tmp.iterdir() if not p.name.startswith("link-")) == (
        [target.name] if exists else [])


INPUT_OUTPUT = [(cmd, parser, spec, dest) for cmd, parser, _, spec in GUARDED
                for dest in inputs_of(cmd)]


@pytest.mark.parametrize("cmd,parser,spec,dest", INPUT_OUTPUT,
                         ids=[f"{c} {s.flag} in --{d}" for c, _, s, d in INPUT_OUTPUT])
def test_force_keeps_an_input_that_an_output_would_replace(tmp_path, capsys, cmd, parser, spec,
                                                           dest):
    shared = tmp_path / "shared"
    value = (shared if spec.kind == "directory"
             else shared / Path(sample_value(spec, tmp_path)).name)
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: str(value), dest: str(shared)})
    args = parse(argv)
    files = ([p for p in planned_files(spec, args) if p.name not in spec.record]
             if named_files(spec, args) else [shared / "model.json"])
    for p in files:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"an input's own bytes")
    before = tree_digest(tmp_path)
    rc, _, err = run([*argv, "--force"], capsys)
    clear_error("input kept", f"{cmd} {spec.flag} into its --{dest} with --force", rc, err,
                "input")
    assert tree_digest(tmp_path) == before


# --- 8. Ctrl-C and SIGTERM in every kind of command ----------------------------------------

@pytest.fixture(scope="module")
def held_world(tmp_path_factory):
    """What the interrupted commands need: a small dataset, a two-step training run, a user
    catalog with a drone the default model does not know."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.catalog.importer import export_mesh
    from dataset_builder.build import build_dataset
    root = tmp_path_factory.mktemp("held")
    cfg = root / "tiny.toml"
    cfg.write_text('description = "tiny"\nseed = 3\nbackend = "embree"\nshard_size = 50\n'
                   'test_fraction = 0.5\nquantize = true\nsupersample = 1\n'
                   'sampling = "random"\nsamples_per_type = 24\n'
                   'types = ["Mavic 3", "A320neo"]\n')
    build_dataset(str(cfg), root / "data", progress=False)
    env = {**os.environ, "APCG_DATA_DIR": str(root / "user")}
    r = subprocess.run([APCG, "train", "--data", root / "data", "-o", root / "run", "--preset",
                        "tiny", "--steps", "2", "--batch-size", "8", "--no-progress"],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    drone = root / "drone.ply"
    export_mesh(default_catalog().mesh("Mavic 3"), drone)
    r = subprocess.run([APCG, "catalog", "add", drone, "--name", "Held Drone", "--kind",
                        "drone"], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    return {"root": root, "env": env, "drone": drone}


HELD = {  # command line in the test's directory; what it leaves (relative to that directory)
    "simulate": (["simulate", *POSE, "-o", "c.ply", "--depth-image", "d.png"],
                 ["c.ply", "d.png"]),
    "figure": (["figure", "13", "--run", str(DEFAULT_MODEL), "-o", "f.png"],
               ["f.png", "f.json"]),
    "generate": (["generate", *POSE, "--count", "2", "-o", "g.npz"], ["g.npz"]),
    "evaluate": (["evaluate", "--data", "{root}/data", "--pairs", "4", "--no-faithfulness",
                  "-o", "rep"], ["rep/metrics.json", "rep/report.md", "rep/fig17.png"]),
    "export": (["export", "--run", "{root}/run", "-o", "model"],
               ["model/model.json", "model/generator.onnx"]),
    "catalog add": (["catalog", "add", "{drone}", "--name", "Held Drone 2", "--kind", "drone",
                     "--preview", "p.png"], ["p.png"]),
    "teach": (["teach", "--model", "work/m", "--type", "Held Drone", "-o", "work", "--force",
               "--samples", "8", "--steps", "2"], ["work/model.json", "work/teach.json"]),
}


@pytest.mark.parametrize("name,sig", [(n, [signal.SIGINT, signal.SIGTERM][i % 2])
                                      for i, n in enumerate(HELD)])
def test_an_interrupted_command_leaves_all_or_nothing_and_runs_again(held_world, tmp_path,
                                                                     hold, name, sig):
    argv, made = HELD[name]
    world = held_world
    argv = [a.format(root=world["root"], drone=world["drone"]) for a in argv]
    if name == "teach":
        shutil.copytree(DEFAULT_MODEL, tmp_path / "work" / "m")
    env = {**hold.env("output.held"), "APCG_DATA_DIR": world["env"]["APCG_DATA_DIR"]}
    before = tree_digest(tmp_path)
    p = subprocess.Popen([APCG, *argv], cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    try:
        hold.wait("output.held", p)
        p.send_signal(sig)
        hold.release("output.held")
        err = p.communicate(timeout=300)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert tree_digest(tmp_path) == before  # nothing under a final name, no temporary left
    assert not [q for q in tmp_path.rglob("*") if q.name.startswith(".")]
    if name == "catalog add":
        listed = subprocess.run([APCG, "catalog", "list", "--json"], capture_output=True,
                                text=True, env=world["env"], timeout=120).stdout
        assert "Held Drone 2" not in listed
    r = subprocess.run([APCG, *argv], cwd=tmp_path, capture_output=True, text=True,
                       env=world["env"], timeout=600)
    assert r.returncode == 0, r.stderr
    for rel in made:
        assert (tmp_path / rel).is_file() and (tmp_path / rel).stat().st_size > 0, rel
    if name == "teach":
        assert tree_digest(tmp_path / "work" / "m") == tree_digest(DEFAULT_MODEL)
    _record("interrupt", f"{name} {signal.Signals(sig).name} with its outputs held", "handled")


def test_an_interrupt_while_outputs_are_renamed_finishes_them(held_world, tmp_path, hold):
    argv = ["evaluate", "--data", held_world["root"] / "data", "--pairs", "4",
            "--no-faithfulness", "-o", "rep"]
    p = subprocess.Popen([APCG, *argv], cwd=tmp_path, env=hold.env("output.committing"),
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        hold.wait("output.committing", p)
        p.send_signal(signal.SIGINT)
        hold.release("output.committing")
        err = p.communicate(timeout=300)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0 and "Traceback" not in err, err
    assert sorted(q.name for q in (tmp_path / "rep").iterdir()) == [
        "fig17.png", "metrics.json", "report.md"]
    _record("interrupt", "evaluate SIGINT while its outputs are renamed", "handled")


# --- 9. the user's catalog as a database, round trips, inputs as users make them ----------

import contextlib  # noqa: E402
import unicodedata  # noqa: E402

import numpy as np  # noqa: E402


@contextlib.contextmanager
def user_catalog(path: Path):
    """Commands in this process see the user catalog in ``path`` (APCG_DATA_DIR), with the
    process-wide catalog made again on entry and on exit."""
    from apcg_core.catalog.catalog import default_catalog
    old = os.environ.get("APCG_DATA_DIR")
    os.environ["APCG_DATA_DIR"] = str(path)
    default_catalog.cache_clear()
    try:
        yield path / "catalog"
    finally:
        if old is None:
            os.environ.pop("APCG_DATA_DIR", None)
        else:
            os.environ["APCG_DATA_DIR"] = old
        default_catalog.cache_clear()


def _box_obj(path: Path, length=10.0, extra: str = "") -> Path:
    v = [[x, y, z] for x in (0.0, length) for y in (0.0, 8.0) for z in (0.0, 2.0)]
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7],
         [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f) + extra)
    return path


def _two_types(data: Path) -> Path:
    from apcg_core.catalog import Catalog
    from apcg_core.catalog.importer import import_model
    mesh, _ = import_model(MESH)
    cat = Catalog(user_path=data / "catalog")
    cat.add_user_type("Jet A", mesh, "aircraft", "user", "a")
    cat.add_user_type("Jet B", mesh, "aircraft", "user", "b")
    return data / "catalog" / "user_types.json"


@fuzz(12)
@given(damage=DAMAGE)
def test_a_damaged_user_catalog_is_named_with_the_fix(tmp_path_factory, capsys, damage):
    """The registry truncated, emptied, replaced by garbage or with a byte flipped: listed
    as what it still says, or one line naming the file and what to do; never rewritten."""
    data = tmp_path_factory.mktemp("reg")
    reg = _two_types(data)
    before = reg.read_bytes()
    reg.write_bytes(_damage(before, *damage))
    assume(reg.read_bytes() != before)
    damaged = reg.read_bytes()
    with user_catalog(data):
        rc, out, err = run(["catalog", "list", "--json"], capsys)
    case = f"user_types.json {damage[0]}"
    assert reg.read_bytes() == damaged, f"{case}: the user's file was rewritten"
    if rc == 0:  # still a valid registry (a flipped byte inside a name, a number)
        listed = [r for r in json.loads(out) if r["index"] >= 1000]
        assert [r["name"] for r in listed] == [e["name"].strip() for e in json.loads(damaged)]
        _record("catalog database", case, "handled")
        return
    assert len(err.strip().splitlines()) == 1, err
    clear_error("catalog database", case, rc, err, "user_types.json", "mv ", "catalog add")


@pytest.mark.parametrize("field", ["index", "name", "kind", "range_band", "length_m",
                                   "category"])
def test_a_user_catalog_entry_short_of_a_field_is_named(tmp_path, capsys, field):
    reg = _two_types(tmp_path)
    entries = json.loads(reg.read_text())
    del entries[1][field]
    reg.write_text(json.dumps(entries))
    with user_catalog(tmp_path):
        rc, _, err = run(["catalog", "list"], capsys)
    clear_error("catalog database", f"registry entry without {field}", rc, err,
                "user_types.json", "entry 2", field, "mv ")


def test_concurrent_adds_of_one_name_in_two_spellings(tmp_path):
    """Four `apcg catalog add` at once, two names in two spellings each: one of each pair is
    added, the other refused naming it; nothing lost, no two types share a file."""
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    obj = _box_obj(tmp_path / "box.obj")
    names = ["Jet A", "jet_a", "Jet B", "JET-B"]
    procs = [subprocess.Popen([APCG, "catalog", "add", str(obj), "--name", n],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for n in names]
    results = [(n, *p.communicate(timeout=300), p.returncode)
               for n, p in zip(names, procs, strict=True)]
    listed = json.loads(subprocess.run([APCG, "catalog", "list", "--json"], env=env,
                                       capture_output=True, text=True).stdout)
    users = sorted(r["name"] for r in listed if r["index"] >= 1000)
    for pair in (names[:2], names[2:]):
        won = [n for n, out, err, rc in results if n in pair and rc == 0]
        assert len(won) == 1 and won[0] in users, results
        for n, _, err, rc in results:
            if n in pair and rc != 0:
                clear_error("catalog database", f"concurrent add {n!r} beside {won[0]!r}", rc,
                            err, repr(won[0]), "--force")
        _record("catalog database", f"concurrent add of {pair}", "handled")
    assert len(users) == 2 and len(list((tmp_path / "data" / "catalog").glob("*.npz"))) == 2


SPELLINGS = st.sampled_from([str.lower, str.upper, str.title,
                             lambda s: s.replace(" ", "_"), lambda s: s.replace(" ", "-"),
                             lambda s: f"  {s}\t", lambda s: s.replace(" ", " _ "),
                             lambda s: unicodedata.normalize("NFD", s),
                             lambda s: s.replace(" ", "\u2013")])


@fuzz(10)
@given(base=st.sampled_from(["Jet A", "Café Jet", "my drone 2", "Ünïcode Plane"]),
       spell=st.lists(SPELLINGS, min_size=1, max_size=3))
def test_a_name_in_another_spelling_is_the_same_type(tmp_path_factory, capsys, base, spell):
    data = tmp_path_factory.mktemp("spell")
    other = base
    for f in spell:
        other = f(other)
    with user_catalog(data):
        rc, _, err = run(["catalog", "add", MESH, "--name", base], capsys)
        assert rc == 0, err
        # --name=VALUE: a spelling may begin with a dash ("  Jet A" with dashes for spaces),
        # which argparse would take for an option after a separate --name
        rc, out, err = run(["catalog", "add", MESH, f"--name={other}"], capsys)
        case = f"catalog add {other!r} after {base!r}"
        if other.strip() == base:  # the same name
            clear_error("new type name", case, rc, err, repr(base))
            return
        clear_error("new type name", case, rc, err, repr(base), "--force")
        rc, out, err = run(["catalog", "add", MESH, f"--name={other}", "--force"], capsys)
        assert rc == 0 and f"replaced {base!r}" in out, err
        rc, out, _ = run(["catalog", "list", "--json"], capsys)
    users = [r["name"] for r in json.loads(out) if r["index"] >= 1000]
    assert users == [unicodedata.normalize("NFC", other).strip()]
    assert len(list((data / "catalog").glob("*.npz"))) == 1
    _record("new type name", f"{case} --force", "handled")


CSV_HEAD = ["type", "range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg"]
CSV_ROWS = [["A320neo", "4500", "3.4", "2", "10", "0"], ["Mavic 3", "250", "3", "1", "-20", "2"],
            ["ATR 72-600", "6000.5", "3.9", "4.5", "-59", "-1.5"]]
DIALECT = st.fixed_dictionaries({"bom": st.booleans(), "crlf": st.booleans(),
                                 "quote": st.sampled_from(["none", "all", "text"]),
                                 "spaces": st.booleans(),
                                 "blank": st.lists(st.sampled_from(["", ",,,,,", " "]),
                                                   max_size=3),
                                 "blank_at": st.integers(0, 3)})


def render_csv(rows: list[list[str]], d: dict) -> tuple[bytes, list[int]]:
    """``rows`` (header first) as a spreadsheet or an editor might save them; with the line
    (1-based) each row starts on."""
    def cell(c: str) -> str:
        q = d["quote"] == "all" or (d["quote"] == "text" and not re.fullmatch(r"[-\d.]+", c))
        c = f'"{c}"' if q or "," in c else c
        return f" {c} " if d["spaces"] and not q else c
    lines, starts = [], []
    for i, r in enumerate(rows):
        if i == d["blank_at"] and i > 0:
            lines += d["blank"]
        starts.append(len(lines) + 1)
        lines.append(",".join(cell(c) for c in r))
    lines += d["blank"]  # trailing empty lines
    nl = "\r\n" if d["crlf"] else "\n"
    data = (nl.join(lines) + nl).encode()
    return (b"\xef\xbb\xbf" + data if d["bom"] else data), starts


@fuzz(10)
@given(d=DIALECT)
def test_a_conditions_csv_as_users_save_it_gives_the_same_clouds(tmp_path_factory, capsys, d):
    tmp = tmp_path_factory.mktemp("dialect")
    plain, _ = render_csv([CSV_HEAD, *CSV_ROWS], {"bom": False, "crlf": False, "quote": "none",
                                                  "spaces": False, "blank": [],
                                                  "blank_at": 0})
    (tmp / "plain.csv").write_bytes(plain)
    (tmp / "user.csv").write_bytes(render_csv([CSV_HEAD, *CSV_ROWS], d)[0])
    outs = []
    for name in ("plain", "user"):
        rc, out, err = run(["generate", "--conditions", tmp / f"{name}.csv", "--seed", "3",
                            "-o", tmp / f"{name}.npz"], capsys)
        assert rc == 0, f"{d}: {err}"
        with np.load(tmp / f"{name}.npz") as z:
            outs.append({k: z[k].copy() for k in z.files})
    assert outs[0].keys() == outs[1].keys()
    assert all(np.array_equal(outs[0][k], outs[1][k]) for k in outs[0]), d
    _record("csv input", f"conditions CSV saved as {d}", "handled")


BAD_CELLS = {"range_m": ["abc", "nan", "-5", "", "1,5", "inf", "20000"],
             "elevation_deg": ["90", "x", "-95", "10"], "pitch_deg": ["91", "--"],
             "yaw_deg": ["181", "1e999"], "roll_deg": ["-180.5", "None"],
             "type": ["No Such Jet", ""]}


@fuzz(15)
@given(d=DIALECT, row=st.integers(0, 2), column=st.sampled_from(sorted(BAD_CELLS)),
       data=st.data())
def test_a_bad_cell_is_named_by_line_column_and_value(tmp_path_factory, capsys, d, row,
                                                      column, data):
    value = data.draw(st.sampled_from(BAD_CELLS[column]), label="value")
    rows = [list(r) for r in CSV_ROWS]
    rows[row][CSV_HEAD.index(column)] = value
    text, starts = render_csv([CSV_HEAD, *rows], d)
    tmp = tmp_path_factory.mktemp("cell")
    (tmp / "c.csv").write_bytes(text)
    rc, _, err = run(["generate", "--conditions", tmp / "c.csv", "-o", tmp / "g.npz"], capsys)
    letter = "ABCDEF"[CSV_HEAD.index(column)]
    clear_error("csv input", f"{column}={value!r} on data row {row + 1} of {d}", rc, err,
                "c.csv", f"line {starts[row + 1]}, column {column} ({letter})", repr(value))
    assert not (tmp / "g.npz").exists()


MESH_FAULTS = {
    "degenerate triangles": ("v 30 0 0\nv 40 0 0\nv 50 0 0\nf 9 10 11\nf 1 1 2\n", None),
    "a repeated point": ("f 1 2 2\n", None),
    "a nan vertex": ("v nan 0 0\nf 1 2 9\n", "non-finite"),
    "an inf vertex": ("v 0 inf 0\nf 1 2 9\n", "non-finite"),
    "a face past the vertices": ("f 1 2 99\n", "box.obj"),
}


@pytest.mark.parametrize("fault,fmt", [(fault, fmt) for fault in sorted(MESH_FAULTS)
                                       for fmt in ("obj", "ply", "stl")
                                       if fmt == "obj" or "past" not in fault])
def test_a_mesh_with_bad_triangles_is_cleaned_or_named(tmp_path, capsys, fault, fmt):
    """Degenerate triangles are dropped with one warning (the rest is the model, its size
    kept); a non-finite vertex, or a face naming a vertex that is not there, is named."""
    extra, words = MESH_FAULTS[fault]
    src = _box_obj(tmp_path / "box.obj", extra=extra)
    path = src
    if fmt != "obj":  # the same triangles through trimesh's writer of that format
        import trimesh
        v = [list(map(float, ln.split()[1:])) for ln in src.read_text().splitlines()
             if ln.startswith("v ")]
        f = [[int(x) - 1 for x in ln.split()[1:]] for ln in src.read_text().splitlines()
             if ln.startswith("f ")]
        path = tmp_path / f"box.{fmt}"
        path.write_bytes(trimesh.Trimesh(v, f, process=False).export(file_type=fmt))
    with user_catalog(tmp_path / "data"):
        rc, out, err = run(["catalog", "add", path, "--name", "boxed"], capsys)
        case = f"{fmt} with {fault}"
        if words is None:
            assert rc == 0 and re.search(r"degenerate \(zero-area\) triangles? dropped", err), err
            rc2, listed, _ = run(["catalog", "list", "--json"], capsys)
            t = [r for r in json.loads(listed) if r["name"] == "boxed"][0]
            assert (t["length_m"], t["span_m"], t["height_m"]) == pytest.approx((10, 8, 2))
            _record("mesh input", case, "handled")
        else:
            clear_error("mesh input", case, rc, err, path.name, words)
            assert not (tmp_path / "data" / "catalog" / "user_types.json").exists()


@pytest.mark.parametrize("preview", ["x.txt", "x.jpg", "x", "x.png.bak", "dir/x.gif"])
def test_an_unknown_preview_format_is_refused_first(tmp_path, capsys, preview):
    with user_catalog(tmp_path / "data"):
        rc, _, err = run(["catalog", "add", tmp_path / "never-read.obj", "--name", "p",
                          "--preview", tmp_path / preview], capsys)
    clear_error("mesh input", f"catalog add --preview {preview}", rc, err, "--preview", ".png")
    assert "never-read" not in err and not (tmp_path / "data").exists()


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".glb"])
def test_every_export_format_reads_back_the_same(tmp_path, capsys, suffix):
    from apcg_core.catalog.catalog import default_catalog
    with user_catalog(tmp_path / "data"):
        rc, _, err = run(["catalog", "export", "ATR 72-600", "-o", tmp_path / f"a{suffix}"],
                         capsys)
        assert rc == 0, err
        rc, _, err = run(["catalog", "add", tmp_path / f"a{suffix}", "--name", "back"],
                         capsys)
        assert rc == 0 and "warning" not in err, err
        got = default_catalog().mesh("back")
    want = default_catalog().mesh("ATR 72-600")
    np.testing.assert_allclose(got.extents, want.extents, rtol=1e-6)
    assert np.abs(np.sort(got.vertices, axis=0) - np.sort(want.vertices, axis=0)).max() < 1e-4
    _record("round trip", f"catalog export -o a{suffix}, then catalog add", "handled")


@pytest.mark.parametrize("name", ["A320neo", "F-16C Fighting Falcon", "C-130J Hercules"])
def test_a_y_up_collada_with_z_up_vertices_is_warned(tmp_path, capsys, name):
    import trimesh

    from apcg_core.catalog.catalog import default_catalog
    m = default_catalog().mesh(name)
    dae = trimesh.Trimesh(m.vertices, m.faces, process=False).export(file_type="dae")
    text = (dae if isinstance(dae, str) else dae.decode())
    assert "<up_axis>Y_UP</up_axis>" in text
    (tmp_path / "m.dae").write_text(text)
    with user_catalog(tmp_path / "data"):
        rc, _, err = run(["catalog", "add", tmp_path / "m.dae", "--name", "m", "--dry-run"],
                         capsys)
    warned = [ln for ln in err.splitlines() if "contradict the shape" in ln]
    assert rc == 0 and len(warned) == 1 and "use --up Z" in warned[0], err
    _record("round trip", f"{name} as a Y_UP COLLADA with Z-up vertices: warned", "handled")


# --- sensor files (issue "Photons"): every key's bad value, unknown and missing keys, junk ------

SENSOR_BAD = {
    "wavelength_nm": [-1064.0, 0.0, 1e9, "1064"], "pulse_energy_j": [-1e-6, 0.0, 11.0],
    "cells_per_pulse": [0, -4, 2.5, "1"], "aperture_m": [0.0, -0.1, 1e3],
    "optics_efficiency": [0.0, 1.5, -0.2], "detector_efficiency": [0.0, 1.01, True],
    "visibility_km": [0.0, -3.0, 1e9], "background_hz": [-1.0, 1e12, "day"],
    "dark_count_hz": [-5.0, 1e11], "pulse_fwhm_ps": [-1.0, 1e7], "jitter_ps": [-0.5, 1e7],
    "gate_m": [0.0, -100.0, 1e6], "dead_time_ns": [-1.0, 1e8], "pulses": [0, -1, 1.5, 10**6],
    "threshold": [0, -2, 3.5, False], "output": ["cloud", "", 3],
}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    return repr(v)


def _sensor_text(table: dict) -> str:
    return "[sensor]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in table.items())


SENSOR_CASES = st.one_of(
    st.tuples(st.just("bad value"), st.sampled_from(sorted(SENSOR_BAD)), st.integers(0, 3)),
    st.tuples(st.just("unknown key"), st.sampled_from(["pulse_energy", "Pulses", "gate",
                                                       "jitter"]), st.just(0)),
    st.tuples(st.just("missing key"), st.sampled_from(sorted(SENSOR_BAD)), st.just(0)),
    st.tuples(st.just("junk"), st.sampled_from(["[sensor\n", "sensor = 3\n", "\x00\x01",
                                                "[lidar]\nwidth = 4\n", ""]), st.just(0)),
    st.tuples(st.just("nan"), st.sampled_from(["pulse_energy_j", "gate_m", "jitter_ps",
                                               "visibility_km"]), st.just(0)),
)


def _write_table_case(f: Path, text, base: dict, bad: dict, kind: str, key, i: int) -> list:
    """Write a TOML table file's fuzz case into ``f`` (``text(table)`` the file's text): a
    key's bad value, an unknown key, a key left out, NaN, or junk bytes (``key``). Returns the
    words its refusal must name: the key, or the file for junk."""
    if kind == "bad value":
        f.write_text(text({**base, key: bad[key][i % len(bad[key])]}))
    elif kind == "unknown key":
        f.write_text(text({**base, key: 1.0}))
    elif kind == "missing key":
        f.write_text(text({k: v for k, v in base.items() if k != key}))
    elif kind == "nan":
        f.write_text(text(base).replace(f"{key} = {_toml_value(base[key])}", f"{key} = nan"))
    else:
        f.write_bytes(key.encode("latin-1"))
        return [f.name]
    return [key]


@fuzz(60)
@given(SENSOR_CASES)
def test_a_sensor_file_is_refused_by_key_or_used(tmp_path_factory, capsys, case):
    import tomllib

    from apcg_core.sensor import PRESET_DIR
    kind, key, i = case
    tmp = tmp_path_factory.mktemp("sensor")
    base = tomllib.loads((PRESET_DIR / "1550nm-night.toml").read_text())["sensor"]
    base.pop("name")
    f = tmp / "s.toml"
    names = _write_table_case(f, _sensor_text, base, SENSOR_BAD, kind, key, i)
    out = tmp / "c.npz"
    rc, _, err = run(["simulate", *POSE, "-o", out, "--sensor", f], capsys)
    if kind == "missing key" and key == "output":  # output has a default: points
        assert rc == 0 and "label" in __import__("numpy").load(out).files, err
        _record("sensor file", kind, "handled")
        return
    assert not out.exists()
    clear_error("sensor file", kind, rc, err, *names)


# --- lidar files (issue 33): every key's bad value, unknown keys and tables, junk -----------

LIDAR_BAD = {
    "r_alpha_deg": [0.0, -0.004, "0.004", True, 1e9], "r_beta_deg": [0.0, -1.0, [0.0076]],
    "r_r_m": [0.0, -0.15, "fine"], "width": [255, 0, -256, 2.0, 70000, "256"],
    "height": [63, 1, 64.0, False],
}
LIDAR_BASE = {"r_alpha_deg": 0.004, "r_beta_deg": 0.0076, "r_r_m": 0.15, "width": 256,
              "height": 64}

LIDAR_CASES = st.one_of(
    st.tuples(st.just("bad value"), st.sampled_from(sorted(LIDAR_BAD)), st.integers(0, 5)),
    st.tuples(st.just("unknown key"), st.sampled_from(["r_alpha", "Width", "bins", "r_r"]),
              st.just(0)),
    st.tuples(st.just("missing key"), st.sampled_from(sorted(LIDAR_BAD)), st.just(0)),
    st.tuples(st.just("junk"), st.sampled_from(["[lidar\n", "lidar = 3\n", "\x00\x01",
                                                "[sensor]\nname = 'x'\n", "",
                                                "[lidar]\n[optics]\nf = 1\n"]), st.just(0)),
    st.tuples(st.just("nan"), st.sampled_from(["r_alpha_deg", "r_beta_deg", "r_r_m"]),
              st.just(0)),
)


@fuzz(40)
@given(LIDAR_CASES)
def test_a_lidar_file_is_refused_by_key_or_used(tmp_path_factory, capsys, case):
    kind, key, i = case
    tmp = tmp_path_factory.mktemp("lidar")
    f = tmp / "l.toml"

    def text(table):
        return "[lidar]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in table.items())
    names = _write_table_case(f, text, LIDAR_BASE, LIDAR_BAD, kind, key, i)
    if kind in ("bad value", "unknown key"):
        names.append("l.toml")
    out = tmp / "c.npz"
    rc, _, err = run(["simulate", *POSE, "-o", out, "--lidar", f], capsys)
    if kind == "missing key":
        assert rc == 0 and out.exists(), err
        _record("lidar file", kind, "handled")
        return
    assert not out.exists()
    clear_error("lidar file", kind, rc, err, *names)
