"""One guard for every file a command writes (apcg_core/outputs.py, apcg_core/io/atomic.py).

The output options are found from the parsers themselves (every ``apcg.commands`` entry
point), by the declaration ``add_output`` puts on each; an option that takes a path and is
neither declared nor listed as an input fails the first test, so a new output cannot skip the
guard. Each declared output is then checked: a file already there is kept without --force,
two outputs that are one file are refused, and --force never replaces an input."""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from output_helpers import (
    NOT_OUTPUTS,
    argv_for,
    commands,
    inputs_of,
    named_files,
    outputs,
    parse,
    planned_files,
    sample_value,
    unclassified,
)

from apcg_core.cli import build_parser, main
from apcg_core.errors import InputError
from apcg_core.io.atomic import atomic_path
from apcg_core.io.dataset import write_atomic
from apcg_core.outputs import FILE, Guard, add_output, guarding, output_problems

APCG = str(Path(sys.executable).parent / "apcg")
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT / "apcg_core/models/default"
MINE = b"the user's own file\n"
POSE = ["--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3"]


def run(argv, capsys, cwd=None) -> tuple[int, str, str]:
    old = Path.cwd()
    if cwd:
        os.chdir(cwd)
    try:
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:
            rc = exc.code if isinstance(exc.code, int) else 2
    finally:
        os.chdir(old)
    out = capsys.readouterr()
    return rc, out.out, out.err


def digest(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


OUTPUTS = outputs()
IDS = [f"{cmd} {spec.flag}" for cmd, _, _, spec in OUTPUTS]


# --- the declarations ---------------------------------------------------------------------

def test_every_option_that_takes_a_path_is_classified():
    assert unclassified() == [], (
        "these options take a path or text but are neither outputs declared with "
        "apcg_core.outputs.add_output nor listed in tests/output_helpers.NOT_OUTPUTS")
    known = {(cmd, a.dest) for cmd, p in commands() for a in p._actions}
    assert set(NOT_OUTPUTS) <= known, set(NOT_OUTPUTS) - known  # no stale entries


def test_an_output_option_added_without_the_helper_is_found():
    def register(sub):
        p = sub.add_parser("sneaky")
        p.add_argument("-o", "--output", help="writes here, unguarded")
        q = sub.add_parser("declared")
        add_output(q, "-o", "--output", kind=FILE, suffixes=(".txt",))
    parser = build_parser(registrars=[register])
    assert unclassified(parser) == ["apcg sneaky --output"]


def test_the_walk_finds_every_commands_outputs():
    found = {(cmd, spec.flag) for cmd, _, _, spec in OUTPUTS}
    assert {("simulate", "--output"), ("simulate", "--depth-image"),
            ("simulate", "--normalized-image"), ("dataset build", "--output"),
            ("evaluate", "--output"), ("figure", "--output"), ("catalog add", "--preview"),
            ("teach", "--output"), ("teach", "--data"), ("train", "--output"),
            ("export", "--output"), ("generate", "--output"), ("compare", "--output"),
            ("choose-tau", "--output")} <= found


@pytest.mark.parametrize("cmd", sorted({cmd for cmd, *_ in OUTPUTS}))
def test_every_command_that_writes_has_force(cmd):
    parser = dict(commands())[cmd]
    assert "--force" in parser._option_string_actions


# --- checked before any work --------------------------------------------------------------

def _fill(spec, args, tmp: Path) -> list[Path]:
    """The user's own files where the output would write; returns them."""
    if named_files(spec, args):  # a resumable job's record would make them its own
        made = [p for p in planned_files(spec, args)
                if not any(fnmatch.fnmatch(p.name, r) for r in spec.record)]
    else:  # a directory whose files are known only afterwards: any file of the user's
        made = [Path(getattr(args, spec.dest)) / "notes.txt"]
    for p in made:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(MINE)
    return made


@pytest.mark.parametrize("cmd,parser,action,spec", OUTPUTS, ids=IDS)
def test_an_existing_file_among_an_outputs_files_is_kept_without_force(tmp_path, capsys, cmd,
                                                                         parser, action, spec):
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: sample_value(spec, tmp_path)})
    args = parse(argv)
    made = _fill(spec, args, tmp_path)
    problems = output_problems(args)
    for p in made:
        named = p.name if named_files(spec, args) else Path(getattr(args, spec.dest)).name
        assert any(named in m and "--force" in m for m in problems), (argv, problems)
    rc, _, err = run(argv, capsys)  # the real command refuses before any work
    assert rc == 2 and "--force" in err, err
    assert all(p.read_bytes() == MINE for p in made)
    assert output_problems(parse([*argv, "--force"])) == []


@pytest.mark.parametrize("cmd,parser,action,spec", OUTPUTS, ids=IDS)
def test_an_empty_output_name_is_refused_not_taken_for_the_working_directory(
        tmp_path, capsys, cmd, parser, action, spec):
    # Path("") is "."; a report written into wherever the command ran was never asked for
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: ""})
    assert any(spec.flag in m and "empty name" in m for m in output_problems(parse(argv)))
    rc, _, err = run(argv, capsys, cwd=tmp_path)
    assert rc == 2 and "empty name" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("cmd,parser,action,spec", [o for o in OUTPUTS if o[3].kind == FILE],
                         ids=[i for i, o in zip(IDS, OUTPUTS, strict=True) if o[3].kind == FILE])
def test_a_directory_given_for_a_file_output_is_called_a_directory(tmp_path, cmd, parser,
                                                                   action, spec):
    d = tmp_path / "a-folder"
    d.mkdir()
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: str(d)})
    problems = [m for m in output_problems(parse(argv)) if spec.flag in m]
    assert problems and "is a directory" in problems[0], problems


@pytest.mark.parametrize("cmd,parser,action,spec",
                         [o for o in OUTPUTS if o[3].resumable],
                         ids=[i for i, o in zip(IDS, OUTPUTS, strict=True) if o[3].resumable])
def test_a_resumable_jobs_own_files_are_its_to_replace(tmp_path, cmd, parser, action, spec):
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: sample_value(spec, tmp_path)})
    args = parse(argv)
    _fill(spec, args, tmp_path)
    assert output_problems(args)  # a user's files: refused
    record = Path(getattr(args, spec.dest)) / spec.record[0].replace("*", "some-run")
    record.parent.mkdir(parents=True, exist_ok=True)
    record.write_text("{}")
    assert output_problems(args) == []  # the job's own, from its earlier run


SAME_FILE = [(cmd, parser, a, b) for cmd, parser in commands()
             for i, a in enumerate(x for x in parser._actions if hasattr(x, "apcg_output"))
             for b in [x for x in parser._actions if hasattr(x, "apcg_output")][i + 1:]
             if a.apcg_output.kind == b.apcg_output.kind == FILE
             and set(a.apcg_output.suffixes) & set(b.apcg_output.suffixes)]


def _spellings(tmp: Path, name: str) -> list[tuple[str, str]]:
    (tmp / "sub").mkdir(exist_ok=True)
    target = tmp / name
    link = tmp / f"link-{name}"
    if not link.exists():
        link.symlink_to(target)
    return [(str(target), str(target)), (str(target), f"{tmp}/./{name}"),
            (str(target), f"{tmp}/sub/../{name}"), (str(target), str(link)),
            (name, f"./{name}")]


@pytest.mark.parametrize("cmd,parser,a,b", SAME_FILE,
                         ids=[f"{c} {a.option_strings[-1]} {b.option_strings[-1]}"
                              for c, _, a, b in SAME_FILE])
def test_two_outputs_that_are_one_file_are_refused_before_any_work(tmp_path, capsys, cmd,
                                                                    parser, a, b):
    assert SAME_FILE, "simulate's two images at least"
    suffix = sorted(set(a.apcg_output.suffixes) & set(b.apcg_output.suffixes))[0]
    for first, second in _spellings(tmp_path, f"img{suffix}"):
        argv = argv_for(cmd, parser, tmp_path, {a.dest: first, b.dest: second})
        old = Path.cwd()
        os.chdir(tmp_path)
        try:
            problems = output_problems(parse(argv))
        finally:
            os.chdir(old)
        assert any("same file" in m for m in problems), (argv, problems)


def test_a_hard_link_is_the_same_file(tmp_path):
    (tmp_path / "a.png").write_bytes(MINE)
    os.link(tmp_path / "a.png", tmp_path / "b.png")
    args = parse(["simulate", *POSE, "-o", str(tmp_path / "c.ply"), "--depth-image",
                  str(tmp_path / "a.png"), "--normalized-image", str(tmp_path / "b.png"),
                  "--force"])
    assert any("same file" in m for m in output_problems(args))


INPUT_CASES = [(cmd, parser, action, spec, dest) for cmd, parser, action, spec in OUTPUTS
               for dest in inputs_of(cmd)]


@pytest.mark.parametrize("cmd,parser,action,spec,dest", INPUT_CASES,
                         ids=[f"{c} {s.flag} into --{d}" for c, _, _, s, d in INPUT_CASES])
def test_force_never_replaces_an_input_of_the_same_command(tmp_path, cmd, parser, action, spec,
                                                           dest):
    """The input given as (or around) the output: --force still keeps what is there."""
    shared = tmp_path / "shared"
    value = str(shared) if spec.kind != FILE else str(shared / Path(sample_value(spec,
                                                                                  tmp_path)).name)
    argv = argv_for(cmd, parser, tmp_path, {spec.dest: value, dest: str(shared)})
    args = parse([*argv, "--force"])
    made = _fill(spec, args, tmp_path)
    problems = output_problems(args)
    assert any("input" in m for m in problems), (argv, problems)
    assert all(p.read_bytes() == MINE for p in made)


# --- kept while the command runs ------------------------------------------------------------

def _args(tmp: Path, **over) -> argparse.Namespace:
    ns = parse(["simulate", *POSE, "-o", str(tmp / "c.ply"), "--depth-image",
                str(tmp / "d.png")])
    for k, v in over.items():
        setattr(ns, k, v)
    return ns


def test_a_file_no_declaration_named_is_not_replaced_without_force(tmp_path):
    other = tmp_path / "elsewhere.json"
    other.write_bytes(MINE)
    with pytest.raises(InputError, match="elsewhere.json already exists"), \
            guarding(_args(tmp_path)):
        write_atomic(other, b"{}")
    assert other.read_bytes() == MINE
    with guarding(_args(tmp_path, force=True)):
        write_atomic(other, b"{}")
    assert other.read_bytes() == b"{}"


def test_an_input_is_never_replaced_even_with_force(tmp_path):
    model = tmp_path / "m"
    model.mkdir()
    (model / "model.json").write_bytes(MINE)
    ns = argparse.Namespace(command="teach", model=str(model), force=True,
                            output=str(tmp_path), _outputs=())
    with pytest.raises(InputError, match="input"), guarding(ns):
        write_atomic(model / "model.json", b"{}")
    assert (model / "model.json").read_bytes() == MINE


@pytest.mark.parametrize("output, scratch", [
    ("g.npz", "g.npz.part"), ("g.npz", "g.npz.range_m.part"), ("g.npz", "g.npz.xyz.part"),
    ("g.ply", "g.ply.part"), ("g.las", "g.las.part")])
def test_an_input_under_a_temporary_name_of_the_output_is_never_written_over(tmp_path, capsys,
                                                                             output, scratch):
    """Every temporary name a command writes (atomic_path's NAME.part, the NPZ writer's zip and
    spill files) goes through the guard: an input of the command under that name is refused
    before any work, with --force too, and left as it was; nothing else is left behind."""
    conditions = tmp_path / scratch
    conditions.write_bytes(b"type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"
                           b"A320neo,4500,3.4,2.3,13.2,0.13\n")
    kept = conditions.read_bytes()
    rc = main(["generate", "--conditions", str(conditions), "--force", "-o",
               str(tmp_path / output)])
    assert rc == 2 and "is an input of this command" in capsys.readouterr().err
    assert conditions.read_bytes() == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == [scratch]


def test_atomic_writes_refuse_an_input_under_their_temporary_name(tmp_path):
    target = tmp_path / "r.json"
    held = tmp_path / "r.json.part"
    held.write_bytes(MINE)
    ns = argparse.Namespace(command="x", given=str(held), force=True, _outputs=())
    with pytest.raises(InputError, match="is an input"), guarding(ns):
        write_atomic(target, b"{}")
    assert held.read_bytes() == MINE and not target.exists()
    with guarding(argparse.Namespace(command="x", force=False, _outputs=())):
        write_atomic(target, b"{}")  # a leftover temporary file, no input: written over
    assert target.read_bytes() == b"{}" and not held.exists()


def test_a_new_output_inside_an_input_directory_is_written_through_its_temporary_name(tmp_path):
    """`choose-tau --model M -o M/tau_sweep.json` (the documented recipe) writes
    M/tau_sweep.json.part first: a new name inside an input directory is the command's to
    write; something already there under that name is not (it may be what the command reads)."""
    model = tmp_path / "m"
    model.mkdir()
    (model / "model.json").write_bytes(MINE)
    ns = argparse.Namespace(command="choose-tau", model=str(model), force=False, _outputs=())
    with guarding(ns):
        write_atomic(model / "tau_sweep.json", b"{}")
        with atomic_path(model / "other.json") as tmp:
            tmp.write_bytes(b"[]")
    assert (model / "tau_sweep.json").read_bytes() == b"{}"
    assert (model / "other.json").read_bytes() == b"[]"
    assert sorted(p.name for p in model.iterdir()) == ["model.json", "other.json",
                                                        "tau_sweep.json"]
    left = model / "again.json.part"
    left.write_bytes(MINE)
    with pytest.raises(InputError, match="inside one"), guarding(ns):
        write_atomic(model / "again.json", b"{}")
    assert left.read_bytes() == MINE and not (model / "again.json").exists()


def test_generate_writes_its_clouds_into_the_models_own_directory(tmp_path, capsys):
    """The NPZ writer's zip and spill files inside an input directory (the model's): new
    names, written, renamed and removed; the model's own files untouched."""
    import shutil

    from apcg_core.families import default_model_dir
    model = tmp_path / "model"
    shutil.copytree(default_model_dir(), model)
    before = digest(model)
    rc = main(["generate", "--model", str(model), "--type", "A320neo", "--range-m", "4500",
               "--elevation-deg", "3.4", "--pitch-deg", "2", "-o", str(model / "g.npz")])
    assert rc == 0, capsys.readouterr().err
    after = digest(model)
    assert after.pop("g.npz") and after == before


def test_a_commands_outputs_appear_together_when_it_ends_and_none_when_it_fails(tmp_path):
    args = _args(tmp_path)
    with guarding(args):
        write_atomic(tmp_path / "c.ply", b"cloud")
        with atomic_path(tmp_path / "d.png") as tmp:
            tmp.write_bytes(b"image")
        assert not (tmp_path / "c.ply").exists() and not (tmp_path / "d.png").exists()
    assert (tmp_path / "c.ply").read_bytes() == b"cloud"
    assert (tmp_path / "d.png").read_bytes() == b"image"
    again = _args(tmp_path, force=True)
    with pytest.raises(KeyboardInterrupt), guarding(again):
        write_atomic(tmp_path / "c.ply", b"new cloud")
        raise KeyboardInterrupt
    assert (tmp_path / "c.ply").read_bytes() == b"cloud"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.ply", "d.png"]  # no .part


def test_a_directory_is_never_replaced_by_a_file(tmp_path):
    (tmp_path / "x.json").mkdir()
    (tmp_path / "x.json" / "keep").write_bytes(MINE)
    with pytest.raises(InputError, match="directory"), \
            guarding(_args(tmp_path, force=True)):
        write_atomic(tmp_path / "x.json", b"{}")
    assert (tmp_path / "x.json" / "keep").read_bytes() == MINE


def test_outside_a_command_writes_are_plain_atomic_writes(tmp_path):
    (tmp_path / "a").write_bytes(MINE)
    write_atomic(tmp_path / "a", b"new")  # library callers decide for themselves
    assert (tmp_path / "a").read_bytes() == b"new"
    assert Guard().refusal(tmp_path / "a") is not None  # a guard without --force would not


# --- the cases users met (issue 31) ---------------------------------------------------------

def test_dataset_build_keeps_a_users_conditions_csv(tmp_path, capsys):
    flights = tmp_path / "flights"
    flights.mkdir()
    (flights / "conditions.csv").write_bytes(MINE)
    argv = ["dataset", "build", "--config", "demo", "-o", flights, "--no-progress"]
    rc, _, err = run(argv, capsys)
    assert rc == 2 and "conditions.csv" in err and "--force" in err, err
    assert (flights / "conditions.csv").read_bytes() == MINE
    assert sorted(p.name for p in flights.iterdir()) == ["conditions.csv"]


def test_a_build_resumes_into_its_own_directory_without_force(tmp_path, capsys):
    cfg = _tiny_config(tmp_path, "same.toml")
    argv = ["dataset", "build", "--config", cfg, "-o", tmp_path / "ds", "--no-progress"]
    assert run(argv, capsys)[0] == 0
    rc, out, err = run(argv, capsys)
    assert rc == 0 and json.loads(out)["skipped_shards"] > 0, err


def test_figure_keeps_the_json_beside_its_png(tmp_path, capsys):
    (tmp_path / "f13.json").write_bytes(MINE)
    rc, _, err = run(["figure", "13", "--run", DEFAULT_MODEL, "-o", tmp_path / "f13.png"],
                     capsys)
    assert rc == 2 and "f13.json" in err and "--force" in err, err
    assert (tmp_path / "f13.json").read_bytes() == MINE
    assert not (tmp_path / "f13.png").exists()
    rc, _, err = run(["figure", "13", "--run", DEFAULT_MODEL, "-o", tmp_path / "f13.png",
                      "--force"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "f13.json").read_text()) and (tmp_path / "f13.png").exists()


def test_simulate_refuses_one_file_for_both_images(tmp_path, capsys):
    rc, _, err = run(["simulate", *POSE, "-o", "c.ply", "--depth-image", "d.png",
                      "--normalized-image", "./d.png"], capsys, cwd=tmp_path)
    assert rc == 2 and "same file" in err, err
    assert list(tmp_path.iterdir()) == []


def _tiny_config(tmp: Path, name: str, r_r_m: float | None = None) -> Path:
    lidar = ("" if r_r_m is None else
             f"\n[lidar]\nr_alpha_deg = 0.004\nr_beta_deg = 0.0076\nr_r_m = {r_r_m}\n"
             "width = 256\nheight = 64\n")
    path = tmp / name
    path.write_text('description = "tiny"\nseed = 3\nbackend = "embree"\nshard_size = 50\n'
                    'test_fraction = 0.5\nquantize = true\nsupersample = 1\n'
                    'sampling = "random"\nsamples_per_type = 24\n'
                    'types = ["Mavic 3", "A320neo"]\n' + lidar)
    return path


@pytest.fixture(scope="module")
def tiny_datasets(tmp_path_factory):
    """Two small datasets: one by the default model's lidar, one by a lidar with 0.3 m bins."""
    from dataset_builder.build import build_dataset
    root = tmp_path_factory.mktemp("tiny")
    out = {}
    for name, r_r in (("same", None), ("other", 0.3)):
        cfg = _tiny_config(root, f"{name}.toml", r_r)
        build_dataset(str(cfg), root / name, progress=False)
        out[name] = root / name
    return out


def test_evaluate_keeps_a_users_report_and_has_force(tiny_datasets, tmp_path, capsys):
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "report.md").write_bytes(MINE)
    argv = ["evaluate", "--data", tiny_datasets["same"], "--pairs", "4", "--no-faithfulness",
            "-o", rep]
    rc, _, err = run(argv, capsys)
    assert rc == 2 and "report.md" in err and "--force" in err, err
    assert sorted(p.name for p in rep.iterdir()) == ["report.md"]
    rc, _, err = run([*argv, "--force"], capsys)
    assert rc == 0, err
    assert (rep / "report.md").read_bytes() != MINE and (rep / "metrics.json").exists()


# --- 7. a dataset of another lidar than the model's ----------------------------------------

def _warnings(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if "warning:" in ln and "lidar" in ln]


@pytest.mark.parametrize("command", ["evaluate", "compare"])
def test_scoring_on_another_lidars_dataset_says_so_in_one_line(tiny_datasets, tmp_path, capsys,
                                                               command):
    extra = (["--model", DEFAULT_MODEL, "--memory-steps", "0", "--no-untrained"]
             if command == "compare" else ["--model", DEFAULT_MODEL])
    for name in ("same", "other"):
        rc, _, err = run([command, "--data", tiny_datasets[name], *extra, "--pairs", "4",
                          "--no-faithfulness", "-o", tmp_path / name], capsys)
        assert rc == 0, err
        lines = _warnings(err)
        if name == "same":
            assert lines == [], err
            continue
        assert len(lines) == 1, err
        line = lines[0]
        assert line.startswith(f"apcg {command}: warning:"), line
        assert str(tiny_datasets["other"]) in line and str(DEFAULT_MODEL) in line, line
        assert "0.3 m bins" in line and "0.15 m bins" in line and "r_r_m" in line, line


# --- teach --force beside its own input (a real process) ------------------------------------

@pytest.fixture(scope="module")
def user_type(tmp_path_factory):
    """A catalog of the user's own with a drone the default model does not know."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.catalog.importer import export_mesh
    root = tmp_path_factory.mktemp("user-catalog")
    mesh = root / "drone.ply"
    export_mesh(default_catalog().mesh("Mavic 3"), mesh)
    env = {**os.environ, "APCG_DATA_DIR": str(root / "data")}
    r = subprocess.run([APCG, "catalog", "add", mesh, "--name", "Guard Drone", "--kind",
                        "drone"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    return env, "Guard Drone"


def test_teach_force_into_the_models_parent_keeps_the_model(tmp_path, user_type):
    import shutil
    env, name = user_type
    work = tmp_path / "work"
    shutil.copytree(DEFAULT_MODEL, work / "m")
    (work / "notes.txt").write_bytes(MINE)
    before = digest(work / "m")
    cmd = [APCG, "teach", "--model", work / "m", "--type", name, "-o", work, "--samples", "8",
           "--steps", "2"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 2 and "--force" in r.stderr, r.stderr  # work/ holds files
    r = subprocess.run([*cmd, "--force"], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    assert digest(work / "m") == before  # the model taught: untouched
    assert (work / "notes.txt").read_bytes() == MINE  # the user's other file: kept
    assert name in json.loads((work / "model.json").read_text())["types"][-1]["name"]
    assert not [p for p in tmp_path.rglob("*") if ".part" in p.name or "staging" in p.name]
