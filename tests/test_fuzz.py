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
    import tempfile

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.catalog.importer import export_mesh
    path = Path(tempfile.gettempdir()) / f"apcg-fuzz-{os.getpid()}" / "a320neo.ply"
    if not path.exists():
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
    """Names a later `--type NAME` could not find as themselves (empty, a number, which
    `--type` reads as an index, a path separator, a taken name) are refused up front."""
    misread = (not name.strip() or name.strip().isdigit() or "/" in name or "\\" in name
               or name.lower() in {"a320neo", "mavic 3"})
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
    from dataset_builder.plan import load_config, make_plan
    base, top, tables = parts
    cfg = {**base, **top, **tables}
    tmp = tmp_path_factory.mktemp("cfg")
    path = tmp / "c.toml"
    path.write_text(toml_text(cfg))
    try:
        plan = make_plan(load_config(str(path)), default_catalog())
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
@given(delay=st.floats(0.3, 2.5),
       sig=st.sampled_from([signal.SIGKILL, signal.SIGINT, signal.SIGTERM]))
def test_a_build_killed_at_any_moment_resumes_byte_for_byte(demo_dataset, tmp_path_factory,
                                                            delay, sig):
    out = tmp_path_factory.mktemp("killed") / "ds"
    cmd = [APCG, "dataset", "build", "--config", "demo", "-o", out, "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
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
    _record("interrupt", f"dataset build signal {int(sig)} after {delay:.1f} s", "handled")
