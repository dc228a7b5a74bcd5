"""A large `apcg generate` is a resumable job (apcg_core/generation_job.py): parts beside the
output, Ctrl-C keeps them, the same command continues, and the output's bytes are those of
one uninterrupted run straight into the file."""

import json
import signal
import subprocess
import sys

import numpy as np
import pytest

import apcg_core.generation_cli as gen
from apcg_core.cli import main

# `apcg` with parts of 512 clouds (two sub-blocks of 256), so that a small request has several
APCG = [sys.executable, "-c", "import sys; import apcg_core.generation_cli as g; "
        "g.BLOCK_CLOUDS = 512; from apcg_core.cli import main; sys.exit(main(sys.argv[1:]))"]
POSE = ["--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3", "--pitch-deg", "2"]


@pytest.mark.parametrize("ext", ["ply", "npz"])
def test_resumable_output_is_the_direct_output(tmp_path, monkeypatch, ext):
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)  # parts of 2 clouds: 3 parts
    assert main(["generate", *POSE, "--count", "5", "-o", str(tmp_path / f"d.{ext}")]) == 0
    assert main(["generate", *POSE, "--count", "5", "--resumable", "-o",
                 str(tmp_path / f"r.{ext}")]) == 0
    if ext == "ply":
        assert (tmp_path / "r.ply").read_bytes() == (tmp_path / "d.ply").read_bytes()
    else:
        import zipfile
        a, b = zipfile.ZipFile(tmp_path / "r.npz"), zipfile.ZipFile(tmp_path / "d.npz")
        assert a.namelist() == b.namelist()
        assert all(a.read(n) == b.read(n) for n in a.namelist())
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"d.{ext}", f"r.{ext}"]


def test_parts_of_another_request_are_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)
    parts = tmp_path / "r.ply.parts"
    parts.mkdir()
    (parts / "job.json").write_text('{"header": {"seed": 99}}\n')
    assert main(["generate", *POSE, "--count", "5", "--resumable", "-o",
                 str(tmp_path / "r.ply")]) == 2
    err = capsys.readouterr().err
    assert "r.ply.parts holds the parts of another request" in err and err.count("\n") == 1
    assert not (tmp_path / "r.ply").exists()


@pytest.mark.parametrize("text", ["", '{"header": {"se', "[1, 2]", "\xff\xfe"])
def test_a_damaged_job_record_is_named_not_a_traceback(tmp_path, monkeypatch, capsys, text):
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)
    parts = tmp_path / "r.npz.parts"
    parts.mkdir()
    (parts / "job.json").write_bytes(text.encode("latin-1"))
    assert main(["generate", *POSE, "--count", "5", "--resumable", "-o",
                 str(tmp_path / "r.npz")]) == 2
    err = capsys.readouterr().err
    assert "job.json is damaged" in err and "delete" in err and err.count("\n") == 1, err
    assert not (tmp_path / "r.npz").exists()


def test_parts_without_a_job_record_never_go_into_the_output(tmp_path, monkeypatch, capsys):
    """Parts of one request, their job.json gone, beside another request's output: refused,
    not merged (its clouds were of other conditions)."""
    import apcg_core.generation_job as job
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)
    out = tmp_path / "r.npz"
    whole = job._write_output

    def stop(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(job, "_write_output", stop)
    assert main(["generate", *POSE, "--count", "5", "--resumable", "-o", str(out)]) == 130
    monkeypatch.setattr(job, "_write_output", whole)
    parts = tmp_path / "r.npz.parts"
    assert len(list(parts.glob("part-*.npz"))) == 3
    (parts / "job.json").unlink()
    other = ["generate", *POSE[:-1], "4", "--count", "5", "--resumable", "-o", str(out)]
    capsys.readouterr()
    assert main(other) == 2
    err = capsys.readouterr().err
    assert "3 part file(s)" in err and "no job.json" in err, err
    assert not out.exists() and len(list(parts.glob("part-*.npz"))) == 3


def test_a_request_of_more_clouds_than_one_may_ask_is_refused_at_once(tmp_path, capsys):
    import apcg_core.generation_job as job
    big = str(job.MAX_CLOUDS + 1)
    assert main(["generate", *POSE, "--count", big, "-o", str(tmp_path / "g.npz")]) == 2
    assert f"--count {big} not accepted" in capsys.readouterr().err
    csv = tmp_path / "c.csv"
    csv.write_text("type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"
                   "A320neo,3000,3,2,0,0\nA320neo,3100,3,2,0,0\n")
    half = str(job.MAX_CLOUDS // 2 + 1)
    assert main(["generate", "--conditions", str(csv), "--count", half, "-o",
                 str(tmp_path / "g.npz")]) == 2
    assert "2 conditions x --count" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]


def test_ctrl_c_keeps_the_parts_and_the_same_command_resumes(tmp_path, hold):
    # 1,300 clouds of one condition: sub-blocks of 256, parts of 2 of them: 3 parts
    cmd = [*APCG, "generate", *POSE, "--count", "1300", "--resumable", "-o",
           str(tmp_path / "g.ply")]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                         env=hold.env("generate.part-written"))
    try:
        hold.wait("generate.part-written", p)
        p.send_signal(signal.SIGINT)
        hold.release("generate.part-written")
        err = p.communicate(timeout=300)[1]
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, err
    assert "apcg generate: interrupted: 1 of 3 parts are done in" in err, err
    assert "Traceback" not in err
    parts = tmp_path / "g.ply.parts"
    assert sorted(x.name for x in parts.iterdir()) == ["job.json", "part-000000.npz"]
    assert [x.name for x in tmp_path.iterdir()] == ["g.ply.parts"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    whole = subprocess.run([*APCG, "generate", *POSE, "--count", "1300", "-o",
                            str(tmp_path / "direct.ply")], capture_output=True, text=True,
                           timeout=300)
    assert whole.returncode == 0, whole.stderr
    assert (tmp_path / "g.ply").read_bytes() == (tmp_path / "direct.ply").read_bytes()
    assert sorted(x.name for x in tmp_path.iterdir()) == ["direct.ply", "g.ply"]


@pytest.mark.parametrize("engine", ["dask", "local"])
def test_an_engine_makes_the_bytes_of_one_process(tmp_path, monkeypatch, engine):
    """--engine: the parts computed by the dataset builder's engines (a local Dask cluster,
    a process pool; 2 workers), the output written here: the bytes of one process."""
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)  # 3 parts, so both workers get some
    assert main(["generate", *POSE, "--count", "5", "-o", str(tmp_path / "one.ply")]) == 0
    assert main(["generate", *POSE, "--count", "5", "--engine", engine, "--workers", "2",
                 "-o", str(tmp_path / "many.ply")]) == 0
    assert (tmp_path / "many.ply").read_bytes() == (tmp_path / "one.ply").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["many.ply", "one.ply"]


def test_address_without_an_engine_is_refused(tmp_path, capsys):
    assert main(["generate", *POSE, "--address", "tcp://127.0.0.1:1", "-o",
                 str(tmp_path / "x.ply")]) == 2
    assert "--address needs --engine dask" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_clouds_with_points_counts_distinct_clouds():
    from apcg_core.generation_job import clouds_with_points
    assert clouds_with_points(np.zeros(0, np.int64)) == 0
    assert clouds_with_points([7]) == 1
    assert clouds_with_points([5, 5, 7, 9, 9, 9]) == 3
    rng = np.random.default_rng(0)
    for _ in range(50):
        first = int(rng.integers(0, 10**6))
        s = np.sort(first + rng.integers(0, 300, int(rng.integers(1, 2000))))
        assert clouds_with_points(s) == len(np.unique(s))
        assert clouds_with_points(rng.permutation(s)) == len(np.unique(s))  # any order


@pytest.mark.parametrize("sensor", [None, "1550nm-night"])
def test_a_damaged_part_is_named_and_made_again_once_deleted(tmp_path, monkeypatch, capsys,
                                                             sensor):
    """The parts are checked whole before they go into the output (zip, members, lengths,
    CRCs): one with a flipped byte or cut short is named with what to do, nothing is written
    under the output's name, and once it is deleted the same command remakes that part alone
    and writes the bytes of an uninterrupted run (photon attributes too)."""
    import zipfile

    import apcg_core.generation_job as job
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)  # parts of 2 clouds: 3 parts
    extra = ["--sensor", sensor] if sensor else []
    out = tmp_path / "r.npz"
    cmd = ["generate", *POSE, "--count", "5", "--resumable", *extra, "-o", str(out)]
    assert main(["generate", *POSE, "--count", "5", *extra, "-o", str(tmp_path / "d.npz")]) == 0
    whole = job._write_output

    def stop(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(job, "_write_output", stop)
    assert main(cmd) == 130  # every part made, none written into the output yet
    monkeypatch.setattr(job, "_write_output", whole)
    part = out.with_name("r.npz.parts") / "part-000001.npz"
    for damage in ("flip", "cut"):
        data = bytearray(part.read_bytes())
        kept = bytes(data)
        if damage == "flip":
            data[len(data) // 3] ^= 0x40
        else:
            data = data[: len(data) - 40]
        part.write_bytes(bytes(data))
        capsys.readouterr()
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "part-000001.npz is damaged" in err and "delete it" in err, err
        assert not out.exists()
        part.write_bytes(kept)
    part.unlink()
    assert main(cmd) == 0
    a, b = zipfile.ZipFile(out), zipfile.ZipFile(tmp_path / "d.npz")
    assert a.namelist() == b.namelist()
    assert all(a.read(n) == b.read(n) for n in a.namelist() if n != "meta.npy")
    assert not out.with_name("r.npz.parts").exists()


@pytest.mark.parametrize("ext", ["npz", "ply", "las"])
@pytest.mark.parametrize("pose, says", [
    (["--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3"],
     "pitch = 0 deg is outside the configured range [1 deg, 5 deg]"),
    # a 777 at 3 km overflows the lidar's window: the refusal must come before that warning
    (["--type", "777-300ER", "--range-m", "3000", "--elevation-deg", "20", "--pitch-deg", "2"],
     "elevation = 20 deg is outside the configured range [3 deg, 4 deg]")])
def test_a_pose_outside_the_models_ranges_is_refused_first(tmp_path, ext, pose, says):
    """A pose outside the model's ranges (Table 1): one line naming it, exit 2, before any
    warning about the request and before any file, and no traceback, not even one Python
    prints while collecting a half-made writer at exit."""
    out = tmp_path / f"g.{ext}"
    p = subprocess.run([*APCG, "generate", *pose, "-o", str(out)], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"apcg generate: error: the condition: "
                                                   f"{says}"), p.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["type", "csv"])
def test_a_target_the_window_cuts_is_warned_of_once(tmp_path, how):
    """The window check runs beside the first blocks: its one line still comes, once, before
    the command's result, for one condition and for a CSV (with its progress bar)."""
    if how == "type":
        request = ["--type", "777-300ER", "--range-m", "3000", "--elevation-deg", "3.5",
                   "--pitch-deg", "2"]
    else:
        csv = tmp_path / "c.csv"
        csv.write_text("type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n" + "".join(
            f"{t},{r},3.5,2,{y},0\n" for t, r in (("777-300ER", 3000), ("A320neo", 15000))
            for y in range(-50, 50, 2)))
        request = ["--conditions", str(csv)]
    p = subprocess.run([*APCG, "generate", *request, "-o", str(tmp_path / "g.npz")],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    said = [ln for ln in p.stderr.splitlines() if "window too small" in ln]
    assert len(said) == 1 and said[0].startswith("apcg generate: warning: window too small: "
                                                 "the lidar's 256 x 64 window cuts"), p.stderr
    assert json.loads(p.stdout)["clouds"] == (1 if how == "type" else 100)
