"""`apcg generate` checks the whole request before it makes anything: options that do not go
together are refused (pose options beside --conditions, --workers without --engine), an
engine's refusal leaves no OUT.parts/ behind, --address works without --workers, and a
refused pose says which values the user did not give and shows enough digits."""

import pytest

import apcg_core.generation_cli as gen
from apcg_core.cli import main

POSE = ["--type", "A320neo", "--range-m", "4500", "--elevation-deg", "3", "--pitch-deg", "2"]
HEAD = "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"


def _refused(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("apcg generate: error: "), err
    for w in words:
        assert w in err[0], err[0]
    return err[0]


@pytest.mark.parametrize("extra", [["--engine", "bogus"], ["--resumable", "--engine", "bogus"],
                                   ["--engine", "local", "--address", "tcp://127.0.0.1:1"]])
def test_a_refused_engine_leaves_no_parts_behind(tmp_path, capsys, extra):
    out = tmp_path / "ge5.npz"
    assert main(["generate", *POSE, *extra, "-o", str(out)]) == 2
    _refused(capsys)
    assert list(tmp_path.iterdir()) == []
    # and the next request into the same output is not blocked by a stale job.json
    assert main(["generate", *POSE, "--resumable", "-o", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ge5.npz"]


def test_address_without_workers_reaches_the_engine(monkeypatch, tmp_path, capsys):
    """--workers not given with --address: the engine is asked for no local workers (as
    `apcg dataset build` asks); given, the engine's own rule refuses it."""
    import apcg_core.generation_job as job
    seen = {}

    def engine(name, workers, address, output):
        seen.update(name=name, workers=workers, address=address)
        from apcg_core.errors import InputError
        raise InputError("stop here")
    monkeypatch.setattr(job, "engine", engine)
    args = ["generate", *POSE, "--engine", "dask", "--address", "tcp://127.0.0.1:1", "-o",
            str(tmp_path / "g.npz")]
    assert main(args) == 2
    assert seen == {"name": "dask", "workers": 1, "address": "tcp://127.0.0.1:1"}
    assert main([*args, "--workers", "3"]) == 2
    assert seen["workers"] == 3
    assert main(["generate", *POSE, "--engine", "local", "-o", str(tmp_path / "g.npz")]) == 2
    assert seen["workers"] == gen.DEFAULT_WORKERS
    capsys.readouterr()
    assert list(tmp_path.iterdir()) == []


def test_workers_without_an_engine_is_refused(tmp_path, capsys):
    assert main(["generate", *POSE, "--workers", "2", "-o", str(tmp_path / "g.npz")]) == 2
    _refused(capsys, "--workers 2 needs --engine")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["", " "])
def test_an_empty_conditions_name_is_refused_as_such(tmp_path, capsys, name):
    assert main(["generate", "--conditions", name, "-o", str(tmp_path / "g.npz")]) == 2
    _refused(capsys, f"--conditions {name!r}: an empty name")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("pose", [["--range-m", "4000"], ["--pitch-deg", "3"],
                                  ["--roll-deg", "0", "--elevation-deg", "3"]])
def test_pose_options_beside_conditions_are_refused(tmp_path, capsys, pose):
    (tmp_path / "c.csv").write_text(HEAD + "A320neo,4500,3,2,0,0\n")
    assert main(["generate", "--conditions", str(tmp_path / "c.csv"), *pose, "-o",
                 str(tmp_path / "g.npz")]) == 2
    _refused(capsys, "not accepted with --conditions", pose[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]


def test_pitch_option_rule_says_what_the_pose_accepts(tmp_path, capsys):
    assert main(["generate", *POSE[:-2], "--pitch-deg", "120", "-o",
                 str(tmp_path / "g.npz")]) == 2
    _refused(capsys, "--pitch-deg 120.0 not accepted", "from -90 to 90")


def test_a_default_pitch_outside_the_range_is_named_as_the_default(tmp_path, capsys):
    assert main(["generate", *POSE[:-2], "-o", str(tmp_path / "g.npz")]) == 2
    _refused(capsys, "pitch = 0 deg is outside", "default of --pitch-deg, which was not given")
    assert main(["generate", *POSE[:-2], "--pitch-deg", "0", "-o",
                 str(tmp_path / "g.npz")]) == 2
    assert "default" not in _refused(capsys, "pitch = 0 deg is outside")


def test_a_value_just_past_a_bound_shows_its_digits(tmp_path, capsys):
    pose = ["--type", "A320neo", "--range-m", "18000.000001", "--elevation-deg", "3",
            "--pitch-deg", "2"]
    assert main(["generate", *pose, "-o", str(tmp_path / "g.npz")]) == 2
    _refused(capsys, "range_m = 18000.000001 m is outside", "[3000 m, 18000 m]")
