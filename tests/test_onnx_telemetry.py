"""onnxruntime runs with its usage telemetry off: `apcg generate` leaves no usage record in the
user's home (onnxruntime 1.29+ keeps one under ~/.cache/Microsoft/DeveloperTools for upload and
syncs it to disk at exit; apcg_core/families/base.py)."""

import os
import subprocess
import sys
from pathlib import Path

APCG = str(Path(sys.executable).parent / "apcg")


def _generate(tmp_path, home, **env):
    home.mkdir()
    run_env = {k: v for k, v in os.environ.items()
               if k not in ("ORT_DISABLE_TELEMETRY", "XDG_CACHE_HOME")}
    run_env.update(HOME=str(home), **env)
    out = subprocess.run([APCG, "generate", "--type", "A320neo", "--range-m", "5000",
                          "--elevation-deg", "3.5", "--pitch-deg", "2", "-o",
                          str(tmp_path / f"{home.name}.npz")],
                         capture_output=True, text=True, timeout=300, env=run_env)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / f"{home.name}.npz").stat().st_size > 1000
    return sorted(str(p.relative_to(home)) for p in home.rglob("*"))


def test_generate_leaves_no_usage_record(tmp_path):
    made = _generate(tmp_path, tmp_path / "home")
    assert not any("Microsoft" in p or "onnxruntime" in p for p in made), made


def test_a_users_own_choice_is_kept(tmp_path):
    """ORT_DISABLE_TELEMETRY set by the user is theirs: the package sets it only when unset
    (here set to 1 explicitly, the command still runs and records nothing)."""
    made = _generate(tmp_path, tmp_path / "home1", ORT_DISABLE_TELEMETRY="1")
    assert not any("Microsoft" in p for p in made), made


def test_the_switch_is_set_only_where_the_user_left_it_unset():
    """The package sets ORT_DISABLE_TELEMETRY=1 when it imports onnxruntime, and keeps a
    value the user gave (0 too: their choice), in a process of its own."""
    code = ("import os; from apcg_core.families.base import onnxruntime; onnxruntime(); "
            "print(os.environ['ORT_DISABLE_TELEMETRY'])")
    for given, seen in ((None, "1"), ("0", "0"), ("1", "1")):
        env = {k: v for k, v in os.environ.items() if k != "ORT_DISABLE_TELEMETRY"}
        if given is not None:
            env["ORT_DISABLE_TELEMETRY"] = given
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120, env=env)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split()[-1] == seen, (given, out.stdout)
