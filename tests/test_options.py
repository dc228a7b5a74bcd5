"""Every numeric option of every command has a rule, and a refused value is named, exit 2."""

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from apcg_core.cli import build_parser
from apcg_core.options import RULES, problems

APCG = str(Path(sys.executable).parent / "apcg")


def _numeric_actions():
    """(command path, action) for every int / float option of every installed command."""
    out = []

    def walk(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    walk(sub, path + [name])
            elif a.type in (int, float):
                out.append((" ".join(path), a))
    walk(build_parser(), [])
    return out


def test_every_numeric_option_has_a_rule():
    actions = _numeric_actions()
    assert len(actions) > 40  # the walk reached the commands' options
    missing = sorted({f"{path}: {a.dest}" for path, a in actions if a.dest not in RULES})
    assert not missing, f"options without a rule in apcg_core/options.py: {missing}"


def test_defaults_pass_their_own_rules():
    for path, a in _numeric_actions():
        if a.default is not None and a.default is not argparse.SUPPRESS:
            assert not problems({a.dest: a.default}), (path, a.dest, a.default)


@given(st.sampled_from(sorted(RULES)), st.sampled_from([float("nan"), float("inf"),
                                                        -float("inf")]))
def test_non_finite_values_are_refused_everywhere(dest, value):
    said = problems({dest: value})
    assert len(said) == 1 and said[0].startswith("--" + dest.replace("_", "-"))


@given(st.integers(min_value=-2**40, max_value=0))
def test_counts_below_one_are_refused(n):
    for dest in ("batch_size", "count", "workers", "columns", "steps"):
        assert problems({dest: n})


def test_zero_is_accepted_where_it_has_a_meaning():
    for dest in ("pairs", "memory_steps", "diverge_gp"):
        assert problems({dest: 0}) == [] and problems({dest: -1})


@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_every_seed_in_range_is_accepted(n):
    assert problems({"seed": n}) == []


@pytest.mark.parametrize("args,needle", [
    (["train", "--data", "nowhere", "-o", "x", "--batch-size", "0"], "--batch-size 0"),
    (["generate", "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
      "--tau", "nan", "-o", "x.ply"], "--tau nan"),
    (["generate", "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
      "--seed", "-1", "-o", "x.ply"], "--seed -1"),
    (["catalog", "show", "--columns", "0", "-o", "s.png"], "--columns 0"),
    (["simulate", "--type", "A320neo", "--range-m", "-5", "--elevation-deg", "3", "-o",
      "x.ply"], "--range-m -5.0"),
    (["catalog", "add", "f.obj", "--name", "x", "--length-m", "1e308"], "--length-m 1e+308"),
    # the condition's own range, so the option is named (it let 200 through to a message that
    # said `roll`; probe finding, stop 53)
    (["simulate", "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
      "--roll-deg=180.00001", "-o", "x.ply"], "--roll-deg 180.00001"),
    (["generate", "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
      "--yaw-deg", "200", "-o", "x.ply"], "--yaw-deg 200.0"),
    (["condition", "--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3",
      "--pitch-deg", "-90.5"], "--pitch-deg -90.5"),
])
def test_cli_names_the_refused_value(tmp_path, args, needle):
    out = subprocess.run([APCG, *args], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert needle in out.stderr and "not accepted" in out.stderr
    assert "Traceback" not in out.stderr
    assert list(tmp_path.iterdir()) == []  # nothing written



@pytest.mark.parametrize("dest,field", [("pitch_deg", "pitch"), ("yaw_deg", "yaw"),
                                        ("roll_deg", "roll")])
def test_attitude_options_accept_what_the_condition_accepts(dest, field):
    """An attitude option's rule is the Condition's own range, at both ends: what the option
    lets through the condition takes, and the first value past either end both refuse (so a
    refusal always names the option the user typed)."""
    import math

    from apcg_core.condition import Condition
    from apcg_core.errors import InputError
    rule = RULES[dest]

    def pose(v):
        return Condition.from_degrees(0, 3000.0, 3.0, **{dest: v})

    for end, outward in ((rule.lo, -math.inf), (rule.hi, math.inf)):
        assert rule.ok(end) and getattr(pose(end), field) == pytest.approx(math.radians(end))
        past = math.nextafter(end, outward)
        assert not rule.ok(past)
        with pytest.raises(InputError):
            pose(past)
        inner = math.nextafter(end, -outward)
        assert rule.ok(inner)
        pose(inner)


@pytest.mark.parametrize("args,needles", [
    # the geometry refuses the range: the option it came from is named
    (["simulate", "--type", "A320neo", "--range-m", "10", "--elevation-deg", "3", "-o", "x.ply"],
     ["inside the target's bounding sphere", "the value of --range-m"]),
    # the model's condition space refuses it
    (["generate", "--type", "A320neo", "--range-m", "2999", "--elevation-deg", "3.5",
      "--pitch-deg", "2", "-o", "x.ply"], ["outside the configured range", "--range-m"]),
    (["generate", "--type", "A320neo", "--range-m", "5000", "--elevation-deg", "7",
      "--pitch-deg", "2", "-o", "x.ply"], ["elevation = 7 deg", "the value of --elevation-deg"]),
    # below the lidar is not overhead
    (["simulate", "--type", "A320neo", "--range-m", "5000", "--elevation-deg", "-90", "-o",
      "x.ply"], ["straight below", "--elevation-deg"]),
])
def test_a_refused_pose_names_the_option_it_came_from(tmp_path, args, needles):
    """The condition names its field (range_m, elevation); the command adds the option the
    user typed (probe finding, stop 54: only a defaulted pitch was named as its option)."""
    out = subprocess.run([APCG, *args], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert all(n in out.stderr for n in needles), out.stderr
    assert list(tmp_path.iterdir()) == []
