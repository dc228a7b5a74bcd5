import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

# the installed console script next to this interpreter (what a user runs)
_SCRIPT = Path(sys.executable).parent / "apcg"
APCG = str(_SCRIPT) if _SCRIPT.exists() else shutil.which("apcg")


def run(*args):
    return subprocess.run([APCG, *args], capture_output=True, text=True, timeout=120)


def test_version_and_help():
    from apcg_core import __version__
    v = run("--version")
    assert v.returncode == 0 and v.stdout.strip() == f"apcg {__version__}"
    h = run("--help")
    assert h.returncode == 0 and "condition" in h.stdout


def test_a_command_loads_its_own_entry_point_alone():
    """Each installed command's entry point registers the command it is named after, so `apcg
    NAME` loads that one alone; anything else (no command, an option, an unknown name) loads
    all of them, and argparse lists every command."""
    from importlib.metadata import entry_points

    from apcg_core.cli import build_parser
    installed = sorted(ep.name for ep in entry_points(group="apcg.commands"))
    assert len(installed) >= 15

    def commands(parser):
        return set(next(a for a in parser._actions if a.dest == "command").choices)
    for name in installed:
        assert commands(build_parser(command=name)) == {name}
    for other in (None, "--help", "no-such-command"):
        assert commands(build_parser(command=other)) == set(installed)
    bad = run("no-such-command")
    assert bad.returncode == 2 and "generate" in bad.stderr and "dataset" in bad.stderr


def test_condition_json_codes_the_type_in_the_model_table():
    from apcg_core.families import load_model
    last = load_model(runtime="onnx").types.names[-1]  # the default model's last type
    out = run("condition", "--type", last, "--range-m", "18000",
              "--elevation-deg", "4", "--pitch-deg", "5", "--yaw-deg", "60", "--roll-deg", "5",
              "--json")
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert d["nu"] == [1, 1, 1, 1, 1, 1] and d["type"] == last
    assert d["reference_range_m"] == 3000.0 and d["q"] == pytest.approx(6.0)
    y, z = d["centre_observation_m"][1:]
    assert d["centre_blender_lidar_local_m"] == [0.0, z, y]


@pytest.mark.parametrize("args,needle", [
    (["--elevation-deg", "90"], "overhead"),
    (["--elevation-deg", "3.5", "--yaw-deg", "nan"], "--yaw-deg nan not accepted"),
    (["--elevation-deg", "3.5", "--pitch-deg", "2", "--yaw-deg", "70"], "yaw = 70 deg is outside"),
])
def test_condition_errors_are_clear(args, needle):
    out = run("condition", "--type", "A320neo", "--range-m", "5000", *args)
    assert out.returncode == 2
    assert needle in out.stderr and "Traceback" not in out.stderr


def test_condition_by_catalog_type_uses_its_range_band():
    out = run("condition", "--type", "Mavic 3", "--range-m", "350", "--elevation-deg", "3.5",
              "--pitch-deg", "2",
              "--json")
    assert out.returncode == 0, out.stderr
    nu = json.loads(out.stdout)["nu"]
    assert nu[1] == pytest.approx(2 * (350 - 100) / 500 - 1)
    far = run("condition", "--type", "Mavic 3", "--range-m", "3000", "--elevation-deg", "3.5",
              "--pitch-deg", "2")
    assert far.returncode == 2 and "range_m" in far.stderr and "600" in far.stderr


def _probe_registrar(seen: dict, hint=None):
    """A command of this test's own, run by the real `apcg` main: it keeps what main gave it,
    then stops as Ctrl-C does."""
    def register(sub):
        p = sub.add_parser("probe")
        p.add_argument("--types")
        p.add_argument("rest", nargs="*")
        p.set_defaults(func=run_probe, **({"resume_hint": hint} if hint else {}))

    def run_probe(args):
        seen["command_line"] = args.command_line
        raise KeyboardInterrupt
    return register


def test_the_command_line_main_records_can_be_pasted_back(capsys):
    import shlex

    from apcg_core.cli import main
    seen: dict = {}
    argv = ["probe", "--types", "A320neo,Mavic 3", "it's", "$HOME", ""]
    assert main(argv, registrars=[_probe_registrar(seen)]) == 130
    assert shlex.split(seen["command_line"]) == ["apcg", *argv]


def test_ctrl_c_says_how_the_command_itself_continues(capsys):
    from apcg_core.cli import RUN_AGAIN, build_parser, main
    assert main(["probe"], registrars=[_probe_registrar({})]) == 130
    assert RUN_AGAIN in capsys.readouterr().err
    assert main(["probe"], registrars=[_probe_registrar({}, "Add --again.")]) == 130
    err = capsys.readouterr().err
    assert "apcg probe: interrupted" in err and "Add --again." in err and RUN_AGAIN not in err
    # the commands that continue say how; a benchmark is not told to add --resume
    hints = {" ".join(words): build_parser().parse_args([*words, *rest]).resume_hint
             for words, rest in ((["dataset", "build"], ["--config", "demo", "-o", "d"]),
                                 (["train"], ["--data", "d", "-o", "r"]),
                                 (["generate"], ["--type", "A320neo", "-o", "g.npz"]))}
    assert "continues" in hints["dataset build"] and "--resume" in hints["train"]
    assert "--resumable" in hints["generate"]
    args = build_parser().parse_args(["benchmark", "recognize", "-o", "r"])
    assert getattr(args, "resume_hint", None) is None


@pytest.mark.parametrize("value,parsed", [("-1e9", -1e9), ("-2.5E-1", -0.25), ("-.5e1", -5.0),
                                          ("-1", -1.0), ("-0.5", -0.5)])
def test_a_negative_number_in_any_notation_is_an_options_value(value, parsed):
    from apcg_core.cli import build_parser, join_signed_values
    argv = ["generate", "--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3",
            "--tau", value, "--yaw-deg", value, "-o", "g.npz"]
    args = build_parser().parse_args(join_signed_values(argv))
    assert args.tau == parsed and args.yaw_deg == parsed


def test_a_negative_infinity_reaches_the_options_rule(capsys):
    from apcg_core.cli import main
    assert main(["simulate", "--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3",
                 "--yaw-deg", "-inf", "-o", "never.ply"]) == 2
    assert "--yaw-deg -inf not accepted: a finite yaw in degrees" in capsys.readouterr().err


def test_a_shard_spec_with_a_minus_is_judged_by_its_own_check(tmp_path, capsys):
    from apcg_core.cli import main
    assert main(["dataset", "build", "--config", "demo", "-o", str(tmp_path / "d"),
                 "--shard", "-1/4"]) == 2
    err = capsys.readouterr().err
    assert "--shard -1/4: need N >= 1 and 0 <= I < N" in err and "usage:" not in err
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("spec", ["\u0661/2", "1/2/3", "a/b", "1.0/2", "", "1/"])
def test_a_shard_spec_takes_ascii_whole_numbers_only(spec):
    from apcg_core.errors import InputError
    from dataset_builder.build import parse_shard_spec
    with pytest.raises(InputError, match="--shard takes I/N"):
        parse_shard_spec(spec)
    assert parse_shard_spec(" 1/ 4") == (1, 4)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_after_the_command_ended_does_not_change_its_status(hold, sig):
    """Python re-raises an uncaught Ctrl-C as SIGINT: a stop while a finished command's
    interpreter exits reported it killed (-2), as test_fuzz's build killed at 0.88 s once saw."""
    p = subprocess.Popen([str(Path(sys.executable).parent / "apcg"), "catalog", "list"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                         env=hold.env("cli.command-ended"))
    pid = hold.wait("cli.command-ended", p)
    os.kill(pid, sig)
    hold.release("cli.command-ended")
    err = p.communicate(timeout=120)[1]
    assert p.returncode == 0 and "Traceback" not in err, (p.returncode, err)


def test_stderr_lines_of_two_threads_are_never_mixed():
    """A worker thread's warning and the main thread's error, each written as print writes
    it (the line, then its end), come out as two whole lines: the window check's warning
    once ran into generate's error ('...a longer rangeapcg generate: error: ...')."""
    import io
    import threading

    from apcg_core.cli import _PipeSafe
    sink = io.StringIO()
    stream = _PipeSafe(sink)
    started, go_on = threading.Event(), threading.Event()

    def warn():
        stream.write("apcg generate: warning: window too small")
        started.set()
        go_on.wait(10)
        stream.write("\n")
    worker = threading.Thread(target=warn)
    worker.start()
    started.wait(10)
    stream.write("apcg generate: error: refused")
    stream.write("\n")
    go_on.set()
    worker.join(10)
    assert sink.getvalue() == ("apcg generate: error: refused\n"
                               "apcg generate: warning: window too small\n")
    stream.write("50%|#####     |\r")  # a bar redrawn in place: out on flush, no line end
    assert sink.getvalue().endswith("small\n")
    stream.flush()
    assert sink.getvalue().endswith("small\n50%|#####     |\r")
    stream.write("held")  # whatever a thread left unended goes out when the command ends
    stream.drain()
    assert sink.getvalue().endswith("|\rheld")


def test_the_apcg_process_ends_every_line_it_starts(tmp_path):
    out = subprocess.run([sys.executable, "-m", "apcg_core.cli", "condition", "--type",
                          "A320neo", "--range-m", "5000", "--elevation-deg", "3.5",
                          "--pitch-deg", "2", "--yaw-deg", "60"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "'yaw_deg': 60.0" in out.stdout  # the degrees given, not 59.99999999999999
